"""Reflectometry: relative reflectance made absolute against a reference, and the thickness of
films from 5 nm to 50 um from normal-incidence reflectance (the Fourier-transform start for the
thick ones), against tmm."""

import numpy as np
import pytest
import tmm

import jaxoptics as jo

WL = np.linspace(400.0, 1000.0, 601)
N_FILM = 1.46


def _si(wl):
    return np.asarray(jo.material("Si").nk(wl / 1000))


def _R(d, wl):
    """Unpolarized normal-incidence reflectance of a film on silicon, from tmm."""
    si = _si(wl)
    return np.asarray([tmm.coh_tmm("s", [1.0, N_FILM, s], [np.inf, d, np.inf], 0.0, w)["R"] for w, s in zip(wl, si)])


def _sample(d0, hi):
    return jo.Sample([jo.Layer(N_FILM, jo.Free(d0, 0.0, hi), name="film")], jo.material("Si"))


def test_relative_reflectance_against_bare_silicon_is_made_absolute():
    wl = WL[::50]
    R = _R(300.0, wl)
    R_si = np.asarray([tmm.coh_tmm("s", [1.0, s], [np.inf, np.inf], 0.0, w)["R"] for w, s in zip(wl, _si(wl))])
    sp = jo.absolute_reflectance(wl, R / R_si, "Si", sigma=np.full(wl.size, 0.01))
    assert sp.kinds == ("R",)
    np.testing.assert_allclose(sp.values[0], R, rtol=1e-12)
    np.testing.assert_allclose(sp.meta["reference_R"], R_si, rtol=1e-12)
    np.testing.assert_allclose(sp.sigma[0], 0.01 * R_si, rtol=1e-12)
    with pytest.raises(ValueError, match="ratios are finite and >= 0"):
        jo.absolute_reflectance(wl, -R / R_si, "Si")


@pytest.mark.slow
def test_fifty_micrometres_from_the_fourier_transform_start_and_five_nanometres_from_the_grid():
    """A 50 um film shows about 230 fringes over 400-1000 nm: its Fourier transform puts it within
    a fraction of a resolution, and the fit searches a few dozen grid points around that. A 5 nm
    film (no fringe) is found by the usual grid from zero."""
    R50 = _R(50000.0, WL)
    sp = jo.make_spectra(WL, 0.0, {"R": R50})
    est = jo.fft_thickness(_sample(10000.0, 60000.0), sp)
    assert abs(float(est.thickness_nm) - 50000.0) < est.resolution_nm and est.resolution_nm < 250
    fit = jo.fit_stack(_sample(10000.0, 60000.0), sp, global_start="fft")
    assert float(fit["film.thickness_nm"]) == pytest.approx(50000.0, abs=0.01) and bool(fit.converged)
    sp5 = jo.make_spectra(WL[::10], 0.0, {"R": _R(5.0, WL[::10])})
    fit5 = jo.fit_stack(_sample(100.0, 1000.0), sp5)
    assert float(fit5["film.thickness_nm"]) == pytest.approx(5.0, abs=1e-4)
    with pytest.raises(ValueError, match="needs reflectance or transmittance data"):
        jo.fft_thickness(_sample(10.0, 100.0), jo.make_spectra(WL[:10], 70.0, {"psi_deg": np.full(10, 20.0)}))


def test_fourier_estimate_of_a_dispersive_film_uses_its_group_index():
    """A Cauchy film's fringes run at its group index n - lambda dn/dlambda: with it the estimate
    of 25 um lies within a fifth of the resolution (with the phase index it would be 2.5 off)."""
    wl = WL
    n = 1.49 + 0.006 / (wl / 1000) ** 2
    si = _si(wl)
    R = [tmm.coh_tmm("s", [1.0, a, s], [np.inf, 25000.0, np.inf], 0.0, w)["R"] for w, a, s in zip(wl, n, si)]
    model = jo.Sample([jo.Layer(jo.Cauchy(A=1.49, B=0.006), jo.Free(1000.0, 0.0, 60000.0), name="film")], jo.material("Si"))
    est = jo.fft_thickness(model, jo.make_spectra(wl, 0.0, {"R": np.asarray(R)}))
    assert abs(float(est.thickness_nm) - 25000.0) < 0.2 * est.resolution_nm
