"""Coating design (`jo.design`, `jo.Target`, needle synthesis, thickness errors) against
independent oracles: the quarter-wave mirror's closed form, tmm's reflectance of textbook
anti-reflection coatings, finite differences of the merit (needle function) and of the phase
(group delay and its dispersion)."""

import math
import subprocess
import sys

import jax
import numpy as np
import pytest
import tmm

import jaxoptics as jo

NS = 1.52  # glass


def _tmm_R(ns_layers, d, wl, angle_deg=0.0, pol="avg"):
    n_list = [1.0] + list(ns_layers) + [NS]
    d_list = [np.inf] + list(d) + [np.inf]
    th = math.radians(angle_deg)
    R = lambda p: tmm.coh_tmm(p, n_list, d_list, th, wl)["R"]
    return {"s": R("s"), "p": R("p"), "avg": (R("s") + R("p")) / 2}[pol]


def test_quarter_wave_mirror_refines_to_the_quarter_wave_stack_and_its_analytic_peak():
    """Maximum R at 600 nm from random starts: the refined stack is the quarter-wave stack and its R
    the closed form `((1 - Y) / (1 + Y))^2`, `Y = (nH/nL)^(2m) nH^2 / ns` (Macleod, ch. 7)."""
    nH, nL, wl0 = 2.3, 1.46, 600.0
    layers = tuple(jo.Layer(nH if j % 2 == 0 else nL, jo.Free(100.0, 40.0, 140.0)) for j in range(5))
    target = jo.Target("R", wl0, 1.0, tolerance=1e-3)
    d = jo.design(jo.Sample(layers, NS), [target], starts=8, seed=2)
    quarter = [wl0 / (4 * (nH if j % 2 == 0 else nL)) for j in range(5)]
    np.testing.assert_allclose(d.values, quarter, rtol=1e-5)
    Y = (nH / nL) ** 4 * nH**2 / NS
    R_peak = ((1 - Y) / (1 + Y)) ** 2
    assert abs((1 - 1e-3 * d.merit) - R_peak) < 1e-10
    assert d.merits.shape == (8,) and d.merit == pytest.approx(np.min(d.merits))
    assert d.layers == 5 and d.names[0] == "layer1.thickness_nm" and d["layer2.thickness_nm"] == pytest.approx(quarter[1], rel=1e-5)


def test_quarter_wave_mirror_stop_band_has_its_closed_form_edges_and_decay():
    """The stop band of a quarter-wave stack (H L)^N at normal incidence, in g = lambda0 / lambda,
    from the period's characteristic matrix (Macleod, ch. 7): the Bloch phase obeys
    `cos(K Lambda) = a(g) = cos^2(pi g / 2) - (rho + 1/rho) sin^2(pi g / 2) / 2`, `rho = nH / nL`, so
    the band is `|a| > 1`, `|g - 1| < (2/pi) asin((nH - nL) / (nH + nL))`, and inside it each
    period multiplies T by `exp(-2 arccosh|a|)`. The stack's T of 30 and 60 periods decays at that
    rate inside the band (to 1e-8: the finite-N correction is `exp(-2 N arccosh|a|)`), and outside
    the band no number of periods from 10 to 40 takes T below 0.1."""
    nH, nL, wl0 = 2.3, 1.46, 600.0
    half_width = 2 / math.pi * math.asin((nH - nL) / (nH + nL))
    rho = nH / nL
    a = lambda g: np.cos(np.pi / 2 * g) ** 2 - (rho + 1 / rho) / 2 * np.sin(np.pi / 2 * g) ** 2
    np.testing.assert_allclose(np.abs(a(1 + half_width * np.array([-1.0, 1.0]))), 1.0, rtol=1e-14)  # the edges

    def T(periods, g):  # every stack 60 periods long, those beyond `periods` of zero thickness (no-ops): one program
        n = jax.numpy.asarray([1.0] + [nH, nL] * 60 + [NS], np.complex128)
        d = jax.numpy.asarray([wl0 / (4 * nH), wl0 / (4 * nL)] * periods + [0.0, 0.0] * (60 - periods))
        wl = jax.numpy.asarray(wl0 / g)
        return np.asarray(jo.stack(n, d, wl, jax.numpy.ones_like(wl)).T_s)

    inside = 1 + half_width * np.array([-0.8, -0.5, 0.0, 0.3, 0.8])
    rate = np.log(T(30, inside) / T(60, inside)) / (2 * 30)
    np.testing.assert_allclose(rate, np.arccosh(np.abs(a(inside))), rtol=1e-8)
    outside = 1 + half_width * np.array([-1.5, -1.2, 1.1, 1.3, 1.5])
    assert np.min([T(N, outside) for N in range(10, 41, 3)]) > 0.1


