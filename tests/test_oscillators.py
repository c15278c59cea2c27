"""The oscillator models of ellipsometry software (Gaussian, Cody-Lorentz, poles, Sellmeier with an
IR pole, the GenOsc sum, the Kramers-Kronig-consistent B-spline) against their published formulas
transcribed at 30 digits (mpmath), the Kramers-Kronig integral of each eps2 done numerically at 20
digits, SciPy's B-spline, pyElli's Gaussian and Cody-Lorentz eps2, and the physical limits of
poles (Lorentz and Drude terms of vanishing damping)."""

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

import jaxoptics as jo

HC = 1.2398419843320026


def _kk(eps2, E, breaks):
    """eps1 - eps_inf = (2/pi) P int_0^inf x eps2(x) / (x^2 - E^2) dx at 20 digits (the pole
    subtracted: P int_0^inf dx / (x^2 - E^2) = 0)."""
    with mp.workdps(20):
        E = mp.mpf(E)
        fE = E * eps2(E)
        pts = sorted({mp.mpf(0), E} | {mp.mpf(b) for b in breaks if b > 0})
        return 2 / mp.pi * mp.quad(lambda x: (x * eps2(x) - fE) / (x * x - E * E), pts + [mp.inf])


def _eps(model, E, dtype=np.float64):
    return np.asarray(jax.jit(model.eps)(jnp.asarray(HC / np.asarray(E, np.float64), dtype)))


GAUSS = dict(A=3.0, E0=4.2, Br=1.1, eps_inf=1.5)


def test_gaussian_is_the_published_formula_and_its_own_kramers_kronig_transform():
    mp.mp.dps = 30
    A, E0, Br = (mp.mpf(GAUSS[k]) for k in ("A", "E0", "Br"))
    s = Br / (2 * mp.sqrt(mp.log(2)))
    dawson = lambda x: mp.sqrt(mp.pi) / 2 * mp.exp(-x * x) * mp.erfi(x)
    eps2 = lambda x: A * (mp.exp(-((x - E0) / s) ** 2) - mp.exp(-((x + E0) / s) ** 2))
    Es = [0.3, 1.5, 3.0, 3.9, 4.2, 4.6, 6.0, 12.0]
    got = _eps(jo.Gaussian(**GAUSS), Es)
    for E, e in zip(Es, got):
        E = mp.mpf(E)
        eps1 = GAUSS["eps_inf"] + 2 * A / mp.sqrt(mp.pi) * (dawson((E + E0) / s) - dawson((E - E0) / s))
        assert e.real == pytest.approx(float(eps1), rel=1e-14)
        assert e.imag == pytest.approx(float(eps2(E)), rel=1e-13, abs=1e-300)
        assert e.real == pytest.approx(GAUSS["eps_inf"] + float(_kk(eps2, E, [E0 - 3 * s, E0, E0 + 3 * s])), rel=1e-13)
    # the peak eps2 is A at E0 (less the mirror term) and the half maximum is at E0 +- Br/2
    half = _eps(jo.Gaussian(**GAUSS), [4.2 - 0.55, 4.2 + 0.55]).imag
    np.testing.assert_allclose(half, 1.5, rtol=1e-6)


def test_gaussian_agrees_with_pyelli():
    elli = pytest.importorskip("elli")
    lam_nm = np.linspace(200, 1600, 57)
    ref = elli.Gaussian().add(A=GAUSS["A"], E=GAUSS["E0"], sigma=GAUSS["Br"]).dielectric_function(lam_nm)
    got = np.asarray(jo.Gaussian(**{**GAUSS, "eps_inf": 0.0}).eps(jnp.asarray(lam_nm / 1000)))
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)


CODY = [
    dict(A=60.0, E0=3.7, C=2.4, Eg=1.65, Ep=1.1, Et=1.8, Eu=0.06, eps_inf=1.1),  # amorphous silicon-like
    dict(A=20.0, E0=3.4, C=0.3, Eg=1.2, Ep=0.4, Et=1.3, Eu=0.02, eps_inf=1.0),  # a narrow band, a steep tail
]


