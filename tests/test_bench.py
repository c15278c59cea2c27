"""The benchmark runs and its output has the expected rows (speed itself is measured by the
benchmark, never asserted in tests: this machine is shared and noisy)."""

import json

import pytest

from jaxoptics.tools.bench import run

pytestmark = pytest.mark.slow  # the quick subset (-m "not slow") leaves this file out


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
              "R and T from one shared graph (two outputs sharing quotients)", "dot of 3-vectors, written out",
              "output floor of refract: (t, tir) from trivial arithmetic",
              "output floor of interface: (r, t, tir, R, T) from trivial arithmetic"):
        assert m in limits, m
    import ctypes.util

    if ctypes.util.find_library("c") and hasattr(ctypes.CDLL(ctypes.util.find_library("c")), "gnu_get_libc_version"):
        for m in ("copy (x * 2), freed memory kept", "fresnel, exact (jaxoptics), freed memory kept",
                  "NumPy textbook fresnel", "NumPy textbook fresnel, freed memory kept"):
            assert m in limits, m
        ratio = {r["use"]: r for r in report["fresnel_vs_naive"]}
        assert set(ratio) == {"on its own (array output)", "consumed by jnp.sum"}
        for r in ratio.values():
            assert r["exact_over_naive"] == r["exact_ns"] / r["naive_ns"] > 0
        assert "Exact fresnel against the naive formula" in text
    assert all(r["run_s"] > 0 for r in report["limits"] if r.get("n"))
    assert all(r["fusions"] >= 1 for r in report["limits"] if r.get("fusions") is not None)
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
    from jaxoptics.tools.bench_kernels import _fusions

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
    # reduced by the caller: the kernel stays one loop feeding the reduction (`unpolarized`); a
    # trailing add and multiply would be taken into the reduction's fusion and cut the kernel into
    # four loops (at sizes where XLA hands reductions to its library fusion: 10^6 here, compiled only)
    big = jnp.linspace(0, 1, 1_000_000, dtype=jnp.float32)
    for name, f in (("sum of fresnel", lambda c: jnp.sum(jo.fresnel(c, 1.5, 1.0))),
                    ("sum of fresnel_rt's R", lambda c: jnp.sum(jo.fresnel_rt(c, 1.5, 1.0)[0]))):
        assert _fusions(jax.jit(f).lower(big).compile()) <= 2, name
    # the unpolarized R of the complex amplitudes: 5 loops (23 with a trailing add and multiply)
    assert _fusions(jax.jit(lambda c: jnp.sum(jo.fresnel_amplitudes(c, 1.5, 1.0).R)).lower(big).compile()) <= 5


def test_fresnel_divides_once_per_polarization():
    """Division is the slowest vector instruction in the Fresnel loop. `fresnel` for a real index
    chooses its forms (rationalized or direct amplitude, or the transmittance) before dividing, so
    its compiled program has two divisions, the textbook formula's count, in one loop; `fresnel_sp`
    has one per output. Pins the structure, not a time (the bench's "What bounds XLA" rows)."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    if jax.default_backend() != "cpu":
        return

    def divisions(f, *args):
        text = jax.jit(f).lower(*args).compile().as_text()
        entry = text.split("ENTRY", 1)[1]
        return text.count(" divide("), entry.count(" fusion(")

    for dt in (jnp.float32, jnp.float64):
        c = jnp.linspace(0, 1, 1000, dtype=dt)
        e = jnp.linspace(1.0, 2.0, 1000, dtype=dt)
        assert divisions(lambda c: jo.fresnel(c, 1.5, 1.0), c) == (2, 1)
        assert divisions(lambda c, e: jo.fresnel(c, e, 1.2), c, e) == (2, 1)
        assert divisions(lambda c, e: jo.fresnel(c, 1.2, e), c, e) == (2, 1)
        assert divisions(lambda c: jo.fresnel_sp(c, 1.0, 1.5)[0], c) == (1, 1)
        assert divisions(lambda c: jo.fresnel_sp(c, 1.0, 1.5)[1], c) == (1, 1)


_FAULTS = """
import ctypes, ctypes.util, resource, sys, jaxoptics as jo
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
applied = None if sys.argv[1] == "default" else jo.keep_freed_memory(enable=sys.argv[1] == "1")
n = 40_000_000  # above glibc's largest mmap threshold (32 MiB): what a 10^7-float32 output is


