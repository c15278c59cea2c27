"""`python -m jaxoptics bench`: speed measured side by side on this machine.

Conventions of every measurement here: warm-up call first (its time, minus a run, is reported as
compile time), `block_until_ready`, the median over repeats, ratios taken between numbers measured
in the same run.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np


def machine_description() -> str:
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"jax {jax.__version__} ({jax.default_backend()}), numpy {np.__version__}")


def timeit(fn, *, repeats=5, warmup=True, settle=0):
    """(compile_s, median_run_s, all runs): the first call (tracing + compilation + one run) is
    timed apart; compile time is reported as first call minus the median run. `settle` more
    untimed calls follow it (with freed memory kept, each thread's malloc arena grows to its
    working size in the first few calls, and those still page-fault)."""
    import jax

    first = None
    if warmup:
        t = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t
    for _ in range(settle):
        jax.block_until_ready(fn())
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t)
    med = statistics.median(runs)
    return (None if first is None else max(first - med, 0.0)), med, runs


def _np_fresnel_unpolarized(cos_i, eta1, eta2):
    """NumPy transcription of the textbook formula (the peer for scipy's model function)."""
    sin2 = 1 - cos_i**2
    ct2 = 1 - (eta1 / eta2) ** 2 * sin2
    ct = np.sqrt(np.maximum(ct2, 0))
    rs = (eta1 * cos_i - eta2 * ct) / (eta1 * cos_i + eta2 * ct)
    rp = (eta2 * cos_i - eta1 * ct) / (eta2 * cos_i + eta1 * ct)
    return np.where(ct2 < 0, 1.0, 0.5 * (rs * rs + rp * rp))


_FIT_SNIPPET = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
from jaxoptics.tools.bench import bench_fit
class Progress:
    def update(self, n=1):
        print("@@progress", n, flush=True)
print(json.dumps(bench_fit(quick=sys.argv[1] == "1", progress=Progress())))
"""


def bench_fit_in_subprocess(*, quick=False, progress=None):
    """`bench_fit` in a fresh process: glibc's allocator in its default state, whatever ran before.

    The state of glibc's malloc decides whether a call page-faults, and earlier measurements change
    it for good: glibc turns its dynamic mmap threshold off once any mallopt parameter is set (so
    after `keep_freed_memory(enable=False)` every block above 128 KiB is mmapped afresh: a
    10^4-curve fit 48.6 against 20.2 ms, 13,642 faults per call against 0), and the fits'
    long-lived small arrays fragment the arenas so that `keep_freed_memory` then no longer keeps a
    40 MB output (a copy kernel 0.91 against 0.18 ns per element), each measured in a process of
    its own. The full benchmark ran into both before the fits got a process of their own."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", _FIT_SNIPPET, "1" if quick else "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    last = None
    for line in proc.stdout:
        if line.startswith("@@progress"):
            if progress:
                progress.update(int(line.split()[1]))
        elif line.strip():
            last = line
    err = proc.stderr.read()
    if proc.wait() != 0 or last is None:
        raise RuntimeError(f"the fit benchmark's process failed: {err.strip().splitlines()[-1] if err.strip() else '?'}")
    return json.loads(last)


def bench_fit(*, quick=False, progress=None):
    """Batched index fits against scipy.optimize.least_squares one curve at a time."""
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    import jaxoptics as jo

    n_curves = 1000 if quick else 10_000
    n_scipy = 40 if quick else 200
    theta = np.deg2rad(np.linspace(0, 85, 90))
    etas = np.linspace(1.01, 4.0, n_curves)
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(0), jnp.asarray(etas), jnp.asarray(theta), noise=1e-3))
    rows = []
    for name, solver, keep in (
            ("jaxoptics fit_eta (default: Gauss-Newton, LM refit)", None, False),
            ("jaxoptics fit_eta, Gauss-Newton (lineax's default QR solve) only", optx.GaussNewton(rtol=1e-10, atol=1e-10), False),
            ("jaxoptics fit_eta, Levenberg-Marquardt", optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10), False),
            # last: glibc keeps its dynamic mmap threshold off once mallopt has been called (see `run`)
            ("jaxoptics fit_eta (default), freed memory kept (jo.keep_freed_memory)", None, True)):
        if keep and not jo.keep_freed_memory():
            continue
        try:
            comp, run, _ = timeit(lambda: jo.fit_eta(theta, R, solver=solver).eta, repeats=3 if quick else 7,
                                  settle=10 if keep else 0)
        finally:
            if keep:
                jo.keep_freed_memory(enable=False)
        res = jo.fit_eta(theta, R, solver=solver)
        rows.append(dict(method=name, curves=n_curves, compile_s=None if keep else comp, run_s=run, per_curve_s=run / n_curves,
                         converged=float(np.mean(np.asarray(res.converged))),
                         max_steps=int(np.max(np.asarray(res.num_steps))),
                         max_abs_z=float(np.max(np.abs((np.asarray(res.eta) - etas) / np.asarray(res.stderr))))))
        if progress:
            progress.update(1)
    try:
        from scipy.optimize import least_squares
    except ImportError:
        rows.append(dict(method="scipy.optimize.least_squares (not installed: skipped)"))
        return rows
    c = np.cos(theta)
    sel = np.linspace(0, n_curves - 1, n_scipy).astype(int)
    jx = np.asarray(jo.fit_eta(theta, R[sel]).eta)
    for label, opts in (("default method='trf', default tolerances", {}),
                        ("method='lm' (MINPACK), xtol=ftol=1e-10", dict(method="lm", xtol=1e-10, ftol=1e-10))):
        passes = []
        for _ in range(3):  # the median of three passes over the curves
            t = time.perf_counter()
            est = []
            for k in sel:
                s = np.sqrt(np.clip(R[k, 0], 0.0, 0.98))
                x0 = (1 + s) / (1 - s)  # the normal-incidence inversion, a good start
                out = least_squares(lambda x: _np_fresnel_unpolarized(c, 1.0, x[0]) - R[k], [x0], **opts)
                est.append(out.x[0])
            passes.append(time.perf_counter() - t)
        dt = float(np.median(passes))
        rows.append(dict(method=f"scipy.optimize.least_squares ({label}), NumPy model, loop over {n_scipy} of the curves",
                         curves=n_scipy, compile_s=None, run_s=dt, per_curve_s=dt / n_scipy, converged=None, max_steps=None,
                         max_abs_diff_vs_jaxoptics=float(np.max(np.abs(np.asarray(est) - jx)))))
        if progress:
            progress.update(1)
    rows += _bench_fit_complex(quick, theta)
    return rows


