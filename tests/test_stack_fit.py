"""Layered-sample fits: the measured quantities against tmm, recovery of known parameters from
tmm-generated spectra with noise, calibrated standard errors, honest reports of what the data do
not determine, and the spectra files."""

import functools
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tmm
from helpers import quick_jit

import jaxoptics as jo

WL = np.linspace(300.0, 1000.0, 100)
ANGLES = (65.0, 70.0, 75.0)
OXIDE = dict(A=1.452, B=0.0036)


def grid():
    return np.tile(WL, len(ANGLES)), np.repeat(ANGLES, len(WL))


def tmm_quantities(film_n, d_nm, wl, ang, substrate="Si"):
    """psi/delta (instrument convention: Delta = 180 - tmm's Delta) and R_s, R_p with tmm, one point
    at a time; indices from the materials (tested separately against their sources)."""
    sub = np.asarray(jo.material(substrate).nk(jnp.asarray(wl / 1000)))
    psi, delta, Rs, Rp = [], [], [], []
    for i in range(len(wl)):
        n = [1.0, film_n[i], sub[i]]
        th = math.radians(ang[i])
        e = tmm.ellips(n, [np.inf, d_nm, np.inf], th, wl[i])
        psi.append(math.degrees(e["psi"]))
        delta.append((180 - math.degrees(e["Delta"]) + 180) % 360 - 180)
        Rs.append(tmm.coh_tmm("s", n, [np.inf, d_nm, np.inf], th, wl[i])["R"])
        Rp.append(tmm.coh_tmm("p", n, [np.inf, d_nm, np.inf], th, wl[i])["R"])
    return np.array(psi), np.array(delta), np.array(Rs), np.array(Rp)


def cauchy_n(wl, A, B):
    return A + B / (wl / 1000) ** 2


@pytest.mark.slow
def test_quantities_agree_with_tmm_and_with_each_other():
    wl, ang = grid()
    sample = jo.Sample([jo.Layer(jo.Cauchy(**OXIDE), 480.0)], jo.material("Si"))
    kinds = ("psi_deg", "delta_deg", "R_s", "R_p", "N", "C", "S", "R")
    q = np.asarray(sample.fixed().quantities(kinds, jnp.asarray(wl), jnp.asarray(np.radians(ang))))
    psi, delta, Rs, Rp = tmm_quantities(cauchy_n(wl, **OXIDE), 480.0, wl, ang)
    np.testing.assert_allclose(q[0], psi, atol=1e-10)
    np.testing.assert_allclose((q[1] - delta + 180) % 360 - 180, 0, atol=1e-9)
    np.testing.assert_allclose(q[2], Rs, atol=1e-13)
    np.testing.assert_allclose(q[3], Rp, atol=1e-13)
    p, dl = np.radians(psi), np.radians(delta)
    np.testing.assert_allclose(q[4], np.cos(2 * p), atol=1e-12)
    np.testing.assert_allclose(q[5], np.sin(2 * p) * np.cos(dl), atol=1e-12)
    np.testing.assert_allclose(q[6], np.sin(2 * p) * np.sin(dl), atol=1e-12)
    np.testing.assert_allclose(q[7], (Rs + Rp) / 2, atol=1e-13)
    # an absorbing substrate in the instrument convention has 0 < Delta < 180 (S > 0)
    bare = jo.Sample([], jo.material("Au"))
    qb = np.asarray(bare.fixed().quantities(("delta_deg", "S"), jnp.asarray(wl), jnp.asarray(np.radians(ang))))
    assert np.all((qb[0] > 0) & (qb[0] < 180)) and np.all(qb[1] > 0)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_delta_of_a_bare_dielectric_is_180_below_brewster_and_0_beyond(dtype):
    """A lossless interface has a real rho = r_p / r_s, its imaginary part an exact zero of either
    sign: delta is exactly 180 degrees below Brewster's angle and 0 beyond (closed form), never
    -180 (the documented range is (-180, 180])."""
    w, a = (x.ravel() for x in np.meshgrid(np.linspace(400.0, 800.0, 9), [0.5, 20.0, 45.0, 55.0, 58.0, 62.0, 75.0, 89.0],
                                            indexing="ij"))
    with jax.enable_x64(dtype == jnp.float64):
        for n in (1.5, 2.4, 4.0):
            delta = np.asarray(jo.Sample([], jo.Constant(n)).fixed().quantities(
                ("delta_deg",), jnp.asarray(w, dtype), jnp.asarray(np.radians(a), dtype)))[0]
            np.testing.assert_array_equal(delta, np.where(a < math.degrees(math.atan(n)), 180.0, 0.0))


@pytest.mark.slow
def test_incoherent_layer_against_tmm():
    """A 1 mm glass slab (incoherent) on a coated back face, unpolarized R against tmm's inc_tmm."""
    wl = np.linspace(400.0, 800.0, 9)
    ang = np.full_like(wl, 30.0)
    sample = jo.Sample([jo.Layer(1.5, 1e6, incoherent=True), jo.Layer(jo.Cauchy(2.0, 0.01), 120.0)], 1.0)
    q = np.asarray(sample.fixed().quantities(("R_s", "R_p"), jnp.asarray(wl), jnp.asarray(np.radians(ang))))
    for i, w in enumerate(wl):
        n = [1.0, 1.5, 2.0 + 0.01 / (w / 1000) ** 2, 1.0]
        for j, pol in enumerate("sp"):
            ref = tmm.inc_tmm(pol, n, [np.inf, 1e6, 120.0, np.inf], ["i", "i", "c", "i"], math.radians(30), w)["R"]
            assert q[j, i] == pytest.approx(ref, abs=1e-12)


@functools.lru_cache(maxsize=None)
def _tmm_psi_delta(d):
    """tmm's psi/delta of the oxide film of thickness `d` on the grid, computed once per thickness
    (maps of many noise draws of one film reuse it)."""
    wl, ang = grid()
    psi, delta, _, _ = tmm_quantities(cauchy_n(wl, **OXIDE), d, wl, ang)
    psi.flags.writeable = delta.flags.writeable = False
    return psi, delta


def _spectra(d_true, seed, sigma=(0.02, 0.05)):
    """psi/delta from tmm for films of thicknesses `d_true` (a map), with Gaussian noise."""
    rng = np.random.default_rng(seed)
    vals = []
    for d in np.atleast_1d(d_true):
        psi, delta = _tmm_psi_delta(float(d))
        vals.append((psi + sigma[0] * rng.normal(size=psi.shape), delta + sigma[1] * rng.normal(size=psi.shape)))
    wl, ang = grid()
    V = np.asarray(vals)
    return jo.make_spectra(wl, ang, {"psi_deg": V[:, 0], "delta_deg": V[:, 1]},
                           sigma={"psi_deg": np.full(V[:, 0].shape, sigma[0]), "delta_deg": np.full(V[:, 0].shape, sigma[1])})


def _model(d0=1000.0):
    return jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.5, 1.3, 1.8), B=jo.Free(0.0, -0.05, 0.05)),
                               jo.Free(d0, 0.0, 2100.0), name="oxide")], jo.material("Si"))