def test_two_layer_v_coat_refines_to_its_closed_form():
    """Zero reflectance at one wavelength with two layers (a V-coat) has two exact solutions: from
    the characteristic matrices, Y = C / B = n0 gives tan^2 d1 = (ns - n0) n1^2 (n0 ns - n2^2) /
    ((n1^2 ns - n0 n2^2) (n1^2 - n0 ns)) and tan d2 = tan d1 n2 (n1^2 - n0 ns) / (n1 (n0 ns - n2^2))
    for the phase thicknesses d1 (outer layer) and d2. Starts near each solution refine to it. (R
    is quadratic in the thicknesses' deviation at a zero, so R to 1e-12 places them to about 1e-6.)"""
    n0, n1, n2, wl0 = 1.0, 1.38, 2.1, 550.0
    t1 = math.sqrt((NS - n0) * n1**2 * (n0 * NS - n2**2) / ((n1**2 * NS - n0 * n2**2) * (n1**2 - n0 * NS)))
    solutions = []
    for sign in (1, -1):
        d1 = math.atan(sign * t1) % math.pi
        d2 = math.atan(sign * t1 * n2 * (n1**2 - n0 * NS) / (n1 * (n0 * NS - n2**2))) % math.pi
        solutions.append([d1 * wl0 / (2 * math.pi * n1), d2 * wl0 / (2 * math.pi * n2)])
    target = jo.Target("R", wl0, 0.0, tolerance=1e-3)
    for exact in solutions:
        assert _tmm_R((n1, n2), exact, wl0) < 1e-28  # the closed form, checked by tmm
        start = jo.Sample((jo.Layer(n1, jo.Free(0.9 * exact[0], 1.0, 300.0)), jo.Layer(n2, jo.Free(1.1 * exact[1], 1.0, 300.0))), NS)
        d = jo.design(start, [target], starts=1)
        np.testing.assert_allclose(d.values, exact, rtol=1e-5)
        assert _tmm_R((n1, n2), d.values, wl0) < 1e-12
        assert d.merit == pytest.approx(_tmm_R((n1, n2), d.values, wl0) / 1e-3, rel=1e-6, abs=1e-15)


@pytest.mark.parametrize("textbook", ["quarter-quarter", "quarter-half-quarter"])
def test_anti_reflection_designs_agree_with_tmm_and_improve_on_the_textbook(textbook):
    """Mean reflectance over 400-700 nm on glass: the merit of the textbook design equals tmm's,
    refinement lowers it, and tmm's reflectance of the refined design gives the refined merit."""
    wl0 = 550.0
    ns = {"quarter-quarter": (1.38, 1.70), "quarter-half-quarter": (1.38, 2.10, 1.62)}[textbook]
    quarters = {"quarter-quarter": (1, 1), "quarter-half-quarter": (1, 2, 1)}[textbook]
    d0 = [q * wl0 / (4 * n) for q, n in zip(quarters, ns)]
    wl = np.linspace(400.0, 700.0, 16)
    targets = [jo.Target("R", wl, 0.0, tolerance=0.005)]
    rms = lambda d: math.sqrt(np.mean([(_tmm_R(ns, d, w) / 0.005) ** 2 for w in wl]))
    start = jo.Sample(tuple(jo.Layer(n, jo.Free(t, 1.0, 400.0)) for n, t in zip(ns, d0)), NS)
    assert jo.merit(start, targets) == pytest.approx(rms(d0), rel=1e-10)
    d = jo.design(start, targets)
    assert d.merit < 0.9 * rms(d0)
    assert d.merit == pytest.approx(rms(d.values), rel=1e-10)


