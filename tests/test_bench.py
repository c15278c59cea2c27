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
              "fresnel_rt, R and T (two outputs sharing divisions)", "dot of 3-vectors, written out"):
        assert m in limits, m
    assert all(r["fusions"] >= 1 and r["run_s"] > 0 for r in report["limits"])
    assert "What bounds XLA on the CPU" in text
