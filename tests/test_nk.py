"""Point-by-point n and k (`fit_nk`): a Tauc-Lorentz film's index recovered at every wavelength from
noisy Psi/Delta at three angles, started from a different Tauc-Lorentz model, with standard
errors that describe the scatter (the normalized deviations' mean square near 1); the smoothness
penalty lowering the solution's curvature at a cost in chi^2; the YAML round trip
through `load_rii_yaml`; and the refusals."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxoptics as jo

TRUTH = jo.TaucLorentz(A=120.0, E0=3.6, C=2.4, Eg=1.7, eps_inf=1.2)
WL = np.repeat(np.linspace(300.0, 900.0, 41), 3)
ANG = np.tile([55.0, 65.0, 75.0], 41)


@pytest.fixture(scope="module")
def data():
    sample = jo.Sample([jo.Layer(TRUTH, 60.0, name="film")], jo.material("Si"))
    q = np.asarray(sample.fixed().quantities(("psi_deg", "delta_deg"), jnp.asarray(WL), jnp.deg2rad(jnp.asarray(ANG))))
    rng = np.random.default_rng(0)
    sig = {"psi_deg": np.full(WL.size, 0.01), "delta_deg": np.full(WL.size, 0.02)}
    sp = jo.make_spectra(WL, ANG, {"psi_deg": q[0] + 0.01 * rng.normal(size=WL.size),
                                   "delta_deg": q[1] + 0.02 * rng.normal(size=WL.size)}, sigma=sig)
    # the seed: the film's thickness known (a parametric fit's), its dispersion off
    seed = jo.Sample([jo.Layer(jo.TaucLorentz(A=110.0, E0=3.5, C=2.3, Eg=1.65, eps_inf=1.3), 60.0, name="film")], jo.material("Si"))
    return seed, sp


@pytest.fixture(scope="module")
def independent(data):
    seed, sp = data
    return jo.fit_nk(seed, sp, "film")


@pytest.mark.slow
def test_recovers_the_index_at_every_wavelength_with_honest_errors(independent, tmp_path):
    f = independent
    N = np.asarray(TRUTH.nk(jnp.asarray(f.wavelength_nm / 1000)))
    np.testing.assert_array_equal(f.wavelength_nm, np.unique(WL))
    assert np.all(f.converged)
    inside = f.k > 1e-6  # (where k sits on its bound 0 the error is the curvature there)
    z = np.concatenate([(f.n - N.real) / f.n_err, ((f.k - N.imag) / f.k_err)[inside]])
    assert 0.6 < np.mean(z * z) < 1.5, np.mean(z * z)
    assert np.max(np.abs(z)) < 4.5
    assert 0.6 < np.median(f.chi2_reduced) < 1.5
    # as a material, and through a refractiveindex.info YAML file
    f.save_yaml(tmp_path / "film.yml")
    m = jo.load_rii_yaml(tmp_path / "film.yml")
    lam = jnp.asarray(f.wavelength_nm / 1000)
    np.testing.assert_allclose(np.asarray(m.nk(lam)), f.n + 1j * f.k, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(np.asarray(f.material().nk(lam)), f.n + 1j * f.k, rtol=1e-15)


@pytest.mark.slow
def test_smoothness_trades_curvature_for_chi2(data, independent):
    """Tikhonov's trade-off: a penalty on the second differences lowers the solution's curvature
    and raises the data's chi^2 (the L-curve is monotone)."""
    seed, sp = data
    curvature = lambda f: np.sum(np.diff(f.n, 2) ** 2 / np.median(independent.n_err) ** 2
                                 + np.diff(f.k, 2) ** 2 / np.median(independent.k_err) ** 2)
    smooth = jo.fit_nk(seed, sp, "film", smoothness=0.3)
    assert np.all(smooth.converged)
    assert curvature(smooth) < 0.9 * curvature(independent)
    assert np.sum(smooth.chi2_reduced) > np.sum(independent.chi2_reduced)
    smoother = jo.fit_nk(seed, sp, "film", smoothness=1.0)
    assert curvature(smoother) < curvature(smooth) and np.sum(smoother.chi2_reduced) > np.sum(smooth.chi2_reduced)
    # the three calls ran the same compiled programs: the smoothness and the data are arguments
    from jaxoptics._fitting._nk import _programs

    prog = _programs(seed, "film", sp.kinds, True, 256, "float64")
    assert [f._cache_size() for f in prog] == [1, 1, 1]


def test_refusals(data):
    seed, sp = data
    with pytest.raises(ValueError, match="layer 'oxide' is not in the sample"):
        jo.fit_nk(seed, sp, "oxide")
    one = jo.make_spectra([500.0, 600.0], [70.0, 70.0], {"psi_deg": [20.0, 21.0]})
    with pytest.raises(ValueError, match="500 nm has 1 data for the two unknowns"):
        jo.fit_nk(seed, one, "film")
    with pytest.raises(ValueError, match="values has 1 entries"):
        jo.fit_nk(seed, sp, "film", values=[1.0])
