"""Index fitting: recovery of known indices (data from tmm, an independent implementation),
statistical honesty of the errors, batching, degenerate data, the CSV reader and the CLI."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tmm
from helpers import quick_jit

import jaxoptics as jo
from jaxoptics.__main__ import main  # in-process calls pass --no-cache: the compilation cache is process-wide

THETA = np.deg2rad(np.linspace(0, 85, 90))


# ---- every fit in this file, also under jax.jit and jax.vmap ----

# How closely a fit under jit or vmap must agree with the eager one. The programs differ (XLA fuses
# the caller's operations, vmap batches the loops), so rounding differs, and an iterative solve
# stops within its tolerance (rtol 1e-9) of the minimum, not on the same bits; Levenberg-Marquardt
# near that tolerance can take many more or fewer steps to stop. So: estimates agree to 1e-7
# relative (100x the tolerance) or to 1e-3 of their standard error; errors, covariances and
# chi-square (first-order quantities at the estimate, themselves known only to about 10%) to 1e-3
# relative, where they are not rounding (an error below 1e-9 of the estimate, on noise-free data);
# convergence flags exactly; step counts are not compared.
_ESTIMATES = ("eta", "eta_alt")


def _parts(x):
    x = np.asarray(x)
    return np.stack([x.real, x.imag]) if np.iscomplexobj(x) else x


def _assert_same(got, want, how):
    """Every field of two fit results (dicts of field name to array) the same, to the solver's
    tolerance (see above)."""
    est, se = _parts(want["eta"]), _parts(want["stderr"])
    small = 1e-9 * np.max(np.abs(est[np.isfinite(est)]), initial=0)  # an error below this is rounding
    assert got.keys() == want.keys()
    for name in want:
        if name == "num_steps":
            continue
        a, b = _parts(want[name]), _parts(got[name])
        if a.dtype.kind == "b":
            np.testing.assert_array_equal(b, a, err_msg=f"{how}: {name}")
            continue
        with np.errstate(invalid="ignore"):
            if name in _ESTIMATES:
                tol = np.maximum(1e-7 * np.abs(a), 1e-3 * np.where(np.isfinite(se), se, 0))
            elif name == "stderr":
                tol = np.maximum(1e-3 * np.abs(a), small)
            elif name == "covariance":
                d = np.abs(np.diagonal(a, axis1=-2, axis2=-1))
                tol = 1e-3 * np.sqrt(d[..., :, None] * d[..., None, :]) + small ** 2
            else:  # residual_rms, chi2_reduced, condition_number
                tol = 1e-3 * np.abs(a) + 1e-13 * (name == "residual_rms") + 1e-20 * (name == "chi2_reduced")
            ok = (np.isnan(a) & np.isnan(b)) | (a == b) | (np.abs(b - a) <= tol)
        assert ok.all(), f"{how}: {name}: {np.count_nonzero(~ok)} of {ok.size} differ, e.g. {b[~ok][:3]} against {a[~ok][:3]}"


def _fields(fit):
    return {f.name: getattr(fit, f.name) for f in dataclasses.fields(fit)}


def _checked_fit_eta(theta, R, *, sigma=None, init=None, eta1=1.0, **kw):
    """`fit_eta` called eagerly and under `jax.jit`: the two agree (the fit and its follow-up solves
    are one JAX program, whatever the caller does with it). `jax.vmap` is compared in
    `test_fit_result_under_jit_and_vmap`. Under `jit` the index of the first medium is an argument
    (one program for every `eta1`)."""
    if any(isinstance(x, jax.core.Tracer) for x in (theta, R, sigma, init, eta1)):  # a test's own jit
        return _fit_eta(theta, R, sigma=sigma, init=init, eta1=eta1, **kw)
    eager = _fit_eta(theta, R, sigma=sigma, init=init, eta1=eta1, **kw)  # raises on bad data, before tracing
    kw = tuple(sorted(kw.items()))
    _assert_same(_jit_fit_eta(theta, R, sigma, init, np.asarray(eta1, np.asarray(R).dtype), kw), _fields(eager), "jit")
    return eager


# The callers' programs are compiled with the package's quick options (`QUICK_COMPILE`, as a
# caller may choose them): the comparison is of the same fit eagerly and under the caller's `jit`,
# to the tolerances above, and these programs compile in well under half the time.
@functools.partial(quick_jit, static_argnames="kw")
def _jit_fit_eta(theta, R, sigma, init, eta1, kw):
    """One jitted function for the whole file (the options static), so that cases with the same
    shapes and options share one compilation."""
    return _fields(_fit_eta(theta, R, sigma=sigma, init=init, eta1=eta1, **dict(kw)))


def _checked_fit_dispersion(wavelength_um, theta, R, **kw):
    """`fit_dispersion` eagerly and under `jax.jit`: the same index curve. (Compared through the
    fitted index at the data's wavelengths: Sellmeier coefficients lie along flat valleys, where
    solves that stop within tolerance can end far apart with the same index.)"""
    eager = _fit_dispersion(wavelength_um, theta, R, **kw)
    sigma = kw.pop("sigma", None)
    init = kw.pop("init", None)
    jitted = _jit_fit_dispersion(wavelength_um, theta, R, sigma, init, tuple(sorted(kw.items())))
    _assert_same(jitted, _dispersion_summary(eager, wavelength_um), "jit")
    return eager


def _dispersion_summary(fit, lam):
    n, se = fit.index(lam)
    return {"eta": n, "stderr": se, "converged": fit.converged, "chi2_reduced": fit.chi2_reduced,
            "residual_rms": fit.residual_rms}


@functools.partial(quick_jit, static_argnames="kw")
def _jit_fit_dispersion(lam, theta, R, sigma, init, kw):
    return _dispersion_summary(_fit_dispersion(lam, theta, R, sigma=sigma, init=init, **dict(kw)), lam)


_fit_eta, _fit_dispersion = jo.fit_eta, jo.fit_dispersion


@pytest.fixture(autouse=True)
def _fits_both_ways(monkeypatch):
    monkeypatch.setattr(jo, "fit_eta", _checked_fit_eta)
    monkeypatch.setattr(jo, "fit_dispersion", _checked_fit_dispersion)


def tmm_curve(n1, n2, theta, pol):
    """Reflectance from tmm (transfer matrices): the oracle, independent of jaxoptics."""
    def one(p):
        return np.array([tmm.coh_tmm(p, [n1, n2], [np.inf, np.inf], t, 0.6)["R"] for t in theta])
    if pol == "unpolarized":
        return (one("s") + one("p")) / 2
    return one(pol)


@pytest.mark.slow
@pytest.mark.parametrize("eta2", [1.01, 1.333, 1.5, 2.4, 4.0])
@pytest.mark.parametrize("pol", ["unpolarized", "s", "p"])
def test_recovers_index_from_tmm_data(eta2, pol):
    R = tmm_curve(1.0, eta2, THETA, pol)
    r = jo.fit_eta(THETA, R, polarization=pol)
    assert bool(r.converged)
    assert abs(float(r.eta) - eta2) < 1e-7 * eta2


@pytest.mark.slow
@pytest.mark.parametrize("eta1,eta2", [(1.5, 1.0), (1.5, 1.2), (1.333, 1.0), (2.4, 1.5), (1.5, 1.45)])
def test_internal_reflection_with_tir_plateau(eta1, eta2):
    R = tmm_curve(eta1, eta2, THETA, "unpolarized")
    r = jo.fit_eta(THETA, R, eta1=eta1)
    assert bool(r.converged) and abs(float(r.eta) - eta2) < 1e-7


@pytest.mark.slow
@pytest.mark.parametrize("eta2", [0.2 + 3.0j, 1.5 + 0.5j, 2.5 + 2.5j, 0.05 + 4.2j, 1.45 + 0.0j])
def test_recovers_complex_index_from_tmm_data(eta2):
    R = tmm_curve(1.0, eta2, THETA, "unpolarized")
    r = jo.fit_eta(THETA, R, absorbing=True)
    assert bool(r.converged)
    assert abs(complex(r.eta) - eta2) < 1e-7 * abs(eta2)
    assert r.eta.real > 0 and r.eta.imag >= 0
    if eta2.imag == 0:  # k = 0: R is quadratic in k there, so its first-order error is unbounded
        assert np.isinf(float(r.stderr.imag)) and np.isfinite(float(r.stderr.real))
    else:
        assert np.all(np.isfinite(np.asarray(r.covariance)))


def test_synthetic_reflectance_matches_tmm():
    for n2, pol in ((1.5, "s"), (0.2 + 3j, "p"), (2.0, "unpolarized")):
        np.testing.assert_allclose(np.asarray(jo.synthetic_reflectance(None, n2, THETA, polarization=pol)),
                                   tmm_curve(1.0, n2, THETA, pol), atol=1e-13)


@pytest.mark.slow
def test_errors_are_honest_cramer_rao():
    """sigma = 1e-3 over 0-85 degrees: all converge; the spread of the estimates matches the reported
    standard error within 20% (it is the Cramer-Rao bound here); ~95% within 2 standard errors."""
    N = 3000
    key = jax.random.PRNGKey(42)
    for eta, sigma in ((1.5, None), (1.5, 1e-3), (2.4, None)):
        R = jo.synthetic_reflectance(key, jnp.full(N, eta), THETA, noise=1e-3)
        r = jo.fit_eta(THETA, R, sigma=sigma)
        assert bool(jnp.all(r.converged))
        spread = float(jnp.std(r.eta))
        reported = float(jnp.sqrt(jnp.mean(r.stderr**2)))
        assert abs(spread / reported - 1) < 0.2, (spread, reported)
        within = float(jnp.mean(jnp.abs(r.eta - eta) < 2 * r.stderr))
        assert 0.93 < within < 0.975, within  # binomial: 0.954 +- 3 sd for N = 3000


@pytest.mark.slow
@pytest.mark.parametrize("degrees", [(0, 85), (20, 70)])
def test_internal_reflection_errors_are_honest(degrees):
    """Noisy internal reflection (eta1 = 1.5, eta2 from 1.0 to 1.49, sigma = 1e-3). Two ways to
    a confident wrong answer, both seen before they were fixed:
    - the sum of squares has a kink wherever the critical angle sits on a data angle, where a
      residual's derivative is infinite; started there (the TIR-onset estimate), Gauss-Newton
      stayed: 8% of fits 5 to 30x the noise away, standard errors of 1e-9, |z| up to 2e6;
    - with the critical angle beyond the data (20-70 degrees), eta2 < eta1 and eta2 > eta1 give
      similar curves: 2.5% of fits took the branch that fits worse (|z| up to 27), and where both
      fit alike the local standard error ignored the other. Both branches are now solved, and
      where the data cannot tell them apart `eta_alt` says so and the error includes it."""
    etas = np.linspace(1.0, 1.49, 400)
    theta = jnp.deg2rad(jnp.linspace(*degrees, 60))
    R = jo.synthetic_reflectance(jax.random.PRNGKey(3), jnp.asarray(etas), theta, eta1=1.5, noise=1e-3)
    r = jo.fit_eta(theta, R, eta1=1.5)
    assert bool(jnp.all(r.converged))
    z = np.abs(np.asarray(r.eta) - etas) / np.asarray(r.stderr)
    assert np.max(z) < 5 and np.mean(z > 3) < 0.01, (np.max(z), np.mean(z > 3))
    assert 0.92 < np.mean(z < 2) < 0.985  # binomial: 0.954 +- 3 sd for N = 400
    alt = np.asarray(r.eta_alt)
    ambiguous = np.isfinite(alt)
    if degrees == (0, 85):  # the TIR plateau tells the branches apart
        assert not ambiguous.any()
    else:
        assert 0.01 < np.mean(ambiguous) < 0.2, np.mean(ambiguous)
        eta = np.asarray(r.eta)[ambiguous]
        assert np.all((eta < 1.5) != (alt[ambiguous] < 1.5))  # the other branch
        assert np.all(np.asarray(r.stderr)[ambiguous] >= np.abs(eta - alt[ambiguous]))


@pytest.mark.slow
@pytest.mark.parametrize("degrees", [(0, 15), (0, 30)])
def test_small_angle_range_branch_ambiguity_is_reported(degrees):
    """External reflection measured at small angles only: eta2 and eta1^2 / eta2 have the same
    normal-incidence reflectance, and with noise 1e-3 the data cannot always tell them apart
    (0.55 fitted for 1.82 with a standard error of 3e-4, |z| = 4500, before both branches were
    solved). Now no |z| beyond what Gaussian errors give, and the other solution is reported."""
    etas = np.linspace(1.2, 4.0, 400)
    theta = jnp.deg2rad(jnp.linspace(*degrees, 40))
    R = jo.synthetic_reflectance(jax.random.PRNGKey(0), jnp.asarray(etas), theta, noise=1e-3)
    r = jo.fit_eta(theta, R)
    assert bool(jnp.all(r.converged))
    z = np.abs(np.asarray(r.eta) - etas) / np.asarray(r.stderr)
    assert np.max(z) < 5 and np.mean(z > 3) < 0.015, (np.max(z), np.mean(z > 3))
    alt = np.asarray(r.eta_alt)
    ambiguous = np.isfinite(alt)
    assert ambiguous.any()
    # the two solutions are close to mirror images (same normal-incidence reflectance)
    np.testing.assert_allclose(alt[ambiguous] * np.asarray(r.eta)[ambiguous], 1.0, rtol=0.05)


@pytest.mark.slow
def test_large_batch_in_blocks_matches_single_fits():
    """Batches larger than a block (about 2^17 points) are fitted block by block inside the one
    compiled call, the last block padded: every curve still gets its own fit."""
    from jaxoptics._fitting._index_solver import _BLOCK_POINTS

    B = 2 * (_BLOCK_POINTS // THETA.size) + 7  # three blocks, the last one padded
    etas = jnp.linspace(1.05, 3.5, B)
    R = jo.synthetic_reflectance(jax.random.PRNGKey(4), etas, THETA, noise=1e-3)
    r = jo.fit_eta(THETA, R)
    assert r.eta.shape == (B,) and bool(jnp.all(r.converged))
    for j in (0, B // 3, B // 2, B - 8, B - 1):
        one = jo.fit_eta(THETA, R[j])
        np.testing.assert_allclose(float(r.eta[j]), float(one.eta), rtol=1e-12)
        np.testing.assert_allclose(float(r.stderr[j]), float(one.stderr), rtol=1e-9)


@pytest.mark.slow
def test_curves_gauss_newton_does_not_finish_are_refitted():
    """Curves Gauss-Newton does not converge on within max_steps are refitted with
    Levenberg-Marquardt in a second batched call (over a padded subset) and reported honestly."""
    etas = jnp.array([1.05, 1.3, 1.5, 2.0, 2.5, 3.0, 4.0])
    R = jo.synthetic_reflectance(jax.random.PRNGKey(1), etas, THETA, noise=1e-3)
    full = jo.fit_eta(THETA, R)
    capped = jo.fit_eta(THETA, R, max_steps=3)
    assert capped.eta.shape == (7,) and int(jnp.max(capped.num_steps)) <= 3
    ok = np.asarray(capped.converged)
    assert not ok.all()
    np.testing.assert_allclose(np.asarray(capped.eta)[ok], np.asarray(full.eta)[ok], rtol=1e-6)


@pytest.mark.slow
def test_complex_errors_are_honest():
    N = 800
    eta = 0.2 + 3.0j
    R = jo.synthetic_reflectance(jax.random.PRNGKey(7), jnp.full(N, eta), THETA, noise=1e-3)
    r = jo.fit_eta(THETA, R, absorbing=True, sigma=1e-3)
    assert bool(jnp.all(r.converged))
    for part in (jnp.real, jnp.imag):
        spread = float(jnp.std(part(r.eta)))
        reported = float(jnp.sqrt(jnp.mean(part(r.stderr) ** 2)))
        assert abs(spread / reported - 1) < 0.2, (spread, reported)
    # the reported correlation of n and k matches the sample correlation
    sample = float(jnp.corrcoef(jnp.real(r.eta), jnp.imag(r.eta))[0, 1])
    assert abs(float(jnp.mean(r.corr_nk)) - sample) < 0.1


@pytest.mark.slow
def test_absorbing_fits_leave_the_k_zero_stationary_point():
    """R depends on k only through k^2, so a complex fit started at k = 0 stays there. The real
    physical estimates used to win the start on moderately absorbing media (n about 3, k about 1),
    and the fit reported n 40 standard errors off with k = 0 (2.2% of such curves, chi-square 20 to
    150 times the noise). Curves ending at k = 0 are now solved again from the grid with k > 0."""
    rng = np.random.default_rng(5)
    n, k = rng.uniform(2.6, 3.0, 300), rng.uniform(0.6, 1.3, 300)
    R = jo.synthetic_reflectance(jax.random.PRNGKey(5), jnp.asarray(n + 1j * k), THETA, noise=1e-3)
    r = jo.fit_eta(THETA, R, absorbing=True)
    assert bool(jnp.all(r.converged))
    for part, true in ((jnp.real, n), (jnp.imag, k)):
        z = np.abs(np.asarray(part(r.eta)) - true) / np.asarray(part(r.stderr))
        assert np.max(z) < 5 and np.mean(z > 3) < 0.015, (np.max(z), np.mean(z > 3))
    assert np.all(np.asarray(r.chi2_reduced) < 2e-6)  # noise 1e-3: chi2_reduced about 1e-6
    # data of a non-absorbing medium fitted as absorbing still come back with k near 0
    d = jo.fit_eta(THETA, jo.synthetic_reflectance(None, 1.5, THETA), absorbing=True)
    assert abs(complex(d.eta) - 1.5) < 1e-6


@pytest.mark.slow
def test_batch_equals_individual_fits_and_keeps_shape():
    etas = jnp.array([[1.2, 1.5, 3.0], [1.05, 2.0, 4.0]])
    R = jo.synthetic_reflectance(jax.random.PRNGKey(0), etas, THETA, noise=1e-3)
    r = jo.fit_eta(THETA, R)
    assert r.eta.shape == (2, 3) and r.covariance.shape == (2, 3, 1, 1)
    for a in range(2):
        for b in range(3):
            one = jo.fit_eta(THETA, R[a, b])
            np.testing.assert_allclose(float(one.eta), float(r.eta[a, b]), rtol=1e-12)
            np.testing.assert_allclose(float(one.stderr), float(r.stderr[a, b]), rtol=1e-9)


@pytest.mark.slow
def test_curves_in_different_polarizations_fit_in_one_call():
    """A batch whose curves are in different polarizations (one name per curve, broadcast to the
    batch shape) gives each curve the fit of its own polarization: the same estimates, errors and
    follow-ups (internal reflection's second branch, absorbing media's restart), in one call."""
    th = THETA[THETA < 1.2]
    pols = ("s", "p", "unpolarized")
    cases = [dict(eta1=1.0, etas=[1.33, 2.4]), dict(eta1=1.5, etas=[1.1, 1.45]), dict(eta1=1.0, etas=[0.2 + 3j, 1.5 + 0.5j])]
    for k, case in enumerate(cases):
        eta1, absorbing = case["eta1"], isinstance(case["etas"][0], complex)
        truth = np.array(case["etas"])[:, None] * np.ones(len(pols))  # (2, 3): polarization along the last axis
        rng = np.random.default_rng(k)
        R = np.stack([[tmm_curve(eta1, n, th, p) for p in pols] for n in case["etas"]]) + 1e-3 * rng.normal(size=truth.shape + th.shape)
        r = jo.fit_eta(th, R, eta1=eta1, polarization=pols, absorbing=absorbing)
        assert r.eta.shape == truth.shape and bool(jnp.all(r.converged))
        assert float(jnp.max(jnp.abs(r.eta - truth) / jnp.abs(r.stderr))) < 5
        for a in range(truth.shape[0]):
            for b, p in enumerate(pols):
                one = _fit_eta(th, R[a, b], eta1=eta1, polarization=p, absorbing=absorbing)  # (eager only)
                # Two programs (six curves, one curve), whose roundings may differ: Gauss-Newton (real
                # index) converges quadratically past its step tolerance (1e-9, `_tol`), to rounding;
                # Levenberg-Marquardt (complex) stops within it.
                rtol = 1e-8 if absorbing else 1e-12
                np.testing.assert_allclose(complex(r.eta[a, b]), complex(one.eta), rtol=rtol)
                np.testing.assert_allclose(complex(r.stderr[a, b]), complex(one.stderr), rtol=max(rtol, 1e-9))
                np.testing.assert_array_equal(np.asarray(r.eta_alt[a, b]), np.asarray(one.eta_alt))
    R = np.asarray(jo.synthetic_reflectance(None, jnp.array([1.5, 1.6]), THETA))
    with pytest.raises(ValueError, match=r"polarization\[1\] must be one of"):
        jo.fit_eta(THETA, R, polarization=("s", "te"))
    with pytest.raises(ValueError, match=r"polarization has shape \(3,\), which does not broadcast to the batch shape \(2,\)"):
        jo.fit_eta(THETA, R, polarization=("s", "p", "s"))


@pytest.mark.slow
def test_wide_range_all_converge():
    etas = jnp.concatenate([jnp.linspace(1.01, 4.0, 300)])
    R = jo.synthetic_reflectance(jax.random.PRNGKey(3), etas, THETA, noise=1e-3)
    r = jo.fit_eta(THETA, R)
    assert bool(jnp.all(r.converged))
    assert float(jnp.max(jnp.abs(r.eta - etas) / r.stderr)) < 5


@pytest.mark.slow
@pytest.mark.parametrize("case", ["external", "internal", "sigma_init", "absorbing"])
def test_fit_result_under_jit_and_vmap(case):
    """vmap over a batch axis agrees with the eager batch fit, for each kind of fit and its
    follow-ups: internal reflection (second-branch solves), sigma and init given, complex index
    (restarts from k > 0)."""
    key = jax.random.PRNGKey(11)
    kw, args = {}, {}
    if case == "internal":
        R = jo.synthetic_reflectance(key, jnp.array([1.1, 1.3, 1.45, 1.2]), THETA[THETA < 1.2], eta1=1.5, noise=1e-3)
        th, kw = THETA[THETA < 1.2], dict(eta1=1.5)
    elif case == "absorbing":
        R = jo.synthetic_reflectance(key, jnp.array([0.2 + 3j, 1.5 + 0.8j, 2.9 + 1j]), THETA, noise=1e-3)
        th, kw = THETA, dict(absorbing=True)
    else:
        R = jo.synthetic_reflectance(key, jnp.array([1.3, 1.7, 2.5]), THETA, noise=1e-3)
        th = THETA
        if case == "sigma_init":
            args = dict(sigma=jnp.full(R.shape, 1e-3), init=jnp.array([1.2, 1.9, 2.4]))
    eager = jo.fit_eta(th, R, **kw, **args)  # (the fixture also compares it under jit)
    one = lambda r, a: _fields(_fit_eta(th, r, **kw, **a))
    _assert_same(jax.vmap(one)(R, args), _fields(eager), "vmap")
    out = jax.jit(lambda r: r)(eager)  # FitResult is a pytree
    assert isinstance(out, jo.FitResult)


def test_degenerate_data_errors():
    with pytest.raises(ValueError, match="1 angle"):
        jo.fit_eta(THETA[:1], np.array([0.04]))
    with pytest.raises(ValueError, match="same reflectance"):
        jo.fit_eta(THETA, np.full(THETA.shape, 0.04))
    R = np.asarray(jo.synthetic_reflectance(None, 1.5, THETA)).copy()
    R[7] = np.nan
    with pytest.raises(ValueError, match=r"R\[7\] = nan is not finite"):
        jo.fit_eta(THETA, R)
    with pytest.raises(ValueError, match=r"theta\[0\] = -0.1 rad"):
        jo.fit_eta(np.r_[-0.1, THETA[1:]], np.asarray(jo.synthetic_reflectance(None, 1.5, THETA)))
    with pytest.raises(ValueError, match="sigma"):
        jo.fit_eta(THETA, np.asarray(jo.synthetic_reflectance(None, 1.5, THETA)), sigma=0.0)
    with pytest.raises(ValueError, match="polarization must be one of"):
        jo.fit_eta(THETA, np.asarray(jo.synthetic_reflectance(None, 1.5, THETA)), polarization="x")
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., 90\)"):
        jo.fit_eta(THETA, np.ones(80))


@pytest.mark.slow
def test_pure_noise_is_not_a_confident_answer():
    """Uniform noise in place of a reflectance curve: the errors are large or the fit is flagged."""
    rng = np.random.default_rng(0)
    R = rng.uniform(0, 1, size=(50, THETA.size))
    for sigma in (None, 0.01):
        r = jo.fit_eta(THETA, R, sigma=sigma)
        confident = np.asarray(r.converged) & (np.asarray(r.stderr) < 0.05 * np.asarray(r.eta))
        assert not np.any(confident & (np.asarray(r.chi2_reduced) < 2 if sigma else True))
        assert np.all(np.asarray(r.residual_rms) > 0.2)


# ---- dispersion ----

def test_published_indices():
    assert float(jo.material_index("fused_silica", 0.5893)) == pytest.approx(1.458403, abs=1e-6)  # Malitson 1965
    assert float(jo.material_index("N-BK7", 0.5876)) == pytest.approx(1.5168, abs=1e-4)  # SCHOTT n_d
    assert float(jo.material_index("water", 0.5893)) == pytest.approx(1.3333, abs=2e-4)  # Daimon & Masumura
    assert float(jo.cauchy(0.5, (1.5, 0.004, 1e-4))) == pytest.approx(1.5 + 0.004 / 0.25 + 1e-4 / 0.0625)
    with pytest.raises(ValueError, match="unknown material"):
        jo.material_index("unobtainium", 0.5)


@pytest.mark.slow
def test_dispersion_fit_recovers_fused_silica():
    lam = np.array([0.365, 0.405, 0.436, 0.486, 0.546, 0.633, 0.706, 0.852, 1.014, 1.33, 1.55])
    theta = np.deg2rad(np.linspace(0, 85, 60))
    R = np.stack([tmm_curve(1.0, float(jo.material_index("fused_silica", l)), theta, "unpolarized") for l in lam])
    f = jo.fit_dispersion(lam, theta, R, model="sellmeier")
    n, se = f.index(0.5893)
    assert bool(f.converged)
    assert abs(float(n) - 1.458403) < 1e-5
    # with noise (sigma = 1e-3) a 2-term law: the error at 589.3 nm is honest (within 3 standard
    # errors, for each of several noise draws)
    for seed in range(3):
        Rn = R + 1e-3 * np.random.default_rng(seed).normal(size=R.shape)
        f = jo.fit_dispersion(lam, theta, Rn, model="sellmeier", terms=2, sigma=1e-3)
        n, se = f.index(0.5893)
        assert bool(f.converged) and abs(float(n) - 1.458403) < 3 * float(se)
        assert 0.7 < float(f.chi2_reduced) < 1.3
    # Cauchy is a coarser law: it converges, its error at 589.3 nm is larger but still small
    fc = jo.fit_dispersion(lam, theta, R, model="cauchy")
    assert bool(fc.converged) and abs(float(fc.index(0.5893)[0]) - 1.458403) < 5e-4


@pytest.mark.slow
def test_dispersion_fit_reports_an_infrared_pole_beyond_the_data_honestly():
    """Fused silica's infrared pole lies at 9.9 um; data that end at 1.55 um see only its tail, so a
    2-term Sellmeier fit cannot place the pole. Over 24 noise draws: a pole put far beyond the data
    (|C_2| > 1000 um^2) always carries a standard error larger than itself, never a confident value;
    every fit converges except where the best fit lies at infinite coefficients (two poles merging
    with opposite B), which says so and carries standard errors larger than its B values; and the
    index at 589.3 nm scatters about Malitson's value as its own error says (RMS of
    (n - n_true)/stderr between 0.7 and 1.3)."""
    lam = np.array([0.365, 0.405, 0.436, 0.486, 0.546, 0.633, 0.706, 0.852, 1.014, 1.33, 1.55])
    theta = np.deg2rad(np.linspace(0, 85, 60))
    R = np.stack([tmm_curve(1.0, float(jo.material_index("fused_silica", l)), theta, "unpolarized") for l in lam])
    pulls, converged = [], 0
    for seed in range(100, 124):
        Rn = R + 1e-3 * np.random.default_rng(seed).normal(size=R.shape)
        f = jo.fit_dispersion(lam, theta, Rn, model="sellmeier", terms=2, sigma=1e-3)
        coef, se_coef = np.asarray(f.coefficients), np.asarray(f.stderr)
        assert abs(coef[3]) < 1e3 or se_coef[3] > abs(coef[3]), (seed, coef, se_coef)
        if bool(f.converged):
            converged += 1
        else:
            assert np.all(se_coef[:2] > np.abs(coef[:2])), (seed, coef, se_coef)
        n, se = f.index(0.5893)
        pulls.append((float(n) - 1.458403) / float(se))
    assert converged >= 22
    assert 0.7 < np.sqrt(np.mean(np.square(pulls))) < 1.3


@pytest.mark.slow
def test_dispersion_fit_gives_undetermined_coefficients_huge_errors():
    """A 3-term Sellmeier law on noisy data (fused silica from tmm, 0.365-1.55 um, noise 1e-3):
    in some draws two ultraviolet poles merge (C_1 = C_2), where only B_1 + B_2 is determined and
    any split fits as well. Such a fit must not report a confident split: the standard errors of
    B_1 and B_2 exceed their values. The index keeps an honest error in every draw (within 3 of
    its standard errors of Malitson's at 589.3 nm, the error below 1e-3)."""
    lam = np.array([0.365, 0.405, 0.436, 0.486, 0.546, 0.633, 0.706, 0.852, 1.014, 1.33, 1.55])
    theta = np.deg2rad(np.linspace(0, 85, 60))
    R = np.stack([tmm_curve(1.0, float(jo.material_index("fused_silica", l)), theta, "unpolarized") for l in lam])
    merged = 0
    for seed in range(100, 112):
        f = jo.fit_dispersion(lam, theta, R + 1e-3 * np.random.default_rng(seed).normal(size=R.shape),
                              model="sellmeier", terms=3, sigma=1e-3)
        coef, se_coef = np.asarray(f.coefficients), np.asarray(f.stderr)
        if abs(coef[3] - coef[4]) < 1e-3 * abs(coef[3]):
            merged += 1
            assert np.all(se_coef[:2] > np.abs(coef[:2])), (seed, coef, se_coef)
        n, se = f.index(0.5893)
        assert abs(float(n) - 1.458403) < 3 * float(se) and float(se) < 1e-3, (seed, float(n), float(se))
    assert merged >= 2


@pytest.mark.slow
def test_dispersion_index_error_is_the_same_along_an_undetermined_direction():
    """Two Sellmeier poles at one wavelength (C_1 = C_2) make a 3-term law that is exactly a 2-term
    law with B_1 + B_2: any split of B fits the same. Moving the solution along that split by hand
    must not change the index's standard error at any wavelength, and that error must be the
    2-term law's (its covariance (J^T J)^-1 has full rank: the textbook delta method in NumPy),
    while the errors of B_1 and B_2 themselves are huge."""
    from jaxoptics._fitting._dispersion_fit import DispersionFit, _estimate, _far_poles, _reciprocal, _residual_fn

    lam = np.array([0.365, 0.405, 0.436, 0.486, 0.546, 0.633, 0.706, 0.852, 1.014, 1.33, 1.55])
    theta = np.deg2rad(np.linspace(0, 85, 30))
    B, C, B3, C3 = 0.6961663 + 0.4079426, 0.0068, 0.8974794, 97.934  # silica's two UV poles merged
    two = np.array([B, B3, C, C3])
    n_true = np.sqrt(1 + B * lam**2 / (lam**2 - C) + B3 * lam**2 / (lam**2 - C3))
    R = np.stack([tmm_curve(1.0, float(n), theta, "unpolarized") for n in n_true])
    w = jnp.full(R.shape, 1e3)  # sigma = 1e-3; noise-free data, so the variance scale is 1
    lam_check = np.linspace(0.3, 1.7, 15)

    def index_error(p, terms):
        p = jnp.asarray(p)
        far = _far_poles("sellmeier", terms, p, jnp.asarray(lam))
        res = _residual_fn(jnp.asarray(theta), jnp.asarray(lam), jnp.asarray(R), w, 1.0, far, model="sellmeier",
                           terms=terms, polarization="unpolarized")
        q = _reciprocal("sellmeier", terms, p, far)
        got = _estimate(res, q, far, model="sellmeier", terms=terms, sigma_given=True)
        fit = DispersionFit("sellmeier", terms, got[0], got[1], got[3], True, 0.0, got[5], 0, got[6], got[2])
        return np.asarray(fit.index(lam_check)[1]), np.asarray(fit.stderr)

    # the 2-term oracle: J in (B, C) by forward differences of the model's residuals, (J^T J)^-1
    def residuals_two(p):
        n = np.sqrt(1 + p[0] * lam**2 / (lam**2 - p[2]) + p[1] * lam**2 / (lam**2 - p[3]))
        return (np.stack([tmm_curve(1.0, float(x), theta, "unpolarized") for x in n]) - R).ravel() * 1e3

    h = 1e-6 * np.maximum(np.abs(two), 1e-3)
    J = np.stack([(residuals_two(two + h[k] * np.eye(4)[k]) - residuals_two(two - h[k] * np.eye(4)[k])) / (2 * h[k])
                  for k in range(4)], 1)
    cov2 = np.linalg.inv(J.T @ J)
    g = lambda l: np.array([l**2 / (l**2 - C), l**2 / (l**2 - C3), B * l**2 / (l**2 - C) ** 2,  # noqa: E731
                            B3 * l**2 / (l**2 - C3) ** 2]) / (2 * np.sqrt(1 + B * l**2 / (l**2 - C) + B3 * l**2 / (l**2 - C3)))
    want = np.array([np.sqrt(g(l) @ cov2 @ g(l)) for l in lam_check])
    for split in (0.5, 0.1, 0.9, -2.0):
        se_n, se_coef = index_error([split * B, (1 - split) * B, B3, C, C, C3], 3)
        np.testing.assert_allclose(se_n, want, rtol=1e-5, err_msg=f"B split {split}")
        assert np.all(se_coef[:2] > 1e3 * B), (split, se_coef)
    np.testing.assert_allclose(index_error(two, 2)[0], want, rtol=1e-5)
    # Poles split by a little (where a solve stops near the merge): the direction that separates
    # them is determined, weakly (singular values ~1e-9 to 1e-7 of the largest), and its share of
    # the index variance does not depend on how weakly; the error is the same for every split.
    near = [index_error([0.5 * B, 0.5 * B, B3, C * (1 + e), C * (1 - e), C3], 3)[0] for e in (1e-7, 1e-6, 1e-5, 1e-4)]
    for e, se_n in zip((1e-6, 1e-5, 1e-4), near[1:]):
        np.testing.assert_allclose(se_n, near[0], rtol=1e-4, err_msg=f"poles split by {e}")


@pytest.mark.slow
def test_plot_dispersion_fit_draws_the_law_and_the_residuals():
    """`plot_dispersion_fit`: the fitted Cauchy law (its closed form from the coefficients) over the
    measured range, at each measured wavelength, and tmm's reflectance of the law's index minus the
    data, one series per wavelength; the title says when the fit did not converge."""
    import matplotlib.pyplot as plt

    lam = np.array([0.4, 0.5, 0.65, 0.8, 1.0])
    theta = np.deg2rad(np.linspace(0, 85, 30))
    R = np.stack([tmm_curve(1.0, float(jo.material_index("fused_silica", l)), theta, "s") for l in lam])
    R = R + 1e-3 * np.random.default_rng(5).normal(size=R.shape)
    f = jo.fit_dispersion(lam, theta, R, model="cauchy", terms=3, polarization="s", sigma=1e-3)
    A, B, C = np.asarray(f.coefficients)
    cauchy = lambda l: A + B / l**2 + C / l**4  # noqa: E731
    fig = jo.plot_dispersion_fit(lam, theta, R, f, polarization="s", title="silica")
    ax, axr = fig.axes[:2]
    law, marks = ax.get_lines()[:2]
    x, y = law.get_data()
    assert x.min() < lam.min() and x.max() > lam.max()
    np.testing.assert_allclose(y, cauchy(x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(marks.get_ydata(), cauchy(lam), rtol=0, atol=1e-12)
    series = [l for l in axr.get_lines() if l.get_marker() == "."]
    assert len(series) == lam.size
    for k, line in enumerate(series):  # drawn in order of wavelength, which lam already is
        np.testing.assert_allclose(line.get_ydata(), tmm_curve(1.0, cauchy(lam[k]), theta, "s") - R[k], rtol=0, atol=1e-12)
    assert axr.get_ylabel() == "model - data" and "NOT converged" not in fig._suptitle.get_text()
    plt.close(fig)
    fig = jo.plot_dispersion_fit(lam, theta, R, dataclasses.replace(f, converged=np.asarray(False)), polarization="s")
    assert fig._suptitle.get_text().endswith("the fit did NOT converge")
    plt.close(fig)
    with pytest.raises(ValueError, match=r"R \(w, m\)"):
        jo.plot_dispersion_fit(lam[:-1], theta, R, f)
    with pytest.raises(ValueError, match="polarization must be"):
        jo.plot_dispersion_fit(lam, theta, R, f, polarization="x")


# ---- CSV and CLI ----

def _write(tmp_path, text, name="data.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_load_reflectance_errors_name_file_line_value(tmp_path):
    cases = [
        ("", "is empty"),
        ("# only a comment\n", "is empty"),
        ("angle_deg,R\n", "no data rows"),
        ("angle,R\n10,0.04\n", r"missing required column 'angle_deg'.*did you mean angle_deg"),
        ("angle_deg;R\n10;0.04\n", r"line 1: columns are separated by commas; this header, 'angle_deg;R', separates them by semicolons"),
        ("angle_deg\tR\n10\t0.04\n", r"line 1: columns are separated by commas; .* separates them by tabs"),
        ("angle_deg,R\n10,0.04\n20\n", r"line 3: 1 fields, but the header \(line 1\) has 2"),
        ("angle_deg,R\n10,0.04\n20,abc\n", r"line 3: column 2 \(R\): 'abc' is not a number"),
        ("angle_deg,R\n10,nan\n", r"line 2: column 2 \(R\): 'nan' is not finite"),
        ("angle_deg,R\n95,0.04\n", r"line 2: column 1 \(angle_deg\): angle 95.0 deg is outside \[0, 90\]"),
        ("angle_deg,R\n10,1.2\n", r"line 2: column 2 \(R\): reflectance 1.2 is outside"),
        ("angle_deg,R,sigma\n10,0.04,0\n", r"line 2: column 3 \(sigma\): 0.0 must be positive"),
        ("angle_deg,R,polarization\n10,0.04,x\n", r"line 2: column 3 \(polarization\): unknown polarization 'x'"),
    ]
    for k, (text, pattern) in enumerate(cases):
        p = _write(tmp_path, text, f"c{k}.csv")
        with pytest.raises(ValueError, match=pattern) as e:
            jo.load_reflectance(p)
        assert str(p) in str(e.value)


def test_load_reflectance_groups_curves(tmp_path):
    text = "# comment\nangle_deg,R,polarization,wavelength_um,note\n20,0.05,s,0.5,a\n10,0.04,s,0.5,b\n10,0.03,TM,0.5,c\n10,0.04,s,0.6,d\n"
    d = jo.load_reflectance(_write(tmp_path, text))
    assert d.ignored_columns == ("note",)
    curves = d.curves()
    assert [(c.wavelength_um, c.polarization, c.R.size) for c in curves] == [(0.5, "p", 1), (0.5, "s", 2), (0.6, "s", 1)]
    np.testing.assert_allclose(curves[1].theta, np.deg2rad([10, 20]))  # sorted by angle
    np.testing.assert_array_equal(curves[1].lines, [4, 3])


@pytest.mark.slow
def test_cli_fit_example(capsys, tmp_path):
    out_png = tmp_path / "fit.png"
    assert main(["fit", "--example", "--plot", str(out_png), "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "combined at 0.5876 um" in out and out_png.stat().st_size > 10000
    # the combined estimate is within 4 standard errors of the index the example was made with
    line = [l for l in out.splitlines() if l.startswith("combined")][0]
    est, se = float(line.split("eta = ")[1].split()[0]), float(line.split("+- ")[1].split()[0])
    assert abs(est - float(jo.material_index("N-BK7", 0.5876))) < 4 * se
    # the lower panel shows model - data: the drawn model at each measured angle minus the measurement
    import matplotlib.pyplot as plt

    ax, axr = plt.gcf().axes[:2]
    assert axr.get_ylabel() == "model - data"
    fits = [l for l in ax.get_lines() if l.get_label().startswith("fit ")]
    assert fits
    for k, fit_line in enumerate(fits):
        data = ax.containers[k].lines[0]  # the errorbar's points
        resid = axr.containers[k].lines[0]
        xd, yd = data.get_data()
        np.testing.assert_array_equal(resid.get_xdata(), xd)
        drawn = np.interp(xd, *fit_line.get_data())
        np.testing.assert_allclose(resid.get_ydata(), drawn - yd, rtol=0, atol=1e-4)  # 400-point line: 3e-5
        assert np.max(np.abs(resid.get_ydata())) > 1e-3  # residuals far above the tolerance: the sign is tested
    plt.close("all")


@pytest.mark.slow
def test_cli_fit_file_and_errors(capsys, tmp_path):
    R = np.asarray(jo.synthetic_reflectance(None, 1.7, THETA[::5]))
    rows = "\n".join(f"{np.rad2deg(t):.6f},{r:.12f}" for t, r in zip(THETA[::5], R))
    p = _write(tmp_path, "angle_deg,R\n" + rows + "\n")
    assert main(["fit", str(p), "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "1.7000000" in out
    # without a wavelength column all rows are one curve (NaN wavelengths once made a curve per row)
    assert f"{R.size} points in 1 curve(s)" in out and out.count("1.7000000") == 1
    assert len(jo.load_reflectance(p).curves()) == 1
    bad = _write(tmp_path, "angle_deg,R\n10,0.04\n20,x\n", "bad.csv")
    assert main(["fit", str(bad), "--no-cache"]) == 2
    assert "bad.csv, line 3" in capsys.readouterr().err



@pytest.mark.slow
def test_cli_fits_curves_on_shared_angles_together(capsys, tmp_path):
    """Curves of several polarizations and wavelengths, on two sets of angles: each curve's line
    reports its own index (data from tmm), in the file's curve order."""
    th_a, th_b = THETA[::6], THETA[3::7]
    truth = [(0.5, "p", th_a, 1.45), (0.5, "s", th_b, 1.46), (0.6, "s", th_a, 1.70), (0.6, "unpolarized", th_a, 2.10)]
    rows = [f"{np.rad2deg(t):.10f},{r:.14f},{pol},{lam}" for lam, pol, th, n in truth
            for t, r in zip(th, tmm_curve(1.0, n, th, pol))]
    p = _write(tmp_path, "angle_deg,R,polarization,wavelength_um\n" + "\n".join(rows) + "\n")
    assert main(["fit", str(p), "--no-cache"]) == 0
    lines = [l.split() for l in capsys.readouterr().out.splitlines() if l.split()[:1] in (["0.5"], ["0.6"])]
    assert [(float(l[0]), l[1]) for l in lines] == [(lam, pol) for lam, pol, _, _ in truth]
    for l, (_, _, th, n) in zip(lines, truth):
        assert int(l[2]) == th.size and abs(float(l[3]) - n) < 1e-6


@pytest.mark.slow
def test_cli_fits_a_dispersion_law(capsys, tmp_path):
    """`fit --dispersion`: tmm s-reflectance of fused silica with noise at six wavelengths, sigma
    given. The printed coefficients are `fit_dispersion`'s on the same data, the printed index at
    each wavelength is within 4 standard errors of Malitson's, and --plot draws the law; files the
    law cannot be fitted to are refused with the reason."""
    import matplotlib.pyplot as plt

    lam = [0.4, 0.5, 0.6, 0.8, 1.0, 1.3]
    th = np.deg2rad(np.linspace(5, 85, 25))
    rng = np.random.default_rng(11)
    R = np.stack([tmm_curve(1.0, float(jo.material_index("fused_silica", l)), th, "s") for l in lam])
    R = R + 1e-3 * rng.normal(size=R.shape)
    rows = [f"{np.rad2deg(t):.10f},{r:.12f},s,{l},0.001" for l, Rl in zip(lam, R) for t, r in zip(th, Rl)]
    head = "angle_deg,R,polarization,wavelength_um,sigma\n"
    p = _write(tmp_path, head + "\n".join(rows[::-1]) + "\n")  # any row order
    png = tmp_path / "law.png"
    assert main(["fit", str(p), "--dispersion", "sellmeier", "--terms", "2", "--plot", str(png), "--no-cache"]) == 0
    out = capsys.readouterr().out.splitlines()
    direct = _fit_dispersion(np.array(lam), th, R, model="sellmeier", terms=2, polarization="s", sigma=1e-3)
    coef = [float(l.split()[-3]) for l in out if l.strip().startswith(("B_", "C_"))]
    np.testing.assert_allclose(coef, np.asarray(direct.coefficients), rtol=1e-6)
    start = [i for i, l in enumerate(out) if l.split()[:2] == ["wavelength_um", "n"]][0]
    table = np.array([[float(x) for x in l.split()] for l in out[start + 1:start + 1 + len(lam)]])
    np.testing.assert_array_equal(table[:, 0], lam)
    truth = np.asarray(jo.material_index("fused_silica", np.array(lam)))
    assert np.all(np.abs(table[:, 1] - truth) < 4 * table[:, 2]), (table, truth)
    assert png.stat().st_size > 10000 and "sellmeier" in plt.gcf()._suptitle.get_text()
    plt.close("all")

    def refused(text, *extra):
        f = _write(tmp_path, text, "bad.csv")
        assert main(["fit", str(f), "--dispersion", "cauchy", "--no-cache", *extra]) == 2
        return capsys.readouterr().err

    assert "choose one with --polarization" in refused(head + "\n".join(rows[:25] + [r.replace(",s,", ",p,") for r in rows[25:50]]) + "\n")
    err = refused(head + "\n".join(rows[:25] + rows[26:50]) + "\n")
    assert "same angles: 0.5 um (lines 27-50) has 24 angles, against 25 at 0.4 um (lines 2-26)" in err
    assert "needs a wavelength_um column" in refused("angle_deg,R\n" + "\n".join(r.rsplit(",", 3)[0] for r in rows[:25]) + "\n")
    assert "two or more wavelengths" in refused(head + "\n".join(rows[:25]) + "\n")
    assert "leave out --absorbing" in refused(head + "\n".join(rows) + "\n", "--absorbing")
    f = _write(tmp_path, head + "\n".join(rows) + "\n", "four.csv")
    assert main(["fit", str(f), "--dispersion", "sellmeier", "--terms", "4", "--no-cache"]) == 2
    assert "--terms 4 is not available" in capsys.readouterr().err
    assert "4 points cannot determine 6 coefficients" in refused(head + "\n".join(rows[0:50:25] + rows[1:50:25]) + "\n", "--terms", "6")
    assert main(["fit", str(p), "--terms", "2", "--no-cache"]) == 2
    assert "--terms goes with --dispersion" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_reports_an_index_the_data_cannot_exclude(capsys, tmp_path):
    """Measured at 0-15 degrees only, this curve (eta = 1.2) fits about as well with 0.834: the
    CLI says so next to the fit, and the standard error covers both."""
    theta = jnp.deg2rad(jnp.linspace(0, 15, 40))
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(0), jnp.linspace(1.2, 4.0, 400), theta, noise=1e-3))[0]
    rows = "\n".join(f"{np.rad2deg(t):.8f},{r:.10f}" for t, r in zip(np.asarray(theta), R))
    p = _write(tmp_path, "angle_deg,R\n" + rows + "\n", "small_angles.csv")
    assert main(["fit", str(p), "--no-cache"]) == 0
    out = capsys.readouterr().out
    note = [l for l in out.splitlines() if "fits these data almost as well" in l]
    assert len(note) == 1, out
    alt = float(note[0].split("eta = ")[1].split()[0])
    fit = jo.load_reflectance(p).curves()[0]
    r = jo.fit_eta(fit.theta, fit.R)
    assert abs(alt - float(r.eta_alt)) < 1e-6 and float(r.stderr) >= abs(float(r.eta) - alt)
    assert abs(alt * float(r.eta) - 1) < 0.05  # eta and 1 / eta: the same normal-incidence reflectance


def test_one_column_solver_matches_lineax_least_squares():
    """The closed-form one-column solver used by the default Gauss-Newton agrees with lineax's QR
    (least squares) and SVD (minimum norm, for the transposed 1 x m system), and returns the
    pseudo-inverse's 0 for a zero column."""
    import lineax as lx
    OneColumnLeastSquares = jo.OneColumnLeastSquares

    rng = np.random.default_rng(3)
    a, b, c = rng.normal(size=(90, 1)), rng.normal(size=90), rng.normal(size=1)
    op = lx.MatrixLinearOperator(jnp.asarray(a))
    x = lx.linear_solve(op, jnp.asarray(b), OneColumnLeastSquares()).value
    np.testing.assert_allclose(x, lx.linear_solve(op, jnp.asarray(b), lx.QR()).value, rtol=1e-12)
    np.testing.assert_allclose(x, np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-12)
    y = lx.linear_solve(op.T, jnp.asarray(c), OneColumnLeastSquares()).value
    np.testing.assert_allclose(y, lx.linear_solve(op.T, jnp.asarray(c), lx.SVD()).value, rtol=1e-12)
    np.testing.assert_allclose(a.T @ np.asarray(y), c, rtol=1e-12)
    zero = lx.MatrixLinearOperator(jnp.zeros((90, 1)))
    assert float(lx.linear_solve(zero, jnp.asarray(b), OneColumnLeastSquares()).value[0]) == 0.0
    # differentiating through the solve uses its transpose: d x / d b = a^T / (a . a)
    g = jax.grad(lambda bb: lx.linear_solve(op, bb, OneColumnLeastSquares()).value[0])(jnp.asarray(b))
    np.testing.assert_allclose(g, a[:, 0] / np.sum(a * a), rtol=1e-12)
    with pytest.raises(ValueError, match="one column or one row"):
        lx.linear_solve(lx.MatrixLinearOperator(jnp.eye(2)), jnp.ones(2), OneColumnLeastSquares())


def test_first_argmin_matches_numpy_argmin():
    """The start's argmin (two plain reductions instead of XLA's (value, index) reduction) agrees
    with NumPy's: first index of the minimum, ties included; NaN never chosen; all-NaN rows 0."""
    from jaxoptics._fitting._index_starts import _first_argmin

    rng = np.random.default_rng(5)
    x = rng.normal(size=(200, 48))
    x[:50] = np.round(x[:50])  # many ties
    x[50:60, ::3] = np.nan
    got = np.asarray(_first_argmin(jnp.asarray(x)))
    np.testing.assert_array_equal(got, np.nanargmin(x, axis=1))
    assert int(_first_argmin(jnp.full((1, 5), np.nan))[0]) == 0
    assert int(_first_argmin(jnp.asarray([[3.0, np.inf, 1.0, 1.0]]))[0]) == 2


@pytest.mark.parametrize("pol", ["unpolarized", "s", "p"])
def test_fit_jacobian_column_matches_mpmath(pol):
    """The fits' own `dR / d eta2` (one fused loop per solver step) against mpmath.diff of the
    50-digit Fresnel reflectance: external and internal reflection, near normal and grazing
    incidence, and 0 under TIR; relative 1e-9 (the Jacobian sets the step and the errors)."""
    import mpmath as mp

    from jaxoptics._fitting._index_model import _model, _reflectance_d_eta2
    from jaxoptics.tools.mpref import fresnel_ref, mpf

    key = {"unpolarized": None, "s": "R_s", "p": "R_p"}[pol]

    def R_ref(c, a, b):
        d = fresnel_ref(c, a, b)
        return (d["R_s"] + d["R_p"]) / 2 if key is None else d[key]

    checked = tir = 0
    for c in (1.0, 0.999, 0.9, 0.62, 0.3, 0.05, 1e-3):
        for a, b in ((1.0, 1.5), (1.0, 1.01), (1.0, 4.0), (1.5, 1.0), (1.5, 1.45), (2.4, 1.5), (3.0, 0.4)):
            got = float(_reflectance_d_eta2(jnp.float64(c), jnp.float64(a), jnp.float64(b), pol))
            # and through the custom derivative the solver's linearization uses
            lin = float(jax.jvp(lambda e: _model(jnp.float64(c), jnp.float64(a), e, pol), (jnp.float64(b),), (jnp.float64(1.0),))[1])
            assert lin == got
            if b < a and c < np.sqrt(1 - (b / a) ** 2) + 1e-3:  # TIR (or within reach of the cusp)
                if c < np.sqrt(1 - (b / a) ** 2) - 1e-3:
                    assert got == 0, (pol, c, a, b, got)
                    tir += 1
                continue
            want = float(mp.diff(lambda t: R_ref(mpf(c), mpf(a), t), mpf(b)))
            assert abs(got - want) <= 1e-9 * abs(want) + 1e-14, (pol, c, a, b, got, want)
            checked += 1
    assert checked > 30 and tir > 5


@pytest.mark.parametrize("pol", ["unpolarized", "s", "p"])
def test_fit_model_is_accurate_in_absolute_terms(pol):
    """The fits' one-loop model (textbook amplitudes on fresnel's k_t^2) against the 50-digit
    reflectance: absolute error a few 1e-16, far below any measurement noise, including grazing
    and normal incidence, Brewster's angle, eta1 == eta2 and large contrasts both ways. Points
    within 1e-9 (in k_t^2) of the critical angle, where R has an infinite slope and both this and
    `fresnel` are limited by the rounding of the inputs, are left out."""
    from jaxoptics._fitting._index_model import _reflectance_plain
    from jaxoptics.tools.mpref import fresnel_ref, mpf

    c = np.concatenate([[0.0, 1e-12, 1e-6, 1.0], np.cos(np.linspace(0, np.pi / 2, 41)[1:-1])])
    worst = 0.0
    for a, b in ((1.0, 1.5), (1.0, 1.0), (1.0, 1.0 + 1e-9), (1.5, 1.0), (1.5, 1.49), (3.0, 1.0), (1.0, 4.0), (1e3, 1.0), (1.0, 1e-3)):
        got = np.asarray(_reflectance_plain(jnp.asarray(c), jnp.float64(a), jnp.float64(b), pol))
        for cj, g in zip(c, got):
            q = b * b - a * a * (1 - cj * cj)
            if abs(q) < 1e-9 * a * a:
                continue
            d = fresnel_ref(mpf(cj), mpf(a), mpf(b))
            want = float((d["R_s"] + d["R_p"]) / 2 if pol == "unpolarized" else d["R_" + pol])
            worst = max(worst, abs(g - want))
            assert abs(g - want) < 2e-15, (pol, cj, a, b, g, want)
    assert worst > 0  # the comparison ran on values that differ in rounding


@pytest.mark.parametrize("pol", ["unpolarized", "s", "p"])
def test_complex_fit_model_and_jacobian_match_mpmath(pol):
    """The complex fits' one-loop model and its closed-form derivative in n and k (the solver's
    Jacobian) against the 50-digit reflectance and mpmath.diff: absolute 1e-14, relative 1e-9."""
    import mpmath as mp

    from jaxoptics._fitting._index_model import _model
    from jaxoptics.tools.mpref import fresnel_ref, mpf

    def R_ref(c, a, n, k):
        d = fresnel_ref(c, a, mp.mpc(n, k))
        return (d["R_s"] + d["R_p"]) / 2 if pol == "unpolarized" else d["R_" + pol]

    for a in (1.0, 1.5):
        for eta in (0.2 + 3j, 1.5 + 0.01j, 2.9 + 1.0j, 0.05 + 0.5j, 4.0 + 6.0j):
            for c in (1.0, 0.9, 0.5, 0.1, 1e-3):
                args = (jnp.float64(c), jnp.float64(a), jnp.complex128(eta))
                got = float(_model(*args, pol))
                want = float(R_ref(mpf(c), mpf(a), mpf(eta.real), mpf(eta.imag)))
                assert abs(got - want) < 1e-14, (pol, a, eta, c, got, want)
                for t, j in ((1.0, 0), (1j, 1)):
                    d = float(jax.jvp(lambda z: _model(args[0], args[1], z, pol), (args[2],), (jnp.complex128(t),))[1])
                    x0 = [mpf(eta.real), mpf(eta.imag)]
                    w = float(mp.diff(lambda s: R_ref(mpf(c), mpf(a), *[s if q == j else x0[q] for q in range(2)]), x0[j]))
                    assert abs(d - w) <= 1e-9 * abs(w) + 1e-14, (pol, a, eta, c, j, d, w)


@pytest.mark.slow
def test_plot_fit_draws_the_fitted_index_and_its_residuals():
    """`plot_fit` draws, for each curve, the measured points, tmm's reflectance of the fitted index
    over all angles (and of the other branch, dashed, where the data allow it), and model - data."""
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(3)
    etas, pols = np.array([1.52, 2.1 + 0.4j]), ("s", "p")
    R = np.stack([tmm_curve(1.0, e, THETA, p) for p, e in zip(pols, etas)]) + 1e-3 * rng.standard_normal((2, THETA.size))
    fit = jo.fit_eta(THETA, R, polarization=pols, sigma=1e-3, absorbing=True)
    fig = jo.plot_fit(THETA, R, fit, polarization=pols, sigma=1e-3, title="two curves")
    ax, axr = fig.axes
    assert ax.get_title() == "two curves" and axr.get_ylabel() == "model - data"
    fits = [l for l in ax.get_lines() if l.get_label().startswith("fit ")]
    assert len(fits) == 2 and "[1]" in fits[1].get_label()
    for k, (line, p) in enumerate(zip(fits, pols)):
        x, y = line.get_data()
        np.testing.assert_allclose(y, tmm_curve(1.0, complex(fit.eta[k]), np.deg2rad(x), p), rtol=0, atol=1e-12)
        xd, yd = ax.containers[k].lines[0].get_data()
        np.testing.assert_array_equal(yd, R[k])
        xr, yr = axr.containers[k].lines[0].get_data()
        np.testing.assert_array_equal(xr, xd)
        np.testing.assert_allclose(yr, tmm_curve(1.0, complex(fit.eta[k]), THETA, p) - R[k], rtol=0, atol=1e-12)
    plt.close(fig)

    # internal reflection near normal incidence: 1.2 and its other branch both fit; both are drawn
    th = np.deg2rad(np.linspace(0, 5, 20))
    R1 = tmm_curve(1.5, 1.2, th, "unpolarized") + 1e-3 * rng.standard_normal(th.size)
    one = jo.fit_eta(th, R1, eta1=1.5)
    assert np.isfinite(float(one.eta_alt))
    fig = jo.plot_fit(th, R1, one, eta1=1.5)
    branch = [l for l in fig.axes[0].get_lines() if l.get_label().startswith("other branch")]
    assert len(branch) == 1 and branch[0].get_linestyle() == "--"
    x, y = branch[0].get_data()
    np.testing.assert_allclose(y, tmm_curve(1.5, float(one.eta_alt), np.deg2rad(x), "unpolarized"), rtol=0, atol=1e-12)
    plt.close(fig)


@pytest.mark.slow
def test_plot_fit_chooses_curves_and_refuses_bad_arguments():
    import matplotlib.pyplot as plt

    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(4), jnp.linspace(1.3, 2.0, 12), THETA, noise=1e-3))
    fit = jo.fit_eta(THETA, R)
    fig = jo.plot_fit(THETA, R, fit)  # more curves than it draws by default: the first ten, and it says so
    assert len(fig.axes[0].containers) == jo._fitting._plot.MAX_CURVES and "(curves 0-9 of 12)" in fig.axes[0].get_title()
    plt.close(fig)
    fig = jo.plot_fit(THETA, R, fit, which=[11, 3])
    xd, yd = fig.axes[0].containers[0].lines[0].get_data()
    np.testing.assert_array_equal(yd, R[11])
    assert len(fig.axes[0].containers) == 2 and "of 12" not in fig.axes[0].get_title()
    plt.close(fig)
    # a fit that did not converge says so in its label, the others do not
    failed = dataclasses.replace(fit, converged=np.arange(12) != 3)
    fig = jo.plot_fit(THETA, R, failed, which=[3, 4])
    labels = [l.get_label() for l in fig.axes[0].get_lines() if l.get_label().startswith("fit ")]
    assert labels[0].endswith("(NOT converged)") and "converged" not in labels[1]
    plt.close(fig)
    for bad, message in [(dict(which=[12]), "which must be"), (dict(which=[]), "which must be"),
                         (dict(which=[True]), "which must be"), (dict(which=[1.0]), "which must be"),
                         (dict(polarization="q"), "polarization must be"), (dict(sigma=np.ones(3)), "sigma has shape")]:
        with pytest.raises(ValueError, match=message):
            jo.plot_fit(THETA, R, fit, **bad)
    with pytest.raises(ValueError, match="batch shape"):
        jo.plot_fit(THETA, R[:3], fit)
    with pytest.raises(ValueError, match="same m"):
        jo.plot_fit(THETA[:-1], R, fit)
    plt.close("all")