def _np_reflectance_complex(c, eta):
    """The textbook unpolarized reflectance of air on n + ik, in NumPy (SciPy's model)."""
    ct = np.sqrt(eta * eta - (1 - c * c) + 0j)
    rs, rp = (c - ct) / (c + ct), (eta * eta * c - ct) / (eta * eta * c + ct)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def _bench_fit_complex(quick, theta):
    """Complex (absorbing) fits of noisy metal curves against SciPy one curve at a time, both
    from a start of their own (SciPy from 1 + 1i)."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    n_curves, n_scipy = (300, 10) if quick else (3000, 40)
    rng = np.random.default_rng(0)
    eta = rng.uniform(0.1, 3.0, n_curves) + 1j * rng.uniform(0.5, 6.0, n_curves)
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(1), jnp.asarray(eta), jnp.asarray(theta), noise=1e-3))
    comp, run, _ = timeit(lambda: jo.fit_eta(theta, R, absorbing=True).eta, repeats=3)
    res = jo.fit_eta(theta, R, absorbing=True)
    rows = [dict(kind="complex", method="jaxoptics fit_eta, absorbing=True (n + ik, metals: n 0.1-3, k 0.5-6)",
                 curves=n_curves, compile_s=comp, run_s=run, per_curve_s=run / n_curves,
                 converged=float(np.mean(np.asarray(res.converged))), max_steps=int(np.max(np.asarray(res.num_steps))))]
    try:
        from scipy.optimize import least_squares
    except ImportError:
        return rows + [dict(kind="complex", method="scipy.optimize.least_squares, complex (not installed: skipped)")]
    c = np.cos(theta)
    sel = np.linspace(0, n_curves - 1, n_scipy).astype(int)
    t = time.perf_counter()
    est = [least_squares(lambda x: _np_reflectance_complex(c, x[0] + 1j * x[1]) - R[k], [1.0, 1.0]).x for k in sel]
    dt = time.perf_counter() - t
    found = np.abs(np.array([e[0] + 1j * abs(e[1]) for e in est]) - np.asarray(res.eta)[sel])
    rows.append(dict(kind="complex", method=f"scipy.optimize.least_squares (default trf, from 1 + 1i), complex NumPy model, "
                     f"loop over {n_scipy} of the curves", curves=n_scipy, compile_s=None, run_s=dt, per_curve_s=dt / n_scipy,
                     converged=None, max_steps=None, agree_with_jaxoptics=float(np.mean(found < 1e-4))))
    return rows


_DEVICE_SNIPPET = """
import json, statistics, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np, jaxoptics as jo
quick = sys.argv[1] == "1"
mesh = jo.batch_mesh()
def med(f, k=5):
    jax.block_until_ready(f()); ts = []
    for _ in range(k):
        t = time.perf_counter(); jax.block_until_ready(f()); ts.append(time.perf_counter() - t)
    return statistics.median(ts)
