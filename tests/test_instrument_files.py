"""Instrument files: real exports (refellips' BSD-3 test files in tests/data/refellips), files
written here in each vendor's documented layout, the conventions as options with round trips
through a fit, and errors that name the file and line."""

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import tmm

import jaxoptics as jo
from jaxoptics._io._conventions import DELTA_CONVENTIONS, delta_from_instrument

DATA = Path(__file__).parent / "data" / "refellips"


def _rows(path, skip, sep="\t"):
    """The numeric rows of a text file, parsed here independently of the readers."""
    out = []
    for l in Path(path).read_text(encoding="utf-8").splitlines()[skip:]:
        t = [x for x in l.strip().split(sep)]
        if t and t[0]:
            out.append(t)
    return out


# ---------------------------------------------------------------------------------------------
# real exports


def test_woollam_completeease_interleaved_export():
    """CompleteEASE 3.65 (M-2000), CRLF: a data row, then its dPolE and uR rows with AOI 0."""
    sp = jo.load_spectra(DATA / "Woolam_staticTest.dat")
    assert sp.meta["format"] == "woollam" and sp.meta["VASEmethod"]["CompleteEASE"] == "3.65"
    raw = [r for r in _rows(DATA / "Woolam_staticTest.dat", 3) if r[0][0].isdigit()]
    A = np.asarray([[float(x) for x in r[:6]] for r in raw])
    assert sp.kinds == ("psi_deg", "delta_deg") and sp.values.shape == (2, len(A)) == (2, 398)
    np.testing.assert_array_equal(sp.wavelength_nm, A[:, 0])
    np.testing.assert_array_equal(sp.angle_deg, A[:, 1])
    np.testing.assert_array_equal(sp.values, A[:, 2:4].T)
    np.testing.assert_array_equal(sp.sigma, A[:, 4:6].T)
    dpol = np.asarray([float(r[3]) for r in _rows(DATA / "Woolam_staticTest.dat", 3) if r[0] == "dPolE"])
    uR = np.asarray([float(r[3]) for r in _rows(DATA / "Woolam_staticTest.dat", 3) if r[0] == "uR"])
    np.testing.assert_array_equal(sp.meta["depolarization_percent"], dpol)
    np.testing.assert_array_equal(sp.meta["uR"], uR)


def test_woollam_dynamic_export_is_a_time_series():
    sp = jo.load_spectra(DATA / "Woolam_kineticTest.dat")
    raw = np.asarray([[float(x) for x in r if x] for r in _rows(DATA / "Woolam_kineticTest.dat", 4)])
    times = list(dict.fromkeys(raw[:, -1]))
    assert sp.values.shape == (len(times), 2, 398) and len(times) == 7
    np.testing.assert_array_equal(sp.meta["times"], times)
    for k, t in enumerate(times):
        block = raw[raw[:, -1] == t]
        np.testing.assert_array_equal(sp.values[k], block[:, 2:4].T)
        np.testing.assert_array_equal(sp.sigma[k], block[:, 4:6].T)


def test_accurion_nulling_zones_are_averaged_not_summed():
    """Zones 1-4 of each point averaged (zone 4 did not null at three angles: the other three
    are), zone 0 (the instrument's average, NaN there) and zone 5 (the range) not mixed in."""
    sp = jo.load_spectra(DATA / "15-1-1.dat")
    rows = _rows(DATA / "15-1-1.dat", 2)
    ang = sorted({float(r[2]) for r in rows})
    assert sp.meta["format"] == "accurion" and sp.values.shape == (2, len(ang)) == (2, 11)
    for p, a in enumerate(ang):
        z = [(float(r[4]), float(r[3])) for r in rows if float(r[2]) == a and r[5] in "1234" and r[3] != "NaN"]
        assert 3 <= len(z) <= 4
        assert sp.values[0, p] == pytest.approx(np.mean([x[0] for x in z]), abs=1e-9)
        assert sp.values[1, p] == pytest.approx(np.mean([x[1] for x in z]), abs=1e-6)  # circular mean of nearby angles
        z0 = [float(r[3]) for r in rows if float(r[2]) == a and r[5] == "0"]
        if len(z) == 4:  # where every zone nulled, the instrument's own average agrees
            assert sp.values[1, p] == pytest.approx(z0[0], abs=1e-3)
        rng = [float(r[3]) for r in rows if float(r[2]) == a and r[5] == "5"]
        assert sp.meta["zone_range_delta_deg"][p] == rng[0]


