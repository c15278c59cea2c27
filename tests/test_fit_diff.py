"""Derivatives of fitted indices with respect to the data (implicit function theorem), checked
against central finite differences of the whole fit, started anew at each perturbed data set."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import quick_jit as _jit

import jaxoptics as jo

TH = np.deg2rad(np.linspace(5, 80, 40))


# central-difference weights (offset in steps, weight) of second and fourth order
_STENCILS = {2: ((-1, -1 / 2), (1, 1 / 2)), 4: ((-2, 1 / 12), (-1, -8 / 12), (1, 8 / 12), (2, -1 / 12))}


def _fd(f, x, h, idx, order=2):
    """Central differences of f along the unit vectors `idx` of x (or along x itself if scalar)."""
    x = np.asarray(x, np.float64)
    out = []
    for i in idx:
        e = np.zeros_like(x)
        e.flat[i] = h
        out.append(sum(w * np.asarray(f(x + k * e)) for k, w in _STENCILS[order]) / h)
    return np.stack(out)


@pytest.mark.slow
@pytest.mark.parametrize("pol", ["unpolarized", "s", "p"])
def test_index_derivative_in_the_data(pol):
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(0), 1.5, TH, polarization=pol, noise=1e-3))
    f = lambda R: jo.fit_eta(TH, R, polarization=pol).eta
    g, g_fwd = _jit(lambda R: (jax.grad(f)(R), jax.jacfwd(f)(R)))(R)  # one compiled program
    idx = np.arange(0, 40, 3)
    np.testing.assert_allclose(g[idx], _fd(f, R, 1e-6, idx), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(g_fwd, g, rtol=1e-12, atol=1e-15)  # forward = reverse
    # every data point counts: the sensitivities of a least-squares estimate sum to dq/dR of a
    # uniform shift, which moves the fitted curve; for R_model linear in eta locally,
    # sum_j (d eta / d R_j) * (d R_j / d eta) = 1
    dR = jax.jacfwd(lambda e: jo.synthetic_reflectance(None, e, TH, polarization=pol))(jo.fit_eta(TH, R, polarization=pol).eta)
    assert abs(float(jnp.sum(g * dR)) - 1) < 1e-2


@pytest.mark.slow
def test_derivatives_in_eta1_angles_and_sigma():
    eta1 = 1.33
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(1), 1.6, TH, eta1=eta1, noise=1e-3))
    sig = np.linspace(1e-3, 3e-3, TH.size)
    f_eta1 = lambda e1: jo.fit_eta(TH, R, eta1=e1, sigma=sig).eta
    np.testing.assert_allclose(_jit(jax.grad(f_eta1))(eta1), _fd(f_eta1, eta1, 1e-6, [0])[0], rtol=1e-6)
    f_th = lambda th: jo.fit_eta(th, R, eta1=eta1, sigma=sig).eta
    np.testing.assert_allclose(_jit(jax.grad(f_th))(TH)[::5], _fd(f_th, TH, 1e-7, range(0, 40, 5)), rtol=1e-5, atol=1e-9)
    f_sig = lambda s: jo.fit_eta(TH, R, eta1=eta1, sigma=s).eta
    g_sig = _jit(jax.grad(f_sig))(sig)
    np.testing.assert_allclose(g_sig[::5], _fd(f_sig, sig, 1e-9, range(0, 40, 5)), rtol=1e-5, atol=1e-9)
    # a common scale of sigma changes nothing
    assert abs(float(jnp.sum(g_sig * sig))) < 1e-9


@pytest.mark.slow
def test_internal_reflection_and_complex_derivatives():
    # internal reflection with a TIR plateau in the data
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(2), 1.2, TH, eta1=1.5, noise=1e-3))
    f = lambda R: jo.fit_eta(TH, R, eta1=1.5).eta
    np.testing.assert_allclose(_jit(jax.grad(f))(R)[::4], _fd(f, R, 1e-6, range(0, 40, 4)), rtol=1e-5, atol=1e-8)
    # a metal: n and k, each with its own derivative. Levenberg-Marquardt locates the minimum to
    # about 1e-10 even with tight tolerances (where it stops depends on rounding), so the
    # differences are fourth order over a step of 3e-3 in R: that noise is then about 1e-10 / 3e-3
    # (a central difference over 1e-4 has 1e-6, 1e-5 of these derivatives)
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(3), 0.2 + 3.0j, TH, noise=1e-3))
    lm = optx.LevenbergMarquardt(rtol=1e-14, atol=1e-14)
    for part in (jnp.real, jnp.imag):
        f = lambda R: part(jo.fit_eta(TH, R, absorbing=True, solver=lm, max_steps=1000).eta)
        np.testing.assert_allclose(_jit(jax.grad(f))(R)[::4], _fd(f, R, 3e-3, range(0, 40, 4), order=4), rtol=1e-5, atol=1e-8)


@pytest.mark.slow
def test_error_and_chi2_derivatives():
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(4), 2.0, TH, noise=1e-3))
    fields = ("stderr", "chi2_reduced", "residual_rms")
    grads = _jit(lambda R: [jax.grad(lambda R: getattr(jo.fit_eta(TH, R), f))(R) for f in fields])(R)
    for field, g in zip(fields, grads):
        f = lambda R: getattr(jo.fit_eta(TH, R), field)
        np.testing.assert_allclose(g[::6], _fd(f, R, 1e-7, range(0, 40, 6)), rtol=1e-4, atol=1e-10, err_msg=field)


@pytest.mark.slow
def test_batched_derivatives_under_jit_and_vmap():
    etas = jnp.array([1.3, 1.7, 2.5])
    R = jo.synthetic_reflectance(jax.random.PRNGKey(5), etas, TH, noise=1e-3)
    one = lambda r: jo.fit_eta(TH, r).eta
    grad_one = _jit(jax.grad(one))
    per_curve = jnp.stack([grad_one(R[i]) for i in range(3)])
    batched = _jit(jax.vmap(jax.grad(one)))(R)
    np.testing.assert_allclose(batched, per_curve, rtol=1e-9, atol=1e-14)
    # the batch fit's Jacobian is block-diagonal: curve i's estimate depends on curve i's data only
    J = _jit(jax.jacrev(lambda R: jo.fit_eta(TH, R).eta))(R)  # (3, 3, m)
    np.testing.assert_allclose(J[np.arange(3), np.arange(3)], per_curve, rtol=1e-9, atol=1e-14)
    assert float(jnp.max(jnp.abs(J[~np.eye(3, dtype=bool)]))) == 0.0


@pytest.mark.slow
def test_unconverged_fits_have_nan_derivatives():
    R = np.asarray(jo.synthetic_reflectance(None, 1.5, TH))
    g = _jit(jax.grad(lambda R: jo.fit_eta(TH, R, max_steps=1, init=3.0).eta))(R)
    assert bool(jnp.all(jnp.isnan(g)))
