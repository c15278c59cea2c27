"""Gradients: finite everywhere, and equal to 50-digit mpmath derivatives where the function is smooth.

"Everywhere" includes the places where a naive implementation produces NaN or inf: under total
internal reflection, at the exact critical angle (cos_i = 0.8, eta1 = 1.25, eta2 = 0.75 is exactly
critical in binary floating point: 1.25 * 0.8 rounds to 1 and (0.75 - 1.25)(0.75 + 1.25) = -1),
at grazing and normal incidence, and with eta1 == eta2 (including grazing, where 0/0 appears).
"""

import itertools

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
from helpers import fresnel_ref, mpf, refract_ref

import jaxoptics as jo

DTYPES = [np.float32, np.float64]

# (name, jax function of (cos_i, eta1, eta2) -> scalar, mpmath reference or None)
SCALAR_KERNELS = [
    ("fresnel", lambda c, a, b: jo.fresnel(c, a, b), lambda c, a, b: (fresnel_ref(c, a, b)["R_s"] + fresnel_ref(c, a, b)["R_p"]) / 2),
    ("R_s", lambda c, a, b: jo.fresnel_sp(c, a, b)[0], lambda c, a, b: fresnel_ref(c, a, b)["R_s"]),
    ("R_p", lambda c, a, b: jo.fresnel_sp(c, a, b)[1], lambda c, a, b: fresnel_ref(c, a, b)["R_p"]),
    ("T", lambda c, a, b: jo.fresnel_rt(c, a, b)[1], lambda c, a, b: (fresnel_ref(c, a, b)["T_s"] + fresnel_ref(c, a, b)["T_p"]) / 2),
    ("re r_s", lambda c, a, b: jnp.real(jo.fresnel_amplitudes(c, a, b).r_s), lambda c, a, b: mp.re(fresnel_ref(c, a, b)["r_s"])),
    ("im r_p", lambda c, a, b: jnp.imag(jo.fresnel_amplitudes(c, a, b).r_p), lambda c, a, b: mp.im(fresnel_ref(c, a, b)["r_p"])),
    ("re r_p", lambda c, a, b: jnp.real(jo.fresnel_amplitudes(c, a, b).r_p), lambda c, a, b: mp.re(fresnel_ref(c, a, b)["r_p"])),
    ("re t_p", lambda c, a, b: jnp.real(jo.fresnel_amplitudes(c, a, b).t_p), lambda c, a, b: mp.re(fresnel_ref(c, a, b)["t_p"])),
    ("schlick", lambda c, a, b: jo.schlick(c, a, b), lambda c, a, b: ((a - b) / (a + b)) ** 2 + (1 - ((a - b) / (a + b)) ** 2) * (1 - c) ** 5),
    ("schlick_tir", lambda c, a, b: jo.schlick_tir(c, a, b), None),
]


def _refract_component(method, k):
    """t_k as a function of the angle of incidence theta (radians) and the indices."""

    def f(theta, a, b):
        i = jnp.stack([jnp.sin(theta), jnp.zeros_like(theta), -jnp.cos(theta)])
        return jo.refract(i, jnp.array([0.0, 0.0, 1.0], theta.dtype), a, b, method=method).t[k]

    return f


VECTOR_KERNELS = [(f"refract[{m}].t{k}", _refract_component(m, k)) for m in ("degreve", "bec", "heckbert", "oliveira") for k in (0, 2)]