def _check_errors_at_the_values(fit, model, sp):
    """The fit's chi^2/dof and covariance against those formed at its values with `jax.jacfwd` of
    the model (an independent route to the Jacobian): where Gauss-Newton ended by its EDM test,
    `fit_stack` forms them from its last step's Jacobian, a step of at most 1e-3 standard errors
    before the values, which moves them by far less than 1e-3 relative."""
    wl, ang = jnp.asarray(sp.wavelength_nm), jnp.deg2rad(jnp.asarray(sp.angle_deg))
    S = np.asarray(sp.sigma).reshape(-1, len(sp.kinds) * len(sp.wavelength_nm))
    V = np.asarray(sp.values).reshape(S.shape)
    m = S.shape[1]
    quantities = lambda x: model.with_values(list(x)).quantities(sp.kinds, wl, ang, flat=True)
    x = np.asarray(fit.values).reshape(S.shape[0], -1)
    p = x.shape[1]
    M = np.asarray(jax.vmap(quantities)(jnp.asarray(x)))
    J = np.asarray(jax.vmap(jax.jacfwd(quantities))(jnp.asarray(x))) / S[:, :, None]
    r = M - V
    r[:, m // 2:] = (r[:, m // 2:] + 180) % 360 - 180  # delta (the second quantity) wraps
    chi2r = np.sum((r / S) ** 2, -1) / (m - p)
    np.testing.assert_allclose(np.asarray(fit.chi2_reduced).reshape(-1), chi2r, rtol=1e-6)
    cov = np.linalg.inv(np.einsum("bmi,bmj->bij", J, J)) * np.maximum(chi2r, 1)[:, None, None]
    np.testing.assert_allclose(np.asarray(fit.covariance).reshape(cov.shape), cov, rtol=1e-3, atol=0)


@pytest.mark.slow
def test_recovers_thickness_from_far_starts():
    """Films from 5 nm to 2000 nm, one start (1000 nm) for all: the grid start finds each one's
    fringe, so no fit lands in a neighbouring minimum."""
    d_true = np.array([5.0, 20.0, 80.0, 250.0, 520.0, 1100.0, 1600.0, 2000.0])
    fit = jo.fit_stack(_model(), _spectra(d_true, seed=1))
    d, sd = np.asarray(fit["oxide.thickness_nm"]), np.asarray(fit.stderr_of("oxide.thickness_nm"))
    assert np.all(np.asarray(fit.converged))
    assert np.all(np.abs(d - d_true) < 4 * sd + 1e-6), (d, d_true, sd)
    A = np.asarray(fit["oxide.A"])
    assert np.all(np.abs(A - OXIDE["A"]) < 4 * np.asarray(fit.stderr_of("oxide.A")))
    assert np.all(np.abs(np.asarray(fit.chi2_reduced) - 1) < 0.25)
    # without the grid, a start 1000 nm away lands in a wrong fringe: the test above is not vacuous
    nogrid = jo.fit_stack(_model(), _spectra(np.array([250.0]), seed=1), global_start=False)
    assert abs(float(nogrid["oxide.thickness_nm"][0]) - 250.0) > 1.0
    assert float(nogrid.chi2_reduced[0]) > 10


@pytest.mark.slow
def test_levenberg_marquardt_stage_runs_only_when_needed(monkeypatch):
    """Gauss-Newton fits these spectra, and the Levenberg-Marquardt stage is not called. With
    Gauss-Newton cut to one step it fits none: the second stage then fits every spectrum, to the
    same minimum (tmm-generated data, the same noise draw)."""
    from jaxoptics._fitting import _stack_fit, _stack_fit_stages
    from jaxoptics._runtime import _cache

    d_true = np.array([80.0, 520.0, 1600.0])
    sp = _spectra(d_true, seed=3)
    called = []
    real_call = _cache.call

    def spy(fn, name, *args, **kwargs):
        called.append(name.rsplit(".", 1)[-1])
        return real_call(fn, name, *args, **kwargs)

    monkeypatch.setattr(_cache, "call", spy)
    ref = jo.fit_stack(_model(), sp)
    assert called == ["first_stage", "errors_stage"]
    assert np.all(np.asarray(ref.converged)) and np.all(np.asarray(ref.num_steps) <= _stack_fit_stages._GN_STEPS)
    called.clear()
    _stack_fit._program.cache_clear()
    monkeypatch.setattr(_stack_fit_stages, "_GN_STEPS", 1)
    try:
        lm = jo.fit_stack(_model(), sp)
    finally:
        _stack_fit._program.cache_clear()  # compiled with the patched step count
    assert called == ["first_stage", "second_stage"]
    assert np.all(np.asarray(lm.converged))
    assert np.all(np.asarray(lm.num_steps) > 1)  # Gauss-Newton's one step, then Levenberg-Marquardt's
    for fit in (ref, lm):  # standard errors from Gauss-Newton's last step; evaluated after Levenberg-Marquardt
        _check_errors_at_the_values(fit, _model(), sp)
    for name in lm.names:
        assert np.allclose(np.asarray(lm[name]), np.asarray(ref[name]), rtol=1e-6, atol=0.01 * np.asarray(ref.stderr_of(name))), name
    d, sd = np.asarray(lm["oxide.thickness_nm"]), np.asarray(lm.stderr_of("oxide.thickness_nm"))
    assert np.all(np.abs(d - d_true) < 4 * sd)
    assert np.allclose(np.asarray(lm.stderr), np.asarray(ref.stderr), rtol=1e-3)


def test_best_start_of_a_spectrum_no_start_fitted_is_its_lowest_chi2():
    """Among a spectrum's starts the converged one of lowest chi^2; where none converged, the
    lowest chi^2 of all (not the first start)."""
    import types

    from jaxoptics._fitting._stack_fit_stages import _Bound, best_start

    prob = types.SimpleNamespace(B=2, starts=3, p=1, bounds=(_Bound(-math.inf, math.inf),))
    u = jnp.array([[1.0], [2.0], [3.0], [4.0], [5.0], [6.0]])
    c2 = jnp.array([5.0, 1.0, 3.0, 9.0, 2.0, jnp.nan])
    ok = jnp.array([True, False, True, False, False, False])
    x, c, conv, _ = best_start(prob, u, c2, ok, jnp.zeros(6, jnp.int32))
    np.testing.assert_array_equal(np.asarray(x)[:, 0], [3.0, 5.0])
    np.testing.assert_array_equal(np.asarray(c), [3.0, 2.0])
    np.testing.assert_array_equal(np.asarray(conv), [True, False])


@pytest.mark.slow
def test_a_spectrum_no_solver_fits_comes_back_below_its_start(monkeypatch):
    """A Gauss-Newton that wanders off (simulated: its points moved far from where it ended, not
    converged) and a Levenberg-Marquardt cut to two steps: no spectrum converges, and each comes
    back at a point whose chi^2 is at most its start's (Levenberg-Marquardt only takes steps that
    lower chi^2; Gauss-Newton's point is kept only where it is lower still), flagged as not
    converged."""
    from jaxoptics._fitting import _stack_fit, _stack_fit_stages

    sp = _spectra(np.array([505.0, 520.0, 535.0]), seed=3)  # started near the minimum: a wandering step is costly
    model = _model(520.0)
    wl, ang = jnp.asarray(sp.wavelength_nm), jnp.deg2rad(jnp.asarray(sp.angle_deg))
    start = model.with_values([_stack_fit_stages._Bound(f.lower, f.upper).inside(f.value) for f in model.free()])
    r0 = (np.asarray(sp.values) - np.asarray(start.quantities(sp.kinds, wl, ang))) / np.asarray(sp.sigma)
    chi2_start = np.sum(r0 ** 2, axis=(-2, -1)) / (r0[0].size - len(model.free()))
    real = _stack_fit_stages.gauss_newton_passes

    def wandering(prob, U0, V, S):
        u, ok, steps, A, c2, have = real(prob, U0, V, S)
        return u + jnp.array([[1.0, 1.0, 0.3]]), jnp.zeros_like(ok), steps, A, c2, jnp.zeros_like(have)

    _stack_fit._program.cache_clear()
    monkeypatch.setattr(_stack_fit_stages, "gauss_newton_passes", wandering)
    try:
        fit = jo.fit_stack(model, sp, global_start=False, max_steps=2)
    finally:
        _stack_fit._program.cache_clear()  # compiled with the patched stage
    assert not np.any(np.asarray(fit.converged))
    assert np.all(np.asarray(fit.chi2_reduced) <= chi2_start), (np.asarray(fit.chi2_reduced), chi2_start)


@pytest.mark.slow
def test_standard_errors_are_calibrated():
    """Over 300 noise draws the spread of the fitted thickness and A over their mean standard
    error lies in [0.8, 1.25]."""
    fit = jo.fit_stack(_model(), _spectra(np.full(300, 480.0), seed=2))
    assert np.all(np.asarray(fit.converged))
    for name in ("oxide.thickness_nm", "oxide.A", "oxide.B"):
        ratio = np.std(np.asarray(fit[name])) / np.mean(np.asarray(fit.stderr_of(name)))
        assert 0.8 <= ratio <= 1.25, (name, ratio)


@pytest.mark.slow
def test_undetermined_parameters_are_reported_not_guessed():
    """A 2 nm film's index and thickness are nearly interchangeable (only their product shows),
    and the index of a layer of zero thickness has no effect at all: the fit reports a
    correlation near 1 for the first pair and an enormous standard error for the second."""
    sample = jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.5, 1.2, 2.2), B=0.0036), jo.Free(3.0, 0.0, 20.0), name="film"),
                        jo.Layer(jo.Constant(n=jo.Free(1.7, 1.0, 3.0)), 0.0, name="ghost")], jo.material("Si"))
    wl, ang = grid()
    truth = jo.Sample([jo.Layer(jo.Cauchy(1.452, 0.0036), 2.0)], jo.material("Si")).fixed()
    q = np.asarray(truth.quantities(("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.asarray(np.radians(ang))))
    rng = np.random.default_rng(3)
    q = q + rng.normal(size=q.shape) * np.array([[0.02], [0.05]])
    sp = jo.make_spectra(wl, ang, {"psi_deg": q[0], "delta_deg": q[1]},
                         sigma={"psi_deg": np.full(q[0].shape, 0.02), "delta_deg": np.full(q[0].shape, 0.05)})
    fit = jo.fit_stack(sample, sp)
    i, j, g = (fit.names.index(n) for n in ("film.A", "film.thickness_nm", "ghost.n"))
    assert abs(float(fit.correlation[i, j])) > 0.95
    assert float(fit.stderr[g]) > 1e6


@pytest.mark.slow
@pytest.mark.parametrize("k_start", [jo.Free(0.0, 0.0, 1.0), jo.Free(0.0, 0.0)], ids=["bounded", "one-sided"])
def test_a_start_on_a_bound_is_fitted(k_start):
    """`k = Free(0, 0, ...)`, the usual way to say "start transparent, k >= 0", starts on a bound,
    where the change of variables that keeps the bound has zero slope: the fit must still move
    `k` and recover an absorbing film (n = 2.0 + 0.05i, 80 nm on Si; tmm's psi/delta with noise)."""
    wl, ang = grid()
    psi, delta, _, _ = tmm_quantities(np.full(wl.shape, 2.0 + 0.05j), 80.0, wl, ang)
    rng = np.random.default_rng(7)
    sig = (0.02, 0.05)
    sp = jo.make_spectra(wl, ang, {"psi_deg": psi + sig[0] * rng.normal(size=psi.shape),
                                   "delta_deg": delta + sig[1] * rng.normal(size=psi.shape)},
                         sigma={"psi_deg": np.full(psi.shape, sig[0]), "delta_deg": np.full(psi.shape, sig[1])})
    model = jo.Sample([jo.Layer(jo.Constant(n=jo.Free(1.9, 1.5, 2.5), k=k_start), jo.Free(70.0, 0.0, 500.0), name="f")],
                      jo.material("Si"))
    fit = jo.fit_stack(model, sp)
    assert bool(fit.converged) and float(fit.chi2_reduced) < 1.5
    for name, truth in (("f.n", 2.0), ("f.k", 0.05), ("f.thickness_nm", 80.0)):
        assert abs(float(fit[name]) - truth) < 4 * float(fit.stderr_of(name)), (name, float(fit[name]), float(fit.stderr_of(name)))


@pytest.mark.slow
def test_mixed_quantities_without_sigma():
    """R and psi/delta together, no sigma in the data: the scale comes from the residuals."""
    wl, ang = grid()
    truth = jo.Sample([jo.Layer(jo.Cauchy(**OXIDE), 700.0)], jo.material("Si")).fixed()
    q = np.asarray(truth.quantities(("psi_deg", "delta_deg", "R"), jnp.asarray(wl), jnp.asarray(np.radians(ang))))
    rng = np.random.default_rng(4)
    noise = np.array([[0.01], [0.02], [0.0004]])
    sp = jo.make_spectra(wl, ang, dict(zip(("psi_deg", "delta_deg", "R"), q + noise * rng.normal(size=q.shape))))
    fit = jo.fit_stack(_model(300.0), sp)
    assert not fit.sigma_given and bool(fit.converged)
    assert float(fit["oxide.thickness_nm"]) == pytest.approx(700.0, abs=4 * float(fit.stderr_of("oxide.thickness_nm")))
    assert "oxide.thickness_nm" in fit.table()


def test_bad_input_is_refused_before_compiling(tmp_path):
    sp = _spectra(np.array([100.0]), seed=0)
    fixed = jo.Sample([jo.Layer(jo.Cauchy(**OXIDE), 100.0)], jo.material("Si"))
    with pytest.raises(ValueError, match="no Free parameter"):
        jo.fit_stack(fixed, sp)
    gold = jo.Sample([jo.Layer(jo.Cauchy(**OXIDE), jo.Free(100.0, 0, 500))], jo.material("Au"))
    wl = np.linspace(300.0, 2500.0, 20)
    sp2 = jo.make_spectra(wl, 70.0, {"psi_deg": np.full(20, 30.0)})
    with pytest.raises(ValueError, match="substrate: the material's tabulated data cover 187.9-1937 nm, the spectra 300-2500 nm"):
        jo.fit_stack(gold, sp2)
    with pytest.raises(ValueError, match="thickness start -1.0 nm is negative"):
        jo.Layer(1.5, jo.Free(-1.0))
    with pytest.raises(ValueError, match="k < 0"):
        jo.Sample([], 1.5 - 0.1j)
    # a constant, tabulated or database medium whose index at a measured wavelength the stack
    # cannot take, named with the value: gain in a constant, in a table, in a formula's k table,
    # and a formula's n^2 < 0 (1 + 0.16/(0.16 - 0.2) = -3 at 400 nm)
    sp3 = jo.make_spectra([400.0, 600.0], 70.0, {"psi_deg": [20.0, 25.0], "delta_deg": [100.0, 120.0]})
    yml = tmp_path / "m.yml"
    yml.write_text("DATA:\n  - type: formula 2\n    wavelength_range: 0.3 2.0\n    coefficients: 0 1.0 0.01\n"
                   "  - type: tabulated k\n    data: |\n        0.3 1e-3\n        0.7 -1e-3\n")
    pole = tmp_path / "p.yml"
    pole.write_text("DATA:\n  - type: formula 2\n    wavelength_range: 0.3 2.0\n    coefficients: 0 1.0 0.2\n")
    for mat, message in ((jo.Constant(n=1.5, k=-0.1), r"film: its index at 400 nm is 1.5-0.1j; the stack takes finite"),
                         (jo.Tabulated(n_table=([0.3, 0.7], [1.5, 1.5]), k_table=([0.3, 0.7], [0.01, -0.01])),
                          r"film: its index at 600 nm is 1.5-0.005j"),
                         (jo.load_rii_yaml(yml), r"film: its index at 600 nm is 1.42428-0.0005j"),
                         (jo.load_rii_yaml(pole), r"film: its index at 400 nm is 0\+1.73205j")):
        with pytest.raises(ValueError, match=message):
            jo.fit_stack(jo.Sample([jo.Layer(mat, jo.Free(100.0, 0.0, 500.0), name="film")], 3.9), sp3)


# ---- spectra files ----------------------------------------------------------------------------


def test_spectra_round_trip_with_sites(tmp_path):
    sp = _spectra(np.array([100.0, 200.0]), seed=5)
    sp = sp._replace(sites=("a1", "b2"))
    jo.save_spectra(tmp_path / "m.csv", sp)
    back = jo.load_spectra(tmp_path / "m.csv")
    assert back.sites == ("a1", "b2") and back.kinds == sp.kinds
    np.testing.assert_array_equal(back.values, sp.values)
    np.testing.assert_array_equal(back.sigma, sp.sigma)
    np.testing.assert_array_equal(back.wavelength_nm, sp.wavelength_nm)
    assert back.site_xy is None
    # with positions: written as x_mm, y_mm and read back
    xy = np.array([[-12.5, 3.0], [40.0, -0.1]])
    jo.save_spectra(tmp_path / "m.csv", sp._replace(site_xy=xy))
    assert (tmp_path / "m.csv").read_text().startswith("site,x_mm,y_mm,wavelength_nm")
    back = jo.load_spectra(tmp_path / "m.csv")
    np.testing.assert_array_equal(back.site_xy, xy)
    np.testing.assert_array_equal(back.values, sp.values)
    made = jo.make_spectra(sp.wavelength_nm, sp.angle_deg, dict(zip(sp.kinds, np.moveaxis(sp.values, -2, 0))), sites=["a1", "b2"],
                           site_xy=xy)
    assert made.sites == ("a1", "b2")
    np.testing.assert_array_equal(made.site_xy, xy)
    V = dict(zip(sp.kinds, np.moveaxis(sp.values, -2, 0)))
    for kw, msg in [(dict(sites=["a"]), r"sites must be 2 distinct labels \(one per spectrum\), got 1"),
                    (dict(sites=["a", "a"]), r"got 2 \(1 distinct\)"),
                    (dict(site_xy=xy[:1]), r"site_xy must be finite positions of shape \(2, 2\), got shape \(1, 2\)"),
                    (dict(site_xy=[[0, 0], [np.nan, 1]]), r"site_xy must be finite positions")]:
        with pytest.raises(ValueError, match=msg):
            jo.make_spectra(sp.wavelength_nm, sp.angle_deg, V, **kw)
    with pytest.raises(ValueError, match="sites and site_xy describe a map"):
        jo.make_spectra(sp.wavelength_nm, sp.angle_deg, {k: v[0] for k, v in V.items()}, site_xy=xy[:1])


def test_mueller_and_ncs_columns(tmp_path):
    psi, delta = np.radians(30.0), np.radians(120.0)
    N, C, S = np.cos(2 * psi), np.sin(2 * psi) * np.cos(delta), np.sin(2 * psi) * np.sin(delta)
    rows = ["wavelength_um,angle_deg,m11,m12,m21,m33,m34,m43,m44"]
    rows += [f"0.{5 + i},70,1,{-N},{-N},{C},{S},{-S},{C}" for i in range(3)]
    (tmp_path / "mm.csv").write_text("\n".join(rows) + "\n")
    sp = jo.load_spectra(tmp_path / "mm.csv")
    assert sp.kinds == ("N", "C", "S")
    np.testing.assert_allclose(sp.values[:, 0], [N, C, S], atol=1e-15)
    np.testing.assert_allclose(sp.wavelength_nm, [500, 600, 700])


@pytest.mark.parametrize("text,message", [
    ("wavelength_nm,angle_deg,psi_deg\n500,70,30\n600,70,nan\n", r"line 3: column 3 \(psi_deg\) is NaN; rows with missing values are rejected"),
    ("wavelength_nm,angle_deg,psi_deg\n500,70,30\n600,70,x\n", r"line 3: column 3 \(psi_deg\): 'x' is not a number"),
    ("wavelength_nm,angle,psi_deg\n500,70,30\n", r"line 1: column 2 'angle' is not a known column \(did you mean angle_deg\?\)"),
    ("wavelength_nm,angle_deg,R\n500,70,45\n", r"line 2: column 3 \(R\) = 45: reflectance and transmittance are fractions"),
    ("wavelength_nm,angle_deg,psi_deg,delta_deg\n500,70,30,120\n600,70,120,30\n",
     r"line 3: column 3 \(psi_deg\) = 120: Psi lies in \[0, 90\] degrees \(Delta in the psi column\?\)"),
    ("wavelength_nm,angle_deg,N,C,S\n500,70,0.5,0.6,-1.2\n", r"line 2: column 5 \(S\) = -1.2: N, C and S are cos 2Psi"),
    ("wavelength_nm,angle_deg,m12,m33,m34\n500,70,-0.5,0.6,1.4\n",
     r"line 2: column 5 \(m34\) = 1.4: the elements of a Mueller matrix normalized by m11 lie in \[-1, 1\]"),
    ("wavelength_nm;angle_deg;psi_deg\n500;70;30\n", r"line 1: columns are separated by commas; .* separates them by semicolons"),
    ("wavelength_nm,angle_deg,psi_deg\n500,95,30\n", r"line 2: column 2 \(angle_deg\) = 95.0: must be in \[0, 90\)"),
    ("wavelength_nm,angle_deg,psi_deg,sigma_psi_deg\n500,70,30,0\n", r"line 2: sigma of psi_deg = 0.0: must be positive"),
    ("# comment\nwavelength_nm,angle_deg,psi_deg\n500,70\n", r"line 3: 2 cells, the header has 3"),
    ("site,wavelength_nm,angle_deg,psi_deg\na,500,70,30\nb,600,70,30\n", r"line 3: site 'b' does not list the same"),
    ("wavelength_nm,wavelength_um,angle_deg,psi_deg\n500,0.5,70,30\n", r"exactly one of the columns wavelength_nm, wavelength_um"),
    ("site,x_mm,wavelength_nm,angle_deg,psi_deg\na,1,500,70,30\n", r"line 1: give both site position columns x_mm and y_mm"),
    ("x_mm,y_mm,wavelength_nm,angle_deg,psi_deg\n1,2,500,70,30\n", r"line 1: x_mm and y_mm give the positions of sites: add a site"),
    ("site,x_mm,y_mm,wavelength_nm,angle_deg,psi_deg\na,1,2,500,70,30\na,1,2.5,600,70,30\n",
     r"line 3: column 3 \(y_mm\) = 2.5: site 'a' is at y_mm = 2.0 on line 2; a site has one position"),
])
def test_bad_spectra_files_name_line_and_column(tmp_path, text, message):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=r"bad.csv, " + message if message.startswith("line") else message):
        jo.load_spectra(p)


def test_values_out_of_range_by_noise_are_kept_beyond_it_refused(tmp_path):
    """Measured values may stray outside their quantity's range by noise (5% of its width: Psi
    -0.3 degrees, R 1.02, N -1.04); beyond that a file or `make_spectra` is refused, naming the
    quantity and the point."""
    p = tmp_path / "noisy.csv"
    p.write_text("wavelength_nm,angle_deg,psi_deg,R,N\n500,70,-0.3,1.02,-1.04\n600,70,90.2,-0.01,1.0\n")
    sp = jo.load_spectra(p)
    got = dict(zip(sp.kinds, sp.values.tolist()))
    assert got == {"psi_deg": [-0.3, 90.2], "R": [1.02, -0.01], "N": [-1.04, 1.0]}
    jo.make_spectra([500, 600], 70, {"psi_deg": [-0.3, 90.2], "C": [1.04, -1.04]})
    with pytest.raises(ValueError, match=r"^R = 1.2 at point 1: reflectance and transmittance are fractions in \[0, 1\]"):
        jo.make_spectra([500, 600], 70, {"R": [0.3, 1.2]})
    with pytest.raises(ValueError, match=r"^N = -1.3 at point 1 of spectrum 1: N, C and S are"):
        jo.make_spectra([500, 600], 70, {"N": [[0.3, 0.2], [0.1, -1.3]]})
    with pytest.raises(ValueError, match=r"^psi_deg = 95 at point 0: Psi lies in \[0, 90\] degrees"):
        jo.make_spectra([500], 70, {"psi_deg": [95.0]})


# ---- the model file and the command line -------------------------------------------------------


@pytest.mark.slow
def test_cli_fit_stack_example(capsys, tmp_path):
    """The bundled example (made with tmm: 512.4 nm of Cauchy SiO2 on Si) is recovered within its
    standard errors, with chi2_reduced near 1, and the plot is written."""
    from jaxoptics.__main__ import main

    png = tmp_path / "fs.png"
    assert main(["fit-stack", "--example", "--plot", str(png), "--no-cache"]) == 0
    out, err = capsys.readouterr()
    rows = {l.split()[0]: l.split()[1:3] for l in out.splitlines() if l.startswith("oxide.")}
    d, sd = (float(x) for x in rows["oxide.thickness_nm"])
    assert abs(d - 512.4) < 4 * sd
    A, sA = (float(x) for x in rows["oxide.A"])
    assert abs(A - 1.44721) < 4 * sA
    chi = float(out.split("chi2_reduced ")[1].split(";")[0])
    assert 0.8 < chi < 1.2
    assert png.stat().st_size > 20000
    assert "no upper bound" not in err


@pytest.mark.slow
def test_cli_fit_stack_names_an_unbounded_thickness_of_a_poor_fit(capsys, tmp_path):
    """The example's model without the thickness's max: no search over fringes, so the fit from
    100 nm ends a fringe away from the 512.4 nm film; the command says why."""
    from jaxoptics.__main__ import main

    data = Path(jo.__file__).parent / "data"
    toml = tmp_path / "nomax.toml"
    toml.write_text((data / "example_sio2_si.toml").read_text().replace("{ value = 100, min = 0, max = 2000 }", "{ value = 100, min = 0 }"))
    main(["fit-stack", str(data / "example_sio2_si.csv"), "--model", str(toml), "--no-cache"])
    out, err = capsys.readouterr()
    d = float(next(l.split()[1] for l in out.splitlines() if l.startswith("oxide.thickness_nm")))
    assert abs(d - 512.4) > 50
    assert "note: oxide.thickness_nm has no upper bound, so no search over fringes was made" in err


@pytest.mark.slow
def test_cli_fit_stack_map(tmp_path, capsys):
    """A map file (sites with positions, tmm-generated data with noise): the command prints the
    summary over sites, `--out` writes every site's value and standard error (each within 4 of
    them of the truth), and `--plot` writes the first site's spectra and the maps."""
    from jaxoptics.__main__ import main

    wl = np.linspace(350.0, 900.0, 60)
    ang = np.full(wl.size, 70.0)
    d_true = np.array([220.0, 260.0, 300.0, 340.0, 380.0, 420.0])
    xy = np.array([[-40.0, 0.0], [0.0, 0.0], [40.0, 0.0], [-20.0, 30.0], [20.0, 30.0], [0.0, -35.0]])
    rng = np.random.default_rng(11)
    psi = np.stack([tmm_quantities(cauchy_n(wl, **OXIDE), d, wl, ang)[0] for d in d_true])
    delta = np.stack([tmm_quantities(cauchy_n(wl, **OXIDE), d, wl, ang)[1] for d in d_true])
    sig = dict(psi_deg=0.02, delta_deg=0.05)
    sp = jo.make_spectra(wl, ang, {"psi_deg": psi + sig["psi_deg"] * rng.normal(size=psi.shape),
                                   "delta_deg": delta + sig["delta_deg"] * rng.normal(size=psi.shape)},
                         sigma={k: np.full(psi.shape, v) for k, v in sig.items()}, sites=[f"p{i}" for i in range(6)], site_xy=xy)
    jo.save_spectra(tmp_path / "map.csv", sp)
    (tmp_path / "m.toml").write_text(f"""
[[layer]]
name = "film"
thickness_nm = {{ value = 100, min = 0, max = 1000 }}
material = {{ model = "cauchy", A = {OXIDE['A']}, B = {OXIDE['B']} }}
[substrate]
material = "Si"
""")
    png = tmp_path / "fit.png"
    assert main(["fit-stack", str(tmp_path / "map.csv"), "--model", str(tmp_path / "m.toml"), "--out", str(tmp_path / "res.csv"),
                 "--plot", str(png), "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "60 points (350-900 nm, angles 70 deg) x psi_deg, delta_deg; 6 sites" in out and "converged at 6 of 6 sites" in out
    mean = float(next(l for l in out.splitlines() if l.startswith("film.thickness_nm")).split()[1])
    assert abs(mean - d_true.mean()) < 0.1
    rows = (tmp_path / "res.csv").read_text().splitlines()
    assert rows[0] == "site,x_mm,y_mm,film.thickness_nm,stderr_film.thickness_nm,ci90_film.thickness_nm,chi2_reduced,mse,mse_ncs,converged"
    for row, d, at in zip(rows[1:], d_true, xy, strict=True):
        site, x, y, value, sd, ci90, chi2, mse, mse_ncs, conv = row.split(",")
        assert abs(float(value) - d) < 4 * float(sd) and conv == "True" and 0.5 < float(chi2) < 2
        assert float(mse) == pytest.approx(float(chi2) ** 0.5) and float(mse_ncs) > 0
        assert float(ci90) == pytest.approx(1.65 * float(sd) / max(1, float(chi2)) ** 0.5 * float(mse) ** 0.5)
        assert (float(x), float(y)) == tuple(at)
    assert [r.split(",")[0] for r in rows[1:]] == [f"p{i}" for i in range(6)]
    assert f"plot saved to {png} (site p0)" in out and f"maps of the fitted parameters saved to {tmp_path / 'fit_map.png'}" in out
    assert png.stat().st_size > 20000 and (tmp_path / "fit_map.png").stat().st_size > 20000


@pytest.mark.slow
def test_plot_draws_the_model_between_the_measurements():
    """`plot_stack_fit`'s curves (`_plot._curves`): the model between the measured points against
    tmm, through the model at each measured point, delta's line broken where it wraps (no segment
    spans more than 180 degrees), and angle scans drawn over angle."""
    from jaxoptics._fitting._plot import _curves

    wl, ang = grid()
    x = [1.452, 0.0036, 0.0, 480.0]  # the free parameters: A, B, C, thickness
    psi, delta, _, _ = tmm_quantities(cauchy_n(wl, 1.452, 0.0036), 480.0, wl, ang)
    sample = jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.46), B=jo.Free(0.0), C=jo.Free(0.0)), jo.Free(100.0, 0, 2000))],
                       jo.material("Si"))
    spectra = jo.make_spectra(wl, ang, {"psi_deg": psi + 0.01, "delta_deg": delta})
    xlabel, panels = _curves(sample, spectra, x)
    assert xlabel == "wavelength (nm)" and [k for k, _ in panels] == ["psi_deg", "delta_deg"]
    for kind, curves in panels:
        assert [c[0] for c in curves] == ["fit, 65 deg", "fit, 70 deg", "fit, 75 deg"]
        for (label, xf, yf, xd, shown, resid, idx), a in zip(curves, ANGLES):
            np.testing.assert_array_equal(xd, WL)
            np.testing.assert_array_equal(ang[idx], a)
            ok = np.isfinite(xf)
            assert ok.sum() == 8 * (WL.size - 1) + 1  # the data's points and 7 more in each gap
            p_ref, d_ref, _, _ = tmm_quantities(cauchy_n(xf[ok], 1.452, 0.0036), 480.0, xf[ok], np.full(ok.sum(), a))
            if kind == "psi_deg":
                np.testing.assert_allclose(yf[ok], p_ref, atol=1e-9)
                np.testing.assert_allclose(resid, -0.01, atol=1e-9)
            else:
                np.testing.assert_allclose((yf[ok] - d_ref + 180) % 360 - 180, 0, atol=1e-8)
                assert np.all((yf[ok] >= 0) & (yf[ok] < 360))
                for seg in np.split(yf, np.flatnonzero(np.isnan(yf))):
                    seg = seg[np.isfinite(seg)]
                    assert np.all(np.abs(np.diff(seg)) < 180)
                np.testing.assert_allclose(resid, 0, atol=1e-8)
            # the line passes through the model at every measured point (data + residual)
            at = np.searchsorted(xf[ok], xd)
            np.testing.assert_allclose(yf[ok][at], shown + resid, atol=1e-9)
    # this film's delta wraps at 70 and 75 degrees, not at 65: its lines are broken there alone
    assert [int(np.isnan(c[2]).sum()) for c in panels[1][1]] == [0, 1, 1]
    # an angle scan at one wavelength is drawn over angle
    a = np.linspace(45.0, 80.0, 15)
    psi1, delta1, _, _ = tmm_quantities(cauchy_n(np.full(15, 632.8), 1.452, 0.0036), 480.0, np.full(15, 632.8), a)
    xlabel, panels = _curves(sample, jo.make_spectra(np.full(15, 632.8), a, {"psi_deg": psi1}), x)
    (label, xf, yf, xd, shown, resid, _), = panels[0][1]
    assert xlabel == "angle of incidence (deg)" and label == "fit, 632.8 nm"
    np.testing.assert_array_equal(xd, a)
    np.testing.assert_allclose(yf, tmm_quantities(cauchy_n(np.full(xf.size, 632.8), 1.452, 0.0036), 480.0,
                                                  np.full(xf.size, 632.8), xf)[0], atol=1e-9)


