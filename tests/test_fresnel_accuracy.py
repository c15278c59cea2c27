"""Values of the Fresnel kernels against a 50-digit mpmath oracle (backward-stability criterion).

A result passes when |got - ref| <= B + 4 ulp(ref), where B is the largest change of the exact
result when each input moves by 2 ulps (what rounding the inputs would cause). This is the
standard mixed forward/backward error bound: it reduces to "4 ulps" where the problem is
well-conditioned and allows the inherent error near the critical angle.
"""


import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
from helpers import backward_bound, fresnel_ref, fresnel_specials, spacing

import jaxoptics as jo

DTYPES = [np.float32, np.float64]
# Complex amplitudes go through complex multiplications and divisions, each good to a few ulps
# normwise; the documented accuracy of fresnel_amplitudes is 8 ulps (normwise) beyond the bound.
AMPLITUDE_ULPS = 8


def _eta_pairs(dtype):
    one_up = float(np.nextafter(dtype(1), dtype(2)))
    one_dn = float(np.nextafter(dtype(1), dtype(0)))
    pairs = [(1.0, 1.5), (1.5, 1.0), (1.0, 1.333), (1.333, 1.0), (1.0, 2.4), (2.4, 1.0),
             (1.0, 1e3), (1e3, 1.0), (1.0, 1e-3), (1e-3, 1.0), (1.0, 1.000001), (1.000001, 1.0),
             (1.0, one_up), (one_up, 1.0), (1.0, one_dn), (1.5, 1.5), (1.0, 1.0), (3.7, 0.37)]
    return [(float(dtype(a)), float(dtype(b))) for a, b in pairs]


def _cosines(dtype, eta1, eta2):
    tiny = float(np.finfo(dtype).smallest_subnormal)
    cs = [0.0, tiny, 1e-38, 1e-20, 1e-8, 1e-3, 0.1, 0.3, 0.5, 0.7071067811865476, 0.9, 0.999, 1.0]
    if eta1 > eta2:  # the critical angle and its neighbours, within 1 to 100 ulps
        cc = dtype(np.sqrt((eta1 - eta2) * (eta1 + eta2)) / eta1)
        cs.append(float(cc))
        for k in (1, 2, 4, 100):
            up, dn = cc, cc
            for _ in range(k):
                up, dn = np.nextafter(up, dtype(2)), np.nextafter(dn, dtype(0))
            cs += [float(up), float(dn)]
    return [float(dtype(c)) for c in cs]


def _cases(dtype):
    return [(c, a, b) for a, b in _eta_pairs(dtype) for c in _cosines(dtype, a, b)]


def _check(got, cases, dtype, key_fn, label, ulps=4):
    """|got - ref| <= backward bound + `ulps` ulp(|ref|) + the smallest normal number.

    The last term is XLA's flush-to-zero: an output below the smallest normal number may be 0.
    Complex values are compared by modulus (normwise), the natural accuracy of complex arithmetic.
    """
    failures = []
    tiny = float(np.finfo(dtype).tiny)
    for g, (c, a, b) in zip(np.asarray(got), cases):
        ref, bound = backward_bound(
            lambda c, a, b: key_fn(fresnel_ref(c, a, b)), (c, a, b), dtype, specials=fresnel_specials, nonneg=(1, 2)
        )
        tol = bound + ulps * spacing(float(abs(ref)), dtype) + tiny
        g = mp.mpc(complex(g)) if np.iscomplexobj(g) else mp.mpf(float(g))
        err = abs(g - ref)
        if not err <= tol:
            failures.append((label, c, a, b, float(g), float(ref), float(err), float(tol)))
    assert not failures, failures[:10]


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
def test_fresnel_sp_rt_against_mpmath(dtype):
    cases = _cases(dtype)
    c, a, b = (jnp.asarray(np.array(x, dtype)) for x in zip(*cases))
    R_s, R_p = jo.fresnel_sp(c, a, b)
    R, T = jo.fresnel_rt(c, a, b)
    assert R_s.dtype == R.dtype == T.dtype == dtype
    _check(R_s, cases, dtype, lambda d: d["R_s"], "R_s")
    _check(R_p, cases, dtype, lambda d: d["R_p"], "R_p")
    _check(R, cases, dtype, lambda d: (d["R_s"] + d["R_p"]) / 2, "R")
    _check(T, cases, dtype, lambda d: (d["T_s"] + d["T_p"]) / 2, "T")
    np.testing.assert_array_equal(np.asarray(jo.fresnel(c, a, b)), np.asarray(R))