def _singular_points(dtype):
    """Where naive gradients blow up."""
    one_up = float(np.nextafter(dtype(1), dtype(2)))
    pts = [
        (0.8, 1.25, 0.75),  # exactly critical
        (float(np.nextafter(dtype(0.8), dtype(1))), 1.25, 0.75),  # one ulp on the transmitting side
        (float(np.nextafter(dtype(0.8), dtype(0))), 1.25, 0.75),  # one ulp into TIR
        (0.3, 1.5, 1.0),  # TIR
        (0.0, 1.5, 1.0),  # grazing, TIR
        (0.0, 1.0, 1.5),  # grazing
        (1e-30, 1.0, 1.5),
        (1.0, 1.0, 1.5),  # normal incidence
        (1.0, 1.5, 1.0),
        (0.5, 1.3, 1.3),  # no interface
        (0.0, 1.3, 1.3),  # no interface, grazing: 0/0
        (0.0, 1.0, one_up),
        (0.0, one_up, 1.0),
        (float(np.nextafter(dtype(1), dtype(2))), 1.0, 1.5),  # cos_i rounded above 1
        (0.5547001962252291, 1.0, 1.5),  # Brewster (cos = 1/sqrt(1 + 1.5^2))
    ]
    return [tuple(dtype(x) for x in p) for p in pts]


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_finite_everywhere(dtype):
    """Every kernel's value, reverse-mode gradient and forward-mode Jacobian in (cos_i, eta1, eta2)
    at every singular point: all of them in one compiled program, mapped over the points with
    `jax.vmap` (which computes each point on its own)."""
    kernels = [(n, f) for n, f, _ in SCALAR_KERNELS] + VECTOR_KERNELS
    cases = []
    for name, f in kernels:
        pts = _singular_points(dtype)
        if name.startswith("refract"):  # refract is parameterized by the angle, which needs cos <= 1
            pts = [(dtype(np.arccos(p[0])),) + p[1:] for p in pts if p[0] <= 1]
        cases.append((name, f, pts, tuple(np.array(col, dtype) for col in zip(*pts))))

    @jax.jit
    def everything(args):
        return [(jax.vmap(f)(*a), jax.vmap(jax.grad(f, argnums=(0, 1, 2)))(*a), jax.vmap(jax.jacfwd(f, argnums=(0, 1, 2)))(*a))
                for (_, f, _, _), a in zip(cases, args)]

    bad = []
    for (name, _, pts, _), (val, rev, fwd) in zip(cases, everything([c[3] for c in cases])):
        assert val.dtype == dtype, (name, val.dtype)
        for mode, grads in (("rev", rev), ("fwd", fwd)):
            grads = [np.asarray(x) for x in grads]
            ok = np.isfinite(np.asarray(val)) & np.all([np.isfinite(x) for x in grads], axis=0)
            bad += [(name, mode, pts[k], [float(x[k]) for x in grads], float(val[k])) for k in np.flatnonzero(~ok)]
    assert not bad, bad[:10]