def test_needle_function_equals_finite_differences_of_the_merit():
    """The derivative of MF^2 per nm of a needle inserted at a depth (inside a layer, at an
    interface, at the substrate) equals the one-sided second-order difference quotient of the
    merit of the design with a thin layer inserted there."""
    from jaxoptics._design import _layers, _needle, _refine, _targets

    sample = jo.Sample((jo.Layer(1.46, 120.0), jo.Layer(2.1, 60.0)), NS)
    targets = [jo.Target("R", np.linspace(450.0, 650.0, 9), 0.0, tolerance=0.01),
               jo.Target("T", 520.0, 0.99, angle_deg=30.0, polarization="p", kind=">=", tolerance=0.01)]
    lay, arrays = _targets.layout(targets)
    mats = [_layers.as_material(1.46, ""), _layers.as_material(2.1, ""), _layers.as_material(1.8, "")]
    s = _layers.from_sample(sample, mats, 2, 0.0, None)
    problem = _refine.make_problem(s, lay, arrays, np.float64)
    z, P, ok, mf2 = _needle.needle_function(problem, s, [0, 1, 2], 9.0)
    assert mf2 == pytest.approx(jo.merit(sample, targets) ** 2, rel=1e-12)
    h = 1e-3
    for near in (40.0, 120.0, 180.0):
        k = int(np.argmin(np.abs(z - near)))
        depth = float(z[k])
        for c, n in enumerate((1.46, 2.1, 1.8)):
            if not ok[k, c]:
                continue

            def f(t):
                edges = [0.0, 120.0, 180.0]
                layers, ns = [], [1.46, 2.1]
                for j in range(2):
                    a, b = edges[j], edges[j + 1]
                    if a < depth < b:
                        layers += [jo.Layer(ns[j], depth - a), jo.Layer(n, t), jo.Layer(ns[j], b - depth)]
                    else:
                        layers += [jo.Layer(n, t)] if depth == a and j == 1 else []
                        layers.append(jo.Layer(ns[j], b - a))
                layers += [jo.Layer(n, t)] if depth == 180.0 else []
                return jo.merit(jo.Sample(tuple(layers), NS), targets) ** 2

            fd = (-3 * f(0.0) + 4 * f(h) - f(2 * h)) / (2 * h)
            assert P[k, c] == pytest.approx(fd, rel=1e-5, abs=1e-6 * abs(mf2)), (depth, n)
    # inside the 1.46 layer a 1.46 needle changes nothing: not a candidate
    assert not ok[int(np.argmin(np.abs(z - 40.0))), 0]


