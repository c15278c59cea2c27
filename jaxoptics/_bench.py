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


def timeit(fn, *, repeats=5, warmup=True):
    """(compile_s, median_run_s, all runs): the first call (tracing + compilation + one run) is
    timed apart; compile time is reported as first call minus the median run."""
    import jax

    first = None
    if warmup:
        t = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t
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
    for name, solver in (("jaxoptics fit_eta (default: Gauss-Newton, LM refit)", None),
                         ("jaxoptics fit_eta, Gauss-Newton only", optx.GaussNewton(rtol=1e-10, atol=1e-10)),
                         ("jaxoptics fit_eta, Levenberg-Marquardt", optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10))):
        comp, run, _ = timeit(lambda: jo.fit_eta(theta, R, solver=solver).eta, repeats=3 if quick else 5)
        res = jo.fit_eta(theta, R, solver=solver)
        rows.append(dict(method=name, curves=n_curves, compile_s=comp, run_s=run, per_curve_s=run / n_curves,
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
        t = time.perf_counter()
        est = []
        for k in sel:
            s = np.sqrt(np.clip(R[k, 0], 0.0, 0.98))
            x0 = (1 + s) / (1 - s)  # the normal-incidence inversion, a good start
            out = least_squares(lambda x: _np_fresnel_unpolarized(c, 1.0, x[0]) - R[k], [x0], **opts)
            est.append(out.x[0])
        dt = time.perf_counter() - t
        rows.append(dict(method=f"scipy.optimize.least_squares ({label}), NumPy model, loop over {n_scipy} of the curves",
                         curves=n_scipy, compile_s=None, run_s=dt, per_curve_s=dt / n_scipy, converged=None, max_steps=None,
                         max_abs_diff_vs_jaxoptics=float(np.max(np.abs(np.asarray(est) - jx)))))
        if progress:
            progress.update(1)
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
print(json.dumps(dict(devices=len(jax.devices()), fresnel_elements=n, fresnel_s=t_k)))
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
    out = ["| devices | fresnel float32, sharded (elements/s) | relative to 1 device |",
           "| ---: | ---: | ---: |"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['devices']} | failed: {r['error']} | |")
            continue
        out.append(f"| {r['devices']} | {r['fresnel_elements'] / r['fresnel_s']:.3g} | {base['fresnel_s'] / r['fresnel_s']:.2f}x |")
    return "\n".join(out)


def fit_table(rows) -> str:
    base = next((r for r in rows if r["method"].startswith("scipy") and "per_curve_s" in r), None)  # default trf
    out = ["| method | curves | compile (s) | run (s) | per curve (us) | converged | max steps | speed-up vs scipy default (trf) loop |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if "per_curve_s" not in r:
            out.append(f"| {r['method']} | | | | | | | |")
            continue
        sp = f"{base['per_curve_s'] / r['per_curve_s']:.3g}x" if base else "-"
        comp = "-" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        conv = "-" if r.get("converged") is None else f"{100 * r['converged']:.2f}%"
        steps = "-" if r.get("max_steps") is None else str(r["max_steps"])
        out.append(f"| {r['method']} | {r['curves']} | {comp} | {r['run_s']:.3f} | {1e6 * r['per_curve_s']:.1f} | {conv} | {steps} | {sp} |")
    return "\n".join(out)


def run(*, quick=False, sections=("fit",), out_dir="bench_out") -> dict:
    from tqdm.auto import tqdm

    import jax

    jax.config.update("jax_enable_x64", True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine_description(), "quick": quick}
    md = [f"Machine: {report['machine']}", ""]
    with tqdm(total=5 * ("fit" in sections) + 3 * ("devices" in sections), desc="bench", unit="step") as bar:
        if "fit" in sections:
            rows = bench_fit(quick=quick, progress=bar)
            report["fit"] = rows
            md += ["### Index fits: 90 angles per curve, float64, noise 1e-3", "", fit_table(rows), ""]
        if "devices" in sections:
            rows = bench_devices(quick=quick, progress=bar)
            report["devices"] = rows
            md += ["### Sharding over devices (forced host devices sharing this machine's cores)", "",
                   devices_table(rows), ""]
    text = "\n".join(md)
    (out / "bench.md").write_text(text + "\n")
    (out / "bench.json").write_text(json.dumps(report, indent=2))
    print(text)
    print(f"\nwritten: {out / 'bench.md'}, {out / 'bench.json'}")
    return report
