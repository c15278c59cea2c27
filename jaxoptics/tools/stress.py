"""`python -m jaxoptics stress`: a numerical stress test of every kernel.

For each dtype, at least 10^6 inputs: random ones, and structured adversarial ones (normal and
grazing incidence down to subnormal cosines, the critical angle and 1 to 100 ulps around it, equal
indices and indices one ulp apart, index ratios 1e-3 to 1e3, cosines rounded just above 1, slightly
unnormalized directions). Values are compared with a reference, gradients (reverse and forward
mode) are checked for NaN and inf, invariants are measured.

References: for float32, the same kernel evaluated in float64 at the float32 inputs (the float64
kernels are within a few float64 ulps of the exact result, as the test suite shows against 50-digit
mpmath, which is far below a float32 ulp); for float64, 50-digit mpmath on a subsample (all
structured inputs and random ones). The error is measured against the backward-stability bound:
the largest change of the exact result when each input moves by 2 ulps (the sup over the interval,
cusps at the critical angle included), plus the result's own rounding.
"""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import numpy as np

# ---- inputs ----------------------------------------------------------------------------------


def _nextafter_k(x, k, dtype):
    x = np.asarray(x, dtype)
    direction = np.asarray(np.inf if k > 0 else -np.inf, dtype)
    for _ in range(abs(k)):
        x = np.nextafter(x, direction)
    return x