n = 1_000_000 if quick else 10_000_000
c, _ = jo.shard_batch(jnp.linspace(0.0, 1.0, n, dtype=jnp.float32), mesh=mesh)
f = jax.jit(lambda c: jo.fresnel(c, 1.0, 1.5))
t_k = med(lambda: f(c))
B = 2000 if quick else 10_000
th = np.deg2rad(np.linspace(0, 85, 90))
R = jo.synthetic_reflectance(jax.random.PRNGKey(0), jnp.linspace(1.01, 4.0, B), jnp.asarray(th), noise=1e-3)
Rs, _ = jo.shard_batch(R, mesh=mesh)
t_f = med(lambda: jo.fit_eta(th, Rs).eta, 3)
print(json.dumps(dict(devices=len(jax.devices()), fresnel_elements=n, fresnel_s=t_k, fit_curves=B, fit_s=t_f)))
"""


def bench_devices(*, quick=False, progress=None):
    """Throughput against the number of (forced host) devices, each count in its own process."""
    import subprocess
    import sys

    rows = []
    for k in (1, 2, 4):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={k}", JAX_PLATFORMS="cpu")
        out = subprocess.run([sys.executable, "-c", _DEVICE_SNIPPET, "1" if quick else "0"], env=env,
                             capture_output=True, text=True, timeout=1200)
        if out.returncode != 0:
            rows.append(dict(devices=k, error=out.stderr.strip().splitlines()[-1][:200]))
        else:
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        if progress:
            progress.update(1)
    return rows


def devices_table(rows) -> str:
    base = rows[0]
    out = ["| devices | fresnel float32, sharded (elements/s) | relative | fit_eta float64, sharded (curves/s) | relative |",
           "| ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['devices']} | failed: {r['error']} | | | |")
            continue
        out.append(f"| {r['devices']} | {r['fresnel_elements'] / r['fresnel_s']:.3g} | {base['fresnel_s'] / r['fresnel_s']:.2f}x | "
                   f"{r['fit_curves'] / r['fit_s']:.3g} | {base['fit_s'] / r['fit_s']:.2f}x |")
    return "\n".join(out)


def fit_table(rows) -> str:
    # the speed-up of each row against the first scipy row (default trf) of the same kind of fit
    base: dict = {}
    for r in rows:
        if r["method"].startswith("scipy") and "per_curve_s" in r:
            base.setdefault(r.get("kind", "real"), r)
    out = ["| method | curves | compile (s) | run (s) | per curve (us) | converged | max steps | speed-up vs scipy default (trf) loop |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if "per_curve_s" not in r:
            out.append(f"| {r['method']} | | | | | | | |")
            continue
        b = base.get(r.get("kind", "real"))
        sp = f"{b['per_curve_s'] / r['per_curve_s']:.3g}x" if b else "-"
        comp = "-" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        conv = "-" if r.get("converged") is None else f"{100 * r['converged']:.2f}%"
        steps = "-" if r.get("max_steps") is None else str(r["max_steps"])
        out.append(f"| {r['method']} | {r['curves']} | {comp} | {r['run_s']:.3f} | {1e6 * r['per_curve_s']:.1f} | {conv} | {steps} | {sp} |")
    return "\n".join(out)


def _sections(sections):
    """(name, title, measure, table) of the requested sections after "kernels", in report order."""
    from .bench_latency import bench_latency, latency_table
    from .bench_stack import LAYERS, bench_stack, stack_table
    from .bench_stack_fit import bench_stack_fit, stack_fit_table

    known = [
        ("fit", "Index fits: 90 angles per curve, float64, noise 1e-3", bench_fit_in_subprocess, fit_table),
        ("stack", f"Thin-film stacks: {LAYERS} coherent layers on Si, R and T of s and p, (wavelength, angle) points",
         bench_stack, stack_table),
        ("stackfit", "Film fits over a wafer map: psi/delta, 200 wavelengths x 3 angles per spectrum; thickness and Cauchy "
         "A, B, C free", bench_stack_fit, stack_fit_table),
        ("latency", "Latency: from the command to the answer (fresh processes)", bench_latency, latency_table),
        ("devices", "Sharding over devices (forced host devices sharing this machine's cores)", bench_devices,
         devices_table),
    ]
    return [k for k in known if k[0] in sections]


def run_stamp() -> str:
    """The date and time of a run, UTC, for the tables the tools write."""
    import datetime

    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def run(*, quick=False, sections=("kernels", "fit", "stack", "stackfit", "devices", "latency"), out_dir="bench_out", sizes=None,
        mitsuba=True) -> dict:
    import jax
    from tqdm.auto import tqdm

    jax.config.update("jax_enable_x64", True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine_description(), "quick": quick, "date": run_stamp()}
    cmd = "python -m jaxoptics bench" + (" --quick" if quick else "") + f" --sections {','.join(sections)}"
    md = [f"Measured by `{cmd}` on {report['date']}. Machine: {report['machine']}.", ""]
    total = (6 * ("fit" in sections) + 3 * ("devices" in sections) + 25 * ("kernels" in sections) + 3 * ("stack" in sections) + 5 * ("stackfit" in sections)
             + 9 * ("latency" in sections))
    with tqdm(total=total, desc="bench", unit="step") as bar:
        if "kernels" in sections:
            rows = bench_kernels(quick=quick, progress=bar, sizes=sizes, mitsuba=mitsuba)
            report["kernels"] = rows
            size = max(r["n"] for r in rows if r.get("n"))
            pareto_chart(rows, size, out / "pareto.png")
            md += [f"### Kernels at N = {size:,} (eta1 = 1.5, eta2 = 1: TIR included; median of repeats)", "",
                   kernels_table(rows, size), "", "### Throughput against batch size", "",
                   scaling_table(rows, sorted({r["n"] for r in rows if r.get("n")})), ""]
            lim = bench_limits(quick=quick, progress=bar, n=max(sizes) if sizes else None)
            report["limits"] = lim
            md += [f"### What bounds XLA on the CPU (float32, N = {lim[0]['n']:,})", "", limits_table(lim), ""]
            ratio = bench_fresnel_ratio(quick=quick, progress=bar, n=max(sizes) if sizes else None)
            report["fresnel_vs_naive"] = ratio
            md += [f"### Exact fresnel against the naive formula (float32, N = {ratio[0]['n']:,}, freed memory kept, "
                   f"{ratio[0].get('rounds', 0)} interleaved rounds)", "", fresnel_ratio_table(ratio), ""]
        for name, title, measure, table in _sections(sections):
            rows = measure(quick=quick, progress=bar)
            report[name] = rows
            md += [f"### {title}", "", table(rows), ""]
    text = "\n".join(md)
    (out / "bench.md").write_text(text + "\n")
    (out / "bench.json").write_text(json.dumps(report, indent=2))
    print(text)
    chart = f", {out / 'pareto.png'}" if "kernels" in sections else ""
    print(f"\nwritten: {out / 'bench.md'}, {out / 'bench.json'}{chart}")
    return report


# ---- kernels: speed against error ---------------------------------------------------------------


def _naive_jax_fresnel(c, e1, e2):
    """The textbook formula transcribed directly (the naive peer)."""
    import jax.numpy as jnp

    sin2 = 1 - c * c
    ct2 = 1 - (e1 / e2) ** 2 * sin2
    ct = jnp.sqrt(jnp.maximum(ct2, 0))
    rs = (e1 * c - e2 * ct) / (e1 * c + e2 * ct)
    rp = (e2 * c - e1 * ct) / (e2 * c + e1 * ct)
    return jnp.where(ct2 < 0, 1.0, 0.5 * (rs * rs + rp * rp))


def _guarded_naive_jax_fresnel(c, e1, e2):
    """The textbook formula with the exact kernel's guards and none of its accuracy forms: NaN for
    invalid input, `|cos_i|`, the 0/0 of grazing incidence with `eta1 == eta2`, and a square root
    whose gradient stays finite at the critical angle (the double `where`). Side by side with the
    exact kernel and the bare formula, it splits the exact kernel's extra time into the price of
    the guards and the price of the accurate forms."""
    import jax.numpy as jnp

    c = jnp.abs(c)
    valid = (c < jnp.inf) & (e1 > 0) & (e1 < jnp.inf) & (e2 > 0) & (e2 < jnp.inf)
    ct2 = 1 - (e1 / e2) ** 2 * (1 - c * c)
    ct = jnp.where(ct2 > 0, jnp.sqrt(jnp.maximum(ct2, jnp.finfo(c.dtype).tiny)), 0)
    ds, dp = e1 * c + e2 * ct, e2 * c + e1 * ct
    ok = (ds * ds > 0) & (dp * dp > 0)
    rs = (e1 * c - e2 * ct) / jnp.where(ok, ds, 1)
    rp = (e2 * c - e1 * ct) / jnp.where(ok, dp, 1)
    R = jnp.where(ok, jnp.where(ct2 < 0, 1.0, 0.5 * (rs * rs + rp * rp)), jnp.where(e1 > e2, 1.0, 0.0))
    return jnp.where(valid, R, jnp.nan)


def _schlick_pow(c, e1, e2):
    import jax.numpy as jnp

    r0 = ((e1 - e2) / (e1 + e2)) ** 2
    return r0 + (1 - r0) * jnp.power(1 - c, jnp.asarray(5.0, c.dtype))


def _mitsuba():
    try:
        if "DRJIT_LIBLLVM_PATH" not in os.environ:
            for cand in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/aarch64-linux-gnu/libLLVM-19.so"):
                if os.path.exists(cand):
                    os.environ["DRJIT_LIBLLVM_PATH"] = cand
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        return mi, dr
    except Exception as e:  # noqa: BLE001 - the peer is optional; say why it was skipped
        return None, f"{type(e).__name__}: {str(e)[:100]}"


def _fresnel_reference(c, e1, e2):
    from . import mpref as _mpref

    out = []
    for x in c:
        d = _mpref.fresnel_ref(_mpref.mpf(x), _mpref.mpf(e1), _mpref.mpf(e2))
        out.append(float((d["R_s"] + d["R_p"]) / 2))
    return np.asarray(out)


def _schlick_reference(c, e1, e2):
    r0 = ((e1 - e2) / (e1 + e2)) ** 2
    return r0 + (1 - r0) * (1 - c.astype(np.float64)) ** 5


def bench_kernels(*, quick=False, progress=None, sizes=None, mitsuba=True, repeats=None):
    """Throughput and error of every Fresnel model and refraction method, float32 and float64,
    side by side with NumPy, a naive JAX transcription and Mitsuba 3, plus a copy kernel."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    sizes = sizes or ((1_000, 100_000, 1_000_000) if quick else (1_000, 100_000, 10_000_000))
    repeats = repeats or (3 if quick else 7)
    e1, e2 = 1.5, 1.0  # leaving glass: the critical angle and TIR are in the sweep
    rows = []
    rng = np.random.default_rng(0)
    sample = rng.uniform(0, 1, 400)
    ref_exact = _fresnel_reference(sample, e1, e2)
    ref_schlick = _schlick_reference(sample, e1, e2)
    models = {
        "fresnel, exact (jaxoptics)": (lambda c: jo.fresnel(c, e1, e2), ref_exact),
        "naive JAX textbook fresnel": (lambda c: _naive_jax_fresnel(c, e1, e2), ref_exact),
        "schlick, multiplications (jaxoptics)": (lambda c: jo.schlick(c, e1, e2), ref_exact),
        "schlick, pow": (lambda c: _schlick_pow(c, e1, e2), ref_exact),
        "schlick_tir (jaxoptics)": (lambda c: jo.schlick_tir(c, e1, e2), ref_exact),
        "copy (x * 2), the memory-bound limit": (lambda c: c * 2, None),
    }
    for dtype in (np.float32, np.float64):
        for name, (f, ref) in models.items():
            fj = jax.jit(f)
            err = {}
            if ref is not None:
                got = np.asarray(fj(jnp.asarray(sample.astype(dtype))), np.float64)
                err = dict(max_err=float(np.max(np.abs(got - ref))), mean_err=float(np.mean(np.abs(got - ref))))
                if "schlick" in name:  # its error against its own formula too (numerical stability)
                    err["max_err_vs_own_formula"] = float(np.max(np.abs(got - ref_schlick))) if "tir" not in name else None
            for N in sizes:
                c = jnp.asarray(rng.uniform(0, 1, N).astype(dtype))
                comp, run, _ = timeit(lambda: fj(c), repeats=repeats)
                rows.append(dict(group="fresnel", method=name, dtype=np.dtype(dtype).name, n=N, compile_s=comp, run_s=run,
                                 ns_per_element=1e9 * run / N, bytes_per_element=2 * np.dtype(dtype).itemsize, **err))
            if progress:
                progress.update(1)
        # NumPy peer (the same textbook formula)
        err_np = np.asarray(_np_fresnel_unpolarized(sample.astype(dtype), dtype(e1), dtype(e2)), np.float64)
        for N in sizes:
            c = rng.uniform(0, 1, N).astype(dtype)
            comp, run, _ = timeit(lambda: _np_fresnel_unpolarized(c, dtype(e1), dtype(e2)), repeats=repeats, warmup=True)
            rows.append(dict(group="fresnel", method="NumPy textbook fresnel", dtype=np.dtype(dtype).name, n=N, compile_s=None,
                             run_s=run, ns_per_element=1e9 * run / N, max_err=float(np.max(np.abs(err_np - ref_exact))),
                             mean_err=float(np.mean(np.abs(err_np - ref_exact)))))
        # gradients with respect to the index: reverse mode (of the sum) and forward mode (per element)
        for mode in ("jax.grad", "forward mode (jvp)"):
            if mode == "jax.grad":
                g = jax.jit(jax.grad(lambda e, c: jnp.sum(jo.fresnel(c, e1, e))))
                call = lambda c: g(jnp.asarray(e2, dtype), c)
            else:
                g = jax.jit(lambda e, c: jax.jvp(lambda e: jo.fresnel(c, e1, e), (e,), (jnp.ones_like(e),))[1])
                e_full = {}  # the per-element index is made once per size, outside the timed region
                call = lambda c: g(e_full.setdefault(c.shape, jnp.full(c.shape, e2, dtype)), c)
            for N in sizes:
                c = jnp.asarray(rng.uniform(0, 1, N).astype(dtype))
                comp, run, _ = timeit(lambda: call(c), repeats=repeats)
                rows.append(dict(group="gradient", method=f"d fresnel / d eta2, {mode}", dtype=np.dtype(dtype).name, n=N,
                                 compile_s=comp, run_s=run, ns_per_element=1e9 * run / N))
        if progress:
            progress.update(1)
        # refraction methods (vectors)
        th = rng.uniform(0, np.pi / 2, 300)
        iv = np.stack([np.sin(th), np.zeros_like(th), -np.cos(th)], -1)
        nz = np.array([0.0, 0.0, 1.0])
        from . import mpref as _mpref

        ref_t = np.array([[float(v) for v in _mpref.refract_ref([_mpref.mpf(x) for x in row], [_mpref.mpf(0), _mpref.mpf(0), _mpref.mpf(1)],
                                                                _mpref.mpf(e1), _mpref.mpf(e2))[0]] for row in iv.astype(dtype)])
        for method in ("degreve", "bec", "heckbert", "oliveira"):
            f = jax.jit(lambda i, m=method: jo.refract(i, jnp.asarray(nz, dtype), e1, e2, method=m).t)
            got = np.asarray(f(jnp.asarray(iv.astype(dtype))), np.float64)
            d = np.max(np.abs(got - ref_t), axis=1)
            for N in sizes:
                t_ = rng.uniform(0, np.pi / 2, N)
                i = jnp.asarray(np.stack([np.sin(t_), np.zeros_like(t_), -np.cos(t_)], -1).astype(dtype))
                comp, run, _ = timeit(lambda: f(i), repeats=repeats)
                rows.append(dict(group="refract", method=f"refract, {method}", dtype=np.dtype(dtype).name, n=N, compile_s=comp,
                                 run_s=run, ns_per_element=1e9 * run / N, max_err=float(np.max(d)), mean_err=float(np.mean(d)),
                                 bytes_per_element=6 * np.dtype(dtype).itemsize))
        if progress:
            progress.update(1)
        # scene specializations of the fused kernel, against the separate kernels
        specs = {
            "interface, full (r, t, tir, R, T)": jo.InterfaceSpec(),
            "interface, R only": jo.InterfaceSpec(outputs=("R",)),
            "interface, R only, no input checks": jo.InterfaceSpec(outputs=("R",), check_inputs=False),
            "interface, t and R, schlick, no TIR": jo.InterfaceSpec(outputs=("t", "R"), fresnel="schlick", tir_possible=False),
            "separate: refract": None,
            "separate: fresnel_rt of |i.n|": None,
            "separate: fresnel of |i.n| (R only)": None,
            "separate: reflect": None,
        }
        for name, spec in specs.items():
            if spec is not None:
                f = jax.jit(lambda i, s=spec: jo.interface(i, jnp.asarray(nz, dtype), e1, e2, spec=s))
            elif "refract" in name:
                f = jax.jit(lambda i: jo.refract(i, jnp.asarray(nz, dtype), e1, e2))
            elif "fresnel_rt" in name:
                f = jax.jit(lambda i: jo.fresnel_rt(jnp.abs(i[..., 2]), e1, e2))
            elif "fresnel of" in name:
                f = jax.jit(lambda i: jo.fresnel(jnp.abs(i[..., 2]), e1, e2))
            else:
                f = jax.jit(lambda i: jo.reflect(i, jnp.asarray(nz, dtype)))
            N = sizes[-1]
            t_ = rng.uniform(0, np.pi / 2, N)
            i = jnp.asarray(np.stack([np.sin(t_), np.zeros_like(t_), -np.cos(t_)], -1).astype(dtype))
            comp, run, _ = timeit(lambda: f(i), repeats=repeats)
            rows.append(dict(group="scene", method=name, dtype=np.dtype(dtype).name, n=N, compile_s=comp, run_s=run,
                             ns_per_element=1e9 * run / N))
        if progress:
            progress.update(1)
    # Mitsuba 3 (float32 only: its llvm_ad_rgb variant)
    mi, dr = _mitsuba() if mitsuba else (None, "not requested")
    if mi is None:
        rows.append(dict(group="fresnel", method=f"Mitsuba 3 fresnel (skipped: {dr})", dtype="float32", n=0))
    else:
        got = np.asarray(mi.fresnel(mi.Float(sample.astype(np.float32)), mi.Float(e2 / e1))[0], np.float64)
        err = dict(max_err=float(np.max(np.abs(got - ref_exact))), mean_err=float(np.mean(np.abs(got - ref_exact))))
        for N in sizes:
            c = mi.Float(rng.uniform(0, 1, N).astype(np.float32))
            eta = mi.Float(e2 / e1)

            def mitsuba_call(c=c, eta=eta):
                r = mi.fresnel(c, eta)[0]
                dr.eval(r)
                dr.sync_thread()

            comp, run, _ = timeit(mitsuba_call, repeats=repeats)
            rows.append(dict(group="fresnel", method="Mitsuba 3 fresnel (Dr.Jit LLVM)", dtype="float32", n=N, compile_s=comp,
                             run_s=run, ns_per_element=1e9 * run / N, **err))
    if progress:
        progress.update(1)
    return rows