@pytest.mark.slow
def test_plot_stack_fit_figure_sites_and_bad_arguments():
    """`plot_stack_fit` on a map: the site chosen by position or label, residuals over sigma on
    request, and clear errors for a bad site, a bad residual kind, or normalized residuals without
    sigma."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wl, ang = grid()
    sample = jo.Sample([jo.Layer(jo.Cauchy(A=1.452, B=0.0036), jo.Free(100.0, 0, 2000), name="film")], jo.material("Si"))
    clean = np.asarray(sample.with_values([480.0]).quantities(("psi_deg",), jnp.asarray(wl), jnp.asarray(np.radians(ang))))[0]
    V = np.stack([clean, clean + 0.02])  # site "b": the model 0.02 degrees below the data
    spectra = jo.Spectra(wl, ang, ("psi_deg",), V[:, None], np.full((2, 1, wl.size), 0.01), ("a", "b"))

    class Fit:  # the fields of a StackFit that the plot reads: both sites at the truth, site b not converged
        names = ("film.thickness_nm",)
        values = np.array([[480.0], [480.0]])
        converged = np.array([True, False])

    for site in (1, "b", -1):
        fig = jo.plot_stack_fit(sample, spectra, Fit, site=site, residuals="normalized")
        ax = fig.axes[1]
        assert ax.get_ylabel() == "(model - data) / sigma" and "(site b of 2) - the fit did NOT converge" in fig._suptitle.get_text()
        for line in ax.get_lines()[:-1]:  # the last is the zero line
            np.testing.assert_allclose(line.get_ydata(), -2.0, atol=1e-9)
        plt.close(fig)
    fig = jo.plot_stack_fit(sample, spectra, Fit)
    assert fig.axes[1].get_ylabel() == "model - data" and "(site a of 2)\n" in fig._suptitle.get_text()
    assert "NOT converged" not in fig._suptitle.get_text()
    np.testing.assert_allclose(fig.axes[1].get_lines()[0].get_ydata(), 0, atol=1e-9)
    plt.close(fig)
    for kw, msg in [(dict(site=2), r"site must be a position in 0..1 or a site label, got 2"),
                    (dict(site="z"), r"site 'z' is not a site of these spectra \(sites: a, b\)"),
                    (dict(residuals="relative"), r"residuals must be 'difference' or 'normalized', got 'relative'"),
                    (dict(fine=0), r"fine must be a whole number of points per gap, at least 1, got 0")]:
        with pytest.raises(ValueError, match=msg):
            jo.plot_stack_fit(sample, spectra, Fit, **kw)
    with pytest.raises(ValueError, match="the fit holds 2 fits, the spectra 1 spectra"):
        jo.plot_stack_fit(sample, jo.make_spectra(wl, ang, {"psi_deg": clean}), Fit)
    with pytest.raises(ValueError, match="residuals='normalized' needs the spectra's sigma"):
        jo.plot_stack_fit(sample, spectra._replace(sigma=None), Fit, residuals="normalized")


def test_plot_stack_map_draws_every_site_where_it_is():
    """`plot_stack_map`: each panel holds the fitted value (its standard error, chi2_reduced) of
    every site at the site's position (interpolated between sites, or as dots for sites on a
    line, or against the position in the file without positions), failed sites marked, and clear
    errors for one spectrum or an unknown parameter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(3)
    xy = rng.uniform(-50, 50, size=(30, 2))
    wl, ang = grid()

    class Fit:  # the fields of a StackFit that the map reads
        names = ("film.thickness_nm", "film.A")
        values = np.stack([300 + xy[:, 0], 1.46 + 1e-4 * xy[:, 1]], -1)
        stderr = np.stack([0.1 + 1e-3 * xy[:, 1] ** 2, np.full(30, 1e-5)], -1)
        chi2_reduced = 1 + 0.01 * np.arange(30)
        converged = np.arange(30) != 7

    sp = jo.make_spectra(wl, ang, {"psi_deg": np.zeros((30, wl.size))}, sites=[f"s{i}" for i in range(30)], site_xy=xy)
    fig = jo.plot_stack_map(sp, Fit)
    panels = [ax for ax in fig.axes if ax.get_title()]
    assert [ax.get_title() for ax in panels] == ["film.thickness_nm", "stderr of film.thickness_nm", "film.A", "stderr of film.A",
                                                 "chi2_reduced"]
    expect = [Fit.values[:, 0], Fit.stderr[:, 0], Fit.values[:, 1], Fit.stderr[:, 1], Fit.chi2_reduced]
    for ax, z in zip(panels, expect):
        mesh, = ax.collections
        np.testing.assert_array_equal(mesh.get_array(), z)  # one value per site, in the sites' order
        np.testing.assert_array_equal(np.stack([mesh._triangulation.x, mesh._triangulation.y], -1), xy)
        failed, = ax.get_lines()
        np.testing.assert_array_equal(np.stack([failed.get_xdata(), failed.get_ydata()], -1), xy[[7]])
    assert "30 sites; 1 not converged (x)" in fig._suptitle.get_text()
    plt.close(fig)
    # sites on one line: dots at the sites
    line_xy = np.stack([np.linspace(-40, 40, 30), np.zeros(30)], -1)
    fig = jo.plot_stack_map(sp._replace(site_xy=line_xy), Fit, names=["film.A"])
    dots, = fig.axes[0].collections
    np.testing.assert_array_equal(dots.get_offsets(), line_xy)
    np.testing.assert_array_equal(dots.get_array(), Fit.values[:, 1])
    assert [ax.get_title() for ax in fig.axes if ax.get_title()] == ["film.A", "stderr of film.A", "chi2_reduced"]
    plt.close(fig)
    # no positions: against the site's position in the file
    fig = jo.plot_stack_map(sp._replace(site_xy=None), Fit)
    values, failed = fig.axes[0].get_lines()
    np.testing.assert_array_equal(values.get_xdata(), np.arange(30))
    np.testing.assert_array_equal(values.get_ydata(), Fit.values[:, 0])
    np.testing.assert_array_equal(failed.get_xdata(), [7])
    plt.close(fig)
    with pytest.raises(ValueError, match="plot_stack_map draws maps: these spectra are one spectrum"):
        jo.plot_stack_map(jo.make_spectra(wl, ang, {"psi_deg": np.zeros(wl.size)}), Fit)
    with pytest.raises(ValueError, match=r"\['film.B'\] are not free parameters of this fit; they are film.thickness_nm, film.A"):
        jo.plot_stack_map(sp, Fit, names=["film.B"])
    with pytest.raises(ValueError, match="the fit holds 30 fits, the spectra 2 spectra"):
        jo.plot_stack_map(jo.make_spectra(wl, ang, {"psi_deg": np.zeros((2, wl.size))}), Fit)


