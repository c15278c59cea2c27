"""Joint fits of several data sets with shared parameters, on tmm-generated data: the shared
parameters are recovered, and better together than from any data set alone."""

import math

import numpy as np
import pytest
import tmm

import jaxoptics as jo
from jaxoptics._fitting._joint import _plan

A_TRUE, B_TRUE = 1.46, 0.004  # Cauchy film, lambda in um
SUB = 3.9 + 0.02j
WL = np.linspace(450.0, 850.0, 17)


def _n(wl):
    return A_TRUE + B_TRUE / (wl / 1000) ** 2


def _psi_delta(d, wl, ang, rng, sig):
    out = []
    for w, a in zip(wl, ang):
        e = tmm.ellips([1.0, _n(w), SUB], [np.inf, d, np.inf], math.radians(a), w)
        out.append((math.degrees(e["psi"]), 180.0 - math.degrees(e["Delta"])))
    v = np.asarray(out).T
    return v + sig[:, None] * rng.normal(size=v.shape)


def _film(d0, name="oxide"):
    return jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.5, 1.3, 1.8), B=jo.Free(0.0, -0.05, 0.05)), jo.Free(d0, 0.0, 600.0),
                               name=name)], SUB)


@pytest.mark.slow
def test_a_dispersion_shared_by_two_films_of_different_thickness():
    """Two samples (20 nm and 300 nm of the same film material) at one angle each: the 20 nm film
    alone hardly determines the index; together the index is shared, each thickness is its own,
    and A's error is below either data set's alone."""
    rng = np.random.default_rng(3)
    sig = np.array([0.02, 0.05])
    ang = np.full(WL.size, 70.0)
    sets = []
    for d, name in ((20.0, "thin"), (300.0, "thick")):
        v = _psi_delta(d, WL, ang, rng, sig)
        sp = jo.make_spectra(WL, ang, {"psi_deg": v[0], "delta_deg": v[1]},
                             sigma={"psi_deg": np.full(WL.size, sig[0]), "delta_deg": np.full(WL.size, sig[1])})
        sets.append(jo.Dataset(_film(100.0), sp, name=name))
    fit = jo.fit_joint(sets, shared=["oxide.A", "oxide.B"])
    assert fit.names == ("oxide.A", "oxide.B", "thin:oxide.thickness_nm", "thick:oxide.thickness_nm")
    assert bool(fit.converged)
    for name, truth in (("oxide.A", A_TRUE), ("oxide.B", B_TRUE), ("thin:oxide.thickness_nm", 20.0),
                        ("thick:oxide.thickness_nm", 300.0)):
        assert abs(float(fit[name]) - truth) < 4 * float(fit.stderr_of(name)), name
    assert 0.6 < float(fit.chi2_reduced) < 1.5
    alone = [jo.fit_stack(s.sample, s.spectra) for s in sets]
    assert float(fit.stderr_of("oxide.A")) < min(float(a.stderr_of("oxide.A")) for a in alone)
    # the default shares every name free in both: here the thickness too (so shared= is needed)
    assert _plan(sets, None)[1] == ["oxide.A", "oxide.B", "oxide.thickness_nm"]


@pytest.mark.slow
def test_ellipsometry_and_reflectance_of_one_sample_share_everything_on_a_map():
    """Psi/Delta at 70 degrees and normal-incidence R of the same films (a map of two sites): the
    default shares thickness and index; the joint errors are below each data set's alone."""
    rng = np.random.default_rng(5)
    sig = np.array([0.02, 0.05])
    ds = (150.0, 420.0)
    ang = np.full(WL.size, 70.0)
    V = np.stack([_psi_delta(d, WL, ang, rng, sig) for d in ds])
    ell = jo.make_spectra(WL, ang, {"psi_deg": V[:, 0], "delta_deg": V[:, 1]},
                          sigma={"psi_deg": np.full((2, WL.size), sig[0]), "delta_deg": np.full((2, WL.size), sig[1])})
    R = np.asarray([[tmm.coh_tmm("s", [1.0, _n(w), SUB], [np.inf, d, np.inf], 0.0, w)["R"] for w in WL] for d in ds])
    R = R + 0.002 * rng.normal(size=R.shape)
    refl = jo.make_spectra(WL, 0.0, {"R": R}, sigma={"R": np.full(R.shape, 0.002)})
    sets = [jo.Dataset(_film(200.0), ell, name="se"), jo.Dataset(_film(200.0), refl, name="rt", weight=1.0)]
    fit = jo.fit_joint(sets)
    assert fit.names == ("oxide.A", "oxide.B", "oxide.thickness_nm") and fit.values.shape == (2, 3)
    assert np.all(np.asarray(fit.converged))
    d_fit, d_sd = np.asarray(fit["oxide.thickness_nm"]), np.asarray(fit.stderr_of("oxide.thickness_nm"))
    assert np.all(np.abs(d_fit - ds) < 4 * d_sd)
    for s in sets:
        alone = jo.fit_stack(s.sample, s.spectra)
        assert np.all(np.asarray(fit.stderr_of("oxide.A")) < np.asarray(alone.stderr_of("oxide.A")))


