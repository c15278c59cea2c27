"""Graded layers (`jo.Graded`): the staircase of slices against the wave equation integrated
through the continuous profile (an independent oracle, with its second-order convergence in the
slice count), against tmm given the same slices, composition grading against explicit effective
medium sublayers, gradients in every profile parameter, a fit of a graded film, and the model
file."""

import cmath
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tmm
from scipy.integrate import solve_ivp

import jaxoptics as jo


def wave_equation_R(N_of_z, d, wl, theta, n0, ns):
    """R_s and R_p of a layer of thickness `d` whose index at depth z is `N_of_z(z)`, by
    integrating Maxwell's equations through it (no slicing): for s, E'' = -k0^2 (eps - beta^2) E;
    for p, with u = H and v = H' / eps, u' = eps v, v' = -k0^2 (1 - beta^2 / eps) u. From the
    substrate side (a transmitted wave only) to the top, where the field splits into incident and
    reflected waves (exp(-i omega t), N = n + ik)."""
    k0 = 2 * math.pi / wl
    beta = n0 * math.sin(theta)
    kz0 = k0 * cmath.sqrt(n0**2 - beta**2)
    kzs = k0 * cmath.sqrt(ns**2 - beta**2)
    eps = lambda z: complex(N_of_z(z)) ** 2
    out = []
    for pol in "sp":
        if pol == "s":
            f = lambda z, y: [y[1], -k0**2 * (eps(z) - beta**2) * y[0]]
            y_end = [1.0 + 0j, 1j * kzs]
        else:
            f = lambda z, y: [eps(z) * y[1], -k0**2 * (1 - beta**2 / eps(z)) * y[0]]
            y_end = [1.0 + 0j, 1j * kzs / ns**2]
        sol = solve_ivp(f, (d, 0.0), y_end, method="DOP853", rtol=1e-12, atol=1e-14)
        u, v = sol.y[:, -1]
        w = v / (1j * kz0) if pol == "s" else v * n0**2 / (1j * kz0)  # A - B
        A, B = (u + w) / 2, (u - w) / 2
        out.append(abs(B / A) ** 2)
    return np.array(out)


def _R(material, d, wl, theta, n0=1.0, ns=3.88 + 0.02j):
    s = jo.Sample([jo.Layer(material, d)], ns, ambient=n0).fixed()
    res = s.stack(jnp.asarray([wl]), jnp.asarray([theta]))
    return np.array([float(res.R_s[0]), float(res.R_p[0])])


@pytest.mark.slow
@pytest.mark.parametrize("theta_deg", [0.0, 65.0])
def test_staircase_converges_to_the_continuous_profile(theta_deg):
    """A 400 nm film whose index rises linearly from 1.7 to 2.0 (and k from 0 to 0.01): the
    default 20 slices give R_s and R_p within 6e-4 of the wave equation integrated through the
    continuous profile (the figure the module docstring states), 80 slices within 4e-5, and each
    doubling of the slices cuts the error fourfold (second order); one slice of a uniform film
    is the wave equation's answer to 1e-12 (the oracle's own check)."""
    top, bottom, d, wl = 1.7 + 0j, 2.0 + 0.01j, 400.0, 550.0
    theta = math.radians(theta_deg)
    uniform = wave_equation_R(lambda z: 1.8, d, wl, theta, 1.0, 3.88 + 0.02j)
    np.testing.assert_allclose(_R(jo.Graded(1.8, 1.8, slices=1), d, wl, theta), uniform, rtol=0, atol=1e-12)
    exact = wave_equation_R(lambda z: top + (bottom - top) * z / d, d, wl, theta, 1.0, 3.88 + 0.02j)
    err = {k: np.abs(_R(jo.Graded(top, bottom, slices=k), d, wl, theta) - exact) for k in (20, 40, 80)}
    assert np.all(err[20] < 6e-4) and np.all(err[80] < 4e-5), err
    for k in (20, 40):
        ratio = err[k] / err[2 * k]
        assert np.all((ratio > 3.8) & (ratio < 4.2)), (k, ratio)


def test_power_and_tabulated_profiles_against_the_wave_equation():
    """`exponent` 2 (w = z^2) and a tabulated profile (0, 0.5, 0.6, 1: a steep start, a plateau)
    follow their continuous profiles to 2e-4 with 40 slices."""
    top, bottom, d, wl, theta = 2.1, 1.6, 300.0, 480.0, math.radians(55)
    cases = [(jo.Graded(top, bottom, exponent=2.0, slices=40), lambda z: top + (bottom - top) * (z / d) ** 2),
             (jo.Graded(top, bottom, profile=(0.0, 0.5, 0.6, 1.0), slices=40),
              lambda z: top + (bottom - top) * np.interp(z / d, [0, 1 / 3, 2 / 3, 1], [0.0, 0.5, 0.6, 1.0]))]
    for g, N in cases:
        np.testing.assert_allclose(_R(g, d, wl, theta), wave_equation_R(N, d, wl, theta, 1.0, 3.88 + 0.02j), atol=2e-4)