def _cody_eps2(p):
    A, E0, C, Eg, Ep, Et, Eu = (mp.mpf(p[k]) for k in ("A", "E0", "C", "Eg", "Ep", "Et", "Eu"))
    GL = lambda x: (x - Eg) ** 2 / ((x - Eg) ** 2 + Ep**2) * A * E0 * C * x / ((x * x - E0 * E0) ** 2 + C * C * x * x)
    return lambda x: GL(x) if x > Et else Et * GL(Et) / x * mp.exp((x - Et) / Eu)


@pytest.mark.parametrize("p", CODY)
def test_cody_lorentz_is_the_published_eps2_and_its_kramers_kronig_transform(p):
    eps2 = _cody_eps2(p)
    Es = [0.4, 1.0, p["Eg"], p["Et"], 2.2, p["E0"], 5.0, 9.0]
    got = _eps(jo.CodyLorentz(**p), Es)
    breaks = [p["Eg"], p["Et"], p["Eg"] + p["Ep"], p["E0"] - p["C"], p["E0"], p["E0"] + p["C"]]
    for E, e in zip(Es, got):
        assert e.imag == pytest.approx(float(eps2(mp.mpf(E))), rel=1e-13)
        assert e.real == pytest.approx(p["eps_inf"] + float(_kk(eps2, E, breaks)), rel=1e-12)
    # continuous at Et (the tail's amplitude E1 is defined by it)
    Et = p["Et"]
    near = _eps(jo.CodyLorentz(**p), [Et * (1 - 1e-9), Et * (1 + 1e-9)]).imag
    assert near[0] == pytest.approx(near[1], rel=1e-6)


def test_cody_lorentz_agrees_with_pyelli_eps2():
    elli = pytest.importorskip("elli")
    p = CODY[0]
    lam_nm = np.linspace(250, 1500, 41)
    ref = elli.CodyLorentz.eps2(HC * 1000 / lam_nm, Eg=p["Eg"], A=p["A"], Et=p["Et"], gamma=p["C"], Ep=p["Ep"], E0=p["E0"],
                                Eu=p["Eu"])
    got = jo.CodyLorentz(**p).eps2(jnp.asarray(HC * 1000 / lam_nm))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12)


def test_cody_lorentz_derivatives_are_finite_at_its_breakpoints_and_match_differences():
    p = CODY[0]

    @jax.jit
    def n_of(E, Eg, Et, E0):
        return jnp.real(jo.CodyLorentz(**{**p, "Eg": Eg, "Et": Et, "E0": E0}).nk(HC / E))

    grad = jax.jit(jax.grad(n_of, argnums=(0, 1, 2, 3)))
    h = 1e-6
    for E in (p["Eg"], p["Et"], p["E0"], 2.5):  # E on each breakpoint of the quadrature
        g = grad(E, p["Eg"], p["Et"], p["E0"])
        assert all(np.isfinite(float(x)) for x in g)
        fd = (n_of(E, p["Eg"], p["Et"], p["E0"] + h) - n_of(E, p["Eg"], p["Et"], p["E0"] - h)) / (2 * h)
        assert float(g[3]) == pytest.approx(float(fd), rel=1e-6)
    f32 = _eps(jo.CodyLorentz(**p), [1.0, 2.0, 4.0], np.float32)
    assert f32.dtype == np.complex64
    np.testing.assert_allclose(f32, _eps(jo.CodyLorentz(**p), [1.0, 2.0, 4.0]), rtol=2e-5)


