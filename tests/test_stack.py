"""Thin-film stacks: `stack` and `ellipsometry` against tmm and pyElli, an mpmath transfer-matrix
oracle, closed forms and physical properties; gradients against mpmath derivatives."""

import warnings

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
import tmm
from helpers import quick_jit, stack_ref

import jaxoptics as jo

# ---- oracles -------------------------------------------------------------------------------------


def _tmm_case(n, d, wl, theta, inc):
    """tmm's R, T and absorption per inner layer for both polarizations, or None where tmm refuses
    the case (it asserts on some evanescent incoherent layers)."""
    dl = [np.inf] + list(d) + [np.inf]
    out = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for pol in "sp":
                if inc:
                    c = ["i"] + ["i" if j in inc else "c" for j in range(len(d))] + ["i"]
                    res = tmm.inc_tmm(pol, n, dl, c, theta, wl)
                    A = np.array(tmm.inc_absorp_in_each_layer(res))[1:-1]
                else:
                    res = tmm.coh_tmm(pol, n, dl, theta, wl)
                    A = tmm.absorp_in_each_layer(res)[1:-1]
                out[pol] = (res["R"], res["T"], A, res.get("r"), res.get("t"))
    except (AssertionError, ValueError, ZeroDivisionError, FloatingPointError):
        return None
    if not all(np.all(np.isfinite(np.r_[v[0], v[1], v[2]])) for v in out.values()):
        return None
    # an incoherent layer in which the wave is evanescent: tmm's intensity matrices divide by its
    # (zero) flux and return values outside [0, 1]; the kernel's answer there is tested separately
    s2 = (n[0].real * np.sin(theta)) ** 2
    if any(abs(np.sqrt(n[j + 1] ** 2 - s2).real) < 1e-6 for j in inc):
        return None
    return out


def _random_stacks(rng, K, L):
    """K random stacks of L media: dielectrics, absorbers, metals, thick absorbers; incident medium
    sometimes denser than the rest (TIR); angles up to 89 degrees."""
    n = rng.uniform(1.0, 3.0, (K, L)) + 0j
    n[:, 0] = rng.uniform(1.0, 2.6, K)
    kind = rng.random((K, L))
    n += np.where(kind < 0.25, 1j * rng.uniform(0, 0.6, (K, L)), 0)
    metal = (kind > 0.9)
    n = np.where(metal, rng.uniform(0.05, 0.6, (K, L)) + 1j * rng.uniform(2, 7, (K, L)), n)
    n[:, 0] = n[:, 0].real
    d = rng.uniform(0, 300, (K, L - 2))
    thick = rng.random((K, L - 2)) < 0.1
    d = np.where(thick, rng.uniform(1e3, 2e4, (K, L - 2)), d)
    zero = rng.random((K, L - 2)) < 0.05
    d = np.where(zero, 0.0, d)
    wl = rng.uniform(250, 1500, K)
    theta = rng.uniform(0, np.deg2rad(89), K)
    return n, d, wl, theta


# ---- agreement with tmm --------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("L", [2, 3, 4, 6, 10, 17, 32])
def test_coherent_stacks_agree_with_tmm(L):
    """Random stacks of 0 to 30 inner layers (metals, absorbers, thick layers, TIR) against tmm's
    coh_tmm, absorp_in_each_layer and ellips, to 1e-10 (absolute) in float64."""
    rng = np.random.default_rng(L)
    K = 40
    n, d, wl, theta = _random_stacks(rng, K, L)
    res = jax.jit(jo.stack)(n, d, wl, np.cos(theta))
    ell = jax.jit(jo.ellipsometry)(n, d, wl, np.cos(theta))
    compared = 0
    for k in range(K):
        ref = _tmm_case(n[k], d[k], wl[k], theta[k], ())
        if ref is None:
            continue
        compared += 1
        for pol in "sp":
            R, T, A, r, t = ref[pol]
            got = {f: np.asarray(getattr(res, f"{f}_{pol}"))[k] for f in ("R", "T", "A", "r", "t")}
            np.testing.assert_allclose(got["R"], R, atol=1e-10, rtol=0)
            np.testing.assert_allclose(got["T"], T, atol=1e-10, rtol=0)
            np.testing.assert_allclose(got["A"], A, atol=1e-10, rtol=0)
            np.testing.assert_allclose(got["r"], r, atol=1e-10, rtol=0)
            np.testing.assert_allclose(got["t"], t, atol=1e-10, rtol=1e-10)
        e = tmm.ellips(n[k], [np.inf] + list(d[k]) + [np.inf], theta[k], wl[k])
        np.testing.assert_allclose(float(ell.psi[k]), e["psi"], atol=1e-10)
        if abs(np.asarray(res.r_p)[k]) > 1e-6:  # delta is undefined where r_p = 0
            dd = (float(ell.delta[k]) - e["Delta"] + np.pi) % (2 * np.pi) - np.pi
            assert abs(dd) < 1e-9, (k, float(ell.delta[k]), e["Delta"])
    assert compared >= 0.8 * K


@pytest.mark.slow
@pytest.mark.parametrize("L,inc", [(3, (0,)), (4, (1,)), (5, (0, 2)), (6, (2,)), (8, (0, 3, 5)), (12, (4, 9))])
def test_incoherent_stacks_agree_with_tmm(L, inc):
    """Mixed coherent/incoherent stacks against tmm's inc_tmm and inc_absorp_in_each_layer."""
    rng = np.random.default_rng(100 + L)
    K = 30
    n, d, wl, theta = _random_stacks(rng, K, L)
    for j in inc:  # incoherent layers are thick
        d[:, j] = rng.uniform(2e3, 5e4, K)
    res = jax.jit(jo.stack, static_argnames="incoherent")(n, d, wl, np.cos(theta), incoherent=inc)
    assert res.r_s is None and res.t_p is None
    compared = 0
    for k in range(K):
        ref = _tmm_case(n[k], d[k], wl[k], theta[k], inc)
        if ref is None:
            continue
        compared += 1
        for pol in "sp":
            R, T, A, _, _ = ref[pol]
            np.testing.assert_allclose(np.asarray(getattr(res, f"R_{pol}"))[k], R, atol=1e-10, rtol=0)
            np.testing.assert_allclose(np.asarray(getattr(res, f"T_{pol}"))[k], T, atol=1e-10, rtol=0)
            np.testing.assert_allclose(np.asarray(getattr(res, f"A_{pol}"))[k], A, atol=1e-10, rtol=0)
    assert compared >= 0.6 * K


def test_mpmath_oracle_agrees_with_tmm():
    """The mpmath oracle used for the gradient tests is itself checked against tmm."""
    rng = np.random.default_rng(5)
    n, d, wl, theta = _random_stacks(rng, 10, 5)
    for k in range(10):
        for pol in "sp":
            ref = tmm.coh_tmm(pol, n[k], [np.inf] + list(d[k]) + [np.inf], theta[k], wl[k])
            r, t, R, T = stack_ref(pol, n[k], d[k], wl[k], theta[k])
            assert abs(r - ref["r"]) < 1e-12 and abs(t - ref["t"]) < 1e-12 * max(1, abs(t))
            assert abs(R - ref["R"]) < 1e-12 and abs(T - ref["T"]) < 1e-12


# ---- closed forms --------------------------------------------------------------------------------


@pytest.mark.slow
def test_one_interface_equals_fresnel():
    c = np.array([1.0, 0.8, 0.3, 1e-6, 0.0])[:, None]
    for n0, n1 in [(1.0, 1.5), (1.5, 1.0), (1.2, 0.2 + 3.0j), (1.33, 1.33), (2.0, 1.0 + 0.1j)]:
        s = jo.stack(np.array([n0, n1]), np.zeros(0), 500.0, c[:, 0])
        f = jo.fresnel_amplitudes(c[:, 0], n0, n1)
        for a, b in [(s.r_s, f.r_s), (s.r_p, f.r_p), (s.t_s, f.t_s), (s.t_p, f.t_p)]:
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=4e-16)
        R_s, R_p = jo.fresnel_sp(c[:, 0], n0, n1)
        np.testing.assert_allclose(np.asarray(s.R_s), np.asarray(R_s), atol=4e-16)
        np.testing.assert_allclose(np.asarray(s.R_p), np.asarray(R_p), atol=4e-16)