def cycle():  # what XLA does per call: allocate the output, write it, free it
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    p = libc.malloc(n)
    ctypes.memset(p, 1, n)
    libc.free(p)
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0


print(applied, *[cycle() for _ in range(4)])
"""


def test_keep_freed_memory_reuses_freed_blocks():
    """The mechanism behind the bench's "freed memory kept" rows, counted rather than timed: with
    glibc's defaults every 40 MB block is a fresh mmap, 9,766 page faults of 4 KiB each time it is
    allocated and written; with `keep_freed_memory` the freed block stays mapped and the next one
    reuses it, without a fault. Allocated from one thread with nothing in between, so the count
    is exact (inside XLA other allocations can split a freed block, see `keep_freed_memory`).
    Each case runs in its own process: the setting is process-wide."""
    import ctypes.util
    import subprocess
    import sys

    libc = ctypes.util.find_library("c")
    if not libc or not hasattr(ctypes.CDLL(libc), "gnu_get_libc_version"):
        import jaxoptics as jo

        assert jo.keep_freed_memory(enable=False) is False  # documented: not applied off glibc
        return
    out = {}
    for flag in ("default", "0", "1"):
        res = subprocess.run([sys.executable, "-c", _FAULTS, flag], capture_output=True, text=True, check=True)
        applied, *faults = res.stdout.split()
        out[flag] = (applied, [int(x) for x in faults])
    assert [out[f][0] for f in ("default", "0", "1")] == ["None", "True", "True"], out
    pages = 40_000_000 // 4096
    for flag in ("default", "0"):  # a fresh mapping each time
        assert all(f >= pages for f in out[flag][1]), out
    assert out["1"][1][1:] == [0, 0, 0], out  # after the first (the heap grows), reused


def test_fit_bench_reports_speed_and_scipy_rows(tmp_path):
    """The fit section: every row has its timing, all curves converge, and the table carries the
    speed-up against the scipy loop."""
    report = run(quick=True, sections=("fit",), out_dir=tmp_path)
    rows = report["fit"]
    jx = [r for r in rows if r["method"].startswith("jaxoptics")]
    assert len(jx) >= 3
    for r in jx:
        assert r["run_s"] > 0 and r["per_curve_s"] > 0 and r["converged"] == 1.0, r
    assert any(r["method"].startswith("scipy") and r.get("per_curve_s", 0) > 0 for r in rows)
    text = (tmp_path / "bench.md").read_text()
    assert "| jaxoptics fit_eta (default: Gauss-Newton, LM refit) | 1000 |" in text


def test_stack_bench_section(tmp_path):
    """The stack section measures, in one run, every case (shared and per-point indices,
    reflectances and every output, forward and gradient, both dtypes) with NumPy computing the same
    outputs, tmm and the floor; the kernel agrees with the NumPy transcription on every output
    (rows computing the same thing), and the table and chart are written."""
    import jaxoptics.tools.bench_stack as bs

    rows = bs.bench_stack(quick=True, repeats=1, layers=(2,), N=2000)
    cases = {(r["dtype"], r["indices"], r["outputs"], r["pass_"]) for r in rows}
    assert cases == {(dt, ind, out, p) for dt in ("float64", "float32") for ind in ("shared", "per point")
                     for out, p in (("R", "forward"), ("all", "forward"), ("R", "gradient"))}
    for r in rows:
        assert r["run_s"] > 0 and r["floor_per_point_s"] > 0 and r["tmm_per_point_s"] > 0
        if r["pass_"] == "forward":
            assert r["numpy_per_point_s"] > 0
            assert r["max_abs_diff_vs_numpy"] < (1e-12 if r["dtype"] == "float64" else 1e-4), r
        else:
            assert r["vs_forward"] > 0
    assert bs.flops_per_point(10, "all") > bs.flops_per_point(10, "R") > 10 * 150
    table = bs.stack_table(rows)
    assert "x the forward pass of R" in table and "per point / shared (R)" in table
    bs.stack_chart(rows, tmp_path / "stack.png")
    assert (tmp_path / "stack.png").stat().st_size > 10_000


def test_latency_section(tmp_path):
    """The latency section runs every case in fresh processes and reports each, with the CLI
    rows compared to the SciPy script measured in the same run."""
    from jaxoptics.tools.bench_latency import bench_latency, latency_table

    rows = bench_latency(repeats=1)
    cases = [r["case"] for r in rows]
    assert len(cases) == 11 and cases[0] == "import jaxoptics"
    assert all(r["median_s"] > 0 for r in rows)
    table = latency_table(rows)
    assert table.count("x |") == 4  # the three rows of fit --example and the SciPy row carry a ratio


def test_stackfit_bench_section():
    """The stackfit section fits a map in one call and the scipy loops (NumPy's and pyElli's model)
    on a sample of it, all recovering the truth, and the table carries the ratios measured in the
    same run."""
    from jaxoptics.tools.bench_stack_fit import bench_stack_fit, stack_fit_table

    rows = bench_stack_fit(quick=True, repeats=1)
    effects = [r for r in rows if "effect" in r]
    rows = [r for r in rows if "effect" not in r]
    assert [r["method"].split()[0] for r in rows] == ["jaxoptics", "scipy", "scipy", "scipy"] and "pyElli" in rows[3]["method"]
    for r in rows[:2] + rows[3:]:
        assert r["run_s"] > 0 and r["converged"] == 1.0 and r["recovered"] >= 0.95, r
    # from 100 nm, 380-420 nm from these films, a local fit converges in a wrong fringe
    assert "start 100 nm" in rows[2]["method"] and rows[2]["recovered"] <= 0.5, rows[2]
    text = stack_fit_table(rows + effects)
    assert "| jaxoptics fit_stack, one call (float64) | 500 |" in text and "vs scipy" in text
    # the models of real samples and instruments: the plain model and all three effects (roughness
    # and angle offset free, a bandwidth), each recovering its own data's thickness, priced against
    # the plain model in the same run
    assert [(r["effect"], r["free"]) for r in effects] == [("plain model", 3), ("+ all three", 5)]
    for r in effects:
        assert r["run_s"] > 0 and r["converged"] == 1.0 and r["recovered"] == 1.0, r
    assert "| plain model | 3 |" in text and "| + all three | 5 |" in text and "1.00x" in text
    # scipy's calls of its model per fit include its finite-difference Jacobian's (4 parameters)
    assert rows[1]["median_calls"] >= 5 and all(r["model_eval_s"] > 0 for r in rows)
    assert "One evaluation of the model at a spectrum's 600 points" in text and "a fit would be 100x faster" in text
    # the one-film bound with a hand-derived Jacobian computes what fit_stack's model does
    agree_deg, agree_jac = rows[0]["bound_agree"]
    assert agree_deg < 1e-9 and agree_jac < 1e-9 and rows[0]["bound_jac_eval_s"] > 0 and "A one-film model written" in text
    # pyElli's model is the same to rounding, and its row's time is read against jaxoptics'
    assert rows[3]["agree_deg"] < 1e-9 and rows[3]["median_calls"] >= 5 and "pyElli's to" in text
    assert "the same scipy loop calls it" in text and text.count("x |") == 4 + len(effects)


def test_design_bench_section():
    """The design section refines the same starts with jaxoptics (one call) and scipy (NumPy's and
    tmm's model, one start at a time), whose models agree with jaxoptics', runs the needle example,
    and tabulates time per start and merit reached side by side."""
    from jaxoptics.tools.bench_design import bench_design, design_table

    rows = bench_design(layers=4, sizes=(12, 4, 2, 1))
    agree = rows[-1]
    assert agree["numpy_vs_jaxoptics"] < 1e-12 and agree["tmm_vs_jaxoptics"] < 1e-12 and agree["points"] == 24
    ours, np_row, tmm_row, needle = rows[:4]
    assert ours["starts"] == 4 and len(ours["merits"]) == 4 and ours["first_call"] >= ours["seconds"] > 0
    assert np_row["starts"] == 2 and tmm_row["starts"] == 1 and np_row["per_start"] > 0
    # from the same starts, LM with exact derivatives reaches what scipy's trust region does, or lower
    assert min(ours["merits"][:2]) <= min(np_row["merits"]) * (1 + 1e-3)
    assert needle["rounds"] >= 1 and needle["merit"] < needle["merit_start"] / 3
    text = design_table(rows)
    assert "| jaxoptics design, 4 starts in one call | 4 |" in text and text.count("x slower") == 2 and "Needle synthesis" in text