def test_group_delay_and_its_dispersion_equal_finite_differences_of_the_phase():
    """GD = d(arg r)/d(omega) and GDD = dGD/d(omega), material dispersion included, against
    central differences of the computed phase (s and p at 45 degrees, reflection and transmission)."""
    si3n4 = jo.material("Si3N4")
    sample = jo.Sample(tuple(jo.Layer(si3n4 if j % 2 else 1.46, 70.0 + 9.0 * j) for j in range(6)), NS)
    wl = np.array([520.0, 610.0, 700.0])
    c = 299.792458
    omega = 2 * np.pi * c / wl
    dw = 1e-4
    cases = [(side, pol) for side in "rt" for pol in "sp"]
    targets = [jo.Target(f"{q}_{side}", wl, 0.0, angle_deg=45.0, polarization=pol) for side, pol in cases for q in ("GD", "GDD")]
    targets += [jo.Target(f"phase_{side}", 2 * np.pi * c / w, 0.0, angle_deg=45.0, polarization=pol)
                for side, pol in cases for w in (omega - dw, omega, omega + dw)]
    values = jo.target_values(sample, targets)
    got = dict(zip([(q, side, pol) for side, pol in cases for q in ("GD", "GDD")], values))
    phases = iter(values[len(got):])
    for side, pol in cases:
        pm, p0, pp = np.unwrap(np.radians(np.stack([next(phases) for _ in range(3)])), axis=0)
        np.testing.assert_allclose(got["GD", side, pol], (pp - pm) / (2 * dw), rtol=1e-6)
        np.testing.assert_allclose(got["GDD", side, pol], (pp - 2 * p0 + pm) / dw**2, rtol=2e-4, atol=1e-3)
    # a delay is positive: reflection from 6 layers of a few hundred nm is delayed by about a femtosecond
    assert np.all(got["GD", "t", "s"] > 0)


@pytest.mark.slow
def test_needle_synthesis_lowers_the_merit_within_the_constraints(monkeypatch):
    """From one thick low-index layer on glass, needle rounds with two candidates lower the
    broadband anti-reflection merit several times over; the result keeps the minimum thickness,
    the layer budget, and has no two neighbours of one material; the same with two needles per
    round, where a round inserts two."""
    from jaxoptics._design import _layers

    start = jo.Sample((jo.Layer(1.46, jo.Free(500.0, 0.0)),), NS)
    targets = [jo.Target("R", np.linspace(450.0, 650.0, 11), 0.0, tolerance=0.01)]
    for needles in (1, 2):
        d = jo.design(start, targets, needle=True, materials=[1.46, 2.1], max_layers=10, min_thickness_nm=5.0,
                      needles=needles)
        assert d.history[0] == pytest.approx(jo.merit(start, targets), rel=1e-6) or d.history[0] < jo.merit(start, targets)
        assert np.all(np.diff(d.history[:-1]) < 0)
        assert d.merit < d.history[0] / 3
        assert 3 <= d.layers <= 10 and np.all(d.values >= 5.0 - 1e-9)
        ns = [float(m.n) for m in d.materials]
        assert all(a != b for a, b in zip(ns, ns[1:]))
        assert d.merit == pytest.approx(jo.merit(d.sample, targets), rel=1e-9)
    # needles inserted in two rounds: one per round, or more than one in a round with needles=2
    inserted = []
    insert = _layers.insert
    monkeypatch.setattr(_layers, "insert", lambda *a, **k: inserted.append(a[1]) or insert(*a, **k))
    for needles, count in ((1, 2), (2, 3)):
        inserted.clear()
        jo.design(start, targets, needle=True, materials=[1.46, 2.1], max_layers=10, max_rounds=2, needles=needles)
        assert len(inserted) >= count and (needles > 1 or len(inserted) == 2), (needles, inserted)


def test_needle_sites_are_the_most_negative_local_minima_over_depth():
    """Several needles per round go where the best candidate's needle function has its most
    negative local minima over depth, each with the candidate that is best there; a depth where no
    candidate is allowed or the slope is not below the threshold is never chosen; the first site
    is the global minimum (the single-needle choice)."""
    from jaxoptics._design._design import needle_sites

    P = np.array([[0.0, -1.0], [-2.0, -3.0], [-1.0, -0.5], [-4.0, 9.0], [-5.0, -6.0], [-0.5, -7.0], [0.0, 0.0],
                  [-0.1, -0.2], [1.0, 1.0]])
    ok = np.ones(P.shape, bool)
    ok[5, 1] = False  # -7 not allowed there (the layer around it is of that material)
    # best per depth: -1, -3, -1, -4, -6, -0.5, 0, -0.2, 1: minima at depths 1 (-3), 4 (-6), 7 (-0.2)
    assert needle_sites(P, ok, 5, -0.1) == [(4, 1), (1, 1), (7, 1)]
    assert needle_sites(P, ok, 2, -0.1) == [(4, 1), (1, 1)]
    assert needle_sites(P, ok, 5, -1.0) == [(4, 1), (1, 1)]  # -0.2 is not below the threshold
    k, c = np.unravel_index(np.argmin(np.where(ok, P, np.inf)), P.shape)
    assert needle_sites(P, ok, 1, 0.0) == [(int(k), int(c))]
    assert needle_sites(P, ok, 3, -10.0) == []