def test_poles_are_the_limits_of_lorentz_and_drude_terms_and_sellmeier_ir_is_poles():
    Es = np.array([0.8, 1.5, 2.5, 3.5])
    poles = jo.Poles(uv_amp=60.0, uv_energy=9.0, ir_amp=0.02, eps_inf=1.2)
    got = _eps(poles, Es)
    np.testing.assert_allclose(got.real, 1.2 + 60.0 / (81.0 - Es**2) - 0.02 / Es**2, rtol=1e-15)
    assert np.all(got.imag == 0)
    # a Lorentz oscillator f E0^2 / (E0^2 - E^2 - i G E) and a Drude term -wp^2 / (E^2 + i g E) of
    # vanishing damping: the IR pole lowers eps1, with the sign of a positive-strength oscillator
    limit = jo.DrudeLorentz(eps_inf=1.2, drude=((0.02**0.5, 1e-9),), lorentz=((60.0 / 81.0, 9.0, 1e-9),))
    np.testing.assert_allclose(got.real, _eps(limit, Es).real, rtol=1e-12)
    assert np.all(_eps(jo.Poles(ir_amp=0.02), Es).real < 1)
    # Sellmeier with an IR pole, n^2 = eps_inf + A l^2 / (l^2 - En^2) - P l^2 (um), is two poles
    s = jo.SellmeierIR(eps_inf=1.3, A=0.9, En=0.11, P=0.012)
    lam = HC / Es
    np.testing.assert_allclose(np.asarray(s.nk(jnp.asarray(lam))) ** 2,
                               1.3 + 0.9 * lam**2 / (lam**2 - 0.11**2) - 0.012 * lam**2, rtol=1e-14)
    same = jo.Poles(uv_amp=0.9 * (HC / 0.11) ** 2, uv_energy=HC / 0.11, ir_amp=0.012 * HC**2, eps_inf=1.3)
    np.testing.assert_allclose(np.asarray(s.nk(jnp.asarray(lam))), np.asarray(same.nk(jnp.asarray(lam))), rtol=1e-13)


BSPL = dict(coefficients=(0.5, 2.0, 3.5, 3.0, 1.2, 0.4, 0.0, 0.8), start=1.5, spacing=0.3, eps_inf=1.3)


@pytest.mark.slow
def test_bspline_eps2_is_scipys_spline_and_eps1_its_kramers_kronig_transform():
    from scipy.interpolate import BSpline as SciPyBSpline

    c, start, h = BSPL["coefficients"], BSPL["start"], BSPL["spacing"]
    knots = start + h * (np.arange(len(c) + 4) - 2)
    # (three zero coefficients on each side: SciPy evaluates a spline only where a full set of
    # basis functions overlaps, and the model's support reaches two spacings beyond its outer nodes)
    ref = SciPyBSpline(start + h * (np.arange(len(c) + 10) - 5), np.concatenate([np.zeros(3), c, np.zeros(3)]), 3,
                       extrapolate=False)
    model = jo.BSpline(**BSPL)
    # at knots, between them, below and above the support, and far beyond (the moment series)
    Es = np.concatenate([knots, [0.2, 1.05, 1.6, 2.27, 3.01, 4.5, 6.0, 20.0, 300.0]])
    got = _eps(model, Es)
    np.testing.assert_allclose(got.imag, np.nan_to_num(ref(Es)), rtol=1e-13, atol=1e-15)
    mp.mp.dps = 30
    Bm = lambda t: (mp.mpf(2) / 3 - t * t + abs(t) ** 3 / 2 if abs(t) < 1 else ((2 - abs(t)) ** 3 / 6 if abs(t) < 2 else mp.mpf(0)))
    eps2 = lambda x: sum(ci * Bm((x - mp.mpf(start) - i * mp.mpf(h)) / mp.mpf(h)) for i, ci in enumerate(c))
    for E, e in zip(Es, got):
        assert e.real == pytest.approx(BSPL["eps_inf"] + float(_kk(eps2, E, list(knots))), rel=1e-13, abs=1e-14), E
    # equal coefficients: a flat eps2 of that value between the outer nodes
    flat = _eps(jo.BSpline(coefficients=(2.0,) * 9, start=1.0, spacing=0.25), [1.5, 1.8, 2.2])
    np.testing.assert_allclose(flat.imag, 2.0, rtol=1e-14)


@pytest.mark.slow
def test_bspline_derivatives_are_finite_at_the_knots():
    @jax.jit
    def n_of(E, c2, h):
        m = jo.BSpline(coefficients=(0.5, 2.0, c2, 3.0), start=1.5, spacing=h)
        return jnp.real(m.nk(HC / E)) + jnp.imag(m.nk(HC / E))

    grad = jax.jit(jax.grad(n_of, argnums=(0, 1, 2)))
    for E in (1.5 - 0.6, 1.5, 1.8, 2.1, 1.95, 3.0):
        g = grad(E, 3.5, 0.3)
        assert all(np.isfinite(float(x)) for x in g), E
    h = 1e-6
    fd = (n_of(1.8, 3.5, 0.3 + h) - n_of(1.8, 3.5, 0.3 - h)) / (2 * h)
    assert float(grad(1.8, 3.5, 0.3)[2]) == pytest.approx(float(fd), rel=1e-6)
    with pytest.raises(ValueError, match="start"):
        jo.BSpline(coefficients=(1.0,), start=0.3, spacing=0.2)
    with pytest.raises(ValueError, match="spacing"):
        jo.BSpline(coefficients=(1.0,), start=1.0, spacing=0.0)