@pytest.mark.parametrize("dtype", DTYPES)
def test_amplitudes_against_mpmath(dtype):
    cases = _cases(dtype)
    c, a, b = (jnp.asarray(np.array(x, dtype)) for x in zip(*cases))
    amp = jo.fresnel_amplitudes(c, a, b)
    assert amp.r_s.dtype == np.result_type(dtype, np.complex64)
    for name in ("r_s", "r_p", "t_s", "t_p"):
        _check(getattr(amp, name), cases, dtype, lambda d, name=name: d[name], name, ulps=AMPLITUDE_ULPS)


@pytest.mark.parametrize("dtype", DTYPES)
def test_complex_index_against_mpmath(dtype):
    """Metals and absorbing media (n + ik): R_s, R_p, R, T and the amplitudes, same criterion,
    with the real and imaginary parts of eta2 perturbed as separate inputs."""
    etas = [0.2 + 3.0j, 1.5 + 0.01j, 0.05 + 4.2j, 2.5 + 2.5j, 1.33 + 1e-6j, 3.0 + 0j, 0.6 + 0j, 0.3 + 1e-4j]
    cos = [0.0, 1e-6, 0.1, 0.5, 0.9, 1.0, 0.8]
    cdt = np.result_type(dtype, np.complex64).type
    cases = [(float(dtype(c)), float(dtype(e.real)), float(dtype(e.imag))) for e in etas for c in cos]
    c = jnp.asarray(np.array([x[0] for x in cases], dtype))
    e2 = jnp.asarray(np.array([cdt(complex(x[1], x[2])) for x in cases]))
    R_s, R_p = jo.fresnel_sp(c, 1.0, e2)
    R, T = jo.fresnel_rt(c, 1.0, e2)
    amp = jo.fresnel_amplitudes(c, 1.0, e2)
    outputs = {"R_s": (R_s, 4), "R_p": (R_p, 4), "R": (R, 4), "T": (T, 4),
               "r_s": (amp.r_s, AMPLITUDE_ULPS), "r_p": (amp.r_p, AMPLITUDE_ULPS),
               "t_s": (amp.t_s, AMPLITUDE_ULPS), "t_p": (amp.t_p, AMPLITUDE_ULPS)}
    tiny = float(np.finfo(dtype).tiny)

    def pick(d, name):
        if name == "R":
            return (d["R_s"] + d["R_p"]) / 2
        if name == "T":
            return (d["T_s"] + d["T_p"]) / 2
        return d[name]

    failures = []
    for name, (vals, ulps) in outputs.items():
        for g, (cc, n, k) in zip(np.asarray(vals), cases):
            ref, bound = backward_bound(
                lambda c, n, k, name=name: pick(fresnel_ref(c, mp.mpf(1), mp.mpc(n, k)), name), (cc, n, k), dtype, nonneg=(1, 2)
            )
            g = mp.mpc(complex(g)) if np.iscomplexobj(g) else mp.mpf(float(g))
            if not abs(g - ref) <= bound + ulps * spacing(float(abs(ref)), dtype) + tiny:
                failures.append((name, cc, n, k, complex(g), complex(ref), float(bound)))
    assert not failures, failures[:10]


def test_the_oracle_keeps_its_precision_whatever_mpmath_is_set_to():
    """The references compute at their own 50 digits whatever precision the caller's mpmath
    context holds: near a cancellation (eta2 - eta1 = 1e-9 at grazing incidence, where 20 digits
    keep 11) a reference at the caller's 20 digits is off by 1e-14 in R, more than the 2e-15 the
    fits' model is held to."""
    args = (mp.mpf(1e-6), mp.mpf(1.0), mp.mpf(1.000000001))
    with mp.workdps(50):
        want = fresnel_ref(*args)["R_s"]
    for digits in (15, 20):
        with mp.workdps(digits):
            got = fresnel_ref(*args)["R_s"]
        assert abs(got - want) < mp.mpf(10) ** -40, digits