@pytest.mark.slow
def test_thickness_errors_yield_and_robust_design():
    """Each drawn design's merit is the merit of that perturbed sample computed on its own; the
    yield counts them; a robust refinement from the nominal optimum lowers the mean merit squared
    over the same draws."""
    wl = np.linspace(420.0, 680.0, 9)
    targets = [jo.Target("R", wl, 0.0, tolerance=0.005)]
    start = jo.Sample((jo.Layer(1.38, jo.Free(100.0, 1.0, 300.0)), jo.Layer(2.1, jo.Free(130.0, 1.0, 300.0)),
                       jo.Layer(1.62, jo.Free(85.0, 1.0, 300.0))), NS)
    nominal = jo.design(start, targets)
    errors = jo.ThicknessErrors("relative", 0.02, draws=24, seed=3)
    ea = jo.thickness_errors(nominal, targets, errors=errors, threshold=2.0)
    rel, _ = errors.sample(3)
    for i in (0, 7):
        pert = jo.Sample(tuple(jo.Layer(m, float(t) * (1 + e)) for m, t, e in zip((1.38, 2.1, 1.62), nominal.values, rel[i])), NS)
        assert ea.merits[i] == pytest.approx(jo.merit(pert, targets), rel=1e-10)
    assert ea.yield_fraction == np.mean(ea.merits <= 2.0) and ea.merit == pytest.approx(nominal.merit, rel=1e-10)
    assert ea.sensitivity.shape == (3,) and np.all(ea.sensitivity > 0)
    again = jo.Sample(tuple(jo.Layer(m, jo.Free(float(t), 1.0, 300.0)) for m, t in zip((1.38, 2.1, 1.62), nominal.values)), NS)
    robust = jo.design(again, targets, robust=errors)
    ea_r = jo.thickness_errors(robust, targets, errors=errors, threshold=2.0)
    assert ea_r.expected_merit < ea.expected_merit
    assert robust.merit >= nominal.merit * (1 - 1e-9)


@pytest.mark.parametrize("make, message", [
    (lambda: jo.Target("X", 500.0, 0.0), "quantity 'X'"),
    (lambda: jo.Target("phase_r", 500.0, 0.0), "needs polarization 's' or 'p'"),
    (lambda: jo.Target("R", [500.0, -1.0], 0.0), "wavelengths must be finite and > 0"),
    (lambda: jo.Target("R", [500.0, 600.0], [0.0, 0.1, 0.2]), "value has 3 values for 2 wavelengths"),
    (lambda: jo.Target("R", 500.0, 0.0, tolerance=0.0), "tolerance must be > 0"),
    (lambda: jo.Target("R", 500.0, 0.0, angle_deg=90.0), "angle_deg must lie in [0, 90)"),
    (lambda: jo.design(jo.Sample((jo.Layer(jo.Cauchy(A=jo.Free(1.5)), jo.Free(10.0)),), NS), [jo.Target("R", 500.0, 0.0)]),
     "layer1.A is Free"),
    (lambda: jo.design(jo.Sample((jo.Layer(1.5, 10.0),), NS), [jo.Target("R", 500.0, 0.0)]), "no free thickness"),
    (lambda: jo.design(jo.Sample((jo.Layer(1.5, jo.Free(10.0)),), NS), [jo.Target("R", 500.0, 0.0)], needle=True),
     "needs candidate materials"),
    (lambda: jo.design(jo.Sample((jo.Layer(1.5, jo.Free(10.0)),), NS), [jo.Target("R", 500.0, 0.0)], needle=True,
                       materials=["unobtainium"]), "unknown material 'unobtainium'"),
    (lambda: jo.ThicknessErrors("relative", -0.01), "size must be a number > 0"),
])
def test_bad_design_input_is_named(make, message):
    with pytest.raises(ValueError, match=None) as e:
        make()
    assert message in str(e.value)


