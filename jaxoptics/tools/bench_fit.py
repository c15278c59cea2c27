"""The `fit` and `devices` sections of `python -m jaxoptics bench`: index fits of 90-angle curves
against scipy.optimize.least_squares one curve at a time, and the batch fit sharded over devices
(both in subprocesses, which set their own JAX configuration)."""

from __future__ import annotations

import json
import os
import time

import numpy as np

from ._measure import _np_fresnel_unpolarized, timeit

_FIT_SNIPPET = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
from jaxoptics.tools.bench_fit import bench_fit
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
        flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={k}".strip()
        env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")  # the caller's own flags kept
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