def test_slices_are_the_stack_tmm_computes():
    """The graded layer is its slices, top first, each a `1/slices` share of the thickness: R_s, R_p
    equal tmm's for the explicit staircase to 1e-12, with an ordinary film above and below."""
    g = jo.Graded(1.5 + 0.001j, 2.2, exponent=0.7, slices=7)
    sample = jo.Sample([jo.Layer(1.46, 30.0), jo.Layer(g, 210.0), jo.Layer(1.38, 90.0)], 3.88 + 0.02j).fixed()
    wl, th = 633.0, math.radians(70)
    res = sample.stack(jnp.asarray([wl]), jnp.asarray([th]))
    z = (np.arange(7) + 0.5) / 7
    slices = list((1.5 + 0.001j) + (2.2 - (1.5 + 0.001j)) * z**0.7)
    n_list = [1.0, 1.46, *slices, 1.38, 3.88 + 0.02j]
    d_list = [np.inf, 30.0, *([30.0] * 7), 90.0, np.inf]
    for pol, ours in (("s", res.R_s), ("p", res.R_p)):
        assert abs(float(ours[0]) - tmm.coh_tmm(pol, n_list, d_list, th, wl)["R"]) < 1e-12


def test_composition_grading_is_effective_medium_sublayers():
    """`Graded(EMA(host, void, f_top), fraction_bottom=f_bot)`: each slice is the Bruggeman
    mixture at the fraction of its depth, equal to a sample of those EMA layers written out."""
    host = jo.Cauchy(A=1.46, B=0.004)
    g = jo.Graded(jo.EMA(host, 1.0, 0.05), fraction_bottom=0.45, slices=5)
    f = 0.05 + 0.4 * (np.arange(5) + 0.5) / 5
    explicit = jo.Sample([jo.Layer(jo.EMA(host, 1.0, float(x)), 50.0) for x in f], jo.material("Si")).fixed()
    graded = jo.Sample([jo.Layer(g, 250.0)], jo.material("Si")).fixed()
    wl, th = jnp.linspace(400.0, 900.0, 6), jnp.full(6, math.radians(70))
    q = ("psi_deg", "delta_deg")
    np.testing.assert_allclose(np.asarray(graded.quantities(q, wl, th)), np.asarray(explicit.quantities(q, wl, th)), rtol=0, atol=1e-10)


@pytest.mark.slow
def test_gradients_in_every_profile_parameter():
    """The derivatives of R in the top and bottom indices, the exponent, the tabulated weights, the
    bottom fraction and the thickness are finite and equal central differences."""
    wl, th = jnp.asarray([550.0]), jnp.asarray([math.radians(60)])

    F = lambda: jo.Free(1.0, 0.0, 1e4)
    templates = {"power": jo.Graded(jo.Constant(n=F()), jo.Constant(n=F()), exponent=F(), slices=8),
                 "profile": jo.Graded(1.6, 2.0, profile=(F(), F(), F()), slices=8),
                 "composition": jo.Graded(jo.EMA(1.9, 1.0, jo.Free(0.5, 0.0, 1.0)), fraction_bottom=jo.Free(0.5, 0.0, 1.0),
                                          exponent=F(), slices=8)}

    def R(x, kind):
        s = jo.Sample([jo.Layer(templates[kind], F())], 3.88 + 0.02j)
        res = s.with_values(list(x)).stack(wl, th)
        return (res.R_s + 2 * res.R_p)[0]

    for kind, x0 in (("power", [1.6, 2.0, 1.5, 250.0]), ("profile", [0.1, 0.4, 0.9, 250.0]), ("composition", [0.1, 0.6, 0.8, 250.0])):
        x0 = np.array(x0)
        g = np.asarray(jax.grad(R)(jnp.asarray(x0), kind))
        assert np.all(np.isfinite(g)), kind
        h = 1e-6 * np.maximum(np.abs(x0), 1.0)
        fd = np.array([(R(jnp.asarray(x0 + h[i] * np.eye(4)[i]), kind) - R(jnp.asarray(x0 - h[i] * np.eye(4)[i]), kind)) / (2 * h[i])
                       for i in range(4)])
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9, err_msg=kind)