@pytest.mark.slow
def test_genosc_sums_its_oscillators_and_names_their_parameters():
    osc = (jo.Gaussian(A=1.0, E0=5.5, Br=1.0), jo.TaucLorentz(A=80.0, E0=4.0, C=2.0, Eg=1.5, eps_inf=0.0),
           jo.Poles(uv_amp=30.0, uv_energy=10.0), jo.CodyLorentz(), jo.BSpline(**BSPL), jo.Drude(2.0, 0.1))
    Es = [0.7, 1.6, 2.5, 4.0]
    expect = 1.4 + sum(_eps(o, Es) - o.eps_inf for o in osc)
    np.testing.assert_allclose(_eps(jo.GenOsc(eps_inf=1.4, oscillators=osc), Es), expect, rtol=1e-13)
    free = (jo.Gaussian(A=jo.Free(1.0, 0.0, 5.0), E0=5.5, Br=1.0),
            jo.TaucLorentz(A=80.0, E0=4.0, C=2.0, Eg=jo.Free(1.5, 1.0, 2.0), eps_inf=0.0)) + osc[2:]
    g = jo.GenOsc(eps_inf=jo.Free(1.4, 1.0, 3.0), oscillators=free)
    s = jo.Sample([jo.Layer(g, jo.Free(50.0, 0.0, 200.0), name="film")], jo.material("Si"))
    assert s.free_names() == ["film.eps_inf", "film.oscillators[0].A", "film.oscillators[1].Eg", "film.thickness_nm"]

    def R(v):  # a stack with the sum as a layer, differentiable in its free parameters
        return jnp.sum(s.with_values(list(v)).quantities(("R",), jnp.asarray([500.0, 700.0]), jnp.asarray([0.2, 0.2]), flat=True))

    assert np.all(np.isfinite(np.asarray(jax.jit(jax.grad(R))(jnp.asarray([1.4, 1.0, 1.5, 50.0])))))
    with pytest.raises(ValueError, match=r"oscillators\[0\].eps_inf is Free"):
        jo.GenOsc(oscillators=(jo.Gaussian(eps_inf=jo.Free(1.0)),))
    with pytest.raises(ValueError, match=r"oscillators\[0\] is Cauchy"):
        jo.GenOsc(oscillators=(jo.Cauchy(),))


def test_model_file_oscillators(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text(
        '[[layer]]\nname = "a"\nthickness_nm = 20\n'
        'material = { model = "genosc", eps_inf = { value = 1.5, min = 1, max = 3 }, oscillators = [\n'
        '  { model = "gaussian", A = { value = 1.0, min = 0, max = 5 }, E0 = 5.0, Br = 1.0 },\n'
        '  { model = "cody-lorentz", A = 50 },\n'
        '  { model = "b-spline", coefficients = [1.0, { value = 2.0, min = 0, max = 10 }, 1.0], start = 2.0, spacing = 0.5 },\n'
        '  { model = "poles", uv_amp = 40, uv_energy = 9 } ] }\n'
        '[[layer]]\nthickness_nm = 5\nmaterial = { model = "sellmeier-ir", A = 1.1, En = 0.1, P = 0.01 }\n'
        '[substrate]\nmaterial = "Si"\n')
    s = jo.load_sample(p)
    g = s.layers[0].material
    assert isinstance(g, jo.GenOsc) and [type(o).__name__ for o in g.oscillators] == ["Gaussian", "CodyLorentz", "BSpline", "Poles"]
    assert s.free_names() == ["a.eps_inf", "a.oscillators[0].A", "a.oscillators[2].coefficients[1]"]
    assert isinstance(s.layers[1].material, jo.SellmeierIR)
    p.write_text('[[layer]]\nthickness_nm = 5\nmaterial = { model = "genosc", oscillators = [ { model = "cauchy" } ] }\n')
    with pytest.raises(ValueError, match=r"layer\[0\].material.oscillators\[0\]"):
        jo.load_sample(p)