@pytest.mark.slow
@pytest.mark.parametrize("n0,n1,ns", [(1.0, 1.38, 1.52), (1.0, 2.0, 1.5), (1.33, 1.8, 3.5)])
def test_quarter_wave_film(n0, n1, ns):
    """A film of optical thickness lambda/4 at normal incidence: R = ((n0 ns - n1^2)/(n0 ns + n1^2))^2."""
    wl = 550.0
    res = jo.stack(np.array([n0, n1, ns]), np.array([wl / (4 * n1)]), wl, 1.0)
    expect = ((n0 * ns - n1**2) / (n0 * ns + n1**2)) ** 2
    np.testing.assert_allclose(float(res.R), expect, rtol=1e-13)
    # half-wave: the film is absent
    res = jo.stack(np.array([n0, n1, ns]), np.array([wl / (2 * n1)]), wl, 1.0)
    np.testing.assert_allclose(float(res.R), ((n0 - ns) / (n0 + ns)) ** 2, rtol=1e-12)


def test_incoherent_slab_closed_form():
    """A thick absorbing slab in air, incoherent: R = R1 + T1^2 R1 P^2 / (1 - R1^2 P^2),
    T = T1^2 P / (1 - R1^2 P^2) with the single-interface R1 and the single-pass P."""
    n1, wl, d = 1.5 + 1e-5j, 600.0, 1e5
    for c in [1.0, 0.7, 0.2]:
        s2 = 1 - c * c
        kz = np.sqrt(n1**2 - s2)
        P = np.exp(-4 * np.pi * d * kz.imag / wl)
        res = jo.stack(np.array([1.0, n1, 1.0]), np.array([d]), wl, c, incoherent=(0,))
        for pol in "sp":
            r = jo.stack(np.array([1.0, n1]), np.zeros(0), wl, c)
            R1 = float(getattr(r, f"R_{pol}"))
            T1 = 1 - R1  # lossless interface: the absorption is in the bulk
            np.testing.assert_allclose(float(getattr(res, f"R_{pol}")), R1 + T1**2 * R1 * P**2 / (1 - R1**2 * P**2), rtol=1e-6)
            np.testing.assert_allclose(float(getattr(res, f"T_{pol}")), T1**2 * P / (1 - R1**2 * P**2), rtol=1e-6)


def test_incoherent_ellipsometry_of_a_slab_is_the_path_sum():
    """psi/delta of a transparent slab with its back face, incoherent: <r_p conj(r_s)> is the
    sum over the paths with 0, 1, 2, ... internal round trips, each a product of Fresnel amplitudes."""
    n0, n1, c = 1.0, 1.7, np.cos(np.deg2rad(65))
    res = jo.stack(np.array([n0, n1, n0]), np.array([1e6]), 633.0, c, incoherent=(0,))
    a = jo.fresnel_amplitudes(c, n0, n1)
    c1 = np.sqrt(1 - (n0 / n1) ** 2 * (1 - c * c))
    b = jo.fresnel_amplitudes(c1, n1, n0)
    X = complex(a.r_p * np.conj(a.r_s))
    Rs, Rp = float(a.R_s), float(a.R_p)
    term_p, term_s = complex(a.t_p * b.t_p), complex(a.t_s * b.t_s)
    for k in range(200):  # internal round trips: reflect (k+1) times at the back, k at the front
        ap = term_p * complex(b.r_p) ** (2 * k + 1)
        as_ = term_s * complex(b.r_s) ** (2 * k + 1)
        X += ap * np.conj(as_)
        Rp += abs(ap) ** 2
        Rs += abs(as_) ** 2
    ell = jo.ellipsometry(np.array([n0, n1, n0]), np.array([1e6]), 633.0, c, incoherent=(0,))
    np.testing.assert_allclose(complex(res.rp_rs), X, rtol=1e-12)
    np.testing.assert_allclose(float(ell.psi), np.arctan(np.sqrt(Rp / Rs)), rtol=1e-12)
    assert abs((float(ell.delta) - np.angle(-X) + np.pi) % (2 * np.pi) - np.pi) < 1e-12
    assert abs(X) < np.sqrt(Rp * Rs) * (1 - 1e-3)  # depolarized


@pytest.mark.slow
def test_ellipsometry_conventions():
    """delta = 0 at normal incidence, pi past Brewster's angle of a bare dielectric, and psi = 45
    degrees at normal incidence; for a film, psi/delta follow from -r_p/r_s."""
    b = np.arctan(1.5)
    e = jo.ellipsometry(np.array([1.0, 1.5]), np.zeros(0), 500.0, np.cos(np.array([0.0, b - 0.1, b + 0.1])))
    np.testing.assert_allclose(np.asarray(e.psi)[0], np.pi / 4, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(e.delta), [0.0, 0.0, np.pi], atol=1e-15)
    assert np.all(np.asarray(e.delta) > -np.pi)
    # SiO2 (1.46) 100 nm on Si (3.88 + 0.02i) at 70 degrees, 633 nm: psi/delta from the oracle
    n, d = np.array([1.0, 1.46, 3.88 + 0.02j]), np.array([100.0])
    rs = stack_ref("s", n, d, 633.0, np.deg2rad(70))[0]
    rp = stack_ref("p", n, d, 633.0, np.deg2rad(70))[0]
    e = jo.ellipsometry(n, d, 633.0, np.cos(np.deg2rad(70)))
    np.testing.assert_allclose(float(e.psi), np.arctan(abs(rp / rs)), rtol=1e-13)
    np.testing.assert_allclose(float(e.delta), np.angle(-rp / rs), rtol=1e-13)


# ---- physical properties -------------------------------------------------------------------------


@pytest.mark.slow
def test_energy_conservation_and_reciprocity():
    rng = np.random.default_rng(11)
    n, d, wl, theta = _random_stacks(rng, 200, 8)
    n[:, -1] = n[:, -1].real  # reciprocity with real outer media
    res = jo.stack(n, d, wl, np.cos(theta))
    for pol in "sp":
        total = getattr(res, f"R_{pol}") + getattr(res, f"T_{pol}") + getattr(res, f"A_{pol}").sum(-1)
        np.testing.assert_allclose(np.asarray(total), 1.0, atol=1e-13)
        assert np.all(np.asarray(getattr(res, f"A_{pol}")) > -1e-13)
    # the reversed stack lit at the corresponding angle transmits the same (Stokes reciprocity)
    s_exit = n[:, 0].real * np.sin(theta) / n[:, -1].real
    ok = s_exit < 1
    c_exit = np.sqrt(1 - np.minimum(s_exit, 1) ** 2)
    rev = jo.stack(n[:, ::-1].copy(), d[:, ::-1].copy(), wl, c_exit)
    for pol in "sp":
        np.testing.assert_allclose(np.asarray(getattr(rev, f"T_{pol}"))[ok], np.asarray(getattr(res, f"T_{pol}"))[ok], atol=1e-12)


@pytest.mark.slow
def test_zero_thickness_layer_is_absent():
    n = np.array([1.0, 1.46, 2.2 + 0.3j, 2.0, 3.9 + 0.02j])
    d = np.array([100.0, 0.0, 50.0])
    c = np.linspace(0.0, 1.0, 11)
    a = jo.stack(n, d, 500.0, c)
    b = jo.stack(np.delete(n, 2), np.delete(d, 1), 500.0, c)
    for f in ("r_s", "r_p", "t_s", "t_p"):
        np.testing.assert_allclose(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), atol=1e-15)
    np.testing.assert_array_equal(np.asarray(a.A_s[:, 1]), 0.0)


def test_index_matched_layers_and_grazing():
    # layers of the incident medium's index change nothing; at grazing incidence R = 1, r = -1
    a = jo.stack(np.array([1.5, 1.5, 1.5, 1.0]), np.array([120.0, 30.0]), 600.0, np.array([1.0, 0.5, 0.0]))
    b = jo.stack(np.array([1.5, 1.0]), np.zeros(0), 600.0, np.array([1.0, 0.5, 0.0]))
    np.testing.assert_allclose(np.asarray(a.R_s), np.asarray(b.R_s), atol=1e-15)
    np.testing.assert_allclose(np.asarray(a.r_p[-1]), -1.0, atol=1e-15)
    # a stack with no interface at all, at grazing incidence: r = 0, t = 1 (as fresnel)
    z = jo.stack(np.array([1.5, 1.5, 1.5]), np.array([100.0]), 600.0, 0.0)
    assert float(z.R) == 0.0 and float(z.T) == 1.0 and complex(z.t_s) == 1.0