@pytest.mark.slow
def test_fit_recovers_a_graded_film():
    """A silicon nitride film whose index falls from 2.05 at the top to 1.90 at the bottom,
    measured by psi/delta at 3 angles with noise: a fit with the top and bottom Cauchy A and the
    thickness free recovers them within 4 standard errors, with a chi^2/dof near 1. The fit's
    Jacobian (its graded parameters each their own tangent through the stack) equals jax.jacfwd
    of the model."""
    from jaxoptics._fitting._stack_jacobian import _model_and_jacobian

    def model(top_A, bottom_A, d):
        g = jo.Graded(jo.Cauchy(A=top_A, B=0.01), jo.Cauchy(A=bottom_A, B=0.01))
        return jo.Sample([jo.Layer(g, d, name="nitride")], jo.material("Si"))

    wl = np.tile(np.linspace(350.0, 1000.0, 66), 3)
    ang = np.repeat([60.0, 70.0, 75.0], 66)
    q = np.asarray(model(2.05, 1.90, 320.0).fixed().quantities(("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.asarray(np.radians(ang))))
    rng = np.random.default_rng(4)
    sig = np.array([[0.02], [0.05]])
    q = q + sig * rng.normal(size=q.shape)
    sp = jo.make_spectra(wl, ang, {"psi_deg": q[0], "delta_deg": q[1]},
                         sigma={"psi_deg": np.full(q[0].shape, 0.02), "delta_deg": np.full(q[0].shape, 0.05)})
    free = model(jo.Free(1.95, 1.7, 2.3), jo.Free(1.95, 1.7, 2.3), jo.Free(300.0, 0.0, 600.0))
    fit = jo.fit_stack(free, sp)
    assert bool(fit.converged)
    truth = {"nitride.top.A": 2.05, "nitride.bottom.A": 1.90, "nitride.thickness_nm": 320.0}
    for name, v in truth.items():
        assert abs(float(fit[name]) - v) < 4 * float(fit.stderr_of(name)), (name, float(fit[name]), float(fit.stderr_of(name)))
    assert 0.7 < float(fit.chi2_reduced) < 1.4, float(fit.chi2_reduced)

    kinds, w, a = ("psi_deg", "delta_deg"), jnp.asarray(wl[::11]), jnp.asarray(np.radians(ang[::11]))
    x = jnp.asarray([2.0, 1.93, 310.0])
    m, J = jax.jit(_model_and_jacobian(free, kinds, w, a))(x)
    ref = lambda x: free.with_values(list(x)).quantities(kinds, w, a, flat=True)
    np.testing.assert_allclose(np.asarray(m), np.asarray(ref(x)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(J), np.asarray(jax.jacfwd(ref)(x)), rtol=1e-8, atol=1e-10)


def test_model_file_and_bad_input(tmp_path):
    """The TOML forms give the same materials as the constructors; a graded layer that is
    incoherent, or a Graded with both or neither of bottom and fraction_bottom, a composition
    grading without an EMA top, an exponent <= 0, no slices or a one-weight profile are refused
    with what is wrong."""
    toml = tmp_path / "g.toml"
    toml.write_text("""
[[layer]]
name = "g"
thickness_nm = { value = 200, min = 0, max = 500 }
material = { top = { n = 1.6 }, bottom = { n = { value = 1.9, min = 1.5, max = 2.3 } }, exponent = 2.0, slices = 12 }

[[layer]]
name = "porous"
thickness_nm = 100

[layer.material]
top = { ema = "bruggeman", host = 1.45, inclusion = 1.0, fraction = 0.1 }
fraction_bottom = { value = 0.4, min = 0, max = 1 }
profile = [0, 0.3, 1]

[substrate]
material = "Si"
""")
    s = jo.load_sample(toml)
    assert s.free_names() == ["g.bottom.n", "porous.fraction_bottom", "g.thickness_nm"]
    assert s.layers[0].material == jo.Graded(jo.Constant(n=1.6), jo.Constant(n=jo.Free(1.9, 1.5, 2.3)), exponent=2.0, slices=12)
    assert s.layers[1].material == jo.Graded(jo.EMA(1.45, 1.0, 0.1), fraction_bottom=jo.Free(0.4, 0.0, 1.0), profile=(0.0, 0.3, 1.0))
    with pytest.raises(ValueError, match="graded layer .* cannot be incoherent"):
        jo.Layer(jo.Graded(1.5, 1.7), 1e5, incoherent=True)
    with pytest.raises(ValueError, match="not both"):
        jo.Graded(jo.EMA(1.5, 1.0, 0.1), 1.7, fraction_bottom=0.3)
    with pytest.raises(ValueError, match="give bottom"):
        jo.Graded(1.5)
    with pytest.raises(ValueError, match="needs an EMA top"):
        jo.Graded(1.5, fraction_bottom=0.3)
    with pytest.raises(ValueError, match=r"exponent=0.0: must be > 0 \(a Free one's lower bound >= 0\)"):
        jo.Graded(1.5, 1.7, exponent=0.0)
    with pytest.raises(ValueError, match="slices=0"):
        jo.Graded(1.5, 1.7, slices=0)
    with pytest.raises(ValueError, match="at least two weights"):
        jo.Graded(1.5, 1.7, profile=(0.5,))
    toml.write_text('[[layer]]\nthickness_nm = 10\nmaterial = { top = 1.5 }\n[substrate]\nmaterial = "Si"\n')
    with pytest.raises(ValueError, match=r"layer\[0\]\.material: a graded layer's material is"):
        jo.load_sample(toml)
