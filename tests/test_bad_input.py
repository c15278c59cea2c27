"""Bad input: shapes, dtypes and options raise a clear ValueError at trace time (under jit too);
out-of-domain values give the documented value (NaN), never an exception."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxoptics as jo

V = jnp.array([0.6, 0.0, -0.8])
N = jnp.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("wrap", [lambda f: f, jax.jit], ids=["eager", "jit"])
def test_errors_at_trace_time(wrap):
    with pytest.raises(ValueError, match=r"i must have shape \(\.\.\., 3\).*\(4, 2\)"):
        wrap(lambda i: jo.refract(i, N, 1.0, 1.5))(jnp.ones((4, 2)))
    with pytest.raises(ValueError, match=r"n must have shape"):
        wrap(lambda n: jo.reflect(V, n))(jnp.ones(4))
    with pytest.raises(ValueError, match=r"cannot be broadcast.*i \(4, 3\).*n \(5, 3\)"):
        wrap(lambda i, n: jo.refract(i, n, 1.0, 1.5))(jnp.ones((4, 3)), jnp.ones((5, 3)))
    with pytest.raises(ValueError, match=r"cannot be broadcast.*cos_i \(3,\).*eta2 \(4,\)"):
        wrap(lambda c, e: jo.fresnel(c, 1.0, e))(jnp.ones(3), jnp.ones(4))
    with pytest.raises(ValueError, match=r"eta2 \(2, 3\)"):
        wrap(lambda e: jo.refract(jnp.ones((4, 3)), N, 1.0, e))(jnp.ones(2))
    with pytest.raises(ValueError, match=r"cos_i must have a floating dtype.*int32"):
        wrap(lambda c: jo.fresnel(c, 1.0, 1.5))(jnp.ones(3, jnp.int32))
    with pytest.raises(ValueError, match=r"eta1 must be real"):
        wrap(lambda e: jo.fresnel(0.5, e, 1.5))(jnp.ones(3, jnp.complex64))
    with pytest.raises(ValueError, match=r"eta2 must be real here"):
        wrap(lambda e: jo.refract(V, N, 1.0, e))(jnp.ones((), jnp.complex64))
    with pytest.raises(ValueError, match=r"eta2 must be real here"):
        wrap(lambda e: jo.schlick_tir(0.5, 1.0, e))(jnp.ones((), jnp.complex64))
    with pytest.raises(ValueError, match=r"boolean"):
        wrap(lambda c: jo.fresnel(c, 1.0, 1.5))(jnp.ones(3, bool))


def test_integer_arrays_and_bad_method():
    with pytest.raises(ValueError, match="floating dtype"):
        jo.refract(np.array([0, 0, -1]), N, 1.0, 1.5)
    with pytest.raises(ValueError, match="method must be one of"):
        jo.refract(V, N, 1.0, 1.5, method="snell")
    with pytest.raises(ValueError, match="complex"):
        jo.brewster_angle(1.0, 1.5 + 0.1j)
    # Python ints for indices are fine (weakly typed)
    assert float(jo.fresnel(1.0, 1, 2)) == pytest.approx(1 / 9)


@pytest.mark.slow
def test_documented_out_of_domain_values():
    """Values cannot raise under jit; what each produces is documented in the kernels."""
    nan = float("nan")
    f = jax.jit(lambda c, a, b: (jo.fresnel(c, a, b), *jo.fresnel_rt(c, a, b), jo.schlick(c, a, b), jo.schlick_tir(c, a, b)))
    bad = [(nan, 1.0, 1.5), (0.5, nan, 1.5), (0.5, 1.0, nan), (jnp.inf, 1.0, 1.5), (0.5, 0.0, 1.5),
           (0.5, 1.0, -1.5), (0.5, jnp.inf, 1.5), (0.5, 1.0, 0.0)]
    for c, a, b in bad:
        for out in f(jnp.float64(c), jnp.float64(a), jnp.float64(b)):
            assert np.isnan(float(out)), (c, a, b)
    amp = jo.fresnel_amplitudes(0.5, 1.0, -2.0)
    assert all(np.isnan(complex(x)).all() for x in amp)
    # complex index with negative real part or gain (k < 0): NaN
    assert np.isnan(float(jo.fresnel(0.5, 1.0, -1.0 + 2.0j)))
    assert np.isnan(float(jo.fresnel(0.5, 1.0, 1.5 - 0.1j)))
    # the sign of cos_i is ignored
    assert float(jo.fresnel(-0.5, 1.0, 1.5)) == float(jo.fresnel(0.5, 1.0, 1.5))
    # |cos_i| slightly above 1 (rounding of a dot product) stays finite and continuous
    c1 = np.nextafter(1.0, 2.0)
    assert abs(float(jo.fresnel(c1, 1.0, 1.5)) - 0.04) < 1e-15
    # zero or non-finite vectors, non-positive indices: NaN direction, tir False
    cases = [(jnp.zeros(3), N, 1.0, 1.5), (V, jnp.zeros(3), 1.0, 1.5), (V.at[0].set(jnp.nan), N, 1.0, 1.5),
             (V.at[0].set(jnp.inf), N, 1.0, 1.5), (V, N, 0.0, 1.5), (V, N, 1.0, -1.0), (V, N, jnp.nan, 1.5)]
    for i, n, a, b in cases:
        for method in ("degreve", "bec", "heckbert", "oliveira"):
            t, tir = jax.jit(lambda i, n, a, b: jo.refract(i, n, a, b, method=method))(i, n, a, b)
            assert np.all(np.isnan(np.asarray(t))) and not bool(tir), (i, n, a, b, method)
    for i, n in ((jnp.zeros(3), N), (V, jnp.zeros(3)), (V.at[1].set(jnp.inf), N)):
        assert np.all(np.isnan(np.asarray(jo.reflect(i, n))))
    for a, b in ((0.0, 1.0), (1.0, -1.0), (jnp.nan, 1.0), (jnp.inf, 1.0)):
        assert np.isnan(float(jo.critical_angle(a, b))) and np.isnan(float(jo.brewster_angle(a, b)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_non_finite_cos_gives_nan_in_every_regime(dtype):
    """`fresnel` has no per-element finiteness test for a real index: a non-finite cos_i must reach
    NaN through the arithmetic in every branch (entering and leaving the denser medium, the
    eta1 > 2 eta2 form of k_t^2, equal indices, extreme ratios), with the indices as constants,
    traced scalars and arrays, while finite lanes beside them keep their values."""
    c = np.array([np.inf, -np.inf, np.nan, 0.0, 1e-30, 0.3, 1.0], dtype)
    pairs = [(1.0, 1.5), (1.5, 1.0), (1.2, 1.2), (3.5, 1.0), (1.0, 1e3), (1e3, 1.0), (1.0, 1.0 + 1e-6)]
    for e1, e2 in pairs:
        runs = {
            "constants": jax.jit(lambda c: jo.fresnel(c, dtype(e1), dtype(e2)))(c),
            "traced scalars": jax.jit(jo.fresnel)(c, dtype(e1), dtype(e2)),
            "arrays": jax.jit(jo.fresnel)(c, np.full(c.shape, e1, dtype), np.full(c.shape, e2, dtype)),
        }
        # finite lanes: the s and p values, which keep their own finiteness test
        R_s, R_p = jo.fresnel_sp(c[3:], dtype(e1), dtype(e2))
        for how, R in runs.items():
            R = np.asarray(R)
            assert R.dtype == dtype
            assert np.isnan(R[:3]).all(), (e1, e2, how, R)
            eps = np.finfo(dtype).eps
            np.testing.assert_allclose(R[3:], 0.5 * (R_s + R_p), rtol=4 * eps, atol=4 * eps, err_msg=f"{e1, e2, how}")


@pytest.mark.parametrize("x", [np.float64(1.0), np.zeros((0, 3))], ids=["scalar", "empty"])
def test_shard_batch_refuses_a_missing_or_empty_batch_axis(x):
    with pytest.raises(ValueError, match="non-empty leading batch axis"):
        jo.shard_batch(x)