def test_model_file_format_and_errors(tmp_path, capsys):
    p = tmp_path / "m.toml"
    p.write_text("""
[[layer]]
name = "film"
thickness_nm = { value = 50, min = 0, max = 300 }
material = { model = "tauc-lorentz", A = { value = 100 }, E0 = 4.0, C = 1.5, Eg = { value = 2.0, min = 1, max = 3 }, eps_inf = 1.2 }

[[layer]]
thickness_nm = 2.0
material = { n = 1.46 }

[substrate]
material = { model = "drude-lorentz", eps_inf = 1.0, drude = [[{ value = 9.0, min = 5, max = 12 }, 0.07]] }
""")
    s = jo.load_sample(p)
    assert s.free_names() == ["film.A", "film.Eg", "substrate.drude[0][0]", "film.thickness_nm"]
    assert isinstance(s.layers[0].material, jo.TaucLorentz) and s.layers[1].thickness_nm == 2.0
    for text, msg in [
        ("[[layer]]\nthickness_nm = 5\nmaterial = { model = 'cauchy', D = 1 }\n[substrate]\nmaterial = 'Si'\n",
         r"m.toml: layer\[0\].material: cauchy has no parameter 'D'"),
        ("[[layer]]\nthickness_nm = { val = 5 }\nmaterial = 'SiO2'\n[substrate]\nmaterial = 'Si'\n",
         r"layer\[0\].thickness_nm: a free parameter is .*unknown keys \['val'\]"),
        ("[substrate]\nmaterial = 'Unobtainium'\n", r"substrate.material: unknown built-in material 'Unobtainium'"),
        ("[[layer]]\nthickness_nm = 5\n[substrate]\nmaterial = 'Si'\n", r"layer\[0\]: `material` is missing"),
        ("title = \"x\"\nlayer = [1, \n  2,, ]\n", r"m.toml: not valid TOML: .*line 3"),
    ]:
        p.write_text(text)
        with pytest.raises(ValueError, match=msg):
            jo.load_sample(p)
    from jaxoptics.__main__ import main

    assert main(["fit-stack", str(tmp_path / "missing.csv"), "--model", str(p), "--no-cache"]) == 2
    assert "missing.csv: cannot read" in capsys.readouterr().err