@pytest.mark.slow
def test_thick_absorbers_do_not_overflow():
    """d k / lambda from 10 to 10^7: transmission decays to 0, R is the bulk reflectance, all
    finite, gradients too (plain transfer matrices overflow here)."""
    for dtype in (np.float32, np.float64):
        ratio = np.array([1e1, 1e3, 1e5, 1e7])
        n = np.array([1.0, 1.5, 2.0 + 0.5j, 1.5], dtype=np.complex64 if dtype == np.float32 else np.complex128)
        d = np.stack([np.full(4, 80.0), ratio * 600 / 0.5], -1).astype(dtype)
        res, bulk, g = jax.jit(lambda n, d: (jo.stack(n, d, dtype(600), dtype(0.8)), jo.stack(n[:3], d[:, :1], dtype(600), dtype(0.8)),
                                             jax.grad(lambda d: jo.stack(n, d, dtype(600), dtype(0.8)).R.sum())(d)))(n, d)
        assert np.all(np.isfinite(np.asarray(res.R))) and np.all(np.asarray(res.T)[1:] == 0)
        # the same reflectance by two computations (the 4-medium stack and the 3-medium one: about 40
        # roundings each)
        np.testing.assert_allclose(np.asarray(res.R)[1:], np.asarray(bulk.R)[1:], rtol=64 * np.finfo(dtype).eps)
        assert np.all(np.isfinite(np.asarray(g)))


def test_evanescent_incoherent_layer_passes_no_light():
    """A thick incoherent layer in which the wave is evanescent is a semi-infinite medium under TIR:
    R = 1 for a lossless stack, T = 0, nothing absorbed behind it (tunnelling is coherent)."""
    th = np.deg2rad(70)
    n = np.array([1.5, 1.2, 1.0, 1.5 + 0.01j, 1.5])
    res = jo.stack(n, np.array([100.0, 5e4, 300.0]), 600.0, np.cos(th), incoherent=(1,))
    for pol in "sp":
        np.testing.assert_allclose(float(getattr(res, f"R_{pol}")), 1.0, atol=1e-14)
        assert float(getattr(res, f"T_{pol}")) == 0.0
        np.testing.assert_allclose(np.asarray(getattr(res, f"A_{pol}")), 0.0, atol=1e-14)


@pytest.mark.slow
def test_frustrated_tir_tunnelling():
    """Glass | air gap | glass past the critical angle: the transmission of the gap decays as
    exp(-2 kappa d) for thick gaps and matches the oracle at every gap."""
    th = np.deg2rad(60)
    gaps = np.array([0.0, 10.0, 100.0, 400.0, 2000.0])
    res = jo.stack(np.array([1.5, 1.0, 1.5]), gaps[:, None], 600.0, np.cos(th))
    for k, g in enumerate(gaps):
        for pol in "sp":
            _, _, R, T = stack_ref(pol, [1.5, 1.0, 1.5], [g], 600.0, th)
            np.testing.assert_allclose(float(getattr(res, f"R_{pol}")[k]), R, atol=1e-14)
            np.testing.assert_allclose(float(getattr(res, f"T_{pol}")[k]), T, rtol=1e-12, atol=1e-300)
    assert float(res.T_s[0]) == pytest.approx(1.0, abs=1e-15)


# ---- gradients -----------------------------------------------------------------------------------


def _grad_cases():
    """(name, n, d, wl, theta) at the special points: an inner layer exactly at its own critical
    angle, TIR into the exit medium, a zero-thickness layer, k = 0, a thick absorber, normal and
    near-grazing incidence."""
    th = 0.7
    return [
        ("inner critical", [1.5, 1.5 * np.sin(th), 1.45, 1.0], [120.0, 80.0], 550.0, th),
        ("exit TIR", [1.6, 1.38, 2.1, 1.0], [90.0, 40.0], 600.0, 1.2),
        ("zero thickness", [1.0, 1.46, 2.0, 3.9 + 0.02j], [100.0, 0.0], 500.0, 0.5),
        ("k = 0", [1.0, 1.46, 2.0 + 0.0j, 1.52], [100.0, 60.0], 500.0, 0.3),
        ("thick absorber", [1.0, 2.0 + 0.01j, 1.5], [3e4], 600.0, 0.4),
        ("normal", [1.0, 1.38, 2.3, 1.52], [99.6, 59.8], 550.0, 0.0),
        ("near grazing", [1.0, 1.38, 0.2 + 3.0j], [99.6], 550.0, 1.55),
    ]


@pytest.mark.slow
@pytest.mark.parametrize("case", _grad_cases(), ids=lambda c: c[0])
def test_gradients_match_mpmath(case):
    """d R_s, d R_p with respect to each thickness, each n and k, the wavelength and the angle,
    against mpmath's numerical derivatives of the 40-digit oracle."""
    _, n, d, wl, th = case
    n = np.asarray(n, complex)
    d = np.asarray(d, float)

    def ours(pol, nr, ni, d, wl, th):
        res = jo.stack(jax.lax.complex(nr, ni), d, wl, jnp.cos(th))
        return getattr(res, f"R_{pol}")

    for pol in "sp":
        args = (jnp.asarray(n.real), jnp.asarray(n.imag), jnp.asarray(d), jnp.float64(wl), jnp.float64(th))
        g = jax.grad(lambda *a: ours(pol, *a), argnums=(0, 1, 2, 3, 4))(*args)
        assert all(np.all(np.isfinite(np.asarray(x))) for x in g), (case[0], pol, g)

        def ref(which, idx, x):
            nn, dd, w, t = [mp.mpc(v) for v in n], list(d), wl, th
            if which == 0:
                nn[idx] = mp.mpc(x, n[idx].imag)
            elif which == 1:
                nn[idx] = mp.mpc(n[idx].real, x)
            elif which == 2:
                dd[idx] = x
            elif which == 3:
                w = x
            else:
                t = x
            return stack_ref(pol, nn, dd, w, t, dps=40, exact=True)[2]

        with mp.workdps(40):
            for which, base in enumerate([n.real, n.imag, d, np.array([wl]), np.array([th])]):
                for idx in range(len(base)):
                    if which == 0 and idx == 0 and case[0] == "inner critical":
                        continue  # n0 moves the critical angle onto a branch point of layer 1's k_z
                    if which == 1 and idx == 0:
                        continue  # the incident medium is real
                    if which == 4 and th == 0.0:
                        continue  # |cos| has a kink at normal incidence
                    x0 = float(base[idx])
                    # k is one-sided at k = 0 (k < 0 is gain, another branch): forward differences
                    direction = 1 if which == 1 else 0
                    expect = float(mp.diff(lambda x: ref(which, idx, x), mp.mpf(x0), h=mp.mpf(10) ** -12,
                                           direction=direction))
                    got = float(np.atleast_1d(np.asarray(g[which]))[idx])
                    assert abs(got - expect) <= 1e-7 * max(1.0, abs(expect)), (case[0], pol, which, idx, got, expect)


@pytest.mark.slow
def test_float32_gradients_finite_at_special_points():
    grad = jax.jit(jax.vmap(jax.grad(lambda d, n, wl, c: jo.stack(n, d, wl, c).R)))
    for names, n, d, wl, c in _cases_by_media(_grad_cases(), np.float32):
        finite = np.isfinite(np.asarray(grad(d, n, wl, c))).all(-1)
        assert finite.all(), [name for name, ok in zip(names, finite) if not ok]