def test_accurion_map_is_split_by_stage_position():
    sp = jo.load_spectra(DATA / "post synthesis.dat")
    rows = _rows(DATA / "post synthesis.dat", 2)
    pos = {(round(float(r[11]), 1), round(float(r[12]), 1)) for r in rows}
    assert sp.values.shape == (32, 2, 5) and len(sp.sites) == 32 and sp.site_xy.shape == (32, 2)
    assert len({(round(x, 1), round(y, 1)) for x, y in sp.site_xy}) == 32 and len(pos) >= 32
    first = [r for r in rows if r[5] in "1234" and abs(float(r[11]) - sp.site_xy[0, 0]) < 0.2
             and abs(float(r[12]) - sp.site_xy[0, 1]) < 0.2 and float(r[2]) == sp.angle_deg[0]]
    assert sp.values[0, 0, 0] == pytest.approx(np.mean([float(r[4]) for r in first]), abs=1e-9)


def test_accurion_wvase_format_export():
    sp = jo.load_spectra(DATA / "testData1_11nm_PNIPAM_on_Si_EP4.dat")
    np.testing.assert_array_equal(sp.angle_deg, [55, 60, 65, 70])
    np.testing.assert_array_equal(sp.values, [[27.7, 23.25, 17.8, 11.7], [170.2, 166.35, 159.65, 143.9]])


def test_filmsense_static_and_dynamic():
    sp = jo.load_spectra(DATA / "Filmsense_staticTest.txt")
    rows = _rows(DATA / "Filmsense_staticTest.txt", 2)
    assert sp.kinds == ("N", "C", "S") and sp.values.shape == (3, 8)
    np.testing.assert_array_equal(sp.wavelength_nm, [float(r[0]) for r in rows[:8]])
    np.testing.assert_array_equal(sp.values, np.asarray([[float(x) for x in r[:3]] for r in rows[8:16]]).T)
    np.testing.assert_array_equal(sp.angle_deg, 70.012)
    np.testing.assert_array_equal(sp.meta["degree_of_polarization"], [float(r[3]) for r in rows[8:16]])
    dyn = jo.load_spectra(DATA / "Filmsense_kineticTest.txt")
    rows = _rows(DATA / "Filmsense_kineticTest.txt", 11)
    assert dyn.values.shape == (7, 3, 8) and len(rows) == 7
    for k, r in enumerate(rows):
        v = np.asarray([float(x) for x in r[1:41]]).reshape(8, 5)
        assert dyn.meta["times"][k] == float(r[0])
        np.testing.assert_array_equal(dyn.values[k], v[:, :3].T)


# ---------------------------------------------------------------------------------------------
# files written here in the documented layouts


def _woollam(path, rows, *, units="nm", dynamic=False, title="sample", newline="\n"):
    head = [title, "VASEmethod[EllipsometerType=4, CompleteEASE=6.37, AcqTime=15.000]"] + (["Dynamic"] if dynamic else [])
    Path(path).write_bytes(newline.join(head + [units] + ["\t".join(map(str, r)) for r in rows] + [""]).encode())


def test_woollam_completeease6_blocks_units_and_inf(tmp_path):
    """E rows in Angstroms at two angles, then uR (inf where not measured) and dPolE blocks
    matched to their point by wavelength and angle."""
    wl_A = [3000.0, 4000.0, 5000.0]
    rows = [["E", w, a, 20.0 + i + a / 100, 100.0 + 10 * i, 0.01, 0.02] for a in (60.0, 70.0) for i, w in enumerate(wl_A)]
    rows += [["uR", w, a, "inf", 1.0] for a in (60.0, 70.0) for w in wl_A]
    rows += [["dPolE", w, a, 0.5 + i + a, 0.1] for a in (70.0, 60.0) for i, w in enumerate(wl_A)]
    _woollam(tmp_path / "ce.dat", rows, units="Angstroms", newline="\r\n")
    sp = jo.load_spectra(tmp_path / "ce.dat")
    np.testing.assert_array_equal(sp.wavelength_nm, [300.0, 400.0, 500.0] * 2)
    np.testing.assert_array_equal(sp.angle_deg, [60.0] * 3 + [70.0] * 3)
    np.testing.assert_array_equal(sp.meta["depolarization_percent"], [60.5, 61.5, 62.5, 70.5, 71.5, 72.5])
    assert np.all(np.isnan(sp.meta["uR"]))
    _woollam(tmp_path / "neg.dat", [[500, 70, 20, -35.5, 0.01, 0.02], [600, 70, 21, -179.9, 0.01, 0.02]])  # negative Delta
    np.testing.assert_array_equal(jo.load_spectra(tmp_path / "neg.dat").values[1], [-35.5, -179.9])
    for unit, x, nm in (("eV", 2.0, 1239.8419843320026 / 2), ("1/cm", 20000.0, 500.0), ("nm", 633.0, 633.0)):
        _woollam(tmp_path / "u.dat", [[x, 70, 20, 100]], units=unit)
        assert jo.load_spectra(tmp_path / "u.dat").wavelength_nm[0] == pytest.approx(nm, rel=1e-12)