@pytest.mark.slow
def test_map_progress_and_noise_free_recovery(capfd):
    """A map of 300 noise-free spectra at one angle (a mapping ellipsometer): every thickness from
    100 to 800 nm is recovered to rounding, and progress is reported from inside the compiled call."""
    wl, ang = np.linspace(350, 900, 50), np.full(50, 70.0)
    m = jo.Sample([jo.Layer(jo.material("SiO2"), jo.Free(300.0, 0, 1500), name="ox")], jo.material("Si"))
    d = np.linspace(100, 800, 300)
    q = np.asarray(jax.jit(jax.vmap(lambda x: m.with_values([x]).quantities(
        ("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.asarray(np.radians(ang)))))(jnp.asarray(d)))
    fit = jo.fit_stack(m, jo.make_spectra(wl, ang, {"psi_deg": q[:, 0], "delta_deg": q[:, 1]}), progress=True)
    assert np.max(np.abs(np.asarray(fit["ox.thickness_nm"]) - d)) < 1e-8
    assert "fit_stack: 300 of 300 spectra fitted" in capfd.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("case", ["film", "absorbing film", "mixed"])
def test_jacobian_through_the_stack_inputs_equals_jacfwd(case):
    """`fit_stack`'s Jacobian (tangents through the stack's inputs, `_jacobian_plan`) equals
    `jax.jacfwd` and `jax.jacrev` of the model and finite differences, for media with many free
    parameters (split into the real and imaginary part of the index, or the real part alone where
    `k` is held at zero), media with one or two, thicknesses, an incoherent layer and every kind of
    quantity."""
    from jaxoptics._fitting._stack_jacobian import _jacobian_plan, _model_and_jacobian

    wl = np.linspace(300.0, 1000.0, 40)
    ang = np.radians(np.repeat([55.0, 70.0], 20))
    if case == "film":
        sample = jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.46), B=jo.Free(0.004), C=jo.Free(1e-4)), jo.Free(480.0))],
                           jo.material("Si"))
        kinds, x = ("psi_deg", "delta_deg"), [1.46, 0.004, 1e-4, 480.0]
        assert len(_jacobian_plan(sample).directions) == 2  # Re n of the film (k held at 0); its thickness
    elif case == "absorbing film":  # an Urbach tail: k depends on the free parameters
        sample = jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.46), B=jo.Free(0.004), k_amp=jo.Free(0.01), k_exp=jo.Free(1.2)),
                                     jo.Free(480.0))], jo.material("Si"))
        kinds, x = ("psi_deg", "delta_deg", "R"), [1.46, 0.004, 0.01, 1.2, 480.0]
        assert len(_jacobian_plan(sample).directions) == 3  # Re n, Im n of the film; its thickness
    else:
        tl = jo.TaucLorentz(A=jo.Free(120.0), E0=jo.Free(3.8), C=jo.Free(1.2), Eg=jo.Free(2.1), eps_inf=1.1)
        sample = jo.Sample([jo.Layer(1.5, 2e5, incoherent=True), jo.Layer(tl, jo.Free(60.0)),
                            jo.Layer(jo.Cauchy(A=jo.Free(1.46)), 300.0)], jo.Constant(n=jo.Free(1.7), k=jo.Free(0.02)))
        kinds = ("R_s", "R_p", "R", "T", "N", "C", "S", "psi_deg", "delta_deg")
        x = [120.0, 3.8, 1.2, 2.1, 1.46, 1.7, 0.02, 60.0]
    jax.config.update("jax_enable_x64", True)
    x = jnp.asarray(x, jnp.float64)
    wl_j, ang_j = jnp.asarray(wl), jnp.asarray(ang)
    m, J = quick_jit(_model_and_jacobian(sample, kinds, wl_j, ang_j))(x)
    # the references compiled once each (the finite differences call the model 32 times)
    model_of = lambda x: sample.with_values([x[i] for i in range(x.shape[0])]).quantities(kinds, wl_j, ang_j, flat=True)
    model = quick_jit(model_of)
    J_ref = quick_jit(jax.jacfwd(model_of))(x)
    np.testing.assert_allclose(m, model(x), rtol=1e-13, atol=1e-13)
    assert np.all(np.isfinite(J))
    scale = np.max(np.abs(J_ref), axis=0)
    np.testing.assert_allclose(np.asarray(J) / scale[None], np.asarray(J_ref) / scale[None], rtol=0, atol=1e-11)
    # reverse mode (the transposed derivative rules) gives the same Jacobian, and both equal
    # fourth-order central differences in every parameter
    J_rev = quick_jit(jax.jacrev(model_of))(x)
    np.testing.assert_allclose(np.asarray(J_rev) / scale[None], np.asarray(J_ref) / scale[None], rtol=0, atol=1e-11)
    angle = np.repeat([k == "delta_deg" for k in kinds], len(wl))

    def diff(a, b):  # delta in degrees jumps by 360 where it crosses 180
        v = np.asarray(a - b)
        return np.where(angle, (v + 180) % 360 - 180, v)

    for i in range(x.shape[0]):
        h = 1e-4 * max(1e-2, abs(float(x[i])))
        e = jnp.zeros_like(x).at[i].set(h)
        fd = (8 * diff(model(x + e), model(x - e)) - diff(model(x + 2 * e), model(x - 2 * e))) / (12 * h)
        # (the differences' truncation error reaches 1e-7 of a column's scale where delta turns fastest)
        np.testing.assert_allclose(np.asarray(J_ref[:, i]) / scale[i], fd / scale[i], rtol=0, atol=1e-6)


