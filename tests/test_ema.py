"""Effective-medium materials against their defining equations, their limits, their common first
order in a small fraction, pyElli's implementation, and a fit of a porous, rough film."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxoptics as jo

PAIRS = [(1.46, 1.0), (3.9 + 0.02j, 1.46), (0.2 + 3.4j, 1.0), (4.2 + 0.05j, 0.3 + 2.9j)]  # dielectric, Si/oxide, metal/void
METHODS = ("bruggeman", "maxwell-garnett", "looyenga", "linear")


def _eps(host, inc, f, method, L=1 / 3):
    return complex(np.asarray(jo.EMA(host, inc, f, method, L).eps(jnp.asarray([0.5])))[0])


@pytest.mark.parametrize("host, inc", PAIRS)
@pytest.mark.parametrize("L", [1 / 3, 0.2])
def test_bruggeman_root_solves_its_equation_and_is_passive(host, inc, L):
    eh, ei = complex(host) ** 2, complex(inc) ** 2
    for f in np.linspace(0, 1, 21):
        e = _eps(host, inc, f, "bruggeman", L)
        resid = (1 - f) * (eh - e) / (e + L * (eh - e)) + f * (ei - e) / (e + L * (ei - e))
        assert abs(resid) < 1e-12 and e.imag >= -1e-15


@pytest.mark.parametrize("host, inc", PAIRS)
@pytest.mark.parametrize("method", METHODS)
def test_limits_first_order_and_continuity(host, inc, method):
    eh, ei = complex(host) ** 2, complex(inc) ** 2
    assert _eps(host, inc, 0.0, method) == pytest.approx(eh, rel=1e-13)
    assert _eps(host, inc, 1.0, method) == pytest.approx(ei, rel=1e-13)
    c = {"linear": 1, "bruggeman": eh / (eh + (ei - eh) / 3), "maxwell-garnett": eh / (eh + (ei - eh) / 3),
         "looyenga": 3 * eh ** (2 / 3) * (ei ** (1 / 3) - eh ** (1 / 3)) / (ei - eh)}[method]
    f = 1e-7
    assert (_eps(host, inc, f, method) - eh) / f == pytest.approx(c * (ei - eh), rel=1e-5)
    e = np.asarray(jo.EMA(host, inc, 0.0, method).eps(jnp.full(1, 0.5)))  # continuity over a fine grid
    vals = np.asarray([_eps(host, inc, x, method) for x in np.linspace(0, 1, 401)])
    assert np.max(np.abs(np.diff(vals))) < 0.05 * max(abs(eh), abs(ei)) and e.shape == (1,)


@pytest.mark.parametrize("method", METHODS[:3])
def test_agrees_with_pyelli(method):
    elli = pytest.importorskip("elli")
    cls = {"bruggeman": elli.BruggemanEMA, "maxwell-garnett": elli.MaxwellGarnettEMA, "looyenga": elli.LooyengaEMA}[method]
    for host, inc in PAIRS:
        mat = lambda n: elli.IsotropicMaterial(elli.ConstantRefractiveIndex(n=n))
        for f in (0.1, 0.5, 0.8):
            ref = complex(cls(mat(host), mat(inc), f).get_refractive_index(np.array([500.0]))[0, 0, 0])
            ours = complex(np.asarray(jo.EMA(host, inc, f, method).nk(jnp.asarray([0.5])))[0])
            assert ours == pytest.approx(ref, rel=1e-10), (host, inc, f)


def test_gradients_in_the_fraction_are_finite_at_the_ends_and_correct_inside():
    def n_of(f, method):
        N = jo.EMA(3.9 + 0.02j, 1.0, f, method).nk(jnp.asarray([0.5]))[0]
        return jnp.stack([N.real, N.imag])

    for method in METHODS:
        for f in (0.0, 1.0):
            g = jax.jacfwd(n_of)(jnp.asarray(f), method)
            assert np.all(np.isfinite(np.asarray(g)))
        f, h = 0.37, 1e-6
        fd = (np.asarray(n_of(jnp.asarray(f + h), method)) - np.asarray(n_of(jnp.asarray(f - h), method))) / (2 * h)
        np.testing.assert_allclose(np.asarray(jax.jacfwd(n_of)(jnp.asarray(f), method)), fd, rtol=1e-6)


def test_bad_ema_arguments():
    with pytest.raises(ValueError, match="method='bruggman'"):
        jo.EMA(1.46, 1.0, 0.5, "bruggman")
    with pytest.raises(ValueError, match="fraction=1.5: must lie in"):
        jo.EMA(1.46, 1.0, 1.5)
    with pytest.raises(ValueError, match="Free bounds must lie within"):
        jo.EMA(1.46, 1.0, jo.Free(0.5, -1.0, 1.0))


@pytest.mark.slow
def test_porous_rough_film_fit_and_the_plain_models_bias():
    """A 200 nm oxide with 30% void under 4 nm of roughness: the full model recovers all three,
    the plain porous film without roughness is biased with a poor chi^2."""
    wl = np.tile(np.linspace(400, 900, 26), 2)
    ang = np.repeat([60.0, 70.0], 26)
    truth = jo.Sample([jo.roughness(jo.EMA(1.46, 1.0, 0.3), 4.0), jo.Layer(jo.EMA(1.46, 1.0, 0.3), 200.0, name="por")],
                      jo.material("Si"))
    q = np.asarray(truth.fixed().quantities(("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.deg2rad(jnp.asarray(ang))))
    sp = jo.make_spectra(wl, ang, {"psi_deg": q[0], "delta_deg": q[1]},
                         sigma={"psi_deg": np.full(wl.size, 0.01), "delta_deg": np.full(wl.size, 0.02)})
    film = jo.Layer(jo.EMA(1.46, 1.0, jo.Free(0.1, 0.0, 1.0)), jo.Free(150.0, 0.0, 500.0), name="por")
    full = jo.fit_stack(jo.Sample([jo.roughness(jo.EMA(1.46, 1.0, 0.3), jo.Free(10.0, 0.0, 30.0)), film], jo.material("Si")), sp)
    assert full.names == ("por.fraction", "roughness.thickness_nm", "por.thickness_nm")
    np.testing.assert_allclose(np.asarray(full.values), [0.3, 4.0, 200.0], atol=1e-6)
    plain = jo.fit_stack(jo.Sample([film], jo.material("Si")), sp)
    assert float(plain.chi2_reduced) > 100 and abs(float(plain["por.thickness_nm"]) - 200.0) > 1


def test_model_file_effective_medium(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text('[[layer]]\nname = "rough"\nthickness_nm = { value = 3, min = 0, max = 20 }\n'
                 'material = { ema = "bruggeman", host = { model = "cauchy", A = 1.46, B = 0.004 }, inclusion = 1.0, fraction = 0.5 }\n'
                 '[[layer]]\nname = "por"\nthickness_nm = 200\n'
                 'material = { ema = "maxwell-garnett", host = "SiO2", inclusion = { n = 1.33 }, fraction = { value = 0.2, min = 0, max = 1 } }\n'
                 '[substrate]\nmaterial = "Si"\n')
    s = jo.load_sample(p)
    assert s.free_names() == ["por.fraction", "rough.thickness_nm"]
    assert isinstance(s.layers[1].material, jo.EMA) and s.layers[1].material.method == "maxwell-garnett"
    p.write_text(p.read_text().replace('"maxwell-garnett"', '"mg"'))
    with pytest.raises(ValueError, match=r"layer\[1\].material.ema: 'mg'"):
        jo.load_sample(p)


def test_a_tabulated_constituent_beyond_its_range_is_refused_before_the_fit():
    sample = jo.Sample([jo.Layer(jo.EMA(jo.material("Au"), 1.0, 0.5), jo.Free(10.0, 0.0, 50.0), name="mix")], jo.material("Si"))
    sp = jo.make_spectra([150.0, 600.0], 70.0, {"psi_deg": [20.0, 25.0], "delta_deg": [100.0, 120.0]})
    with pytest.raises(ValueError, match=r"mix.host: the material's tabulated data cover"):
        jo.fit_stack(sample, sp)
