"""Property tests (hypothesis): invariants over inputs drawn with extra weight near the
singularities (grazing, normal incidence, the critical angle, equal indices)."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxoptics as jo

eta = st.one_of(st.floats(1e-3, 1e3), st.sampled_from([1.0, 1.5, 1.333, 1.0 + 2**-52, 1.0 - 2**-53]))
cosine = st.one_of(st.floats(0.0, 1.0), st.sampled_from([0.0, 1.0, 5e-324, 1e-300, 1e-20, 1e-8, 1 - 2**-53]))


@st.composite
def near_critical(draw):
    a = draw(st.floats(1.01, 10.0))
    b = draw(st.floats(0.1, 0.99)) * a
    cc = np.sqrt((a - b) * (a + b)) / a
    k = draw(st.integers(-50, 50))
    c = cc
    for _ in range(abs(k)):
        c = np.nextafter(c, 2.0 if k > 0 else 0.0)
    return float(c), a, b


def _check_fresnel(c, a, b):
    R, T = jo.fresnel_rt(jnp.float64(c), jnp.float64(a), jnp.float64(b))
    R_s, R_p = jo.fresnel_sp(jnp.float64(c), jnp.float64(a), jnp.float64(b))
    R, T, R_s, R_p = (float(x) for x in (R, T, R_s, R_p))
    assert 0 <= R <= 1 and 0 <= T <= 1
    assert 0 <= R_s <= 1 and 0 <= R_p <= 1
    assert abs(R + T - 1) <= 4e-16
    # R of `fresnel_rt` and the mean of `fresnel_sp` are compiled as separate fused loops, each
    # contracting its multiply-adds its own way: they agree to rounding, and within an ulp or two
    # of the critical angle (where R is ill-conditioned) to what moving the inputs by 2 ulps
    # changes, the accuracy both document
    cs = np.array([c, np.nextafter(np.nextafter(c, 2), 2), np.nextafter(np.nextafter(c, -1), -1)])
    spread_R = float(np.max(np.abs(np.asarray(jo.fresnel_rt(cs, a, b)[0]) - R)))
    assert abs(R - (R_s + R_p) / 2) <= 2e-16 + spread_R
    if a == b:
        assert R == 0 and T == 1
    # The complex path (amplitudes) and the real path agree to within what moving the inputs by
    # 2 ulps changes (both are backward stable; near the critical angle that is a lot).
    amp = jo.fresnel_amplitudes(jnp.float64(c), jnp.float64(a), jnp.float64(b))
    for k, (r, Rk) in enumerate(((amp.r_s, R_s), (amp.r_p, R_p))):
        nb = np.asarray(jo.fresnel_sp(cs, a, b)[k])
        spread = np.max(np.abs(nb - Rk)) + 2 * abs(float(jo.fresnel_sp(c, a, b * (1 + 4e-16))[k]) - Rk)
        # amplitudes: 8 ulps documented (so 16 for |r|^2); R_s, R_p: 4 ulps
        assert abs(abs(complex(r)) ** 2 - Rk) <= spread + 20 * np.finfo(float).eps * Rk + 1e-300, (k, c, a, b)


@pytest.mark.slow
@given(cosine, eta, eta)
def test_fresnel_invariants(c, a, b):
    _check_fresnel(c, a, b)


@pytest.mark.slow
@given(near_critical())
def test_fresnel_invariants_near_critical(x):
    _check_fresnel(*x)


@pytest.mark.slow
@given(st.floats(0, np.pi / 2), st.floats(0, 2 * np.pi), eta, eta, st.booleans())
def test_refract_invariants(theta, phi, a, b, flip):
    n = np.array([0.0, 0.0, -1.0 if flip else 1.0])
    i = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)])
    t, tir = jo.refract(i, n, a, b)
    t = np.asarray(t)
    assert np.all(np.isfinite(t))
    assert abs(np.linalg.norm(t) - 1) < 1e-14 * max(1.0, a / b)
    sin_i = np.hypot(i[0], i[1])
    if not bool(tir):
        assert t[2] * i[2] >= 0  # into medium 2
        assert abs(a * sin_i - b * np.hypot(t[0], t[1])) <= 1e-14 * max(a, b)
    else:
        assert a * sin_i >= b * (1 - 1e-15)
        np.testing.assert_allclose(t, np.asarray(jo.reflect(i, n)), rtol=0, atol=4e-16)  # refract normalizes i
