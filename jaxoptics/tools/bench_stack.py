"""The `stack` section of `python -m jaxoptics bench`: a 10-layer coherent stack over (wavelength,
angle) points, against tmm in a Python loop and a vectorized NumPy transfer-matrix baseline.

All three compute R and T of both polarizations of the same stack at the same points, measured
in one run: medians over repeats, the first call's extra time reported as compile time.
"""

from __future__ import annotations

import time

import numpy as np

from ._measure import timeit

LAYERS = 10


def example_stack(dtype=np.float64):
    """A 10-layer coherent stack on silicon: alternating TiO2/SiO2-like films, one absorbing."""
    rng = np.random.default_rng(0)
    inner = np.where(np.arange(LAYERS) % 2 == 0, 2.35, 1.46) + 0j
    inner[3] = 2.0 + 0.05j  # a weakly absorbing film
    n = np.r_[1.0, inner, 3.9 + 0.02j]
    d = rng.uniform(40, 160, LAYERS)
    cdt = np.complex128 if dtype == np.float64 else np.complex64
    return n.astype(cdt), d.astype(dtype)


def points(N, dtype=np.float64):
    """N (wavelength, cos_i) points on a grid (N a multiple of 1000): 400-800 nm, 0-80 degrees."""
    wl, th = np.meshgrid(np.linspace(400, 800, N // 1000), np.deg2rad(np.linspace(0, 80, 1000)), indexing="ij")
    return wl.ravel().astype(dtype), np.cos(th.ravel()).astype(dtype)


def numpy_tmm(n, d, wl, cos_i):
    """Plain vectorized transfer matrices (characteristic matrices, one per layer, as a textbook
    would write them in NumPy) over all points at once: R and T of s and p."""
    s2 = (n[0].real ** 2) * (1 - cos_i**2)
    kz = [np.sqrt(n[j] ** 2 - s2 + 0j).astype(n.dtype) for j in range(len(n))]
    kz = [np.where(k.imag < 0, -k, k) for k in kz]
    out = []
    for pol in "sp":
        eta = [k if pol == "s" else n[j] ** 2 / k for j, k in enumerate(kz)]
        m11 = np.ones_like(kz[0])
        m12 = np.zeros_like(kz[0])
        m21 = np.zeros_like(kz[0])
        m22 = np.ones_like(kz[0])
        for j in range(1, len(n) - 1):
            dl = 2 * np.pi * d[j - 1] / wl * kz[j]
            c, s = np.cos(dl), np.sin(dl)
            a11, a12, a21 = c, -1j * s / eta[j], -1j * eta[j] * s
            m11, m12, m21, m22 = (m11 * a11 + m12 * a21, m11 * a12 + m12 * c, m21 * a11 + m22 * a21, m21 * a12 + m22 * c)
        B = m11 + m12 * eta[-1]
        C = m21 + m22 * eta[-1]
        D = eta[0] * B + C
        r = (eta[0] * B - C) / D
        R = np.abs(r) ** 2
        T = 4 * eta[0].real * eta[-1].real / np.abs(D) ** 2
        out += [R, T]
    return out[0], out[2], out[1], out[3]  # R_s, R_p, T_s, T_p


def bench_stack(*, quick=False, progress=None, repeats=None):
    import jax
    import jax.numpy as jnp
    import tmm

    import jaxoptics as jo

    N = 100_000 if quick else 1_000_000
    reps = repeats or (3 if quick else 5)
    rows = []

    # tmm, one point at a time (s and p), over a sample of the points
    n64, d64 = example_stack()
    wl, c = points(N)
    K = 100 if quick else 400
    idx = np.linspace(0, len(c) - 1, K).astype(int)
    dl = [np.inf] + list(d64) + [np.inf]
    runs = []
    for _ in range(3):
        t = time.perf_counter()
        for i in idx:
            th = np.arccos(c[i])
            tmm.coh_tmm("s", n64, dl, th, wl[i])
            tmm.coh_tmm("p", n64, dl, th, wl[i])
        runs.append((time.perf_counter() - t) / K)
    per_tmm = float(np.median(runs))
    rows.append(dict(method="tmm (Python loop, per point)", dtype="float64", points=K, compile_s=None,
                     run_s=per_tmm * K, per_point_s=per_tmm))
    if progress:
        progress.update(1)

    for dtype in (np.float64, np.float32):
        n, d = example_stack(dtype)
        wl, c = points(N, dtype)
        name = np.dtype(dtype).name
        _, t_np, _ = timeit(lambda: numpy_tmm(n, d, wl, c), repeats=max(3, reps - 2), warmup=True)
        rows.append(dict(method="NumPy vectorized transfer matrices", dtype=name, points=len(c), compile_s=None, run_s=t_np,
                         per_point_s=t_np / len(c)))
        jn, jd, jw, jc = (jnp.asarray(x) for x in (n, d, wl, c))
        f = jax.jit(lambda n, d, w, c: (lambda r: (r.R_s, r.R_p, r.T_s, r.T_p))(jo.stack(n, d, w, c)))
        comp, t_f, _ = timeit(lambda: f(jn, jd, jw, jc), repeats=reps)
        fwd_row = dict(method="jaxoptics.stack (R, T; s and p)", dtype=name, points=len(c), compile_s=comp,
                       run_s=t_f, per_point_s=t_f / len(c))
        rows.append(fwd_row)
        g = jax.jit(jax.grad(lambda n, d, w, c: jnp.sum(jo.stack(n, d, w, c).R), argnums=(0, 1)))
        comp_g, t_g, _ = timeit(lambda: g(jn, jd, jw, jc), repeats=reps)
        rows.append(dict(method="grad of sum(R) w.r.t. every n, k and d", dtype=name, points=len(c),
                         compile_s=comp_g, run_s=t_g, per_point_s=t_g / len(c), vs_forward=t_g / t_f))
        # a loss whose cotangent depends on R (so the gradient needs R's values: a forward pass more)
        R_data = 0.9 * f(jn, jd, jw, jc)[0]
        h = jax.jit(jax.grad(lambda n, d, w, c: jnp.sum((jo.stack(n, d, w, c).R - R_data) ** 2), argnums=(0, 1)))
        comp_h, t_h, _ = timeit(lambda: h(jn, jd, jw, jc), repeats=reps)
        rows.append(dict(method="grad of sum((R - R_data)^2) w.r.t. every n, k and d", dtype=name, points=len(c),
                         compile_s=comp_h, run_s=t_h, per_point_s=t_h / len(c), vs_forward=t_h / t_f))
        # agreement with the NumPy baseline (a check that the rows compute the same thing)
        ref = numpy_tmm(n, d, wl, c)
        got = f(jn, jd, jw, jc)
        fwd_row["max_abs_diff_vs_numpy"] = float(max(np.max(np.abs(np.asarray(a) - b)) for a, b in zip(got, ref)))
        if progress:
            progress.update(1)
    return rows


def stack_table(rows) -> str:
    tmm_row = rows[0]
    np_rows = {r["dtype"]: r for r in rows if r["method"].startswith("NumPy")}
    out = ["| method | dtype | points | compile (s) | run (s) | per point (ns) | vs tmm | vs NumPy | notes |",
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in rows:
        comp = "-" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        vt = f"{tmm_row['per_point_s'] / r['per_point_s']:.3g}x"
        b = np_rows.get(r["dtype"])
        vn = f"{b['per_point_s'] / r['per_point_s']:.2f}x" if b and not r["method"].startswith("tmm") else "-"
        notes = []
        if "vs_forward" in r:
            notes.append(f"{r['vs_forward']:.2f}x the forward pass")
            vn = "-"
        if "max_abs_diff_vs_numpy" in r:
            notes.append(f"max |diff| vs NumPy {r['max_abs_diff_vs_numpy']:.1e}")
        out.append(f"| {r['method']} | {r['dtype']} | {r['points']:,} | {comp} | {r['run_s']:.3f} | "
                   f"{1e9 * r['per_point_s']:.0f} | {vt} | {vn} | {'; '.join(notes)} |")
    return "\n".join(out)