def test_design_runs_in_float32():
    """With float64 off, the design computes in float32 and still finds the quarter wave."""
    with jax.enable_x64(False):
        d = jo.design(jo.Sample((jo.Layer(1.38, jo.Free(80.0, 10.0, 200.0)),), NS), [jo.Target("R", 550.0, 0.0)])
    assert d.values[0] == pytest.approx(550.0 / (4 * 1.38), rel=1e-3)


DESIGN_FILE = """
title = "two-layer AR"
[[layer]]
name = "outer"
material = { n = 1.38 }
thickness_nm = { value = 110, min = 20, max = 250 }
[[layer]]
material = "Al2O3"
thickness_nm = { value = 60, min = 20, max = 250 }
[substrate]
material = { model = "sellmeier", B = [1.03961212, 0.231792344, 1.01046945], C = [0.00600069867, 0.0200179144, 103.560653] }
[[target]]
quantity = "R"
wavelength_nm = { from = 450, to = 650, step = 25 }
value = 0.0
tolerance = 0.01
[[target]]
quantity = "T"
wavelength_nm = [550.0]
value = 0.95
kind = ">="
angle_deg = 30
polarization = "s"
[design]
starts = 3
seed = 1
"""


@pytest.mark.slow
def test_design_file_round_trip_through_the_command_line(tmp_path, capsys):
    """`design FILE --out OUT --plot P`: the file's sample, targets and options are those of the
    Python API; the written sample file reads back (`load_sample`) to the designed sample, whose
    merit is the design's."""
    from jaxoptics.__main__ import main

    path = tmp_path / "ar.toml"
    path.write_text(DESIGN_FILE)
    sample, targets, options = jo.load_design(path)
    assert options == {"starts": 3, "seed": 1}
    assert [t.quantity for t in targets] == ["R", "T"] and targets[0].points == 9 and targets[1].kind == ">="
    assert sample.free_names() == ["outer.thickness_nm", "layer2.thickness_nm"]
    out, png = tmp_path / "out.toml", tmp_path / "d.png"
    assert main(["design", str(path), "--out", str(out), "--plot", str(png), "--no-cache"]) == 0
    printed = capsys.readouterr().out
    designed = jo.load_sample(out)
    expected = jo.design(sample, targets, **options)
    assert f"merit {expected.merit:.4g}" in printed
    assert [layer.thickness_nm for layer in designed.layers] == pytest.approx(list(expected.values), rel=1e-12)
    assert jo.merit(designed, targets) == pytest.approx(expected.merit, rel=1e-10)
    assert png.stat().st_size > 20000


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace('quantity = "T"', 'quantity = "Q"'), "target[1]: Target quantity 'Q'"),
    (lambda s: s.replace("step = 25", "step = -25"), "target[0].wavelength_nm: the range needs"),
    (lambda s: s.replace("starts = 3", "starts = 3.5"), "design.starts must be int"),
    (lambda s: s.replace("seed = 1", "speed = 1"), "design.speed is not an option"),
    (lambda s: s.replace("kind = \">=\"", "knd = \">=\""), "target[1]: unknown keys ['knd']"),
    (lambda s: s.split("[[target]]")[0], "no targets"),
])
def test_bad_design_files_are_named(tmp_path, edit, message):
    path = tmp_path / "bad.toml"
    path.write_text(edit(DESIGN_FILE))
    with pytest.raises(ValueError) as e:
        jo.load_design(path)
    assert str(path) in str(e.value) and message in str(e.value)