@pytest.mark.slow
def test_pooled_solves_equal_one_solve_per_problem():
    """`pooled_least_squares` (lanes refilled as problems stop) gives each problem the solution,
    step count and status of its own `optx.least_squares` call; problems outside `order[:count]`
    are left at their starts."""
    import optimistix as optx

    from jaxoptics._fitting._pool import pooled_least_squares

    jax.config.update("jax_enable_x64", True)
    t = jnp.linspace(0, 4, 30)
    rng = np.random.default_rng(3)
    truth = jnp.asarray(np.stack([rng.uniform(0.5, 2, 23), rng.uniform(0.2, 3, 23)], -1))
    data = truth[:, :1] * jnp.exp(-truth[:, 1:] * t[None]) + 0.01 * jnp.asarray(rng.normal(size=(23, 30)))
    y0 = jnp.asarray(np.stack([rng.uniform(0.2, 4, 23), rng.uniform(0.05, 6, 23)], -1))
    fn = lambda y, i: y[0] * jnp.exp(-y[1] * t) - data[i]
    for solver in (optx.GaussNewton(rtol=1e-9, atol=1e-9), optx.LevenbergMarquardt(rtol=1e-9, atol=1e-9)):
        ref = [optx.least_squares(fn, solver, y0[i], i, max_steps=12, throw=False) for i in range(23)]
        order = jnp.asarray(rng.permutation(23))
        y, ok, steps, touched, info = jax.jit(lambda order: pooled_least_squares(
            fn, solver, y0, jnp.arange(23), order, 17, lanes=4, max_steps=12))(order)
        assert info is None  # no early stop
        done = np.zeros(23, bool)
        done[np.asarray(order[:17])] = True
        np.testing.assert_array_equal(touched, done)
        for i in range(23):
            if not done[i]:
                np.testing.assert_array_equal(y[i], y0[i])
                continue
            r = ref[i]
            assert int(steps[i]) == int(r.stats["num_steps"])
            assert bool(ok[i]) == bool(r.result == optx.RESULTS.successful)
            np.testing.assert_allclose(y[i], r.value, rtol=1e-12, atol=1e-12)
        # the problems stop after different numbers of steps (the case the pool exists for)
        assert len(set(np.asarray(steps)[done].tolist())) >= 3