@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
def test_second_derivatives_finite_everywhere(dtype):
    """The Hessian in (cos_i, eta1, eta2) at the singular points, in all four compositions of
    forward and reverse mode: a fit's implicit-function gradient differentiates the kernels' own
    derivative rules, and reverse over forward meets 0 * inf in an unguarded rule that the first
    derivatives never see (grazing incidence under TIR)."""
    pts = np.asarray(_singular_points(dtype)).T
    modes = {"fwd-fwd": (jax.jacfwd, jax.jacfwd), "rev-fwd": (jax.jacrev, jax.jacfwd),
             "fwd-rev": (jax.jacfwd, jax.jacrev), "rev-rev": (jax.jacrev, jax.jacrev)}
    cases = list(itertools.product(SCALAR_KERNELS, modes.items()))

    @jax.jit  # every kernel and composition in one program (mapped over the points)
    def hessians(x):
        return [jax.vmap(outer(lambda x: inner(lambda y: f(*y))(x)))(x) for (_, f, _), (_, (outer, inner)) in cases]

    bad = []
    for ((name, _, _), (mode, _)), h in zip(cases, hessians(jnp.asarray(pts.T))):
        assert h.shape == (len(pts[0]), 3, 3) and h.dtype == dtype, (name, mode, h.shape, h.dtype)
        for p, hp in zip(pts.T, np.asarray(h)):
            if not np.all(np.isfinite(hp)):
                bad.append((name, mode, tuple(float(x) for x in p), hp.tolist()))
    assert not bad, bad[:10]


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
def test_vector_input_gradients_finite(dtype):
    """d/d(i, n, eta1, eta2) of refract and reflect at TIR, critical, grazing, normal, both normal
    orientations, eta1 == eta2 (all cases mapped over with `jax.vmap`, every method in one
    compiled program)."""
    cases = [((0.6, 0.0, -0.8), (0, 0, 1), 1.25, 0.75),  # exactly critical
             ((0.6, 0.0, -0.8), (0, 0, -1), 1.25, 0.75),
             ((0.9, 0.0, -0.435889894), (0, 0, 1), 1.5, 1.0),  # TIR
             ((1.0, 0.0, 0.0), (0, 0, 1), 1.0, 1.5),  # grazing
             ((1.0, 0.0, 0.0), (0, 0, 1), 1.5, 1.5),  # grazing, no interface
             ((0.0, 0.0, -1.0), (0, 0, 1), 1.0, 1.5),  # normal
             ((0.0, 0.0, -1.0), (0, 0, -1), 1.5, 1.0)]
    args = tuple(jnp.asarray(np.array(col, dtype)) for col in zip(*cases))
    methods = ("degreve", "bec", "heckbert", "oliveira")
    w = jnp.asarray([1.0, 2.0, 3.0], dtype)
    pairs = np.array([(1.25, 0.75), (1.0, 1.0), (1.0, 1.5)], dtype).T

    @jax.jit
    def everything(args, pairs):
        out = {}
        for method in methods:
            f = lambda i, n, a, b, method=method: jnp.sum(jo.refract(i, n, a, b, method=method).t * w)
            out[f"{method} reverse"] = jax.vmap(jax.grad(f, argnums=(0, 1, 2, 3)))(*args)
            out[f"{method} forward"] = jax.vmap(jax.jacfwd(f, argnums=(0, 1, 2, 3)))(*args)
        out["reflect"] = jax.vmap(jax.grad(lambda i, n: jnp.sum(jo.reflect(i, n)), argnums=(0, 1)))(args[0], args[1])
        for fn in (jo.critical_angle, jo.brewster_angle):
            out[fn.__name__] = jax.vmap(jax.grad(fn, argnums=(0, 1)))(*pairs)
        return out

    for key, grads in everything(args, pairs).items():
        finite = np.all([np.all(np.isfinite(np.asarray(x)).reshape(len(x), -1), axis=1) for x in grads], axis=0)
        assert finite.all(), (key, [cases[k] if len(finite) == len(cases) else pairs.T[k] for k in np.flatnonzero(~finite)])


SMOOTH_POINTS = [(c, a, b) for c in (0.05, 0.3, 0.62, 0.9, 0.999) for a, b in ((1.0, 1.5), (1.0, 1.333), (1.5, 1.0), (1.0, 3.2), (2.4, 1.0), (1.3, 1.3))]


def _smooth(c, a, b):
    if a > b:
        cc = np.sqrt(1 - (b / a) ** 2)
        return abs(c - cc) > 1e-3  # stay off the critical angle (a sqrt cusp)
    return True


@pytest.mark.parametrize("name,f,ref", [k for k in SCALAR_KERNELS if k[2] is not None], ids=lambda x: x if isinstance(x, str) else "")
def test_gradients_match_mpmath(name, f, ref):
    """float64 jax.grad and forward mode against mpmath.diff at 50 digits, relative 1e-9."""
    grad = jax.jit(jax.grad(f, argnums=(0, 1, 2)))
    fwd = jax.jit(jax.jacfwd(f, argnums=(0, 1, 2)))
    for c, a, b in SMOOTH_POINTS:
        if not _smooth(c, a, b):
            continue
        args = (jnp.float64(c), jnp.float64(a), jnp.float64(b))
        x0 = [mpf(c), mpf(a), mpf(b)]
        want = [mp.diff(lambda t, j=j: ref(*[t if k == j else x0[k] for k in range(3)]), x0[j]) for j in range(3)]
        for got in (grad(*args), fwd(*args)):
            for j in range(3):
                w = float(want[j])
                assert abs(float(got[j]) - w) <= 1e-9 * abs(w) + 1e-12, (name, (c, a, b), j, float(got[j]), w)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["degreve", "bec", "heckbert"])
