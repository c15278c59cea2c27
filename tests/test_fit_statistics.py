"""The statistics users compare with WVASE and CompleteEASE, each against a hand computation from
tmm's model at the fitted values."""

import math

import numpy as np
import pytest
import tmm

import jaxoptics as jo

WL = np.linspace(450.0, 850.0, 21)
ANG = (65.0, 75.0)
N_FILM, N_SUB = 1.46, 3.9 + 0.02j


def _tmm_psi_delta(d, wl, ang):
    out = []
    for w, a in zip(wl, ang):
        e = tmm.ellips([1.0, N_FILM, N_SUB], [np.inf, d, np.inf], math.radians(a), w)
        out.append((math.degrees(e["psi"]), 180.0 - math.degrees(e["Delta"])))
    return np.asarray(out).T


def _ncs(psi, delta):
    p2, d = np.radians(2 * psi), np.radians(delta)
    return np.stack([np.cos(p2), np.sin(p2) * np.cos(d), np.sin(p2) * np.sin(d)])


def _sample():
    return jo.Sample([jo.Layer(N_FILM, jo.Free(150.0, 0.0, 400.0), name="film")], N_SUB)


@pytest.mark.slow
def test_mse_ncs_mse_and_confidence_limits_by_hand():
    wl, ang = np.tile(WL, len(ANG)), np.repeat(ANG, len(WL))
    rng = np.random.default_rng(7)
    sig = np.array([0.02, 0.05])
    truth = np.stack([_tmm_psi_delta(d, wl, ang) for d in (180.0, 240.0)])
    # the second site's noise is twice its stated sigma: MSE near 2, so the covariance that
    # StackFit scales by chi2_reduced is unscaled again for the confidence limits
    noisy = truth + np.array([1.0, 2.0])[:, None, None] * sig[:, None] * rng.normal(size=truth.shape)
    sp = jo.make_spectra(wl, ang, {"psi_deg": noisy[:, 0], "delta_deg": noisy[:, 1]},
                         sigma={"psi_deg": np.full(noisy[:, 0].shape, sig[0]), "delta_deg": np.full(noisy[:, 0].shape, sig[1])})
    fit = jo.fit_stack(_sample(), sp)
    st = jo.fit_statistics(_sample(), sp, fit)
    n, M = wl.size, 1
    assert (st.n_points, st.n_data, st.n_params, st.n_ncs) == (n, 2 * n, 1, 3 * n)
    for s in range(2):
        d_fit = float(fit.values[s, 0])
        model = _tmm_psi_delta(d_fit, wl, ang)
        dpsi = (model[0] - noisy[s, 0]) / sig[0]
        ddel = ((model[1] - noisy[s, 1] + 180) % 360 - 180) / sig[1]
        mse = math.sqrt(np.sum(dpsi**2 + ddel**2) / (2 * n - M))  # WVASE
        assert st.mse[s] == pytest.approx(mse, rel=1e-6)
        r = _ncs(*model) - _ncs(*noisy[s])
        mse_ncs = 1000 * math.sqrt(np.sum(r**2) / (3 * n - M))  # CompleteEASE
        assert st.mse_ncs[s] == pytest.approx(mse_ncs, rel=1e-6)
        h = 1e-3  # C = (J^T W J)^-1 with J by central differences of tmm's model
        J = (_tmm_psi_delta(d_fit + h, wl, ang) - _tmm_psi_delta(d_fit - h, wl, ang)) / (2 * h) / sig[:, None]
        C = 1.0 / np.sum(J**2)
        assert st.ci90[s, 0] == pytest.approx(1.65 * math.sqrt(mse * C), rel=1e-5)
    assert 0.7 < st.mse[0] < 1.3 and 1.5 < st.mse[1] < 2.6
    assert "90% confidence" in st.table(site=1) and "MSE (WVASE" in st.table()


@pytest.mark.slow
def test_photometric_data_have_no_ncs_mse_and_unweighted_data_no_wvase_mse():
    wl = WL
    R = np.asarray([tmm.coh_tmm("s", [1.0, N_FILM, N_SUB], [np.inf, 200.0, np.inf], 0.0, w)["R"] for w in wl])
    sp = jo.make_spectra(wl, 0.0, {"R": R})
    fit = jo.fit_stack(_sample(), sp)
    st = jo.fit_statistics(_sample(), sp, fit)
    assert np.isnan(st.mse_ncs) and np.isnan(st.mse) and st.n_ncs == 0
    assert st.ci90[0] == pytest.approx(1.65 * float(fit.stderr[0]))
    assert "MSE n/a (the data carry no sigma)" in fit.table(statistics=st) and "MSE n/a (no ellipsometric data)" in fit.table(statistics=st)