@pytest.mark.slow
def test_gauss_newton_edm_stop_ends_within_a_thousandth_of_a_standard_error():
    """With `gauss_newton_edm_stop`, each pooled Gauss-Newton solve ends at the minimum found by
    optimistix's own stopping test (steps below 1e-12 relative, far tighter) to within 1e-3 of
    the standard errors computed there, in fewer steps on noisy data; the normal matrix it keeps
    is `J^T J` at the point its last step began, and its predicted sum of squares is the
    minimum's to within the EDM tolerance."""
    import optimistix as optx

    from jaxoptics._fitting._pool import gauss_newton_edm_stop, pooled_least_squares

    jax.config.update("jax_enable_x64", True)
    t = jnp.linspace(0, 4, 60)
    rng = np.random.default_rng(5)
    M = 40
    truth = np.stack([rng.uniform(0.5, 2, M), rng.uniform(0.2, 3, M)], -1)
    sig = 0.01
    data = jnp.asarray(truth[:, :1] * np.exp(-truth[:, 1:] * np.asarray(t)[None]) + sig * rng.normal(size=(M, 60)))
    y0 = jnp.asarray(truth * rng.uniform(0.7, 1.3, truth.shape))
    fn = lambda y, i: (y[0] * jnp.exp(-y[1] * t) - data[i]) / sig
    tight = optx.GaussNewton(rtol=1e-12, atol=1e-12)
    ref = [optx.least_squares(fn, tight, y0[i], i, max_steps=100, throw=False) for i in range(M)]
    scale = lambda r: jnp.maximum(jnp.sum(r * r) / (60 - 2), 1)
    gn = optx.GaussNewton(rtol=1e-9, atol=1e-9)
    run = lambda stop: jax.jit(lambda: pooled_least_squares(fn, gn, y0, jnp.arange(M), jnp.arange(M), M, lanes=8,
                                                            max_steps=100, early_stop=stop))()
    y, ok, steps, _, ((y_jac, A, c2), early) = run(gauss_newton_edm_stop(1e-6, scale, normal_matrix=True))
    _, ok_c, steps_c, _, _ = run(None)
    assert np.all(np.asarray(ok)) and np.all(np.asarray(ok_c))
    assert np.sum(np.asarray(early)) >= M // 2  # most end by this test, the rest by optimistix's
    for i in range(M):
        assert ref[i].result == optx.RESULTS.successful
        J = np.asarray(jax.jacfwd(fn)(ref[i].value, i))
        r = np.asarray(fn(ref[i].value, i))
        sd = np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * max(1.0, r @ r / 58))
        assert np.all(np.abs(np.asarray(y[i]) - np.asarray(ref[i].value)) < 1e-3 * sd), i
        if early[i]:
            Jy = np.asarray(jax.jacfwd(fn)(y_jac[i], i))
            np.testing.assert_allclose(A[i], Jy.T @ Jy, rtol=1e-10)
            assert abs(float(c2[i]) - r @ r) <= 1e-6 * max(1.0, r @ r / 58), i
    assert np.all(np.asarray(steps) <= np.asarray(steps_c))
    assert np.mean(np.asarray(steps)) < np.mean(np.asarray(steps_c)) - 0.5