@pytest.mark.slow
# no layer; coherent layers; an incoherent first layer and an incoherent layer behind a coherent one
@pytest.mark.parametrize("L,inc", [(2, ()), (4, ()), (5, (0, 2))])
def test_float32_gradients_finite_without_any_interface_near_grazing(L, inc):
    """Every medium of the incident medium's index (no interface), at and near grazing incidence
    in float32, coherent and with incoherent layers: R = 0 and T = 1, with finite reverse-mode
    derivatives in n, k, the thicknesses, the wavelength and cos_i, and finite forward-mode ones in
    k, the thicknesses, the wavelength and cos_i, and of a coherent stack's R in n (the stack's divisor is about 1e-10
    there, its fourth power below float32's range, and the tangent of its reciprocal above it; an
    incoherent layer's flux normalization is of order cos_i, and its derivative receives a
    cotangent of order 1 / cos_i^2). Forward-mode derivatives in n of T, and with incoherent
    layers of R too, pass through the normalization of T, whose own tangent (of order
    1 / cos_i^3) overflows float32 below cos_i of about 1e-13 (docs/thin-films.md)."""
    c = np.array([0.0, np.cos(np.pi / 2), 1e-30, 1e-18, 1e-14, 1e-10, 1e-6], np.float32)
    d = np.full(L - 2, 100.0, np.float32)

    def RT(nr, ni, d, c, wl):
        res = jo.stack(jax.lax.complex(nr, ni), d, wl, c, incoherent=inc)
        return jnp.stack([res.R_s, res.R_p, res.T_s, res.T_p])

    nr, ni, wl = np.full(L, 1.5, np.float32), np.zeros(L, np.float32), np.float32(550.0)
    out = np.asarray(RT(nr, ni, d, c, wl))
    np.testing.assert_allclose(out, np.repeat([[0.0], [0.0], [1.0], [1.0]], len(c), axis=1), atol=1e-6)
    # reverse mode: one pullback of a cotangent with every component nonzero is non-finite in an
    # input wherever a row of the Jacobian is (a NaN or an infinity in any row reaches the sum)
    w = jnp.asarray(np.linspace(1.0, 2.0, out.size).reshape(out.shape), np.float32)
    g = jax.jit(jax.grad(lambda *a: jnp.sum(w * RT(*a)), argnums=(0, 1, 2, 3, 4)))(nr, ni, d, c, wl)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
    J = jax.jit(jax.jacfwd(RT, argnums=(0, 1, 2, 3, 4)))(nr, ni, d, c, wl)
    if not inc:
        assert np.all(np.isfinite(np.asarray(J[0])[:2])), "forward mode, R in n"
    assert all(np.all(np.isfinite(np.asarray(j))) for j in J[1:]), "forward mode, in k, d, cos_i and the wavelength"