def test_woollam_trig_rows_are_n_and_c(tmp_path):
    """TRIG files hold tan Psi and cos Delta: read as N = cos 2Psi, C = sin 2Psi cos Delta."""
    psi, delta = np.array([10.0, 35.0, 60.0]), np.array([30.0, 150.0, 300.0])
    rows = [[500 + 10 * i, 70, math.tan(math.radians(p)), math.cos(math.radians(d))] for i, (p, d) in enumerate(zip(psi, delta))]
    _woollam(tmp_path / "t.dat", rows, units="nm\tTRIG")
    sp = jo.load_spectra(tmp_path / "t.dat")
    assert sp.kinds == ("N", "C")
    np.testing.assert_allclose(sp.values[0], np.cos(np.radians(2 * psi)), atol=1e-14)
    np.testing.assert_allclose(sp.values[1], np.sin(np.radians(2 * psi)) * np.cos(np.radians(delta)), atol=1e-14)


def test_spectraray_psi_delta_with_decimal_comma(tmp_path):
    wl = np.array([400.0, 500.0, 600.0])
    psi = {50.2: [40.0, 41.0, 42.0], 60.2: [30.0, 31.0, 32.0]}
    delta = {50.2: [352.0, 2.5, 180.0], 60.2: [100.0, 110.0, 120.0]}
    lines = ["; WAVELENGTH " + " ".join(f"{a:.5f} {a:.5f}" for a in psi)]
    for i, w in enumerate(wl):
        lines.append(" ".join([f"{w:.5f}"] + [f"{psi[a][i]:.5f} {delta[a][i]:.5f}" for a in psi]).replace(".", ",") + " ")
    (tmp_path / "s.txt").write_text("\n".join(lines) + "\n")
    sp = jo.load_spectra(tmp_path / "s.txt")
    assert sp.meta["format"] == "spectraray"
    np.testing.assert_array_equal(sp.angle_deg, [50.2] * 3 + [60.2] * 3)
    np.testing.assert_array_equal(sp.values, [psi[50.2] + psi[60.2], delta[50.2] + delta[60.2]])


def _spectraray_mueller(path, angle, wl, N, C, S, s3):
    M = np.zeros((len(wl), 4, 4))
    M[:, 0, 0] = M[:, 1, 1] = 1
    M[:, 0, 1] = M[:, 1, 0] = -N
    M[:, 2, 2] = M[:, 3, 3] = C
    M[:, 2, 3], M[:, 3, 2] = s3 * S, -s3 * S
    lines = ["; WAVELENGTH" + f" {angle:.5f}" * 16] + [" ".join(f"{x:.8f}" for x in [w, *M[i].ravel()]) for i, w in enumerate(wl)]
    Path(path).write_text("\n".join(lines) + "\n")


def test_accurion_imaging_layout_with_a_cp1252_micro_sign(tmp_path):
    """Each region of interest is a site of a map; the units row's micro sign is not UTF-8."""
    head = "#ROIidx\tAOI\tLambda\tBandwidth\tExposureTime\tROI_x\tROI_y\tDelta\tPsi\n#-\tdeg\tnm\tnm\tus\t\xb5m\t\xb5m\tdeg\tdeg\n"
    rows = [f"{roi}\t{a:.3f}\t{w:.1f}\t4.0\t1000\t{400 + 100 * roi}\t500\t{170 + roi + a / 10:.6f}\t{30 + roi:.6f}"
            for roi in (0, 1) for a in (40.0, 50.0) for w in (500.0, 600.0)]
    (tmp_path / "i.ds.dat").write_bytes((head + "\n".join(rows) + "\n").encode("cp1252"))
    sp = jo.load_spectra(tmp_path / "i.ds.dat")
    assert sp.values.shape == (2, 2, 4) and sp.sites == ("0", "1") and sp.meta["layout"] == "imaging"
    np.testing.assert_allclose(sp.site_xy, [[0.4, 0.5], [0.5, 0.5]])
    np.testing.assert_allclose(sp.values[1, 1], [175.0, 175.0, 176.0, 176.0])


