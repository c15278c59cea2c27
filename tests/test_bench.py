"""The benchmark runs and its output has the expected rows (speed itself is measured by the
benchmark, never asserted in tests: this machine is shared and noisy)."""

import json

from jaxoptics._bench import run


def test_bench_runs_and_reports_every_method(tmp_path):
    report = run(quick=True, sections=("kernels",), out_dir=tmp_path, sizes=(1_000, 4_000), mitsuba=False)
    methods = {r["method"] for r in report["kernels"]}
    for m in ("fresnel, exact (jaxoptics)", "naive JAX textbook fresnel", "NumPy textbook fresnel",
              "schlick, multiplications (jaxoptics)", "schlick, pow", "schlick_tir (jaxoptics)",
              "copy (x * 2), the memory-bound limit", "refract, degreve", "refract, bec", "refract, heckbert",
              "refract, oliveira", "d fresnel / d eta2, jax.grad", "d fresnel / d eta2, forward mode (jvp)",
              "interface, full (r, t, tir, R, T)", "interface, R only"):
        assert m in methods, m
    dtypes = {r["dtype"] for r in report["kernels"]}
    assert dtypes == {"float32", "float64"}
    for r in report["kernels"]:
        if r.get("n"):
            assert r["run_s"] > 0 and r["ns_per_element"] > 0
    assert (tmp_path / "pareto.png").stat().st_size > 10_000
    text = (tmp_path / "bench.md").read_text()
    assert "| fresnel | fresnel, exact (jaxoptics) | float32 |" in text
    assert json.loads((tmp_path / "bench.json").read_text())["kernels"]
    limits = {r["method"] for r in report["limits"]}
    for m in ("copy (x * 2)", "copy (x * 2), input donated", "fresnel, exact (jaxoptics), input donated",
              "R and T from one shared graph (two outputs sharing quotients)", "dot of 3-vectors, written out"):
        assert m in limits, m
    assert all(r["fusions"] >= 1 and r["run_s"] > 0 for r in report["limits"])
    assert "What bounds XLA on the CPU" in text


def test_single_output_kernels_compile_to_one_loop():
    """XLA on the CPU has no multi-output loop fusion: a quotient or square root feeding two
    consumers that end up in different loops is materialized, and a kernel then reads and writes
    memory several times (measured in the bench's "what bounds XLA" table: 4x slower). This pins
    the structure, not a time: each single-output kernel, and its derivative in the index, is one
    fused loop."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo
    from jaxoptics._bench import _fusions

    if jax.default_backend() != "cpu":
        return
    c = jnp.linspace(0, 1, 1000, dtype=jnp.float32)
    e = jnp.full(1000, 1.2, jnp.float32)
    i = jnp.stack([c, jnp.zeros_like(c), -jnp.ones_like(c)], -1)
    n = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    for name, f, args in (
        ("fresnel", lambda c: jo.fresnel(c, 1.5, 1.0), (c,)),
        ("R_s", lambda c: jo.fresnel_sp(c, 1.5, 1.0)[0], (c,)),
        ("R_p", lambda c: jo.fresnel_sp(c, 1.5, 1.0)[1], (c,)),
        ("schlick_tir", lambda c: jo.schlick_tir(c, 1.5, 1.0), (c,)),
        ("d fresnel / d eta2, forward mode", lambda e, c: jax.jvp(lambda e: jo.fresnel(c, 1.5, e), (e,), (jnp.ones_like(e),))[1], (e, c)),
        ("reflect", lambda i: jo.reflect(i, n), (i,)),
    ):
        assert _fusions(jax.jit(f).lower(*args).compile()) == 1, name
    # R and T: one loop each (plus the one that writes k_t^2 for both)
    assert _fusions(jax.jit(lambda c: jo.fresnel_rt(c, 1.5, 1.0)).lower(c).compile()) <= 3