def _fusions(compiled) -> int:
    """Number of fused loops XLA emitted for a compiled program (each reads and writes memory)."""
    text = compiled.as_text()
    entry = text.split("ENTRY", 1)[1] if "ENTRY" in text else text
    return entry.count(" fusion(")


def bench_limits(*, quick=False, progress=None, n=None):
    """What bounds XLA on the CPU, measured (float32, one size): output allocation (the same
    kernels with the input buffer donated, so no fresh output pages are touched), the fusion split
    of a kernel with two outputs sharing divisions and square roots, and a reduction over a
    length-3 minor axis against the same dot product written out. Fresh inputs are made for every
    donated call, outside the timed region."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    N = n or (1_000_000 if quick else 10_000_000)
    repeats = 3 if quick else 7
    e1, e2 = 1.5, 1.0
    rng = np.random.default_rng(1)
    base = rng.uniform(0, 1, N).astype(np.float32)
    rows = []

    def run_rows(name, f, donate, arg, suffix=""):
        fj = jax.jit(f, donate_argnums=0) if donate else jax.jit(f)
        inputs = [jnp.array(arg) for _ in range(repeats + 1)] if donate else None
        compiled = fj.lower(arg).compile()
        if donate:
            jax.block_until_ready(inputs)
            it = iter(inputs)
            comp, run, _ = timeit(lambda: compiled(next(it)), repeats=repeats)
        else:
            comp, run, _ = timeit(lambda: compiled(arg), repeats=repeats, settle=10 if suffix else 0)
        rows.append(dict(group="limits", method=name + (", input donated" if donate else "") + suffix, dtype="float32", n=N,
                         compile_s=comp, run_s=run, ns_per_element=1e9 * run / N, fusions=_fusions(compiled)))

    def numpy_row(suffix):
        comp, run, _ = timeit(lambda: _np_fresnel_unpolarized(base, np.float32(e1), np.float32(e2)), repeats=repeats,
                              warmup=True, settle=10 if suffix else 0)
        rows.append(dict(group="limits", method="NumPy textbook fresnel" + suffix, dtype="float32", n=N, compile_s=None,
                         run_s=run, ns_per_element=1e9 * run / N, fusions=None))

    c = jnp.asarray(base)
    kernels = (("copy (x * 2)", lambda c: c * 2),
               ("fresnel, exact (jaxoptics)", lambda c: jo.fresnel(c, e1, e2)),
               ("naive JAX textbook fresnel", lambda c: _naive_jax_fresnel(c, e1, e2)),
               ("naive JAX textbook fresnel with the exact kernel's guards", lambda c: _guarded_naive_jax_fresnel(c, e1, e2)))
    for name, f in kernels:
        for donate in (False, True):
            run_rows(name, f, donate, c)
        if progress:
            progress.update(1)
    numpy_row("")
    # the kernels as part of a caller's program: reduced (a loss, a radiance sum), where XLA fuses
    # the kernel's loop into the reduction
    consumers = (("fresnel, exact (jaxoptics), consumed by jnp.sum", lambda c: jnp.sum(jo.fresnel(c, e1, e2))),
                 ("naive JAX textbook fresnel, consumed by jnp.sum", lambda c: jnp.sum(_naive_jax_fresnel(c, e1, e2))),
                 ("naive JAX textbook fresnel with the exact kernel's guards, consumed by jnp.sum",
                  lambda c: jnp.sum(_guarded_naive_jax_fresnel(c, e1, e2))))
    for name, f in consumers:
        run_rows(name, f, False, c)
    # the fused interface kernel against its most expensive part (vector outputs: 3x the bytes)
    t_ = rng.uniform(0, np.pi / 2, N)
    iv = jnp.asarray(np.stack([np.sin(t_), np.zeros_like(t_), -np.cos(t_)], -1).astype(np.float32))
    nz = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    # and the floor under each: the same output arrays from trivial arithmetic (XLA on the CPU
    # writes each output in a loop of its own, reading the inputs again)
    vector_kernels = (("refract (degreve)", lambda i: jo.refract(i, nz, e1, e2)),
                      ("interface, full (r, t, tir, R, T)", lambda i: jo.interface(i, nz, e1, e2, spec=jo.InterfaceSpec())),
                      ("output floor of refract: (t, tir) from trivial arithmetic",
                       lambda i: (i * 2 + nz[None, :], i[..., 0] > i[..., 2])),
                      ("output floor of interface: (r, t, tir, R, T) from trivial arithmetic",
                       lambda i: (i * 2 + nz[None, :], i - nz[None, :], i[..., 0] > i[..., 2], i[..., 0] * i[..., 2],
                                  i[..., 1] * i[..., 2])))
    for name, f in vector_kernels:
        run_rows(name, f, False, iv)
    from .._fresnel import _sp_rt

    def shared_rt(c):  # R and T from one graph: the quotients both need feed two outputs
        R_s, R_p, T_s, T_p = _sp_rt(c, jnp.full_like(c, e1), jnp.full_like(c, e2))
        return 0.5 * (R_s + R_p), 0.5 * (T_s + T_p)

    run_rows("R and T from one shared graph (two outputs sharing quotients)", shared_rt, False, c)
    run_rows("the same, consumed as 0.3 R + 0.7 T (one output)", lambda c: (lambda R, T: 0.3 * R + 0.7 * T)(*shared_rt(c)), False, c)
    run_rows("jo.fresnel_rt (R and T as two loops)", lambda c: jo.fresnel_rt(c, e1, e2), False, c)
    v = jnp.asarray(np.stack([base, 1 - base, base * 0.5], -1))
    w = jnp.asarray(np.array([0.2, 0.3, 0.5], np.float32))
    run_rows("dot of 3-vectors, jnp.sum(a * b, axis=-1)", lambda v: jnp.sum(v * w[None, :], axis=-1), False, v)
    run_rows("dot of 3-vectors, written out", lambda v: v[..., 0] * w[0] + v[..., 1] * w[1] + v[..., 2] * w[2], False, v)
    # The same with freed memory kept mapped (glibc mallopt, `jo.keep_freed_memory`): no page
    # faults on fresh output buffers, for JAX and NumPy alike. Last: glibc's values are restored
    # after, but not its dynamic mmap threshold (see `run`).
    if jo.keep_freed_memory():
        try:
            for name, f in kernels:
                run_rows(name, f, False, c, ", freed memory kept")
            run_rows("jo.fresnel_rt (R and T as two loops)", lambda c: jo.fresnel_rt(c, e1, e2),
                     False, c, ", freed memory kept")
            for name, f in consumers:
                run_rows(name, f, False, c, ", freed memory kept")
            numpy_row(", freed memory kept")
            for name, f in vector_kernels:
                run_rows(name, f, False, iv, ", freed memory kept")
        finally:
            jo.keep_freed_memory(enable=False)
    else:
        rows.append(dict(group="limits", method="freed memory kept: not available (not glibc), skipped", n=0))
    if progress:
        progress.update(2)
    return rows


def bench_fresnel_ratio(*, quick=False, progress=None, n=None, rounds=None):
    """The exact `fresnel` against the naive transcription of the textbook formula, as a kernel on
    its own (an array output) and consumed by a reduction (`jnp.sum`), float32, with freed memory
    kept (so page faults on fresh outputs do not dilute the difference). The kernels are timed in
    interleaved rounds (exact, naive, naive with the exact kernel's guards; again and again), so a
    drift of the machine's speed reaches all of them alike; each kernel's time is the median over
    its rounds, and the ratios are taken between those medians."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    N = n or (1_000_000 if quick else 10_000_000)
    rounds = rounds or (2 if quick else 5)
    e1, e2 = 1.5, 1.0
    c = jnp.asarray(np.random.default_rng(2).uniform(0, 1, N).astype(np.float32))
    forms = {"exact": lambda c: jo.fresnel(c, e1, e2), "naive": lambda c: _naive_jax_fresnel(c, e1, e2),
             "guarded": lambda c: _guarded_naive_jax_fresnel(c, e1, e2)}
    uses = {"on its own (array output)": lambda f: f, "consumed by jnp.sum": lambda f: lambda c: jnp.sum(f(c))}
    if not jo.keep_freed_memory():
        return [dict(use="freed memory kept: not available (not glibc), skipped", n=0)]
    try:
        compiled = {(u, k): jax.jit(wrap(f)).lower(c).compile() for u, wrap in uses.items() for k, f in forms.items()}
        times: dict = {key: [] for key in compiled}
        for _ in range(rounds):
            for key, fn in compiled.items():
                times[key].append(timeit(lambda fn=fn: fn(c), repeats=7, settle=3)[1])
    finally:
        jo.keep_freed_memory(enable=False)
    rows = []
    for u in uses:
        ns = {k: 1e9 * statistics.median(times[(u, k)]) / N for k in forms}
        rows.append(dict(use=u, n=N, rounds=rounds, exact_ns=ns["exact"], naive_ns=ns["naive"], guarded_ns=ns["guarded"],
                         exact_over_naive=ns["exact"] / ns["naive"], guarded_over_naive=ns["guarded"] / ns["naive"]))
    if progress:
        progress.update(1)
    return rows


def fresnel_ratio_table(rows) -> str:
    out = ["| use | exact (ns/element) | naive (ns/element) | naive with the guards (ns/element) | exact / naive "
           "| guarded / naive |", "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if not r.get("n"):
            out.append(f"| {r['use']} | | | | | |")
            continue
        out.append(f"| {r['use']} | {r['exact_ns']:.3g} | {r['naive_ns']:.3g} | {r['guarded_ns']:.3g} "
                   f"| {r['exact_over_naive']:.2f}x | {r['guarded_over_naive']:.2f}x |")
    return "\n".join(out)


def limits_table(rows) -> str:
    out = ["| what | elements/s | ns/element | XLA fused loops |", "| --- | ---: | ---: | ---: |"]
    for r in rows:
        if not r.get("n"):
            out.append(f"| {r['method']} | | | |")
            continue
        fus = "" if r.get("fusions") is None else r["fusions"]
        out.append(f"| {r['method']} | {r['n'] / r['run_s']:.3g} | {r['ns_per_element']:.3g} | {fus} |")
    return "\n".join(out)


def kernels_table(rows, size) -> str:
    out = ["| group | method | dtype | elements/s | ns/element | compile (s) | max error | mean error | GB/s |",
           "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if r.get("n") != size:
            if r.get("n") == 0:
                out.append(f"| {r['group']} | {r['method']} | {r['dtype']} | | | | | | |")
            continue
        eps = r["n"] / r["run_s"]
        gbs = f"{r['bytes_per_element'] * eps / 1e9:.1f}" if r.get("bytes_per_element") else ""
        comp = "" if r.get("compile_s") is None else f"{r['compile_s']:.2f}"
        me = "" if r.get("max_err") is None else f"{r['max_err']:.2e}"
        mn = "" if r.get("mean_err") is None else f"{r['mean_err']:.2e}"
        out.append(f"| {r['group']} | {r['method']} | {r['dtype']} | {eps:.3g} | {r['ns_per_element']:.3g} | {comp} | {me} | {mn} | {gbs} |")
    return "\n".join(out)


def scaling_table(rows, sizes) -> str:
    head = "| method | dtype | " + " | ".join(f"N = {n:.0e}" for n in sizes) + " |"
    out = [head, "| --- | --- | " + " | ".join("---:" for _ in sizes) + " |"]
    keys = []
    for r in rows:
        k = (r["method"], r["dtype"])
        if r.get("n") and r["group"] in ("fresnel", "refract", "gradient") and k not in keys:
            keys.append(k)
    for k in keys:
        cells = []
        for n in sizes:
            m = [r for r in rows if (r["method"], r["dtype"]) == k and r.get("n") == n]
            cells.append(f"{n / m[0]['run_s']:.3g}/s" if m else "")
        out.append(f"| {k[0]} | {k[1]} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def pareto_chart(rows, size, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 6))
    markers = {"float32": "o", "float64": "s"}
    for r in rows:
        if r.get("n") != size or r.get("max_err") is None or r["group"] not in ("fresnel", "refract"):
            continue
        err = max(r["max_err"], 1e-17)
        color = "C0" if "jaxoptics" in r["method"] or r["group"] == "refract" else ("C3" if "Mitsuba" in r["method"] else "C1")
        ax.scatter(r["ns_per_element"], err, marker=markers[r["dtype"]], color=color, s=40)
        ax.annotate(f"{r['method'].replace(' (jaxoptics)', '')} [{r['dtype'][-2:]}]", (r["ns_per_element"], err),
                    fontsize=6.5, xytext=(4, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"time per element (ns), N = {size:,}")
    ax.set_ylabel("max abs error against 50-digit mpmath")
    ax.set_title("Speed against error (lower left is better); circles float32, squares float64")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