def test_horiba_spe(tmp_path):
    text = ("# SAMPLE:\nSiO2 on Si\n\n# INCIDENCE ANGLE:\n70.00 deg\n\n# DATA:\nnm Is Ic Psi Delta\n"
            "400.0 0.1 0.2 20.5 110.0\n500.0 0.1 0.2 25.0 120.5\n\n")
    (tmp_path / "h.spe").write_text(text, encoding="cp1252")
    sp = jo.load_spectra(tmp_path / "h.spe")
    assert sp.meta["format"] == "horiba" and sp.meta["sample"] == "SiO2 on Si"
    np.testing.assert_array_equal(sp.angle_deg, [70.0, 70.0])
    np.testing.assert_array_equal(sp.values, [[20.5, 25.0], [110.0, 120.5]])


def test_photometric_text_scale_is_read_or_refused(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text("Wavelength (nm),%R\n400,4.5\n500,4.3\n")
    sp = jo.load_spectra(p, angle_deg=8)
    assert sp.kinds == ("R",) and sp.meta["scale"].startswith("percent")
    np.testing.assert_allclose(sp.values[0], [0.045, 0.043])
    p.write_text("wavelength_um\tT_s\tT_p\n0.4\t91.0\t93.5\n0.5\t92.0\t94.0\n")  # percent from the values, stated
    sp = jo.load_spectra(p, angle_deg=45)
    assert sp.kinds == ("T_s", "T_p") and "values up to 94" in sp.meta["scale"]
    np.testing.assert_allclose(sp.values, [[0.91, 0.92], [0.935, 0.94]])
    np.testing.assert_array_equal(sp.wavelength_nm, [400.0, 500.0])
    p.write_text("# AR coating\n400;0,8\n500;0,4\n")  # fractions or percent? not guessed
    with pytest.raises(ValueError, match="no header line: pass wavelength_unit"):
        jo.load_spectra(p, angle_deg=8)
    with pytest.raises(ValueError, match=r"line 2: cannot tell fractions from percent.*\[0.4, 0.8\]"):
        jo.load_spectra(p, angle_deg=8, wavelength_unit="nm", quantity="R")
    sp = jo.load_spectra(p, angle_deg=8, wavelength_unit="nm", quantity="R", scale="percent")
    np.testing.assert_allclose(sp.values[0], [0.008, 0.004])
    with pytest.raises(ValueError, match="does not give the angle of incidence; pass angle_deg"):
        jo.load_spectra(p, wavelength_unit="nm", quantity="R", scale="percent")


def test_jcamp_dx(tmp_path):
    pytest.importorskip("jcamp")
    p = tmp_path / "m.jdx"
    p.write_text("##TITLE=mirror\n##JCAMP-DX=4.24\n##DATA TYPE=UV/VIS SPECTRUM\n##XUNITS=NANOMETERS\n##YUNITS=%R\n"
                 "##XFACTOR=1\n##YFACTOR=0.01\n##FIRSTX=400\n##LASTX=700\n##NPOINTS=4\n##FIRSTY=45.0\n"
                 "##XYDATA=(X++(Y..Y))\n400 4500 4600\n600 4700 4800\n##END=\n")
    sp = jo.load_spectra(p, angle_deg=8)
    assert sp.meta["format"] == "jcamp" and sp.kinds == ("R",)
    np.testing.assert_allclose(sp.wavelength_nm, [400, 500, 600, 700])
    np.testing.assert_allclose(sp.values[0], [0.45, 0.46, 0.47, 0.48])
    p.write_text(p.read_text().replace("%R", "ABSORBANCE"))
    with pytest.raises(ValueError, match=r"line 5: ##YUNITS=ABSORBANCE"):
        jo.load_spectra(p, angle_deg=8)


@pytest.mark.parametrize("name, text, match", [
    ("w.dat", "t\nVASEmethod[x]\nnm\n500\t70\t20\t100\nfoo\t1\t2\t3\n", r"w.dat, line 5: unknown row 'foo'"),
    ("w.dat", "t\nVASEmethod[x]\nnm\n500\t70\t20\t100\t0.1\t0.2\n510\t70\t21\t101\n",
     r"line 5: 4 numbers, line 4 has 6: give sigma on every row or on none"),
    ("w.dat", "t\nVASEmethod[x]\nfeet\n500\t70\t20\t100\n", r"line 3: expected the units line"),
    ("w.dat", "t\nVASEmethod[x]\nnm\n500\t70\t20\t1O0\n", r"line 4: column 4: '1O0' is not a number"),
    ("w.dat", "t\nVASEmethod[x]\nnm\n500\t70\t120\t100\n", r"line 4: psi_deg = 120: Psi lies in \[0, 90\]"),
    ("w.dat", "t\nVASEmethod[x]\nnm\n500\t70\t20\t100\ndPolE\t600\t70\t1\t1\n", r"line 5: this dpole row .* matches no data row"),
    ("s.txt", "; WAVELENGTH 70 70\n500 20 100\n600 20\n", r"s.txt, line 3: 2 columns, the header names 3"),
    ("s.txt", "; WAVELENGTH 60 70\n500 20 100\n", r"line 1: a SpectraRay header names each angle twice"),
])
def test_malformed_files_name_the_line(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=match):
        jo.load_spectra(tmp_path / name)


def test_format_option_and_bad_conventions(tmp_path):
    p = tmp_path / "w.dat"
    _woollam(p, [[500, 70, 20, 100]])
    assert jo.load_spectra(p, format="woollam").meta["format"] == "woollam"
    with pytest.raises(ValueError, match=r"not a spectraray file \(detected: woollam\)"):
        jo.load_spectra(p, format="spectraray")
    with pytest.raises(ValueError, match="format='vase'"):
        jo.load_spectra(p, format="vase")
    with pytest.raises(ValueError, match=r"delta_convention='180\+delta': must be one of"):
        jo.load_spectra(p, delta_convention="180+delta")
    with pytest.raises(ValueError, match="mueller_s3_sign=0"):
        jo.load_spectra(p, mueller_s3_sign=0)
    with pytest.raises(ValueError, match="angle_deg: only for photometric files"):
        jo.load_spectra(p, angle_deg=70)
    with pytest.raises(ValueError, match=r"line 4: Delta = 200 lies outside delta_range='-180..180'"):
        _woollam(p, [[500, 70, 20, 200]])
        jo.load_spectra(p, delta_range="-180..180")


# ---------------------------------------------------------------------------------------------
# conventions: written in each, read back, fitted


D_TRUE = 180.0
WL = np.linspace(400.0, 900.0, 26)
ANG = (60.0, 70.0)


def _truth():
    """Psi and Delta (instrument convention: 180 - tmm's Delta) of a 180 nm SiO2-like film on a
    substrate of fixed index, from tmm, point by point."""
    wl, ang = np.tile(WL, len(ANG)), np.repeat(ANG, len(WL))
    psi, delta = [], []
    for w, a in zip(wl, ang):
        e = tmm.ellips([1.0, 1.46, 3.9 + 0.02j], [np.inf, D_TRUE, np.inf], math.radians(a), w)
        psi.append(math.degrees(e["psi"]))
        delta.append(180.0 - math.degrees(e["Delta"]))
    return wl, ang, np.asarray(psi), np.asarray(delta)


def _model():
    return jo.Sample([jo.Layer(1.46, jo.Free(150.0, 0.0, 400.0))], 3.9 + 0.02j)


def _wrap(d):
    return (np.asarray(d) + 180.0) % 360.0 - 180.0


@pytest.mark.slow
def test_delta_conventions_round_trip_through_a_fit(tmp_path):
    """A file written in each Delta convention (tmm's own `ellips` Delta is "180-delta") and read
    with that option gives the instrument's Delta; all of them, as one map, fit back to the film.
    The same file read with the wrong convention does not."""
    wl, ang, psi, delta = _truth()
    got = []
    for conv in DELTA_CONVENTIONS + ("wrong",):
        written = "-delta" if conv == "wrong" else conv
        d_file = delta_from_instrument(delta, written) % 360.0
        _woollam(tmp_path / f"{conv}.dat", [[w, a, p, d] for w, a, p, d in zip(wl, ang, psi, d_file)])
        sp = jo.load_spectra(tmp_path / f"{conv}.dat", delta_convention="delta" if conv == "wrong" else conv)
        np.testing.assert_array_equal(sp.values[0], psi)
        if conv != "wrong":
            np.testing.assert_allclose(_wrap(sp.values[1] - delta), 0.0, atol=1e-9)
        got.append(sp.values)
    maps = jo.make_spectra(wl, ang, {"psi_deg": np.stack([g[0] for g in got]), "delta_deg": np.stack([g[1] for g in got])},
                           sigma={"psi_deg": np.full((5, wl.size), 0.01), "delta_deg": np.full((5, wl.size), 0.02)})
    fit = jo.fit_stack(_model(), maps)
    d = np.asarray(fit[fit.names[0]])
    np.testing.assert_allclose(d[:4], D_TRUE, atol=1e-6)
    assert np.all(np.asarray(fit.chi2_reduced)[:4] < 1e-8)
    assert np.asarray(fit.chi2_reduced)[4] > 100


@pytest.mark.slow
def test_folded_delta_is_read_as_n_and_c_and_fits(tmp_path):
    """A rotating analyzer without compensator folds Delta into [0, 180]: read with
    delta_range="0..180" the file gives N and C, which fit back to the film; read as a full Delta
    it does not fit."""
    wl, ang, psi, delta = _truth()
    d360 = delta % 360.0
    assert np.any(d360 > 180) and np.any(d360 < 180)  # both halves occur, so the fold matters
    folded = np.where(d360 > 180, 360.0 - d360, d360)
    _woollam(tmp_path / "rae.dat", [[w, a, p, d, 0.01, 0.02] for w, a, p, d in zip(wl, ang, psi, folded)])
    sp = jo.load_spectra(tmp_path / "rae.dat", delta_range="0..180")
    assert sp.kinds == ("N", "C")
    np.testing.assert_allclose(sp.values[0], np.cos(np.radians(2 * psi)), atol=1e-12)
    np.testing.assert_allclose(sp.values[1], np.sin(np.radians(2 * psi)) * np.cos(np.radians(delta)), atol=1e-12)
    fit = jo.fit_stack(_model(), sp)
    assert float(fit[fit.names[0]]) == pytest.approx(D_TRUE, abs=1e-6)
    as_full = jo.load_spectra(tmp_path / "rae.dat")
    assert np.max(np.abs(_wrap(as_full.values[1] - delta))) > 10  # the fold is not undone by reading it as full


@pytest.mark.slow
def test_mueller_s3_sign_round_trip_through_a_fit(tmp_path):
    """Normalized Mueller matrices written with M34 = +S (Sentech, Woollam) and with M34 = -S
    (pyElli 0.23), each read with its sign, give the same N, C, S and fit back to the film; read
    with the other sign, S flips and the fit fails."""
    wl, ang, psi, delta = _truth()
    sel = ang == 70.0
    p2, d = np.radians(2 * psi[sel]), np.radians(delta[sel])
    N, C, S = np.cos(p2), np.sin(p2) * np.cos(d), np.sin(p2) * np.sin(d)
    got = []
    for s3, read in ((1, 1), (-1, -1), (1, -1)):
        _spectraray_mueller(tmp_path / "mm.txt", 70.0, wl[sel], N, C, S, s3)
        sp = jo.load_spectra(tmp_path / "mm.txt", mueller_s3_sign=read)
        assert sp.kinds == ("N", "C", "S") and sp.meta["mueller"].shape == (4, 4, sel.sum())
        got.append(sp.values)
    np.testing.assert_allclose(got[0], [N, C, S], atol=1e-8)
    np.testing.assert_allclose(got[1], [N, C, S], atol=1e-8)
    np.testing.assert_allclose(got[2], [N, C, -S], atol=1e-8)
    maps = jo.make_spectra(wl[sel], 70.0, dict(zip(("N", "C", "S"), np.moveaxis(np.stack(got), 1, 0))),
                           sigma=dict.fromkeys(("N", "C", "S"), np.full((3, sel.sum()), 1e-3)))
    fit = jo.fit_stack(_model(), maps)
    d_fit = np.asarray(fit[fit.names[0]])
    np.testing.assert_allclose(d_fit[:2], D_TRUE, atol=1e-5)
    assert np.asarray(fit.chi2_reduced)[2] > 100


def test_psi_delta_of_jaxoptics_and_tmm_are_the_180_minus_delta_convention():
    """`jo.ellipsometry` and tmm's `ellips` return delta = arg(-r_p/r_s): written to a file, their
    Delta is read with delta_convention="180-delta" (checked against tmm here)."""
    wl, ang, psi, delta = _truth()
    e = jo.ellipsometry(jnp.asarray([1.0, 1.46, 3.9 + 0.02j]), jnp.asarray([D_TRUE]), jnp.asarray(wl[:5]),
                        jnp.cos(jnp.deg2rad(jnp.asarray(ang[:5]))))
    ours = np.degrees(np.asarray(e[1]))
    np.testing.assert_allclose(_wrap(delta_from_instrument(delta[:5], "180-delta") - ours), 0, atol=1e-9)


@pytest.mark.slow
def test_cli_fit_stack_reads_an_instrument_file_with_its_conventions(tmp_path, capsys):
    """`fit-stack` on a Woollam export (detected) whose Delta is tmm's, with --delta-convention."""
    from jaxoptics.__main__ import main

    wl, ang, psi, delta = _truth()
    d_file = delta_from_instrument(delta, "180-delta")
    _woollam(tmp_path / "m.dat", [[w, a, p, d, 0.01, 0.02] for w, a, p, d in zip(wl, ang, psi, d_file)])
    (tmp_path / "m.toml").write_text('ambient = 1.0\n[[layer]]\nname = "film"\nthickness_nm = { value = 150, min = 0, max = 400 }\n'
                                     'material = { n = 1.46 }\n[substrate]\nmaterial = { n = 3.9, k = 0.02 }\n')
    assert main(["fit-stack", str(tmp_path / "m.dat"), "--model", str(tmp_path / "m.toml"), "--delta-convention", "180-delta",
                 "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "(woollam)" in out
    row = next(l for l in out.splitlines() if l.startswith("film.thickness_nm"))
    assert float(row.split()[1]) == pytest.approx(D_TRUE, abs=1e-5)
    assert main(["fit-stack", str(tmp_path / "m.dat"), "--model", str(tmp_path / "m.toml"), "--delta-convention", "180+delta",
                 "--no-cache"]) == 2
    assert "delta_convention='180+delta': must be one of" in capsys.readouterr().err


def _nexus(path, layout, psi, delta, wl_values, wl_units, aoi, sigma=None, data_type=None):
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "w") as f:
        e = f.create_group("entry")
        if layout == "NXellipsometry":
            dc = e.create_group("data_collection")
            dc["data_type"] = data_type or "Psi/Delta"
            dc["measured_data"] = np.stack([psi, delta], axis=1)  # (angles, observables, spectrum)
            if sigma is not None:
                dc["data_error"] = np.broadcast_to(np.asarray(sigma)[None, :, None], (len(aoi), 2, len(wl_values))).copy()
            dc["wavelength_spectrum"] = wl_values
            if wl_units:
                dc["wavelength_spectrum"].attrs["units"] = wl_units
        else:
            s = e.create_group("sample")
            s["data_type"] = data_type or "psi/delta"
            s["measured_data"] = np.stack([psi, delta], axis=1)[None, None]
            e.create_group("instrument/spectrometer")
            e["instrument/spectrometer/wavelength"] = wl_values
            if wl_units:
                e["instrument/spectrometer/wavelength"].attrs["units"] = wl_units
        e["instrument/angle_of_incidence"] = np.asarray(aoi, float)
        e["instrument/angle_of_incidence"].attrs["units"] = "degree"


@pytest.mark.parametrize("layout, wl_values, units, assumed", [
    ("NXellipsometry", [4000.0, 5000.0, 6000.0], "angstrom", False),
    ("NXellipsometry", [400.0, 500.0, 600.0], "nm", False),       # the unit is read, not assumed to be Angstrom
    ("legacy", [4000.0, 5000.0, 6000.0], None, True),              # the definition's default, stated
])
def test_nexus_nxellipsometry_both_layouts_units_honoured(tmp_path, layout, wl_values, units, assumed):
    psi = np.array([[20.0, 21.0, 22.0], [30.0, 31.0, 32.0]])
    delta = np.array([[100.0, 110.0, 120.0], [200.0, 210.0, 220.0]])
    p = tmp_path / "m.nxs"
    _nexus(p, layout, psi, delta, np.asarray(wl_values), units, [60.0, 70.0],
           sigma=(0.01, 0.02) if layout == "NXellipsometry" else None)
    sp = jo.load_spectra(p)
    assert sp.meta["format"] == "nexus" and sp.meta["layout"] == layout
    np.testing.assert_allclose(sp.wavelength_nm, [400.0, 500.0, 600.0] * 2)
    np.testing.assert_array_equal(sp.angle_deg, [60.0] * 3 + [70.0] * 3)
    np.testing.assert_array_equal(sp.values, [psi.ravel(), delta.ravel()])
    assert bool(sp.meta["assumed_units"]) == assumed
    if layout == "NXellipsometry":
        np.testing.assert_array_equal(sp.sigma[0], 0.01)
    _nexus(p, layout, psi, delta, np.asarray(wl_values), "furlong", [60.0, 70.0])
    with pytest.raises(ValueError, match=r"m.nxs, entry/.*wavelength.*: units 'furlong'"):
        jo.load_spectra(p)


def test_nk_tables_and_the_sign_of_k(tmp_path):
    """n, k tables: as written when k >= 0; a table of the n - ik convention with negative k is
    refused unless k_sign='-'; e1, e2 in eV from a SpectraRay .mat converted by the principal root."""
    lam = np.array([400.0, 500.0, 600.0])
    n, k = np.array([4.0, 3.9, 3.8]), np.array([0.5, 0.2, 0.1])
    p = tmp_path / "si_nk.csv"
    p.write_text("wavelength_nm,n,k\n" + "\n".join(f"{a},{b},{c}" for a, b, c in zip(lam, n, k)) + "\n")
    m = jo.load_nk(p)
    np.testing.assert_allclose(np.asarray(m.nk(lam / 1000)), n + 1j * k)
    p.write_text("wavelength_nm,n,k\n" + "\n".join(f"{a},{b},{-c}" for a, b, c in zip(lam, n, k)) + "\n")
    with pytest.raises(ValueError, match=r"si_nk.csv, line 2: k = -0.5: every nonzero k is negative.*k_sign='-'"):
        jo.load_nk(p)
    np.testing.assert_allclose(np.asarray(jo.load_nk(p, k_sign="-").nk(lam / 1000)), n + 1j * k)
    p.write_text("wavelength_nm,n,k\n400,4.0,0.5\n500,3.9,-0.2\n")
    with pytest.raises(ValueError, match="line 3: k = -0.2 while others are positive"):
        jo.load_nk(p)
    E = 1239.8419843320026 / lam
    eps = (n + 1j * k) ** 2
    mat = tmp_path / "Si.mat"
    mat.write_text("###### File Layer=3\nUnits=eV,E1E2\nBegin of array\n"
                   + "\n".join(f"{float(e)!r} {float(z.real)!r} {float(z.imag)!r}" for e, z in zip(E, eps)) + "\nEnd of array\n")
    np.testing.assert_allclose(np.asarray(jo.load_nk(mat).nk(lam / 1000)), n + 1j * k, rtol=1e-9)


@pytest.mark.slow
def test_nk_table_of_the_other_sign_round_trip_through_a_fit(tmp_path):
    """The substrate's n, k written as a tool of the n - ik convention writes absorption (k < 0),
    read with k_sign='-' in the sample's TOML, fits the film back from tmm's Psi/Delta."""
    wl, ang, psi, delta = _truth()
    w = np.linspace(350.0, 950.0, 13)
    (tmp_path / "sub.csv").write_text("wavelength_nm,n,k\n" + "\n".join(f"{x},3.9,-0.02" for x in w) + "\n")
    (tmp_path / "m.toml").write_text('[[layer]]\nthickness_nm = { value = 150, min = 0, max = 400 }\nmaterial = { n = 1.46 }\n'
                                     '[substrate]\nmaterial = { file = "sub.csv", k_sign = "-" }\n')
    sample = jo.load_sample(tmp_path / "m.toml")
    sp = jo.make_spectra(wl, ang, {"psi_deg": psi, "delta_deg": delta})
    fit = jo.fit_stack(sample, sp)
    assert float(fit[fit.names[0]]) == pytest.approx(D_TRUE, abs=1e-6)
    (tmp_path / "m.toml").write_text((tmp_path / "m.toml").read_text().replace(', k_sign = "-"', ""))
    with pytest.raises(ValueError, match="k_sign='-'"):
        jo.load_sample(tmp_path / "m.toml")


def test_the_values_refellips_own_tests_publish():
    """refellips' test suite (BSD-3) states values its readers give for these files; ours agree:
    the EP4 zone average at 70 degrees, Film Sense's Psi/Delta (here from the N, C, S read, in the
    instrument convention), and the Woollam Dynamic times (written in minutes; refellips gives
    seconds)."""
    assert jo.load_spectra(DATA / "15-1-1.dat").values[0, -1] == pytest.approx(12.72666667, abs=1e-8)

    def psi_delta(sp, k=None):
        N, C, S = sp.values if k is None else sp.values[k]
        return np.degrees(np.arccos(N)) / 2, np.degrees(np.arctan2(S, C)) % 360

    static = np.array([[26.46, 158.74], [15.77, 173.19], [12.64, 174.05], [11.13, 174.54], [10.25, 174.92],
                       [9.51, 175.37], [8.76, 175.98], [8.35, 176.36]]).T
    np.testing.assert_allclose(psi_delta(jo.load_spectra(DATA / "Filmsense_staticTest.txt")), static, rtol=1e-3)
    dyn = jo.load_spectra(DATA / "Filmsense_kineticTest.txt")
    np.testing.assert_allclose(dyn.meta["times"], [4.95, 14.86, 24.77, 34.66, 44.57, 54.48, 64.38], rtol=1e-3)
    third = np.array([[27.04, 148.91], [16.09, 162.67], [12.91, 163.83], [11.36, 164.72], [10.45, 165.54],
                      [9.68, 166.52], [8.89, 167.94], [8.45, 168.86]]).T
    np.testing.assert_allclose(psi_delta(dyn, 2), third, rtol=1e-3)
    times = jo.load_spectra(DATA / "Woolam_kineticTest.dat").meta["times"]
    np.testing.assert_allclose(60 * times[::2][:4], [1.4, 6.4, 11.5, 16.5], rtol=1e-2)