@pytest.mark.slow
@pytest.mark.parametrize("case", _grad_cases(), ids=lambda c: c[0])
def test_hessians_match_mpmath(case):
    """Second derivatives of R_s and R_p in the real parts of the indices after the first medium,
    the thicknesses, the wavelength and the angle, against mpmath's numerical second derivatives
    of the 40-digit oracle (Newton-type solvers and implicit-function gradients of a user's fit
    through `stack` take them)."""
    name, n, d, wl, th = case
    n = np.asarray(n, complex)
    d = np.asarray(d, float)
    L, m = len(n), len(d)
    x0 = np.concatenate([n.real[1:], d, [wl, th]])
    skip = {L - 1 + m + 1} if th == 0.0 else set()  # |cos| has a kink at normal incidence

    def split(x, lib):
        nn = [n[0]] + [lib.mpc(x[j - 1], n[j].imag) if lib is mp else jax.lax.complex(x[j - 1], n[j].imag)
                       for j in range(1, L)]
        return nn, x[L - 1:L - 1 + m], x[L - 1 + m], x[L + m]

    def ours(x):
        nn, dd, w, t = split(x, jnp)
        res = jo.stack(jnp.stack([jnp.complex128(nn[0])] + nn[1:]), dd, w, jnp.cos(t))
        return jnp.stack([res.R_s, res.R_p])

    Hsp = np.asarray(jax.jit(jax.hessian(ours))(jnp.asarray(x0)))
    for pol, H in zip("sp", Hsp):
        assert np.all(np.isfinite(H)), (name, pol)

        def ref(*x):
            nn, dd, w, t = split(list(x), mp)
            return stack_ref(pol, [mp.mpc(nn[0])] + nn[1:], list(dd), w, t, dps=40, exact=True)[2]

        with mp.workdps(40):
            for i in range(len(x0)):
                for j in range(i, len(x0)):
                    if i in skip or j in skip:
                        continue
                    orders = [0] * len(x0)
                    orders[i] += 1
                    orders[j] += 1
                    expect = float(mp.diff(ref, [mp.mpf(v) for v in x0], orders, h=mp.mpf(10) ** -10))
                    assert abs(H[i, j] - expect) <= 1e-7 * max(1.0, abs(expect)), (name, pol, i, j, H[i, j], expect)
                    assert H[j, i] == pytest.approx(H[i, j], rel=1e-9, abs=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_hessians_finite_at_special_points(dtype):
    """Finite Hessians of R and T where every medium has the incident medium's index, at grazing
    incidence (no interface: every layer's k_z is 0), and in float32 at the special points too
    (`test_hessians_match_mpmath` checks them in float64)."""
    if dtype == np.float32:
        # the special points, those of one number of media in one batch (one compiled program each)
        def RT_one(nr, ni, d, wl, c):
            res = jo.stack(jax.lax.complex(nr, ni), d, wl, c)
            return jnp.stack([res.R_s, res.R_p, res.T_s, res.T_p])

        hessians = jax.jit(jax.vmap(jax.hessian(RT_one, argnums=(0, 2, 4))))
        for names, n, d, wl, c in _cases_by_media(_grad_cases(), dtype):
            H = hessians(n.real, n.imag, d, wl, c)
            finite = np.all([np.isfinite(np.asarray(h)).reshape(len(names), -1).all(-1) for h in jax.tree.leaves(H)], axis=0)
            assert finite.all(), [name for name, ok in zip(names, finite) if not ok]
    # exact and near grazing incidence (cos(pi/2) in float64 is 6.1e-17), one batch. Near it the
    # second derivatives in the indices grow like 1/cos_i^4, beyond float32's range at 1e-10.
    near = [np.cos(np.pi / 2), 1e-10] if dtype == np.float64 else []
    n, d, wl, c = np.full(4, 1.5, dtype), np.array([100.0, 50.0], dtype), dtype(550.0), np.array([0.0] + near, dtype)

    def RT(nr, d, c):
        res = jo.stack(jax.lax.complex(nr, jnp.zeros_like(nr)), d, wl, c)
        return jnp.stack([res.R_s, res.R_p, res.T_s, res.T_p])

    H = jax.jit(jax.hessian(RT, argnums=(0, 1, 2)))(n, d, c)
    assert all(np.all(np.isfinite(np.asarray(h))) for h in jax.tree.leaves(H)), "index matched, grazing"


def _cases_by_media(cases, dtype):
    """`_grad_cases()` grouped by their number of media: (names, n (K, L) complex, d (K, L - 2),
    wavelength (K,), cos_i (K,)) in `dtype`."""
    cdt = np.complex64 if dtype == np.float32 else np.complex128
    for L in sorted({len(c[1]) for c in cases}):
        group = [c for c in cases if len(c[1]) == L]
        yield ([c[0] for c in group], np.array([c[1] for c in group], cdt), np.array([c[2] for c in group], dtype),
               np.array([c[3] for c in group], dtype), np.cos(np.array([c[4] for c in group])).astype(dtype))


def _incoherent_cases():
    """(name, n, d, wl, cos_i, smooth) of five media whose middle inner layer is incoherent: three
    smooth points (an absorbing incoherent layer between films; TIR into the exit medium; a
    lossless incoherent layer on a metal) and the special points where finite differences do not
    apply (a film and the incoherent layer each at its own critical angle, the wave evanescent in
    the incoherent layer, every medium of the incident index at grazing incidence)."""
    s = 1.5 * np.sin(0.7)
    return [
        ("absorbing incoherent layer", [1.0, 1.46, 2.0 + 0.01j, 1.38 + 0.002j, 1.52], [100.0, 3e4, 60.0], 550.0, np.cos(0.5), True),
        ("exit TIR", [1.6, 1.38, 1.75 + 0.001j, 2.1, 1.0], [90.0, 5e4, 40.0], 600.0, np.cos(1.2), True),
        ("lossless incoherent layer", [1.0, 1.7, 1.45, 2.3, 3.9 + 0.02j], [120.0, 2e4, 70.0], 480.0, np.cos(0.9), True),
        ("film at its critical angle", [1.5, s, 1.45 + 0.001j, 1.3, 1.0], [120.0, 5e4, 80.0], 550.0, np.cos(0.7), False),
        ("incoherent layer at its critical angle", [1.5, 1.45, s, 1.3, 1.52], [120.0, 5e4, 80.0], 550.0, np.cos(0.7), False),
        ("evanescent incoherent layer", [1.5, 1.45, 1.0, 1.3, 1.52], [120.0, 5e4, 80.0], 550.0, np.cos(1.2), False),
        ("index matched, grazing", [1.5] * 5, [100.0, 5e4, 50.0], 550.0, 0.0, False),
    ]


def _richardson_derivatives(f, x0, scale):
    """Gradient and Hessian of `f` (vector-valued) at `x0` in the coordinates `u` with
    `x = x0 + scale * u`: fourth-order central differences at steps 5e-3 and 2.5e-3, combined by
    Richardson extrapolation (truncation error of order h^6; rounding about 1e-16 / h^2)."""
    k = len(x0)
    F = lambda u: f(x0 + scale * u)
    e = np.eye(k)
    c1 = {-2: 1 / 12, -1: -2 / 3, 1: 2 / 3, 2: -1 / 12}
    c2 = {-2: -1 / 12, -1: 4 / 3, 0: -5 / 2, 1: 4 / 3, 2: -1 / 12}

    def at(h):
        G = np.array([sum(w * F(a * h * e[i]) for a, w in c1.items()) / h for i in range(k)])
        H = np.zeros((k, k) + G.shape[1:])
        for i in range(k):
            H[i, i] = sum(w * F(a * h * e[i]) for a, w in c2.items()) / h**2
            for j in range(i + 1, k):
                H[i, j] = H[j, i] = sum(wa * wb * F(a * h * e[i] + b * h * e[j])
                                        for a, wa in c1.items() for b, wb in c1.items()) / h**2
        return G, H

    (G1, H1), (G2, H2) = at(5e-3), at(2.5e-3)
    return (16 * G2 - G1) / 15, (16 * H2 - H1) / 15


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_incoherent_derivatives(dtype):
    """First and second derivatives of R_s, T_s, R_p, T_p of stacks with an incoherent layer, in
    the real parts of the indices after the first medium, the thicknesses, the wavelength and
    cos_i: at the smooth points (float64) against finite differences of tmm's `inc_tmm`,
    extrapolated; finite at every point in both dtypes. Derivatives are compared in coordinates
    scaled to each variable's own scale (indices 1, films a sixth of a wave in them, the thick
    layer 5 um, the wavelength 50 nm, cos_i 0.3), in which they are of order one."""
    cases = _incoherent_cases()
    cdt = np.complex64 if dtype == np.float32 else np.complex128
    x0 = np.array([np.concatenate([np.real(n[1:]), d, [wl, c]]) for _, n, d, wl, c, _ in cases], dtype)
    n_imag = np.array([np.imag(n[1:]) for _, n, _, _, _, _ in cases], dtype)
    n0 = np.array([n[0] for _, n, _, _, _, _ in cases], cdt)
    scale = np.array([[1.0] * 4 + [wl / (2 * np.pi * n[1].real), 5e3, wl / (2 * np.pi * n[3].real), 50.0, 0.3]
                      for _, n, _, wl, _, _ in cases], dtype)

    def ours(u, x0, scale, n_imag, n0):
        x = x0 + scale * u
        n = jnp.concatenate([n0[None], jax.lax.complex(x[:4], n_imag)])
        res = jo.stack(n, x[4:7], x[7], x[8], incoherent=(1,))
        return jnp.stack([res.R_s, res.T_s, res.R_p, res.T_p])

    args = (np.zeros_like(x0), x0, scale, n_imag, n0)
    # forward over forward: the same derivative rule at both orders, and a far quicker compile
    # than forward over reverse through the scans; the Jacobian comes with the Hessian (one program)
    jac = jax.jacfwd(ours)
    H, J = (np.asarray(a) for a in jax.jit(jax.vmap(jax.jacfwd(lambda *a: (jac(*a), jac(*a)), has_aux=True)))(*args))
    for k, (name, n, d, wl, c, smooth) in enumerate(cases):
        assert np.all(np.isfinite(J[k])) and np.all(np.isfinite(H[k])), name
        if dtype != np.float64 or not smooth:
            continue

        def tmm_RT(x):
            nn = [n[0]] + [complex(a, b) for a, b in zip(x[:4], np.imag(n[1:]))]
            out = []
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for pol in "sp":
                    r = tmm.inc_tmm(pol, nn, [np.inf, *x[4:7], np.inf], ["i", "c", "i", "c", "i"], np.arccos(x[8]), x[7])
                    out += [r["R"], r["T"]]
            return np.array(out)

        G, Hf = _richardson_derivatives(tmm_RT, x0[k].astype(np.float64), scale[k].astype(np.float64))
        np.testing.assert_allclose(J[k].T, G, atol=1e-9, rtol=0, err_msg=name)
        np.testing.assert_allclose(np.moveaxis(H[k], 0, -1), Hf, atol=1e-7, rtol=0, err_msg=name)


@pytest.mark.slow
def test_incoherent_layer_at_its_critical_angle_has_finite_derivatives_under_any_rounding():
    """An incoherent layer within a few ulps of its own critical angle (k_z^2 within rounding of
    0), in float32, compiled with XLA's optimizations off: the rounding then differs from the
    default compilation's (no contracted multiply-adds), and the root's mask and its input must
    still agree (they read k_z^2 once: `sqrt_where`). The Jacobian and the Hessian of R and T of
    both polarizations are finite at each point."""
    s = np.float32(1.5 * np.sin(0.7))
    x = np.array([1.45, s, 1.3, 1.52, 120.0, 5e4, 80.0, 550.0, np.cos(0.7)], np.float32)
    X = np.repeat(x[None], 5, 0)
    X[:, 8] += np.arange(-2, 3) * np.spacing(X[0, 8])

    def f(x):
        n = jnp.concatenate([jnp.asarray([1.5], jnp.complex64), x[:4].astype(jnp.complex64)])
        r = jo.stack(n, x[4:7], x[7], x[8], incoherent=(1,))
        return jnp.stack([r.R_s, r.T_s, r.R_p, r.T_p])

    jac = jax.jacfwd(f)
    both = jax.vmap(jax.jacfwd(lambda x: (jac(x), jac(x)), has_aux=True))
    H, J = jax.jit(both, compiler_options={"xla_backend_optimization_level": 0})(jnp.asarray(X))
    assert np.all(np.isfinite(np.asarray(J))) and np.all(np.isfinite(np.asarray(H)))


# ---- API, dtype, bad input -----------------------------------------------------------------------


@pytest.mark.slow
def test_float32_in_float32_out_and_accuracy():
    rng = np.random.default_rng(3)
    n, d, wl, theta = _random_stacks(rng, 100, 6)
    d = np.minimum(d, 500)
    r64 = jo.stack(n, d, wl, np.cos(theta))
    r32 = jo.stack(n.astype(np.complex64), d.astype(np.float32), wl.astype(np.float32), np.cos(theta).astype(np.float32))
    assert r32.R_s.dtype == np.float32 and r32.r_p.dtype == np.complex64 and r32.A_p.dtype == np.float32
    np.testing.assert_allclose(np.asarray(r32.R), np.asarray(r64.R), atol=2e-4)


@pytest.mark.slow
def test_jit_vmap_and_broadcasting():
    n = np.array([1.0, 1.46, 3.9 + 0.02j])
    wl = np.linspace(400, 800, 5)
    c = np.linspace(0.3, 1, 4)[:, None]
    d = np.array([[80.0], [120.0], [160.0], [200.0]])  # (4, 1): one thickness per angle row
    res = jo.stack(n, d[:, None], wl, c)  # n (3,), d (4, 1, 1), wl (5,), c (4, 1) -> (4, 5)
    assert res.R.shape == (4, 5) and res.A_s.shape == (4, 5, 1)
    for i in range(4):
        for j in range(5):
            one = jo.stack(n, d[i], wl[j], c[i, 0])
            np.testing.assert_allclose(float(res.R_p[i, j]), float(one.R_p), rtol=1e-14)
    jitted = jax.jit(jo.stack)(n, d[:, None], wl, c)
    mapped = jax.vmap(lambda w: jo.stack(n, d[:, None], w, c))(wl[:, None])
    np.testing.assert_allclose(np.asarray(jitted.R_s), np.asarray(res.R_s), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(mapped.R_s)[:, :, 0].T, np.asarray(res.R_s), rtol=1e-14)


def test_absorption_per_layer_compiles_to_loops_that_do_not_grow_with_the_layers():
    """The absorption of every inner layer (`A_s`, `A_p`) is masked and laid out as one array: the
    compiled program's fused loops are about as many for 24 layers as for 3 (the prefix sum of
    the attenuations adds a few, logarithmically). Masking each layer on its own and stacking
    them costs two loops per layer, and the compile time grows with them."""

    def fused_loops(L, N=64):
        args = (jnp.full((N, L + 2), 1.5 + 0.01j), jnp.full((L,), 100.0), jnp.full((N,), 500.0), jnp.full((N,), 0.8))
        fn = jax.jit(lambda *a: (lambda r: (r.A_s, r.A_p))(jo.stack(*a)))
        return fn.lower(*args).compile().as_text().count(" fusion(")

    assert fused_loops(24) - fused_loops(3) < 24 - 3


@pytest.mark.slow
def test_an_eager_call_is_one_compiled_program_and_a_traced_one_is_inlined():
    """Called eagerly, `stack` and `ellipsometry` run the kernel as one compiled program (a first
    call at a new shape compiles that program and a few operations of the checks, not each of the
    kernel's hundreds of operations), and a second call at that shape compiles nothing; inside a
    caller's trace the kernel is inlined: no nested call in the caller's jaxpr."""
    compiles = []
    listener = lambda event, duration, **kw: compiles.append(event) if event.endswith("backend_compile_duration") else None
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        rng = np.random.default_rng(5)
        for f in (jo.stack, jo.ellipsometry):
            for inc in ((), (1,)):
                # a shape no other test uses, so that nothing is compiled already
                n = np.concatenate([[1.0], 1.3 + rng.random(5) + 0.01j], dtype=complex)
                args = (n, np.array([90.0, 3e3, 40.0, 70.0]), np.linspace(400, 700, 13), np.full(13, 0.6))
                del compiles[:]
                jax.block_until_ready(f(*args, incoherent=inc))
                assert 1 <= len(compiles) <= 8, (f.__name__, inc, len(compiles))
                del compiles[:]
                jax.block_until_ready(f(args[0] * 1.01, *args[1:], incoherent=inc))
                assert compiles == [], (f.__name__, inc)
                eqns = jax.make_jaxpr(lambda *a: f(*a, incoherent=inc))(*args).jaxpr.eqns
                names = {str(e.params.get("name")) for e in eqns if e.primitive.name in ("pjit", "jit")}
                assert not any(name.endswith("_program") for name in names), (f.__name__, inc, names)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


@pytest.mark.parametrize("kwargs,match", [
    (dict(n=np.array([1.0, 1.5, 2.0]), d=np.array([10.0, 20.0])), r"d must have shape \(\.\.\., L-2\)"),
    (dict(n=np.array([1.0]), d=np.zeros(0)), "L >= 2"),
    (dict(incoherent=(1,)), "incoherent must hold positions"),
    (dict(incoherent=(0, 0)), "repeated"),
    (dict(d=np.array([-5.0])), r"d\[0\] = -5\.0: thicknesses must be finite and >= 0"),
    (dict(n=np.array([1.0 + 0.1j, 1.5, 2.0])), "incident medium"),
    (dict(n=np.array([1.0, 1.5 - 0.1j, 2.0])), r"n\[1\]"),
    (dict(wavelength=0.0), "wavelength"),
    (dict(d=np.array([1])), "floating dtype"),
])
def test_bad_input_raises_before_tracing(kwargs, match):
    args = dict(n=np.array([1.0, 1.5, 2.0]), d=np.array([10.0]), wavelength=500.0, cos_i=0.5)
    inc = kwargs.pop("incoherent", ())
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        jo.stack(args["n"], args["d"], args["wavelength"], args["cos_i"], incoherent=inc)


def test_negative_k_within_rounding_is_zero_and_gain_is_refused():
    """A k below zero by at most 1e-12 |n| (interpolating a k table near zero gives -1e-39) is
    rounding: taken as k = 0, eagerly and under jit, in stack and fresnel alike (tmm as oracle). A
    k further below zero is gain: refused before tracing, NaN inside jit."""
    n0 = np.array([1.0, 2.2046 + 0j, 3.8 + 0.01j])
    want = tmm.coh_tmm("s", list(n0), [np.inf, 100.0, np.inf], np.arccos(0.8), 500.0)["R"]
    for k in (-9.99e-40, -1e-15, -2.2e-12):
        n = n0 + np.array([0, 1j * k, 0])
        for f in (jo.stack, jax.jit(jo.stack)):
            np.testing.assert_allclose(float(f(n, np.array([100.0]), 500.0, 0.8).R_s), want, rtol=1e-12, atol=0)
        assert float(jo.fresnel(0.8, 1.0, 2.2046 + 1j * k)) == float(jo.fresnel(0.8, 1.0, 2.2046 + 0j))
    gain = n0 + np.array([0, -3e-12j, 0])
    with pytest.raises(ValueError, match=r"n\[1\] = \(2\.2046-3e-12j\).*at most 1e-12 \|n\| is rounding"):
        jo.stack(gain, np.array([100.0]), 500.0, 0.8)
    assert np.isnan(float(jax.jit(jo.stack)(gain, np.array([100.0]), 500.0, 0.8).R_s))
    assert np.isnan(float(jo.fresnel(0.8, 1.0, 2.2046 - 3e-12j)))


@pytest.mark.slow
def test_out_of_domain_inside_jit_is_nan():
    f = jax.jit(jo.stack)
    n = np.array([[1.0, 1.5, 2.0], [1.0, 1.5, -2.0], [1.0, 1.5 - 0.1j, 2.0], [1.0 + 0.1j, 1.5, 2.0]])
    res = f(n, np.array([[10.0], [10.0], [10.0], [10.0]]), 500.0, 0.5)
    assert np.isfinite(float(res.R[0]))
    assert np.all(np.isnan(np.asarray(res.R[1:]))) and np.all(np.isnan(np.asarray(res.A_s[1:])))
    res = f(np.array([1.0, 1.5, 2.0]), np.array([[-1.0], [np.inf]]), 500.0, 0.5)
    assert np.all(np.isnan(np.asarray(res.R))) and np.all(np.isnan(np.asarray(jnp.abs(res.r_s))))


@pytest.mark.slow
def test_jitted_float32_inner_layer_at_its_critical_angle():
    """Regression: under jit, XLA recomputed k_z^2 of a layer in several fused loops with different
    FMA contraction; where it is near 0 (the layer at its critical angle) the copies fell on both
    sides of 0, and the branch of the written-out root disagreed between them (R = 0.22 instead of
    1 for a lossless stack with the exit under TIR). Lossless, exit under TIR: R = 1 exactly."""
    rng = np.random.default_rng(7)
    K = 2000
    n0 = rng.uniform(1.5, 2.5, K)
    n1 = rng.uniform(1.0, n0 - 0.05)
    theta = np.arcsin(n1 / n0)
    n_exit = rng.uniform(0.5, 0.99, K) * n1  # below n0 sin(theta): TIR into the exit medium
    n = np.stack([n0, n0 * np.sin(theta), n_exit], -1).astype(np.complex64)
    d = rng.uniform(0, 300, (K, 1)).astype(np.float32)
    wl = rng.uniform(300, 1200, K).astype(np.float32)
    res = jax.jit(jo.stack)(n, d, wl, np.cos(theta).astype(np.float32))
    np.testing.assert_allclose(np.asarray(res.R_s), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(res.R_p), 1.0, atol=1e-5)


@pytest.mark.slow
def test_float32_absorption_in_front_of_a_thick_absorber():
    """Regression: the attenuation in front of each interface was formed as (total - suffix) of the
    layers' attenuations; with 10^5 nepers in a thick absorber behind a thin one, that difference
    lost about 0.02 nepers in float32 (2.7e-3 error in the thin layer's absorption). It is a prefix
    sum now: float32 agrees with float64 on the same inputs to float32 rounding."""
    n = np.array([1.0, 2.0 + 0.3j, 2.2 + 0.5j, 1.5], np.complex64)
    d = np.stack([np.linspace(5.0, 120.0, 50), np.geomspace(1e5, 3e7, 50)], -1).astype(np.float32)
    wl, c = np.float32(600.0), np.float32(0.8)
    a32 = jo.stack(n, d, wl, c).A
    a64 = jo.stack(n.astype(np.complex128), d.astype(np.float64), np.float64(wl), np.float64(c)).A
    np.testing.assert_allclose(np.asarray(a32, np.float64), np.asarray(a64), atol=2e-6)


# ---- large batches: blocks -----------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("inc", [(), (1,)])
def test_large_batches_in_blocks_agree_with_tmm(monkeypatch, inc):
    """Batches larger than `_BLOCK` points run in blocks (a `lax.map` over them). With a block of
    7 points, a (samples x points) batch of 45 (the last block partial) whose indices and
    thicknesses vary per sample and wavelength and angle per point (inputs broadcast on different
    axes) agrees with tmm point by point, and its gradients equal those of the batch in one
    block."""
    import jaxoptics._films._stack as S

    rng = np.random.default_rng(11)
    Sn, W, L = 5, 9, 5
    n, d, _, _ = _random_stacks(rng, Sn, L)
    if inc:
        d[:, 1] = rng.uniform(2e3, 5e4, Sn)
    wl = rng.uniform(300, 1200, W)
    theta = rng.uniform(0, np.deg2rad(85), W)
    args = (n[:, None, :], d[:, None, :], wl, np.cos(theta))

    def run(block):
        monkeypatch.setattr(S, "_BLOCK", block)
        loss = lambda n, d, w: jnp.sum(jo.stack(n, d, w, args[3], incoherent=inc).R * jnp.linspace(0.5, 1.5, W)[None])
        # a new function: traced anew, with this block size; values and gradients in one program
        return quick_jit(lambda *a: (jo.stack(*a, incoherent=inc), jax.grad(loss, argnums=(0, 1, 2))(*a[:3])))(*args)

    res, grads = run(7)
    compared = 0
    for s in range(Sn):
        for w in range(W):
            ref = _tmm_case(n[s], d[s], wl[w], theta[w], inc)
            if ref is None:
                continue
            compared += 1
            for pol in "sp":
                R, T, A, r, _ = ref[pol]
                np.testing.assert_allclose(np.asarray(getattr(res, f"R_{pol}"))[s, w], R, atol=1e-10, rtol=0)
                np.testing.assert_allclose(np.asarray(getattr(res, f"T_{pol}"))[s, w], T, atol=1e-10, rtol=0)
                np.testing.assert_allclose(np.asarray(getattr(res, f"A_{pol}"))[s, w], A, atol=1e-10, rtol=0)
                if not inc:
                    np.testing.assert_allclose(np.asarray(getattr(res, f"r_{pol}"))[s, w], r, atol=1e-10, rtol=0)
    assert compared >= 0.6 * Sn * W
    _, grads_one = run(10**6)
    for g, g1 in zip(grads, grads_one):
        assert np.all(np.isfinite(np.asarray(g)))
        np.testing.assert_allclose(np.asarray(g), np.asarray(g1), rtol=1e-11, atol=1e-13)


def test_blocks_are_equal_and_per_point_layers_arrive_layer_first():
    """`_chunked` cuts N points into ceil(N / block) blocks of ceil(N / blocks) points (100 points
    with blocks of at most 32: four of 25, none padded), hands a per-point argument to the kernel
    with its layer axis first and an argument of one point whole, and puts the results back in
    order."""
    import jaxoptics._films._stack as S

    x = np.arange(100.0).reshape(4, 25)  # per point
    lay = np.arange(300.0).reshape(4, 25, 3)  # per point, 3 layers
    one = np.array([[[7.0, 8.0, 9.0]]])  # one point, 3 layers
    seen = []

    def f(x, lay, one):
        seen.append((x.shape, lay.shape, one.shape))
        return {"x": x + 0 * lay[0], "first_layer": lay[0], "sum_one": jnp.broadcast_to(jnp.sum(one), x.shape)}

    out = S._chunked(f, ((x, 0), (lay, 1), (one, 1)), (4, 25), 32)
    assert seen == [((25,), (3, 25), (3, 1))]
    np.testing.assert_array_equal(np.asarray(out["x"]), x)
    np.testing.assert_array_equal(np.asarray(out["first_layer"]), lay[..., 0])
    np.testing.assert_array_equal(np.asarray(out["sum_one"]), 24.0)
    seen.clear()
    out = S._chunked(f, ((x.ravel()[:45], 0), (lay.reshape(100, 3)[:45], 1), (one[0], 1)), (45,), 7)
    assert seen == [((7,), (3, 7), (3, 1))]  # 7 blocks of 7: 4 padded points
    np.testing.assert_array_equal(np.asarray(out["first_layer"]), lay.reshape(100, 3)[:45, 0])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_layer_entries_against_mpmath(dtype):
    """A layer's scaled matrix entries (`_layer_cs`: c = g cos(delta), s = g a sin(delta) / delta,
    g = exp(-Im delta)) against mpmath: within 4 ulps of their modulus for decays from 0 to 100
    nepers and phases from 1e-12 to 1e6 radians (1e4 in float32), at multiples of pi/2, and for
    |delta| down to 1e-30; and exactly real where delta is real or imaginary (lossless layers)."""
    from jaxoptics._films._layers import _layer_cs

    rng = np.random.default_rng(3)
    K = 3000
    y = np.concatenate([10.0 ** rng.uniform(-12, 2, K), np.zeros(600), 10.0 ** rng.uniform(-12, 1, 600),
                        np.zeros(100), 10.0 ** rng.uniform(-30, -12, 100)])
    x = np.concatenate([rng.choice([-1, 1], K) * 10.0 ** rng.uniform(-12, 6 if dtype == np.float64 else 4, K),
                        np.pi / 2 * rng.integers(-4000, 4000, 200), np.pi / 2 * rng.integers(-100, 100, 200),
                        rng.uniform(-50, 50, 200), np.zeros(600), 10.0 ** rng.uniform(-30, -12, 100),
                        np.zeros(100)])
    a = 10.0 ** rng.uniform(-3, 3, len(x))
    x, y, a = x.astype(dtype), y.astype(dtype), a.astype(dtype)
    delta = jax.lax.complex(jnp.asarray(x), jnp.asarray(y))
    c, s = (np.asarray(v) for v in jax.jit(_layer_cs)(delta, jnp.asarray(a)))
    with mp.workdps(40):
        ref_c, ref_s = [], []
        for xi, yi, ai in zip(x, y, a):
            d = mp.mpc(float(xi), float(yi))
            g = mp.exp(-d.imag)
            ref_c.append(complex(g * mp.cos(d)))
            ref_s.append(complex(g * ai * (mp.sin(d) / d if d != 0 else 1)))
    eps = np.finfo(dtype).eps
    for got, ref in ((c, np.array(ref_c)), (s, np.array(ref_s))):
        err = np.abs(got - ref) / np.abs(ref) / eps
        assert err.max() < 4, (err.max(), x[np.argmax(err)], y[np.argmax(err)])
    lossless = (x == 0) | (y == 0)
    assert lossless.sum() >= 1400
    assert np.all(c.imag[lossless] == 0) and np.all(s.imag[lossless] == 0)


@pytest.mark.slow
def test_lossless_stack_under_tir_reflects_everything():
    """A stack of lossless layers lit near grazing incidence, with an evanescent wave in the last
    medium: R = 1 and no absorption in either dtype, to a few ulps, across the cavity resonances
    that the first interface and the last form there (their finesse grows like 1 / cos_i; the
    fields inside are then large against the incident one)."""
    n = np.array([1.3426915, 2.333902, 1.6949325, 2.4660966, 1.275991])
    d0 = np.linspace(100, 200, 20001)
    d = np.stack([d0, np.full_like(d0, 113.73018), np.full_like(d0, 41.285183)], -1)
    for dtype in (np.float32, np.float64):
        eps = np.finfo(dtype).eps
        for cos_i in (1e-2, 1e-4, 1e-6):
            res = jax.jit(jo.stack)(n.astype(dtype), d.astype(dtype), dtype(940.0), dtype(cos_i))
            for pol in "sp":
                R = np.asarray(getattr(res, f"R_{pol}"), np.float64)
                assert np.abs(R - 1).max() <= 8 * eps, (dtype, cos_i, pol, np.abs(R - 1).max())
                assert np.all(np.asarray(getattr(res, f"A_{pol}")) == 0)
                assert np.all(np.asarray(getattr(res, f"T_{pol}")) == 0)


@pytest.mark.slow
def test_ellipsometry_in_the_instrument_convention():
    """The conversion the docs state, against an independent transcription: the Airy formula of one
    film in the convention of Azzam-Bashara and Fujiwara (time dependence exp(+i omega t), index
    N = n - ik, rho = r_p / r_s with r_p = (N1 cos0 - N0 cos1) / (N1 cos0 + N0 cos1)). There
    Delta = pi - delta (mod 2 pi) and Psi = psi; a bare dielectric has Delta = 180 degrees below
    Brewster's angle."""
    rng = np.random.default_rng(5)
    K = 200
    n1 = rng.uniform(1.3, 2.5, K) + 1j * rng.uniform(0, 0.3, K)
    n2 = rng.uniform(1.5, 4.5, K) + 1j * rng.uniform(0, 2.0, K)
    d = rng.uniform(0, 400, K)
    wl = rng.uniform(300, 1000, K)
    th = rng.uniform(0, np.deg2rad(85), K)
    N0, N1, N2 = np.ones(K), np.conj(n1), np.conj(n2)  # n - ik

    def cos_in(N):  # exp(+i omega t): the wave decays into the medium when Im(N cos) <= 0
        c = np.sqrt(1 - (np.sin(th) / N) ** 2 + 0j)
        return np.where((N * c).imag > 0, -c, c)

    c0, c1, c2 = np.cos(th), cos_in(N1), cos_in(N2)
    beta = 2 * np.pi * d * N1 * c1 / wl
    rho = []
    for pol in "sp":
        if pol == "s":
            r01 = (N0 * c0 - N1 * c1) / (N0 * c0 + N1 * c1)
            r12 = (N1 * c1 - N2 * c2) / (N1 * c1 + N2 * c2)
        else:
            r01 = (N1 * c0 - N0 * c1) / (N1 * c0 + N0 * c1)
            r12 = (N2 * c1 - N1 * c2) / (N2 * c1 + N1 * c2)
        ph = np.exp(-2j * beta)
        rho.append((r01 + r12 * ph) / (1 + r01 * r12 * ph))
    ratio = rho[1] / rho[0]
    Psi, Delta = np.arctan(np.abs(ratio)), np.angle(ratio)
    e = jo.ellipsometry(np.stack([np.ones(K), n1, n2], -1), d[:, None], wl, np.cos(th))
    np.testing.assert_allclose(np.asarray(e.psi), Psi, rtol=1e-12, atol=1e-14)
    diff = (np.pi - np.asarray(e.delta) - Delta + np.pi) % (2 * np.pi) - np.pi
    assert np.max(np.abs(diff)) < 1e-10
    # a bare dielectric in that convention: 180 degrees below Brewster's angle, 0 beyond
    b = np.arctan(1.5)
    e = jo.ellipsometry(np.array([1.0, 1.5]), np.zeros(0), 500.0, np.cos(np.array([0.3, b - 0.1, b + 0.1])))
    np.testing.assert_allclose((np.pi - np.asarray(e.delta)) % (2 * np.pi), [np.pi, np.pi, 0.0], atol=1e-12)


@pytest.mark.slow
def test_psi_delta_agree_with_pyelli():
    """The instrument convention against a second peer: pyElli, which writes the index `n + ik`
    like jaxoptics but `rho = tan(Psi) exp(-i Delta)`, with its own 2x2 transfer matrices. Two-film
    stacks (one film absorbing) on an absorbing substrate, normal to grazing incidence: pyElli's
    Psi and Delta equal `psi` and `pi - delta` of `ellipsometry`, and the `psi_deg` and
    `delta_deg` that `fit_stack` fits."""
    import elli  # pyElli, a test dependency (the `tools` extra)
    rng = np.random.default_rng(11)
    K, wl, angles = 12, np.linspace(300.0, 1000.0, 7), np.array([0.0, 35.0, 70.0, 89.0])
    n1 = rng.uniform(1.3, 2.5, K) + 1j * rng.uniform(0, 0.3, K)
    n2 = rng.uniform(1.3, 2.5, K)
    ns = rng.uniform(1.5, 4.5, K) + 1j * rng.uniform(0, 3.0, K)
    d = np.stack([rng.uniform(0, 300, K), rng.uniform(0, 600, K)], -1)
    const = lambda n: elli.IsotropicMaterial(elli.ConstantRefractiveIndex(n=n))
    Psi, Delta = np.zeros((K, angles.size, wl.size)), np.zeros((K, angles.size, wl.size))
    for i in range(K):
        s = elli.Structure(elli.AIR, [elli.Layer(const(n1[i]), d[i, 0]), elli.Layer(const(n2[i]), d[i, 1])], const(ns[i]))
        for j, a in enumerate(angles):
            r = s.evaluate(wl, a, solver=elli.Solver2x2)
            Psi[i, j], Delta[i, j] = r.psi, r.delta
    wrap = lambda x: (x + 180) % 360 - 180
    n = np.stack([np.ones(K), n1, n2, ns], -1)[:, None, None, :]
    e = jo.ellipsometry(n, d[:, None, None, :], wl, np.cos(np.deg2rad(angles))[:, None])
    np.testing.assert_allclose(np.rad2deg(np.asarray(e.psi)), Psi, rtol=1e-10, atol=1e-10)
    assert np.max(np.abs(wrap(180 - np.rad2deg(np.asarray(e.delta)) - Delta))) < 1e-8
    free = lambda: jo.Free(1.0)
    sample = jo.Sample([jo.Layer(jo.Constant(free(), free()), free()), jo.Layer(jo.Constant(free()), free())], jo.Constant(free(), free()))
    wl_p, ang_p = np.tile(wl, angles.size), np.repeat(np.deg2rad(angles), wl.size)
    quantities = jax.jit(jax.vmap(lambda v: sample.with_values(v).quantities(("psi_deg", "delta_deg"), wl_p, ang_p)))
    assert sample.free_names() == ["layer1.n", "layer1.k", "layer2.n", "substrate.n", "substrate.k", "layer1.thickness_nm",
                                   "layer2.thickness_nm"]
    q = np.asarray(quantities(jnp.stack([n1.real, n1.imag, n2, ns.real, ns.imag, d[:, 0], d[:, 1]], -1)))
    q = q.reshape(K, 2, angles.size, wl.size)
    np.testing.assert_allclose(q[:, 0], Psi, rtol=1e-10, atol=1e-10)
    assert np.max(np.abs(wrap(q[:, 1] - Delta))) < 1e-8


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_vectorized_atan2_against_mpmath(dtype):
    """`_atan2` (the ellipsometric angles of `fit_stack`'s model) within 2 ulps of mpmath's
    atan2 over every octant and 20 decades of magnitude, at the ends of its reduction (|y/x| at
    tan(pi/8) and 1), on the axes with signed zeros as `np.arctan2`, NaN for non-finite input;
    its derivative is the closed form."""
    from jaxoptics._films._elementary import _atan2

    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(9)
    n = 4000
    mag = 10.0 ** rng.uniform(-10, 10, n)
    ang = rng.uniform(-np.pi, np.pi, n)
    y, x = mag * np.sin(ang), mag * np.cos(ang)
    edge = np.array([np.tan(np.pi / 8), 1.0])
    ys = np.concatenate([edge * (1 + np.array([[-4e-16], [0.0], [4e-16]])) for _ in range(1)]).ravel()
    y = np.concatenate([y, ys, -ys, ys, -ys, 1 / ys])
    x = np.concatenate([x, np.ones(ys.size), np.ones(ys.size), -np.ones(ys.size), -np.ones(ys.size), np.ones(ys.size)])
    y, x = y.astype(dtype), x.astype(dtype)
    got = np.asarray(_atan2(jnp.asarray(y), jnp.asarray(x)))
    assert got.dtype == dtype
    ref = np.array([float(mp.atan2(mp.mpf(float(a)), mp.mpf(float(b)))) for a, b in zip(y, x)])
    ulp = np.spacing(np.abs(ref).astype(dtype)).astype(np.float64)
    assert np.max(np.abs(got - ref) / ulp) <= 2.0
    z = dtype(0)
    special = [(z, z), (-z, z), (z, -z), (-z, -z), (z, dtype(-2)), (-z, dtype(-2)), (dtype(3), z), (dtype(-3), -z)]
    for a, b in special:
        assert np.asarray(_atan2(jnp.asarray(a), jnp.asarray(b))) == np.arctan2(a, b), (a, b)
    assert np.all(np.isnan(np.asarray(_atan2(jnp.asarray([np.inf, 1, np.nan], dtype), jnp.asarray([1, -np.inf, 1], dtype)))))
    yy, xx = jnp.asarray(y[:50]), jnp.asarray(x[:50])
    dy, dx = jax.vmap(jax.grad(_atan2, argnums=(0, 1)))(yy, xx)
    r2 = np.asarray(xx, np.float64) ** 2 + np.asarray(yy, np.float64) ** 2
    np.testing.assert_allclose(dy, np.asarray(xx) / r2, rtol=1e-5 if dtype == np.float32 else 1e-13)
    np.testing.assert_allclose(dx, -np.asarray(yy) / r2, rtol=1e-5 if dtype == np.float32 else 1e-13)
