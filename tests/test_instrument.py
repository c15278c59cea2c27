"""Instrument and sample non-idealities (`Instrument` in a `Sample`) against the plain model where
they reduce to it, and against brute-force averages: many coherent calculations of the plain
sample summed in intensity (`R_s`, `R_p`, `r_p conj(r_s)`) over the spread of conditions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import quick_jit

import jaxoptics as jo

KINDS = ("N", "C", "S", "psi_deg", "delta_deg", "R")
FILM = jo.Layer(jo.Cauchy(A=1.46, B=0.004), 800.0, name="ox")
SUB = jo.Constant(3.9, 0.02)  # smooth in wavelength (a table's linear interpolation has kinks)
WL = jnp.linspace(400.0, 900.0, 7)
ANG = jnp.deg2rad(jnp.asarray([55.0, 60.0, 65.0, 70.0, 70.0, 75.0, 65.0]))


def _q(inst, sample_layers=(FILM,), sub=SUB, wl=WL, ang=ANG):
    return np.asarray(jo.Sample(list(sample_layers), sub, instrument=inst).fixed().quantities(KINDS, wl, ang))


def _brute(dwl=None, dang=None, scale=None, weights=None):
    """sum_k w_k (R_s, R_p, X) of the plain sample at each of the shifted conditions k (one
    coherent `stack` calculation per condition and point, all in one batched call), and N, C, S
    from the sums."""
    K = len(weights)
    col = lambda v: np.zeros((K, 1)) if v is None else np.asarray(v, np.float64)[:, None]
    wl = np.asarray(WL)[None] + col(dwl)
    n, d = jo.Sample([FILM], SUB).fixed().stack_inputs(jnp.asarray(wl))
    d = np.asarray(d)[None, None, :] * (1 if scale is None else np.asarray(scale)[:, None, None])
    r = jo.stack(n, jnp.asarray(d), jnp.asarray(wl), jnp.cos(np.asarray(ANG)[None] + col(dang)))
    w = np.asarray(weights)[:, None]
    Rs, Rp, X = (np.sum(w * np.asarray(a), axis=0) for a in (r.R_s, r.R_p, r.rp_rs))
    tot = Rs + Rp
    return np.stack([(Rs - Rp) / tot, 2 * X.real / tot, -2 * X.imag / tot])


@pytest.mark.slow
def test_an_ideal_instrument_and_offsets_are_the_plain_model():
    plain = np.asarray(jo.Sample([FILM], SUB).fixed().quantities(KINDS, WL, ANG))
    np.testing.assert_array_equal(_q(jo.Instrument()), plain)
    assert np.max(np.abs(1 - (plain[0] ** 2 + plain[1] ** 2 + plain[2] ** 2))) < 1e-14  # fully polarized
    shifted = np.asarray(jo.Sample([FILM], SUB).fixed().quantities(KINDS, WL + 1.5, ANG + np.deg2rad(0.8)))
    np.testing.assert_allclose(_q(jo.Instrument(angle_offset_deg=0.8, wavelength_shift_nm=1.5)), shifted, rtol=1e-13, atol=1e-12)


def _gauss(fwhm, n=2001):
    z = np.linspace(-8, 8, n)
    w = np.exp(-z * z / 2)
    return z * fwhm / (2 * np.sqrt(2 * np.log(2))), w / w.sum()


@pytest.mark.slow
@pytest.mark.parametrize("effect", ["bandwidth", "spread", "nonuniformity", "all"])
def test_averages_equal_brute_force_sums_of_intensities_and_depolarize(effect):
    inst = {"bandwidth": jo.Instrument(bandwidth_nm=6.0, nodes=9), "spread": jo.Instrument(angle_spread_deg=2.0, nodes=9),
            "nonuniformity": jo.Instrument(thickness_nonuniformity=0.04, nodes=9),
            "all": jo.Instrument(bandwidth_nm=4.0, angle_spread_deg=1.0, thickness_nonuniformity=0.02, nodes=7)}[effect]
    got = _q(inst)
    if effect == "bandwidth":
        dwl, w = _gauss(6.0)
        ref = _brute(dwl=dwl, weights=w)
    elif effect == "spread":
        da, w = _gauss(np.deg2rad(2.0))
        ref = _brute(dang=da, weights=w)
    elif effect == "nonuniformity":  # uniform over +-2%: the midpoint rule
        u = (np.arange(4000) + 0.5) / 4000 - 0.5
        ref = _brute(scale=1 + 0.04 * u, weights=np.full(u.size, 1 / u.size))
    else:  # the product of the three distributions, each on a coarser grid
        dwl, w1 = _gauss(4.0, 61)
        da, w2 = _gauss(np.deg2rad(1.0), 61)
        u = (np.arange(61) + 0.5) / 61 - 0.5
        grid = [(a, b, c, x * y / 61) for a, x in zip(dwl, w1) for b, y in zip(da, w2) for c in 1 + 0.02 * u]
        ref = _brute(*(np.asarray(v) for v in zip(*grid)))
    # the reference's midpoint rule over the thickness limits the agreement: 4.4e-9 with 4000
    # points over 4%, 5.2e-6 with 61 over 2% in the product grid (its error falls as 1/points^2)
    tol = 1e-8 if effect != "all" else 1e-5
    np.testing.assert_allclose(got[:3], ref, atol=tol)
    depol = 1 - (got[0] ** 2 + got[1] ** 2 + got[2] ** 2)
    assert np.all(depol > 1e-6), depol  # partially depolarized, as an ellipsometer sees it
    psi = np.degrees(np.arctan2(np.sqrt(1 - got[0]), np.sqrt(1 + got[0])))  # from N: Psi of the averaged intensities
    np.testing.assert_allclose(got[3], psi, atol=1e-10)


@pytest.mark.slow
def test_backside_reflections_are_an_incoherent_slab_times_the_fraction_collected():
    glass = 1.52
    slab = np.asarray(jo.Sample([FILM, jo.Layer(glass, 1e6, incoherent=True)], 1.0).fixed().stack(WL, ANG).R_s)
    front = np.asarray(jo.Sample([FILM], glass).fixed().stack(WL, ANG).R_s)
    full = _q(jo.Instrument(backside=1.0), sub=glass)
    np.testing.assert_allclose(full, np.asarray(jo.Sample([FILM, jo.Layer(glass, 1e6, incoherent=True)], 1.0).fixed()
                                                .quantities(KINDS, WL, ANG)), rtol=1e-13, atol=1e-12)
    part = jo.Sample([FILM], glass, instrument=jo.Instrument(backside=0.3)).fixed()
    np.testing.assert_allclose(np.asarray(part.instrument.averaged(part, WL, ANG).R_s), front + 0.3 * (slab - front), rtol=1e-13)
    assert np.all(slab > front)  # the back surface adds light
    np.testing.assert_array_equal(_q(jo.Instrument(backside=0.0), sub=glass),
                                  np.asarray(jo.Sample([FILM], glass).fixed().quantities(KINDS, WL, ANG)))


@pytest.mark.slow
def test_instrument_parameters_are_free_parameters_and_a_fit_recovers_an_angle_offset():
    truth = jo.Sample([FILM], SUB, instrument=jo.Instrument(angle_offset_deg=0.7, bandwidth_nm=3.0))
    wl = np.repeat(np.linspace(400.0, 900.0, 40), 2)
    ang = np.tile([65.0, 75.0], 40)
    vals = np.asarray(truth.fixed().quantities(("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.deg2rad(jnp.asarray(ang))))
    noise = np.random.default_rng(3).normal(size=vals.shape) * np.array([[0.01], [0.02]])
    sp = jo.make_spectra(wl, ang, {"psi_deg": vals[0] + noise[0], "delta_deg": vals[1] + noise[1]},
                         sigma={"psi_deg": np.full(wl.size, 0.01), "delta_deg": np.full(wl.size, 0.02)})
    model = jo.Sample([jo.Layer(FILM.material, jo.Free(780.0, 700.0, 900.0), name="ox")], SUB,
                      instrument=jo.Instrument(angle_offset_deg=jo.Free(0.0, -3.0, 3.0), bandwidth_nm=3.0))
    assert model.free_names() == ["ox.thickness_nm", "instrument.angle_offset_deg"]
    fit = jo.fit_stack(model, sp)
    x, sd = np.asarray(fit.values), np.asarray(fit.stderr)
    assert bool(fit.converged)
    assert abs(x[0] - 800.0) < 4 * sd[0] and abs(x[1] - 0.7) < 4 * sd[1] and sd[1] < 0.05
    assert float(fit.chi2_reduced) == pytest.approx(1.0, abs=0.4)


@pytest.mark.slow
def test_gradients_in_every_effect_are_finite_and_match_differences():
    s = jo.Sample([jo.Layer(FILM.material, jo.Free(800.0, 0.0, 2000.0), name="ox")], 1.52,
                  instrument=jo.Instrument(*(jo.Free(v, 0.0, 1.0 if i == 5 else 10.0) for i, v in enumerate([0.5, 1.0, 3.0, 1.0, 0.02, 0.4]))))
    f_of = lambda x: jnp.sum(s.with_values(list(x)).quantities(KINDS, WL, ANG))
    f = quick_jit(f_of)
    x0 = jnp.asarray([800.0, 0.5, 1.0, 3.0, 1.0, 0.02, 0.4])
    g = np.asarray(quick_jit(jax.grad(f_of))(x0))
    assert np.all(np.isfinite(g))
    for i in range(7):
        h = 1e-4 * max(1.0, float(x0[i]))
        e = jnp.zeros(7).at[i].set(h)
        assert g[i] == pytest.approx(float((f(x0 + e) - f(x0 - e)) / (2 * h)), rel=1e-5, abs=1e-7), i


def test_bad_instruments_and_the_model_file(tmp_path):
    with pytest.raises(ValueError, match="bandwidth_nm must be >= 0"):
        jo.Instrument(bandwidth_nm=-1.0)
    with pytest.raises(ValueError, match="backside is a fraction"):
        jo.Instrument(backside=jo.Free(0.5, 0.0, 2.0))
    with pytest.raises(ValueError, match="instrument must be an Instrument"):
        jo.Sample([FILM], SUB, instrument=0.5)
    p = tmp_path / "m.toml"
    p.write_text('[[layer]]\nthickness_nm = 100\nmaterial = 1.46\n[substrate]\nmaterial = "Si"\n'
                 '[instrument]\nangle_offset_deg = { value = 0.0, min = -2, max = 2 }\nbandwidth_nm = 2.5\nnodes = 7\n')
    s = jo.load_sample(p)
    assert s.instrument == jo.Instrument(angle_offset_deg=jo.Free(0.0, -2.0, 2.0), bandwidth_nm=2.5, nodes=7)
    assert s.free_names() == ["instrument.angle_offset_deg"]
    p.write_text('[[layer]]\nthickness_nm = 100\nmaterial = 1.46\n[substrate]\nmaterial = "Si"\n[instrument]\nbandwith_nm = 2\n')
    with pytest.raises(ValueError, match=r"instrument: unknown keys \['bandwith_nm'\]"):
        jo.load_sample(p)


@pytest.mark.slow
def test_depolarization_is_a_measured_quantity_read_from_files_and_fitted(tmp_path):
    """The model's depolarization is 1 - sqrt(N^2 + C^2 + S^2) of the averaged intensities; a
    Woollam file's dPolE rows (percent, with sigma) become the quantity `depolarization`, and a
    fit of Psi, Delta and the depolarization recovers a thickness non-uniformity."""
    s = jo.Sample([FILM], SUB, instrument=jo.Instrument(thickness_nonuniformity=0.05))
    q = np.asarray(s.fixed().quantities(("N", "C", "S", "depolarization"), WL, ANG))
    np.testing.assert_allclose(q[3], 1 - np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2), atol=1e-15)
    assert np.all(q[3] > 1e-4)
    plain = np.asarray(jo.Sample([FILM], SUB).fixed().quantities(("depolarization",), WL, ANG))
    assert np.max(np.abs(plain)) < 1e-14
    # a file: Psi/Delta rows, then dPolE rows (wavelength, AOI, percent, sigma)
    wl = 400.0 + 17.0 * np.arange(30)  # (exact in the file's decimals)
    ang = np.full(30, 70.0)
    kinds = ("psi_deg", "delta_deg", "depolarization")
    vals = np.asarray(s.fixed().quantities(kinds, jnp.asarray(wl), jnp.deg2rad(jnp.asarray(ang))))
    lines = ["title", "VASEmethod[EllipsometerType=4, CompleteEASE=6.37]", "nm"]
    lines += [f"{w:.3f}\t{a:.1f}\t{p:.8f}\t{d:.8f}\t0.01\t0.02" for w, a, p, d in zip(wl, ang, vals[0], vals[1])]
    lines += [f"dPolE\t{w:.3f}\t{a:.1f}\t{100 * x:.8f}\t0.1" for w, a, x in zip(wl, ang, vals[2])]
    (tmp_path / "d.dat").write_text("\n".join(lines) + "\n")
    sp = jo.load_spectra(tmp_path / "d.dat")
    assert sp.kinds == ("psi_deg", "delta_deg")
    sd = sp.with_depolarization()
    assert sd.kinds == kinds and sd.meta["format"] == "woollam"
    np.testing.assert_allclose(sd.values[2], vals[2], atol=1e-10)
    np.testing.assert_allclose(sd.sigma[2], 0.001)
    model = jo.Sample([jo.Layer(FILM.material, jo.Free(790.0, 700.0, 900.0), name="ox")], SUB,
                      instrument=jo.Instrument(thickness_nonuniformity=jo.Free(0.02, 0.0, 0.2)))
    fit = jo.fit_stack(model, sd, global_start=False)
    # noise-free data: the solution is the truth to the solver's stop (a step below 1e-3 of a
    # standard error); the errors are those of the files' sigmas
    x, sd = np.asarray(fit.values), np.asarray(fit.stderr)
    assert np.all(np.abs(x - [800.0, 0.05]) < 0.01 * sd) and sd[1] < 0.005, (x, sd)
    with pytest.raises(ValueError, match="no depolarization in the file"):
        jo.make_spectra(wl, ang, {"psi_deg": vals[0]}).with_depolarization()