def test_joint_fit_refuses_what_it_cannot_join():
    sp = jo.make_spectra(WL, 70.0, {"psi_deg": np.full(WL.size, 30.0)})
    sp2 = jo.make_spectra(WL, 70.0, {"psi_deg": np.full((2, WL.size), 30.0)})
    with pytest.raises(ValueError, match="shared parameter 'oxide.C' is no data set's free parameter"):
        jo.fit_joint([jo.Dataset(_film(10.0), sp), jo.Dataset(_film(10.0), sp)], shared=["oxide.C"])
    with pytest.raises(ValueError, match="data set data2 has map shape"):
        jo.fit_joint([jo.Dataset(_film(10.0), sp), jo.Dataset(_film(10.0), sp2)])
    other = jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.5, 1.0, 1.8), B=0.0), 10.0, name="oxide")], SUB)
    with pytest.raises(ValueError, match=r"shared parameter 'oxide.A' has bounds \(1.3, 1.8\) .* \(1.0, 1.8\) in data2"):
        jo.fit_joint([jo.Dataset(_film(10.0), sp), jo.Dataset(other, sp)])
    with pytest.raises(ValueError, match="Dataset.weight must be a finite number > 0"):
        jo.Dataset(_film(10.0), sp, weight=0.0)


@pytest.mark.slow
def test_cli_joint_fit_from_a_toml_listing_data_sets(tmp_path, capsys):
    """`fit-stack --model joint.toml`: a Woollam export and a spectrophotometer's %R file of one
    film, each with its model file, fitted together (thickness and index shared)."""
    from jaxoptics.__main__ import main

    rng = np.random.default_rng(11)
    ang = np.full(WL.size, 70.0)
    v = _psi_delta(250.0, WL, ang, rng, np.array([0.02, 0.05]))
    rows = "\n".join(f"{w}\t70\t{p}\t{d}\t0.02\t0.05" for w, p, d in zip(WL, v[0], v[1]))
    (tmp_path / "se.dat").write_text(f"film\nVASEmethod[EllipsometerType=4]\nnm\n{rows}\n")
    R = [tmm.coh_tmm("s", [1.0, _n(w), SUB], [np.inf, 250.0, np.inf], 0.0, w)["R"] for w in WL]
    (tmp_path / "r.csv").write_text("wavelength_nm,%R\n" + "\n".join(f"{w},{100 * r}" for w, r in zip(WL, R)) + "\n")
    model = ('[[layer]]\nname = "oxide"\nthickness_nm = { value = 200, min = 0, max = 600 }\n'
             'material = { model = "cauchy", A = { value = 1.5, min = 1.3, max = 1.8 }, B = { value = 0.0, min = -0.05, max = 0.05 } }\n'
             '[substrate]\nmaterial = { n = 3.9, k = 0.02 }\n')
    (tmp_path / "film.toml").write_text(model)
    (tmp_path / "joint.toml").write_text(
        '[[dataset]]\nname = "se"\ndata = "se.dat"\nmodel = "film.toml"\n'
        '[[dataset]]\nname = "rt"\ndata = "r.csv"\nmodel = "film.toml"\nangle_deg = 0.0\nweight = 0.5\n')
    assert main(["fit-stack", "--model", str(tmp_path / "joint.toml"), "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "joint fit of 2 data sets" in out and "se.dat (woollam)" in out and "r.csv (text)" in out and "weight 0.5" in out
    row = next(l for l in out.splitlines() if l.startswith("oxide.thickness_nm"))
    d, sd = float(row.split()[1]), float(row.split()[2])
    assert abs(d - 250.0) < 4 * sd
    (tmp_path / "joint.toml").write_text('[[dataset]]\ndata = "se.dat"\nmodel = "missing.toml"\n')
    assert main(["fit-stack", "--model", str(tmp_path / "joint.toml"), "--no-cache"]) == 2
    assert "dataset[0]" in capsys.readouterr().err