def test_color_targets_equal_colour_science():
    """Chromaticity and CIELAB of a coating's reflectance and transmittance under D65 and A equal
    colour-science's (`sd_to_XYZ` by integration with the observer and illuminant on the same 5 nm
    grid, `XYZ_to_Lab` with the illuminant's white)."""
    with np.printoptions():  # (its import sets NumPy's legacy printing for the whole process)
        import colour

    sample = jo.Sample((jo.Layer(2.1, 95.0), jo.Layer(1.46, 160.0), jo.Layer(2.1, 70.0)), NS)
    grid = np.arange(380.0, 781.0, 5.0)
    quantities = ("x", "y", "L*", "a*", "b*")
    for ill in ("D65", "A"):
        targets = [jo.Target(f"{side}_{q}", grid, 0.0, illuminant=ill) for side in "RT" for q in quantities]
        spectra = jo.target_values(sample, [jo.Target("R", grid, 0.0), jo.Target("T", grid, 0.0)])
        got = [float(v[0]) for v in jo.target_values(sample, targets)]
        shape = colour.SpectralShape(380, 780, 5)
        cmfs = colour.colorimetry.reshape_msds(colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"], shape)
        illum = colour.colorimetry.reshape_sd(colour.SDS_ILLUMINANTS[ill], shape)
        expect = []
        for spec in spectra:
            sd = colour.SpectralDistribution(dict(zip(grid, spec)))
            XYZ = colour.sd_to_XYZ(sd, cmfs, illum, method="Integration")
            white = colour.sd_to_XYZ(colour.SpectralDistribution(dict(zip(grid, np.ones_like(grid)))), cmfs, illum,
                                     method="Integration")
            xy = colour.XYZ_to_xy(XYZ)
            Lab = colour.XYZ_to_Lab(XYZ / 100, colour.XYZ_to_xy(white))
            expect += [xy[0], xy[1], *Lab]
        np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-9)


@pytest.mark.slow
def test_gradual_evolution_goes_on_where_needle_rounds_stall():
    """A single-layer coating refined to its quarter-wave optimum has no needle that helps: the
    rounds stall at once. With gradual evolution the design is thickened and needle rounds go on,
    to a merit several times lower with more layers; the result is the best design met."""
    start = jo.Sample((jo.Layer(1.46, jo.Free(150.0, 0.0)),), NS)
    targets = [jo.Target("R", np.linspace(420.0, 680.0, 14), 0.0, tolerance=0.005)]
    plain = jo.design(start, targets, needle=True, materials=[1.46, 2.1], max_layers=14)
    grown = jo.design(start, targets, needle=True, materials=[1.46, 2.1], max_layers=14, gradual=0.3)
    assert plain.layers == 1 and plain.history.size == 2
    assert grown.layers > 2 and grown.merit < plain.merit / 3
    assert grown.merit == pytest.approx(min(grown.history), rel=1e-9)
    assert np.max(grown.history) > plain.merit  # a thickened design is worse before needles go in


def test_colour_targets_leave_numpy_printing_as_it_was():
    """colour-science sets NumPy's legacy print options (12 digits in `str` of a float64) when it
    is imported; evaluating a colour target imports it without changing the user's options (a file
    written with `str` of its values keeps every digit)."""
    code = ("import numpy as np, jaxoptics as jo; "
            "jo.target_values(jo.Sample((jo.Layer(2.1, 95.0),), 1.52), [jo.Target('R_x', np.arange(380.0, 781.0, 5.0), 0.3)]); "
            "print(np.get_printoptions()['legacy'], str(np.float64(23.83255325383033)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300).stdout.split()
    assert out == ["False", "23.83255325383033"], out