def test_refract_gradients_match_mpmath(method):
    def ref(theta, a, b, k):
        t, _ = refract_ref([mp.sin(theta), mp.mpf(0), -mp.cos(theta)], [mp.mpf(0), mp.mpf(0), mp.mpf(1)], a, b)
        return t[k]

    for k in (0, 2):
        f = _refract_component(method, k)
        grad = jax.jit(jax.grad(f, argnums=(0, 1, 2)))
        for c, a, b in SMOOTH_POINTS:
            if not _smooth(c, a, b):
                continue
            theta = float(np.arccos(c))
            x0 = [mpf(theta), mpf(a), mpf(b)]
            want = [mp.diff(lambda t, j=j: ref(*[t if q == j else x0[q] for q in range(3)], k), x0[j]) for j in range(3)]
            got = grad(jnp.float64(theta), jnp.float64(a), jnp.float64(b))
            for j in range(3):
                w = float(want[j])
                assert abs(float(got[j]) - w) <= 1e-9 * abs(w) + 1e-12, (method, k, (c, a, b), j, float(got[j]), w)


def test_complex_index_gradients():
    """d/dn and d/dk of R for a metal (eta2 = n + ik), against mpmath; finite at k = 0 with TIR."""

    def R(c, n, k):
        return jo.fresnel(c, 1.0, jax.lax.complex(n, k))

    g = jax.jit(jax.grad(R, argnums=(1, 2)))
    for c, n, k in ((0.3, 0.2, 3.0), (0.8, 2.5, 2.5), (0.5, 1.5, 0.01)):
        got = g(jnp.float64(c), jnp.float64(n), jnp.float64(k))
        x0 = [mpf(c), mpf(n), mpf(k)]

        def ref(cc, nn, kk):
            d = fresnel_ref(cc, mp.mpf(1), mp.mpc(nn, kk))
            return (d["R_s"] + d["R_p"]) / 2

        for j, argj in ((0, 1), (1, 2)):
            w = float(mp.diff(lambda t: ref(*[t if q == argj else x0[q] for q in range(3)]), x0[argj]))
            assert abs(float(got[j]) - w) <= 1e-9 * abs(w) + 1e-12, (c, n, k, j, float(got[j]), w)
    # k = 0 below the critical angle (TIR) and exactly at it: finite
    for c in (0.3, 0.8):
        got = g(jnp.float64(c), jnp.float64(0.6), jnp.float64(0.0))
        assert all(bool(jnp.isfinite(x)) for x in got)
    got = jax.grad(lambda c, n, k: jo.fresnel(c, 1.25, jax.lax.complex(n, k)), argnums=(0, 1, 2))(
        jnp.float64(0.8), jnp.float64(0.75), jnp.float64(0.0))
    assert all(bool(jnp.isfinite(x)) for x in got)


def test_second_derivatives_match_mpmath():
    """The closed-form first derivatives of the real-index kernels are themselves differentiable:
    d^2 R / d eta2^2 and d^2 R / d cos_i d eta2 against mpmath at 50 digits."""
    ref = lambda c, a, b: (fresnel_ref(c, a, b)["R_s"] + fresnel_ref(c, a, b)["R_p"]) / 2
    h = jax.jit(jax.hessian(lambda c, a, b: jo.fresnel(c, a, b), argnums=(0, 2)))
    for c, a, b in ((0.3, 1.0, 1.5), (0.9, 1.5, 1.0), (0.62, 1.0, 3.2), (0.05, 1.0, 1.333)):
        got = h(jnp.float64(c), jnp.float64(a), jnp.float64(b))
        want_bb = float(mp.diff(lambda t: ref(mpf(c), mpf(a), t), mpf(b), 2))
        want_cb = float(mp.diff(lambda x, y: ref(x, mpf(a), y), (mpf(c), mpf(b)), (1, 1)))
        assert abs(float(got[1][1]) - want_bb) <= 1e-8 * abs(want_bb) + 1e-11, (c, a, b, float(got[1][1]), want_bb)
        assert abs(float(got[0][1]) - want_cb) <= 1e-8 * abs(want_cb) + 1e-11, (c, a, b, float(got[0][1]), want_cb)