def make_scalar_inputs(dtype, n_random, seed=0):
    """(cos_i, eta1, eta2, category) arrays: random plus structured adversarial inputs."""
    rng = np.random.default_rng(seed)
    tiny_sub = np.finfo(dtype).smallest_subnormal
    cats, cs, e1s, e2s = [], [], [], []

    def add(cat, c, e1, e2):
        c, e1, e2 = np.broadcast_arrays(np.asarray(c, dtype), np.asarray(e1, dtype), np.asarray(e2, dtype))
        cs.append(c.ravel()), e1s.append(e1.ravel()), e2s.append(e2.ravel())
        cats.append(np.full(c.size, cat, dtype=object))

    # random: eta1 in [0.5, 3], ratio eta2 / eta1 log-uniform in [1e-3, 1e3], cos uniform
    e1 = np.exp(rng.uniform(np.log(0.5), np.log(3.0), n_random))
    add("random", rng.uniform(0, 1, n_random), e1, e1 * np.exp(rng.uniform(np.log(1e-3), np.log(1e3), n_random)))
    m = max(n_random // 50, 1000)
    e1 = np.exp(rng.uniform(np.log(0.5), np.log(3.0), m))
    e2 = e1 * np.exp(rng.uniform(np.log(1e-3), np.log(1e3), m))
    add("normal incidence", 1.0, e1, e2)
    for g in (0.0, tiny_sub, 1e-38, 1e-20, 1e-8):
        add("grazing", g, e1[: m // 5], e2[: m // 5])
    # the critical angle and 1..100 ulps around it, ratios from 1 - 1e-6 down to 1e-3
    e1c = np.exp(rng.uniform(np.log(0.5), np.log(3.0), m))
    ratio = np.concatenate([1 - np.exp(rng.uniform(np.log(1e-6), np.log(0.5), m // 2)),
                            np.exp(rng.uniform(np.log(1e-3), np.log(0.5), m - m // 2))])
    e2c = (e1c * ratio).astype(dtype)
    e1c = e1c.astype(dtype)
    cc = np.sqrt((e1c.astype(np.float64) - e2c) * (e1c.astype(np.float64) + e2c)) / e1c
    for k in (0, 1, -1, 2, -2, 4, -4, 10, -10, 100, -100):
        add("critical +-100 ulp", _nextafter_k(cc.astype(dtype), k, dtype), e1c, e2c)
    # no interface and indices one ulp apart
    e = np.exp(rng.uniform(np.log(0.5), np.log(3.0), m)).astype(dtype)
    c = np.concatenate([rng.uniform(0, 1, m - 6), [0, tiny_sub, 1e-30, 1e-8, 1, 0.5]]).astype(dtype)
    add("eta1 == eta2", c, e, e)
    add("eta2 one ulp above", c, e, _nextafter_k(e, 1, dtype))
    add("eta2 one ulp below", c, e, _nextafter_k(e, -1, dtype))
    # extreme ratios
    for r in (1e-3, 1e3):
        add("ratio 1e-3 / 1e3", rng.uniform(0, 1, m // 2), e1[: m // 2], e1[: m // 2] * r)
    # subnormal cosines and cosines rounded just above 1
    add("subnormal cos", rng.uniform(0, 1, m // 4) * np.finfo(dtype).tiny, e1[: m // 4], e2[: m // 4])
    for k in (1, 2, 4):
        add("cos just above 1", _nextafter_k(np.ones(m // 4, dtype), k, dtype), e1[: m // 4], e2[: m // 4])
    return (np.concatenate(cs), np.concatenate(e1s), np.concatenate(e2s), np.concatenate(cats))


def make_vector_inputs(c, dtype, seed=1):
    """Unit-ish directions with the given cosines against random normals of random orientation;
    a fraction slightly unnormalized (a few ulps off unit length)."""
    rng = np.random.default_rng(seed)
    N = c.size
    n = rng.normal(size=(N, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    a = np.cross(n, rng.normal(size=(N, 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    c64 = np.minimum(c.astype(np.float64), 1.0)
    i = np.sqrt(1 - c64**2)[:, None] * a - c64[:, None] * n
    flip = rng.choice([-1.0, 1.0], size=(N, 1))
    eps = np.finfo(dtype).eps
    scale = np.where(rng.uniform(size=(N, 1)) < 0.1, 1 + rng.integers(-4, 5, size=(N, 1)) * eps, 1.0)
    return (i * scale).astype(dtype), (flip * n).astype(dtype)


# ---- kernels under test -----------------------------------------------------------------------


def _scalar_kernels():
    import jax

    import jaxoptics as jo

    return {
        "fresnel": lambda c, a, b: jo.fresnel(c, a, b),
        "fresnel_sp.R_s": lambda c, a, b: jo.fresnel_sp(c, a, b)[0],
        "fresnel_sp.R_p": lambda c, a, b: jo.fresnel_sp(c, a, b)[1],
        "fresnel_rt.T": lambda c, a, b: jo.fresnel_rt(c, a, b)[1],
        "fresnel_amplitudes.r_s": lambda c, a, b: jo.fresnel_amplitudes(c, a, b).r_s,
        "fresnel_amplitudes.r_p": lambda c, a, b: jo.fresnel_amplitudes(c, a, b).r_p,
        "schlick": lambda c, a, b: jo.schlick(c, a, b),
        "schlick_tir": lambda c, a, b: jo.schlick_tir(c, a, b),
        "fresnel, complex eta2 = n + 0.1 n i": lambda c, a, b: jo.fresnel(c, a, jax.lax.complex(b, 0.1 * b)),
    }


EXACT = {"fresnel", "fresnel_sp.R_s", "fresnel_sp.R_p", "fresnel_rt.T", "fresnel_amplitudes.r_s", "fresnel_amplitudes.r_p",
         "fresnel, complex eta2 = n + 0.1 n i"}
TARGET_ULPS = {"fresnel": 4, "fresnel_sp.R_s": 4, "fresnel_sp.R_p": 4, "fresnel_rt.T": 4,
               "fresnel_amplitudes.r_s": 8, "fresnel_amplitudes.r_p": 8, "refract[degreve]": 4, "refract[bec]": 4}


def _ulp(x, dtype):
    return np.spacing(np.abs(x).astype(dtype)).astype(np.float64)


def _scalar_bound_f64(f64, c, a, b, dtype, ulps=2):
    """Backward bound of a float32 computation, evaluated with the float64 kernel: the sum over inputs
    of the largest change within +-2 float32 ulps (ends, the critical-angle cusp, and 0 for subnormal
    inputs, which XLA flushes)."""
    import jax.numpy as jnp

    base = np.asarray(f64(jnp.asarray(c, jnp.float64), jnp.asarray(a, jnp.float64), jnp.asarray(b, jnp.float64)))
    total = np.zeros(base.shape)
    c64, a64, b64 = (x.astype(np.float64) for x in (c, a, b))
    tiny = np.finfo(dtype).tiny
    for j in range(3):
        x = (c64, a64, b64)[j]
        h = ulps * _ulp((c, a, b)[j], dtype)
        cands = [x + h, x - h]
        # interior points where the sup may lie: the critical angle and Brewster's angle (within
        # an ulp of each other for a large index contrast)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_i = np.sqrt(np.maximum(1 - c64 * c64, 1e-300))
            if j == 0:
                special = [np.sqrt(np.maximum((a64 - b64) * (a64 + b64), 0)) / a64, a64 / np.hypot(a64, b64)]
                cands.append(np.where((np.abs(x) < tiny) & (x != 0), 0.0, x))
            elif j == 1:
                special = [b64 / s_i, b64 * c64 / s_i]
            else:
                special = [a64 * s_i, a64 * s_i / np.maximum(c64, 1e-300)]
        for sp in special:
            inside = np.abs(sp - x) <= h
            cands.append(np.where(inside, sp, x))
            # Near Brewster's angle at a large index contrast the extremum of the result lies a
            # fraction of an ulp from the special point, and the result changes by many ulps
            # across that fraction: Newton iterates toward it, each kept in the window
            cands += _toward_extremum(f64, (c64, a64, b64), j, base, np.where(inside, sp, x), x - h, x + h)
        worst = np.zeros(base.shape)
        for v in cands:
            args = [c64, a64, b64]
            args[j] = np.where((j > 0) & (v <= 0), x, v)
            val = np.asarray(f64(*(jnp.asarray(t) for t in args)))
            d = np.abs(val - base)
            worst = np.maximum(worst, np.where(np.isfinite(d), d, 0))
        total += worst
    return base, total


def _toward_extremum(f64, args, j, base, v0, lo, hi, steps=6):
    """Newton iterates, from `v0`, toward a stationary point of |f - base|^2 in argument `j`, each
    clipped to [lo, hi]: more candidates for the sup of `_scalar_bound_f64` (any point of the
    window is a valid one; where the derivatives are not finite the iterate stays put)."""
    import jax.numpy as jnp

    step = _newton_step(f64, j)
    v, out = v0, []
    consts = [jnp.asarray(x) for x in args]
    for _ in range(steps):
        nxt = np.asarray(step(jnp.asarray(v), jnp.asarray(base), *consts))
        v = np.clip(np.where(np.isfinite(nxt), nxt, v), lo, hi)
        out.append(v)
    return out


@functools.cache
def _newton_step(f64, j):
    """One Newton step on d/dv |f - base|^2 = 0 in argument `j`, compiled once per kernel."""
    import jax
    import jax.numpy as jnp

    def g(v, base, *xs):
        xs = list(xs)
        xs[j] = v
        d = f64(*xs) - base
        return jnp.real(d * jnp.conj(d))

    def step(v, base, *xs):
        d1 = lambda v: jax.jvp(lambda u: g(u, base, *xs), (v,), (jnp.ones_like(v),))[1]
        g1, g2 = jax.jvp(d1, (v,), (jnp.ones_like(v),))
        return v - g1 / g2

    return jax.jit(step)


def _grad_counts(f, args, complex_out, weights=None):
    """Non-finite counts of reverse-mode and forward-mode derivatives of a kernel (reverse mode
    with the cotangent `weights`, broadcast to the output; ones by default)."""
    import jax
    import jax.numpy as jnp

    g = (lambda *x: jnp.abs(f(*x)) ** 2) if complex_out else f

    @jax.jit  # both modes in one compiled program (called eagerly, each is traced and compiled)
    def counts(*args):
        out, vjp = jax.vjp(g, *args)
        ct = jnp.ones_like(out) if weights is None else jnp.broadcast_to(weights, out.shape).astype(out.dtype)
        bad_rev = sum(jnp.sum(~jnp.isfinite(r)) for r in vjp(ct))
        return bad_rev, sum(jnp.sum(~jnp.isfinite(d)) for d in _along_each_input(g, args))

    bad_rev, bad_fwd = counts(*args)
    return int(bad_rev), int(bad_fwd)


def _along_each_input(f, args):
    """The forward-mode derivatives of `f` along each of its arguments in turn (the others held)."""
    import jax
    import jax.numpy as jnp

    out = []
    for j in range(len(args)):
        t = [jnp.zeros_like(a) for a in args]
        t[j] = jnp.ones_like(args[j])
        out.append(jax.jvp(f, tuple(args), tuple(t))[1])
    return out


def stress_scalar(dtype, n_random, progress=None, mp_samples=2000):
    import jax
    import jax.numpy as jnp

    c, a, b, cats = make_scalar_inputs(dtype, n_random)
    rows = []
    kernels = _scalar_kernels()
    exact_f64 = kernels["fresnel"]
    for name, f in kernels.items():
        fj = jax.jit(f)
        t0 = time.perf_counter()
        args = tuple(jnp.asarray(x) for x in (c, a, b))
        got = np.asarray(fj(*args))
        complex_out = np.iscomplexobj(got)
        row = dict(kernel=name, dtype=np.dtype(dtype).name, n=int(c.size),
                   nan_inf_values=int(np.sum(~np.isfinite(got))))
        row["nan_inf_grad_rev"], row["nan_inf_grad_fwd"] = _grad_counts(fj, args, complex_out)
        if dtype == np.float32:
            ref, bound = _scalar_bound_f64(jax.jit(f), c, a, b, dtype)
            # ulps of the larger of result and reference (an error on an exact 0 is not infinite ulps)
            scale = _ulp(np.maximum(np.abs(ref), np.abs(got)), dtype)
            err = np.abs(got.astype(np.complex128 if complex_out else np.float64) - ref)
            ok = np.isfinite(err)
            row["max_err_ulp"] = float(np.max(err[ok] / scale[ok]))
            row["p99.9_err_ulp"] = float(np.percentile(err[ok] / scale[ok], 99.9))
            # XLA flushes results below the smallest normal number to zero: allow that much
            excess = np.maximum(err - bound - np.finfo(dtype).tiny, 0) / scale
            row["max_excess_over_bound_ulp"] = float(np.max(excess[ok]))
            k = int(np.argmax(np.where(ok, excess, -1)))
            row["worst_input"] = dict(cos_i=float(c[k]), eta1=float(a[k]), eta2=float(b[k]), category=str(cats[k]))
            row["reference"] = "float64 kernel, all inputs"
        else:
            row.update(_mp_check(name, f, c, a, b, cats, dtype, mp_samples))
        if name.startswith("schlick"):
            ex = np.asarray(jax.jit(exact_f64)(*args), np.float64)
            row["approx_err_vs_exact_max"] = float(np.max(np.abs(got - ex)))
        if name == "fresnel_rt.T":
            R = np.asarray(jax.jit(kernels["fresnel"])(*args), np.float64)
            row["worst_R_plus_T_minus_1"] = float(np.max(np.abs(R + got - 1)))
        row["seconds"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        if progress:
            progress.update(1)
    return rows


def _mp_check(name, f, c, a, b, cats, dtype, samples):
    """float64 against 50-digit mpmath on a subsample: structured inputs first, then random."""
    import jax
    import mpmath as mp

    from . import mpref as _mpref

    rng = np.random.default_rng(5)
    structured = np.flatnonzero(cats != "random")
    rand = np.flatnonzero(cats == "random")
    pick = np.concatenate([rng.choice(structured, min(samples // 2, structured.size), replace=False),
                           rng.choice(rand, min(samples - samples // 2, rand.size), replace=False)])
    got = np.asarray(jax.jit(f)(c[pick], a[pick], b[pick]))
    worst_ex = 0.0
    errs = []
    worst_input = None
    for k, idx in enumerate(pick):
        ref, bound = _mpref.bound(name, float(c[idx]), float(a[idx]), float(b[idx]), dtype)
        g = mp.mpc(complex(got[k])) if np.iscomplexobj(got) else mp.mpf(float(got[k]))
        err = abs(g - ref)
        u = float(np.spacing(abs(complex(ref)) if np.iscomplexobj(got) else abs(float(ref))))
        u = max(u, float(np.finfo(dtype).smallest_subnormal))
        e_ulp = float(err) / u
        errs.append(e_ulp)
        ex = max(float(err - bound) / u, 0.0)
        if ex > worst_ex or worst_input is None:
            worst_ex = max(worst_ex, ex)
            worst_input = dict(cos_i=float(c[idx]), eta1=float(a[idx]), eta2=float(b[idx]), category=str(cats[idx]))
    errs = np.asarray(errs)
    return {"max_err_ulp": float(np.max(errs)), "p99.9_err_ulp": float(np.percentile(errs, 99.9)),
            "max_excess_over_bound_ulp": worst_ex, "worst_input": worst_input,
            "reference": f"mpmath 50 digits, {pick.size} of the inputs ({min(samples // 2, structured.size)} structured)"}


def _vector_bound_f64(exact, i, n, a, b, dtype, ulps=2):
    """Backward bound for directions, with the float64 kernel: the sum over the 8 scalar inputs
    (components of i and n, the two indices) of the largest change (max over components) when that
    input moves by +-2 ulps of dtype."""
    import jax.numpy as jnp

    base_args = [i.astype(np.float64), n.astype(np.float64), a.astype(np.float64), b.astype(np.float64)]
    ref = np.asarray(exact(*(jnp.asarray(x) for x in base_args)))
    total = np.zeros(ref.shape[0])
    for j, comp in [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, None), (3, None)]:
        x = (i, n, a, b)[j]
        col = x[:, comp] if comp is not None else x
        h = ulps * np.spacing(np.abs(col)).astype(np.float64)
        worst = np.zeros(ref.shape[0])
        for sg in (1, -1):
            moved = [y.copy() for y in base_args]
            if comp is None:
                moved[j] = np.where(moved[j] + sg * h > 0, moved[j] + sg * h, moved[j])
            else:
                moved[j][:, comp] += sg * h
            d = np.max(np.abs(np.asarray(exact(*(jnp.asarray(m) for m in moved))) - ref), axis=1)
            worst = np.maximum(worst, np.where(np.isfinite(d), d, 0))
        total += worst
    return ref, total


def stress_vector(dtype, n_random, progress=None, mp_samples=400):
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    c, a, b, cats = make_scalar_inputs(dtype, n_random)
    ok_dom = c <= 1  # the directions are built from the angle
    c, a, b, cats = c[ok_dom], a[ok_dom], b[ok_dom], cats[ok_dom]
    i, n = make_vector_inputs(c, dtype)
    rows = []
    weights = jnp.asarray([[1.0, 2.0, 3.0]], dtype)
    exact = jax.jit(lambda i, n, a, b: jo.refract(i, n, a, b).t)
    for method in ("degreve", "bec", "heckbert", "oliveira", "reflect"):
        t0 = time.perf_counter()
        if method == "reflect":
            f = jax.jit(lambda i, n, a, b: jo.reflect(i, n))
            ref_fn = f
        else:
            f = jax.jit(lambda i, n, a, b, m=method: jo.refract(i, n, a, b, method=m).t)
            # an approximation is checked for stability against its own formula in float64;
            # its distance from the exact direction is reported apart
            ref_fn = f if method == "oliveira" else exact
        args = tuple(jnp.asarray(x) for x in (i, n, a, b))
        t = np.asarray(f(*args))
        if method != "reflect":  # the mask from the same compiled computation as t
            tir = np.asarray(jax.jit(lambda i, n, a, b, m=method: jo.refract(i, n, a, b, method=m))(*args).tir)
        name = method if method == "reflect" else f"refract[{method}]"
        row = dict(kernel=name, dtype=np.dtype(dtype).name, n=int(c.size), nan_inf_values=int(np.sum(~np.isfinite(t))))
        row["nan_inf_grad_rev"], row["nan_inf_grad_fwd"] = _grad_counts(f, args, False, weights)
        t64, i64, n64 = t.astype(np.float64), i.astype(np.float64), n.astype(np.float64)
        row["worst_abs_norm_minus_1"] = float(np.max(np.abs(np.linalg.norm(t64, axis=1) - np.linalg.norm(i64, axis=1))))
        if method != "reflect":
            sin_i = np.linalg.norm(np.cross(i64, n64), axis=1) / np.linalg.norm(i64, axis=1)
            sin_t = np.linalg.norm(np.cross(t64, n64), axis=1)
            res = np.abs(a * sin_i - b * sin_t) / np.maximum(a, b)
            row["worst_snell_residual"] = float(np.max(res[~tir])) if np.any(~tir) else 0.0
        eps = float(np.finfo(dtype).eps)
        if method == "oliveira":
            ex64 = np.asarray(exact(*(jnp.asarray(x, jnp.float64) for x in (i, n, a, b))))
            cosang = np.clip(np.sum(t64 * ex64, axis=1) / np.linalg.norm(t64, axis=1), -1, 1)
            into = ~tir & (b > a)
            row["approx_angle_err_deg_entering_denser"] = float(np.degrees(np.max(np.arccos(cosang[into])))) if np.any(into) else 0.0
        if dtype == np.float32:
            ref, bound = _vector_bound_f64(ref_fn, i, n, a, b, dtype)
            err = np.max(np.abs(t64 - ref), axis=1)
            row["max_err_ulp"] = float(np.max(err) / eps)
            row["p99.9_err_ulp"] = float(np.percentile(err, 99.9) / eps)
            excess = np.maximum(err - bound, 0) / eps
            row["max_excess_over_bound_ulp"] = float(np.max(excess))
            k = int(np.argmax(excess))
            row["worst_input"] = dict(cos_i=float(c[k]), eta1=float(a[k]), eta2=float(b[k]), category=str(cats[k]))
            row["reference"] = ("degreve" if method not in ("reflect", "oliveira") else method) + " in float64, all inputs"
        else:
            row.update(_vector_mp(method, t64, i, n, a, b, cats, dtype, mp_samples))
        row["seconds"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        if progress:
            progress.update(1)
    return rows


def _vector_mp(method, t, i, n, a, b, cats, dtype, samples):
    import mpmath as mp

    from . import mpref as _mpref

    rng = np.random.default_rng(6)
    # a quarter at the critical angle (where the TIR decision hinges on the last ulp of cos_i; a
    # band of wrong decisions there once hid from a sample drawn over all structured inputs), a
    # quarter from the other structured inputs, half random
    critical = np.flatnonzero(cats == "critical +-100 ulp")
    structured = np.flatnonzero((cats != "random") & (cats != "critical +-100 ulp"))
    rand = np.flatnonzero(cats == "random")
    q = samples // 4
    pick = np.concatenate([rng.choice(critical, min(q, critical.size), replace=False),
                           rng.choice(structured, min(q, structured.size), replace=False),
                           rng.choice(rand, min(samples - 2 * q, rand.size), replace=False)])
    eps = float(np.finfo(dtype).eps)

    def f(*x):
        if method == "reflect":
            d = sum(x[j] * x[3 + j] for j in range(3))
            return [x[j] - 2 * d * x[3 + j] for j in range(3)]
        t, tir = _mpref.refract_ref(list(x[0:3]), list(x[3:6]), x[6], x[7])
        if method == "oliveira" and not tir:  # its own formula: normalize(i - c n_f), c = 1
            d = sum(x[j] * x[3 + j] for j in range(3))
            nf = [-x[3 + j] if d > 0 else x[3 + j] for j in range(3)]
            v = [x[j] - nf[j] for j in range(3)]
            nv = mp.sqrt(sum(u * u for u in v))
            return [u / nv for u in v]
        return t

    errs, worst_ex, worst_input = [], 0.0, None
    for k in pick:
        args = tuple(float(v) for v in i[k]) + tuple(float(v) for v in n[k]) + (float(a[k]), float(b[k]))
        ref, bnd = _mpref.backward_bound(f, args, dtype, nonneg=(6, 7))
        err = max(abs(mp.mpf(float(t[k, j])) - ref[j]) for j in range(3))
        errs.append(float(err) / eps)
        ex = max(float(err - bnd) / eps, 0.0)
        if worst_input is None or ex > worst_ex:
            worst_ex = ex
            worst_input = dict(cos_i=float(abs(np.dot(i[k], n[k]))), eta1=float(a[k]), eta2=float(b[k]), category=str(cats[k]))
    errs = np.asarray(errs)
    return {"max_err_ulp": float(np.max(errs)), "p99.9_err_ulp": float(np.percentile(errs, 99.9)),
            "max_excess_over_bound_ulp": worst_ex, "worst_input": worst_input,
            "reference": f"mpmath 50 digits, {pick.size} of the inputs ({min(q, critical.size)} at the critical angle)"}


def mitsuba_comparison(n=200_000, progress=None):
    """Mitsuba 3's float32 `fresnel` (LLVM backend) on the hardest inputs: eta = 1.000001 within
    1e-6 of the critical angle, and its automatic derivative under TIR near grazing incidence.
    Skipped with a note when Mitsuba is not installed or its LLVM backend cannot start."""
    from ._measure import _mitsuba

    mi, dr = _mitsuba()
    if mi is None:
        return {"skipped": f"Mitsuba 3 LLVM backend not available ({dr})"}
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    # light leaving a medium of index 1.000001 into 1.0: Mitsuba's eta = n_t / n_i
    e1, e2 = np.float32(1.000001), np.float32(1.0)
    cc = np.sqrt((np.float64(e1) - e2) * (np.float64(e1) + e2)) / np.float64(e1)
    rng = np.random.default_rng(9)
    c = (cc + rng.uniform(-1e-6, 1e-6, n)).astype(np.float32)
    ref = np.asarray(jo.fresnel(jnp.asarray(c, jnp.float64), jnp.float64(e1), jnp.float64(e2)))
    ours = np.asarray(jo.fresnel(jnp.asarray(c), e1, e2), np.float64)
    r_mi = mi.fresnel(mi.Float(c), mi.Float(float(e2 / e1)))[0]
    mits = np.asarray(r_mi, np.float64)
    # derivatives under TIR at near-grazing incidence, glass to air
    cg = np.linspace(1e-7, 1e-3, 1000).astype(np.float32)
    x = mi.Float(cg)
    dr.enable_grad(x)
    y = mi.fresnel(x, mi.Float(1 / 1.5))[0]
    dr.backward(y)
    g_mi = np.asarray(dr.grad(x))
    g_jo = np.asarray(jax.vmap(jax.grad(lambda c: jo.fresnel(c, jnp.float32(1.5), jnp.float32(1.0))))(jnp.asarray(cg)))
    if progress:
        progress.update(1)
    return {
        "case": "float32 fresnel, eta1 = 1.000001 -> eta2 = 1, cos_i within 1e-6 of the critical cosine; reference: jaxoptics float64",
        "n": int(n),
        "mitsuba_max_abs_err": float(np.max(np.abs(mits - ref))),
        "jaxoptics_max_abs_err": float(np.max(np.abs(ours - ref))),
        "grad_case": "d R / d cos_i, glass (1.5) to air under TIR, cos_i in [1e-7, 1e-3] (1000 points)",
        "mitsuba_nan_inf_grads": int(np.sum(~np.isfinite(g_mi))),
        "jaxoptics_nan_inf_grads": int(np.sum(~np.isfinite(g_jo))),
    }


# ---- report ------------------------------------------------------------------------------------


def table(rows) -> str:
    out = [("| kernel | dtype | inputs | max err (ulp) | 99.9% err (ulp) | max excess over 2-ulp bound (ulp) | NaN/inf values "
           "| NaN/inf grads (rev / fwd) | invariant | reference |"),
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |"]
    for r in rows:
        inv = []
        if "worst_abs_norm_minus_1" in r:
            inv.append(f"max abs(abs(t) - abs(i)) {r['worst_abs_norm_minus_1']:.1e}")
        if "worst_snell_residual" in r:
            inv.append(f"Snell residual {r['worst_snell_residual']:.1e}")
        if "worst_R_plus_T_minus_1" in r:
            inv.append(f"abs(R + T - 1) {r['worst_R_plus_T_minus_1']:.1e}")
        if "approx_err_vs_exact_max" in r:
            inv.append(f"approximation error vs exact {r['approx_err_vs_exact_max']:.3f}")
        if "approx_angle_err_deg_entering_denser" in r:
            inv.append(f"angle from exact t {r['approx_angle_err_deg_entering_denser']:.1f} deg (entering denser)")
        out.append(
            f"| {r['kernel']} | {r['dtype']} | {r['n']:,} | {r['max_err_ulp']:.3g} | {r['p99.9_err_ulp']:.3g} | "
            f"{r['max_excess_over_bound_ulp']:.3g} | {r['nan_inf_values']} | {r['nan_inf_grad_rev']} / {r['nan_inf_grad_fwd']} | "
            f"{'; '.join(inv)} | {r['reference']} |")
    return "\n".join(out)


def run(*, n=1_000_000, out_dir="stress_out", mp_samples=2000, mitsuba=True, quiet=False, stack_media=None) -> dict:
    """Run the sweep; write stress.json and stress.md into `out_dir`; return the report.
    `stack_media`: the numbers of media of the thin-film section's stacks (default: all of
    `stress_stack.L_CHOICES`)."""
    import jax
    from tqdm.auto import tqdm

    jax.config.update("jax_enable_x64", True)
    from ._measure import machine_description, run_stamp

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_random = max(int(n * 0.8), 1000)  # the structured inputs bring the total above n
    report = {"machine": machine_description(), "n_requested": n, "rows": [], "date": run_stamp()}
    from .stress_stack import CATEGORIES, L_CHOICES, stack_stress_table, stress_stack

    media = L_CHOICES if stack_media is None else tuple(stack_media)

    total = 2 * (len(_scalar_kernels()) + 5) + (1 if mitsuba else 0) + len(CATEGORIES)
    with tqdm(total=total, desc="stress", unit="kernel", disable=quiet) as bar:
        for dtype in (np.float32, np.float64):
            report["rows"] += stress_scalar(dtype, n_random, bar, mp_samples=mp_samples)
            report["rows"] += stress_vector(dtype, n_random, bar, mp_samples=max(mp_samples // 5, 50))
        report["stack"] = stress_stack(n_points=max(n // 10, 4000), mp_samples=max(mp_samples // 10, 40), progress=bar,
                                       media=media)
        if mitsuba:
            report["mitsuba"] = mitsuba_comparison(progress=bar)
    md = [f"Measured by `python -m jaxoptics stress --n {n}` on {report['date']}. Machine: {report['machine']}.", "", table(report["rows"]), "",
          f"Thin-film stacks (`stack`, {', '.join(map(str, media))} media; float32 against float64 on the same inputs):", "",
          stack_stress_table(report["stack"])]
    if "mitsuba" in report:
        m = report["mitsuba"]
        if "skipped" in m:
            md += ["", f"Mitsuba 3: {m['skipped']}"]
        else:
            md += ["", f"Mitsuba 3 side by side ({m['case']}, {m['n']:,} inputs): max abs error of R "
                   f"Mitsuba {m['mitsuba_max_abs_err']:.3g}, jaxoptics {m['jaxoptics_max_abs_err']:.3g}. "
                   f"{m['grad_case']}: NaN/inf derivatives Mitsuba {m['mitsuba_nan_inf_grads']}, jaxoptics {m['jaxoptics_nan_inf_grads']}."]
    text = "\n".join(md)
    (out / "stress.md").write_text(text + "\n")
    (out / "stress.json").write_text(json.dumps(report, indent=2, default=str))
    if not quiet:
        print(text)
        print(f"\nwritten: {out / 'stress.md'}, {out / 'stress.json'}")
    return report