@pytest.mark.slow
def test_two_pass_gauss_newton_of_a_map_equals_one_pass(monkeypatch):
    """A map of 32 films from 5 nm to 2000 nm is large enough for the two Gauss-Newton passes (the
    first on the grid's subset of 45 of the 100 wavelengths): every film is recovered, and the
    values equal those of one pass over all the data (a small fit's program, forced here) to
    within 2e-3 of their standard errors, with the same standard errors."""
    from jaxoptics._fitting import _stack_fit, _stack_fit_stages

    d_true = np.linspace(5.0, 2000.0, 32)
    sp = _spectra(d_true, seed=6)
    two = jo.fit_stack(_model(), sp)
    d, sd = np.asarray(two["oxide.thickness_nm"]), np.asarray(two.stderr_of("oxide.thickness_nm"))
    assert np.all(np.asarray(two.converged))
    assert np.all(np.abs(d - d_true) < 4 * sd), (d - d_true) / sd
    _check_errors_at_the_values(two, _model(), sp)
    _stack_fit._program.cache_clear()
    monkeypatch.setattr(_stack_fit_stages, "_QUICK_COMPILE_RESIDUALS", 10**9)
    try:
        one = jo.fit_stack(_model(), sp)
    finally:
        _stack_fit._program.cache_clear()
    assert np.all(np.asarray(one.converged))
    for name in two.names:
        assert np.all(np.abs(np.asarray(two[name]) - np.asarray(one[name])) < 2e-3 * np.asarray(one.stderr_of(name))), name
    np.testing.assert_allclose(np.asarray(two.stderr), np.asarray(one.stderr), rtol=1e-4)


@pytest.mark.slow
def test_several_starts_pick_the_lowest_chi2():
    """`starts=3` refines the three best grid points of each spectrum and keeps the lowest chi^2:
    on these films the best grid point already lies in the right fringe, so the result equals
    that of one start, and each chi^2 is at most the one-start fit's."""
    d_true = np.array([80.0, 520.0, 1600.0])
    sp = _spectra(d_true, seed=7)
    one = jo.fit_stack(_model(), sp)
    three = jo.fit_stack(_model(), sp, starts=3)
    assert np.all(np.asarray(three.converged))
    assert np.all(np.asarray(three.chi2_reduced) <= np.asarray(one.chi2_reduced) * (1 + 1e-9))
    for name in one.names:
        assert np.all(np.abs(np.asarray(three[name]) - np.asarray(one[name])) < 2e-3 * np.asarray(one.stderr_of(name))), name


@pytest.mark.slow
def test_float32_fit_recovers_the_films():
    """With `jax_enable_x64` off the fit runs in float32: every film is fitted within 4 of its
    standard errors of the truth, and agrees with the float64 fit to 0.1 of a standard error,
    with standard errors within 1% of the float64 fit's."""
    d_true = np.array([80.0, 520.0, 1600.0])
    sp = _spectra(d_true, seed=8)
    ref = jo.fit_stack(_model(), sp)
    jax.config.update("jax_enable_x64", False)
    try:
        fit = jo.fit_stack(_model(), sp)
        assert fit.values.dtype == jnp.float32
        conv, d, sd = (np.asarray(a, np.float64) for a in (fit.converged, fit["oxide.thickness_nm"], fit.stderr_of("oxide.thickness_nm")))
    finally:
        jax.config.update("jax_enable_x64", True)
    assert np.all(conv)
    assert np.all(np.abs(d - d_true) < 4 * sd), (d - d_true) / sd
    np.testing.assert_allclose(sd, np.asarray(ref.stderr_of("oxide.thickness_nm")), rtol=0.01)
    assert np.all(np.abs(d - np.asarray(ref["oxide.thickness_nm"])) < 0.1 * sd)


def test_wrapped_delta_residuals():
    """Delta residuals are wrapped to the nearest multiple of 360 degrees: equal to NumPy's
    remainder (exact) within an ulp of the input, in [-180, 180]."""
    from jaxoptics._fitting._stack_fit_stages import _wrap_deg

    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(4)
    d = np.concatenate([rng.uniform(-2000, 2000, 10_000), [-540.0, -180.0, 0.0, 179.999, 180.0, 359.0, 360.0, 1e6 + 0.5]])
    w = np.asarray(_wrap_deg(jnp.asarray(d)))
    ref = np.remainder(d + 180, 360) - 180
    assert np.all(np.abs(w) <= 180)
    diff = np.abs(w - ref)
    assert np.all((diff <= np.spacing(np.abs(d)) + 1e-300) | (np.abs(diff - 360) <= np.spacing(np.abs(d))))  # +-180 both allowed
    np.testing.assert_array_equal(np.asarray(jax.grad(lambda x: _wrap_deg(x))(200.0)), 1.0)
