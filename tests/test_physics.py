"""Physics truths: closed forms, textbook values, invariants, and tmm as a peer oracle."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tmm

import jaxoptics as jo

DTYPES = [np.float32, np.float64]


def _tol(dtype, k=8):
    return k * float(np.finfo(dtype).eps)


def _rays(rng, n, dtype, max_theta=np.pi / 2):
    """Random unit normals (either orientation) and incident directions toward the surface."""
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    a = np.cross(nrm, rng.normal(size=(n, 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    th = rng.uniform(0, max_theta, size=n)
    i = np.sin(th)[:, None] * a - np.cos(th)[:, None] * nrm
    flip = rng.choice([-1.0, 1.0], size=(n, 1))
    return i.astype(dtype), (flip * nrm).astype(dtype), th


# ---- published values (Hecht, Optics, 5th ed., sec. 4.6; closed forms) ----

def test_textbook_values_glass():
    # Air to glass, n = 1.5: R at normal incidence 0.04, Brewster 56.31 deg, critical (glass to air) 41.81 deg.
    assert float(jo.fresnel(1.0, 1.0, 1.5)) == pytest.approx(0.04, abs=1e-15)
    assert np.rad2deg(float(jo.brewster_angle(1.0, 1.5))) == pytest.approx(56.3099, abs=1e-4)
    assert np.rad2deg(float(jo.critical_angle(1.5, 1.0))) == pytest.approx(41.8103, abs=1e-4)
    # Water (1.333): critical angle 48.6 deg (Hecht)
    assert np.rad2deg(float(jo.critical_angle(1.333, 1.0))) == pytest.approx(48.61, abs=1e-2)
    # At 45 deg air->glass: R_s = 0.0920, R_p = 0.0085 (closed form)
    Rs, Rp = jo.fresnel_sp(np.cos(np.pi / 4), 1.0, 1.5)
    ct = np.sqrt(1 - (np.sin(np.pi / 4) / 1.5) ** 2)
    ci = np.cos(np.pi / 4)
    assert float(Rs) == pytest.approx(((ci - 1.5 * ct) / (ci + 1.5 * ct)) ** 2, rel=1e-14)
    assert float(Rp) == pytest.approx(((1.5 * ci - ct) / (1.5 * ci + ct)) ** 2, rel=1e-14)
    assert float(Rs) == pytest.approx(0.0920, abs=1e-4) and float(Rp) == pytest.approx(0.0085, abs=1e-4)


@pytest.mark.parametrize("dtype", DTYPES)
def test_normal_incidence_and_brewster(dtype):
    e2 = np.array([1.2, 1.333, 1.5, 2.4, 4.0, 0.5], dtype)
    for a in (1.0, 1.7):
        r0 = ((a - e2) / (a + e2)) ** 2
        np.testing.assert_allclose(np.asarray(jo.fresnel(jnp.ones_like(e2), a, e2)), r0, rtol=_tol(dtype))
        np.testing.assert_allclose(np.asarray(jo.schlick(jnp.ones_like(e2), a, e2)), r0, rtol=_tol(dtype))
        # R_p vanishes at Brewster's angle: |r_p| is of the order of the rounding of cos(theta_B)
        cb = jnp.cos(jo.brewster_angle(dtype(a), jnp.asarray(e2)))
        _, Rp = jo.fresnel_sp(cb, dtype(a), jnp.asarray(e2))
        assert np.all(np.sqrt(np.asarray(Rp)) < _tol(dtype, 32))
        Rs, _ = jo.fresnel_sp(cb, dtype(a), jnp.asarray(e2))
        assert np.all(np.asarray(Rs) > 1e-3)


def test_tir_exactly_beyond_critical_angle():
    th_c = float(jo.critical_angle(1.5, 1.0))
    th = np.array([th_c - 1e-9, th_c + 1e-9, 1.2, 0.1])
    R = jo.fresnel(np.cos(th), 1.5, 1.0)
    assert float(R[1]) == 1.0 and float(R[2]) == 1.0 and float(R[0]) < 1.0
    i = np.stack([np.sin(th), 0 * th, -np.cos(th)], -1)
    t, tir = jo.refract(i, np.array([0.0, 0.0, 1.0]), 1.5, 1.0)
    np.testing.assert_array_equal(np.asarray(tir), [False, True, True, False])
    np.testing.assert_allclose(np.asarray(t[1:3]), np.asarray(jo.reflect(i[1:3], np.array([0.0, 0.0, 1.0]))), atol=0)
    # no critical angle when entering a denser medium: pi/2 by convention
    assert float(jo.critical_angle(1.0, 1.5)) == np.pi / 2 and float(jo.critical_angle(1.2, 1.2)) == np.pi / 2


def test_tir_phase_closed_form():
    """Under TIR |r| = 1 with arg r_s = -2 atan(kappa / k_i), arg r_p = -2 atan(eta1^2 kappa / (eta2^2 k_i))."""
    e1, e2 = 1.5, 1.0
    th = np.linspace(float(jo.critical_angle(e1, e2)) + 1e-3, np.pi / 2 - 1e-3, 50)
    c = np.cos(th)
    a = jo.fresnel_amplitudes(c, e1, e2)
    kappa = np.sqrt(e1**2 * np.sin(th) ** 2 - e2**2)
    np.testing.assert_allclose(np.abs(np.asarray(a.r_s)), 1, atol=4e-16)
    np.testing.assert_allclose(np.abs(np.asarray(a.r_p)), 1, atol=4e-16)
    np.testing.assert_allclose(np.angle(np.asarray(a.r_s)), -2 * np.arctan(kappa / (e1 * c)), atol=1e-13)
    np.testing.assert_allclose(np.angle(np.asarray(a.r_p)), -2 * np.arctan(e1**2 * kappa / (e2**2 * e1 * c)), atol=1e-13)


# ---- invariants over random rays ----

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("method", ["degreve", "bec", "heckbert"])
def test_refract_invariants(dtype, method):
    rng = np.random.default_rng(3)
    i, n, th = _rays(rng, 4000, dtype)
    e1 = rng.uniform(1.0, 2.5, size=4000).astype(dtype)
    e2 = rng.uniform(1.0, 2.5, size=4000).astype(dtype)
    t, tir = jo.refract(i, n, e1, e2, method=method)
    t, tir = np.asarray(t, np.float64), np.asarray(tir)
    i64, n64 = i.astype(np.float64), n.astype(np.float64)
    eps = float(np.finfo(dtype).eps)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1, atol=8 * eps)  # unit length, TIR too
    # coplanar with i and n
    assert np.max(np.abs(np.einsum("ij,ij->i", np.cross(i64, n64), t))) < 16 * eps
    # Snell: eta1 sin_i = eta2 sin_t (tangential components) where transmitted
    sin_i = np.linalg.norm(np.cross(i64, n64), axis=1)
    sin_t = np.linalg.norm(np.cross(t, n64), axis=1)
    ok = ~tir
    assert np.max(np.abs(e1[ok] * sin_i[ok] - e2[ok] * sin_t[ok]) / np.maximum(e1[ok], e2[ok])) < 32 * eps
    # t goes into medium 2 (same side as i), the reflection back
    side_i = np.sign(np.einsum("ij,ij->i", i64, n64))
    side_t = np.sign(np.einsum("ij,ij->i", t, n64))
    assert np.all(side_t[ok] == side_i[ok]) and np.all(side_t[tir] == -side_i[tir])
    # TIR exactly where eta1 sin_i > eta2
    margin = np.abs(e1 * sin_i - e2) > 1e3 * eps
    np.testing.assert_array_equal(tir[margin], (e1 * sin_i > e2)[margin])
    # independent of the normal's orientation (bitwise)
    t2, tir2 = jo.refract(i, -n, e1, e2, method=method)
    np.testing.assert_array_equal(np.asarray(t2, np.float64), t)
    np.testing.assert_array_equal(np.asarray(tir2), tir)


@pytest.mark.parametrize("dtype", DTYPES)
def test_every_method_is_independent_of_the_normals_orientation_in_a_compiled_program(dtype):
    """`refract` and `interface` give bit-identical results for `n` and `-n` with every method,
    inside a caller's `jit` with every input an argument (what a renderer runs: XLA fuses the
    kernel into the caller's program and contracts multiply-adds into FMAs)."""
    rng = np.random.default_rng(3)
    i, n, _ = _rays(rng, 4000, dtype)
    e1 = rng.uniform(1.0, 2.5, size=4000).astype(dtype)
    e2 = rng.uniform(1.0, 2.5, size=4000).astype(dtype)
    for method in ("degreve", "bec", "heckbert", "oliveira"):
        spec = jo.InterfaceSpec(outputs=("t", "tir", "r", "R", "T"), method=method)
        compiled = jax.jit(lambda *a: (jo.refract(*a, method=method), jo.interface(*a, spec=spec)))
        for a, b in zip(jax.tree_util.tree_leaves(compiled(i, n, e1, e2)), jax.tree_util.tree_leaves(compiled(i, -n, e1, e2))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=method)


@pytest.mark.parametrize("dtype", DTYPES)
def test_methods_agree(dtype):
    rng = np.random.default_rng(4)
    i, n, th = _rays(rng, 4000, dtype, max_theta=np.pi / 2 - 1e-2)
    e1 = rng.uniform(1.0, 2.5, size=4000).astype(dtype)
    e2 = rng.uniform(1.0, 2.5, size=4000).astype(dtype)
    td, tird = jo.refract(i, n, e1, e2)
    tb, tirb = jo.refract(i, n, e1, e2, method="bec")
    to, tiro = jo.refract(i, n, e1, e2, method="oliveira")
    np.testing.assert_array_equal(np.asarray(tird), np.asarray(tirb))
    np.testing.assert_array_equal(np.asarray(tird), np.asarray(tiro))
    # degreve and bec agree to rounding, except within rounding of the critical angle where the
    # direction has an infinite slope
    sin_i = np.linalg.norm(np.cross(i.astype(np.float64), n.astype(np.float64)), axis=1)
    cos_t2 = 1 - (e1 / e2) ** 2 * sin_i**2
    away = cos_t2 > 1e-3
    eps = float(np.finfo(dtype).eps)
    assert np.max(np.abs(np.asarray(td) - np.asarray(tb))[away]) < 64 * eps


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
def test_no_interface(dtype):
    """eta1 == eta2: R = 0 and T = 1 at every angle, grazing included, and t == i (bit for bit
    for exactly unit i; refract normalizes its inputs, so otherwise within the rounding of that)."""
    rng = np.random.default_rng(5)
    i, n, th = _rays(rng, 1000, dtype)
    g = np.cross(n[:10].astype(np.float64), rng.normal(size=(10, 3)))
    i[:10] = (g / np.linalg.norm(g, axis=1, keepdims=True)).astype(dtype)  # grazing
    axes = np.array([[0, 0, -1], [1, 0, 0], [0, -1, 0]], dtype)  # exactly unit: t == i bit for bit
    for eta in (1.0, 1.33, 2.7):
        t, tir = jo.refract(i, n, eta, eta)
        np.testing.assert_allclose(np.asarray(t), i, rtol=0, atol=2 * np.finfo(dtype).eps)
        assert not np.any(np.asarray(tir))
        t_ax, _ = jo.refract(axes, np.array([0.6, 0.0, 0.8], dtype), eta, eta)
        np.testing.assert_array_equal(np.asarray(t_ax), axes)
        c = np.concatenate([np.abs(np.einsum("ij,ij->i", i, n)), [0.0, 1.0]]).astype(dtype)
        R, T = jo.fresnel_rt(c, eta, eta)
        np.testing.assert_array_equal(np.asarray(R), 0)
        np.testing.assert_array_equal(np.asarray(T), 1)
        a = jo.fresnel_amplitudes(c, eta, eta)
        np.testing.assert_array_equal(np.asarray(a.r_s), 0)
        np.testing.assert_array_equal(np.asarray(a.t_p), 1)


@pytest.mark.parametrize("dtype", DTYPES)
def test_energy_conservation(dtype):
    rng = np.random.default_rng(6)
    c = rng.uniform(0, 1, 5000).astype(dtype)
    e1 = rng.uniform(0.5, 3, 5000).astype(dtype)
    e2 = rng.uniform(0.5, 3, 5000).astype(dtype)
    R, T = jo.fresnel_rt(c, e1, e2)
    np.testing.assert_allclose(np.asarray(R) + np.asarray(T), 1, atol=4 * float(np.finfo(dtype).eps))
    k = rng.uniform(0, 5, 5000).astype(dtype)
    R, T = jo.fresnel_rt(c, 1.0, jax.lax.complex(jnp.asarray(e2), jnp.asarray(k)))
    np.testing.assert_allclose(np.asarray(R) + np.asarray(T), 1, atol=16 * float(np.finfo(dtype).eps))
    assert np.all(np.asarray(T) >= 0)


def test_stokes_reciprocity():
    """Stokes relations: r' = -r and t t' = 1 - r^2, with r' the amplitude for the reverse path at
    the refraction angle (Hecht sec. 4.10)."""
    e1, e2 = 1.0, 1.5
    th = np.linspace(0, np.pi / 2 - 1e-6, 200)
    c = np.cos(th)
    ct = np.sqrt(1 - (e1 / e2 * np.sin(th)) ** 2)
    a = jo.fresnel_amplitudes(c, e1, e2)
    b = jo.fresnel_amplitudes(ct, e2, e1)
    for r, rr, t, tt in ((a.r_s, b.r_s, a.t_s, b.t_s), (a.r_p, b.r_p, a.t_p, b.t_p)):
        np.testing.assert_allclose(np.asarray(rr), -np.asarray(r), atol=1e-13)
        np.testing.assert_allclose(np.asarray(t) * np.asarray(tt), 1 - np.asarray(r) ** 2, atol=1e-13)


@pytest.mark.slow
def test_fresnel_against_tmm():
    """A peer implementation: tmm (transfer matrices), a single interface between two half-spaces,
    real and complex indices (including metals), s and p, amplitudes and powers."""
    cases = [(1.0, 1.5), (1.5, 1.0), (1.0, 0.2 + 3.0j), (1.0, 2.5 + 2.5j), (1.33, 1.0 + 0.1j), (1.0, 4.0 + 0.0j)]
    for n1, n2 in cases:
        for th in np.linspace(0, np.deg2rad(89), 45):
            c = np.cos(th)
            amp = jo.fresnel_amplitudes(c, n1, n2)
            R_s, R_p = jo.fresnel_sp(c, n1, n2)
            for pol, r, R in (("s", amp.r_s, R_s), ("p", amp.r_p, R_p)):
                out = tmm.coh_tmm(pol, [n1, n2], [np.inf, np.inf], th, 0.5)
                assert complex(r) == pytest.approx(complex(out["r"]), abs=1e-12), (n1, n2, th, pol)
                assert float(R) == pytest.approx(float(out["R"]), abs=1e-12)
                t = amp.t_s if pol == "s" else amp.t_p
                assert complex(t) == pytest.approx(complex(out["t"]), abs=1e-12), (n1, n2, th, pol)
                if n1 < np.real(n2) or np.imag(n2) > 0:  # tmm's T is the Poynting flux into medium 2
                    R_, T_ = jo.fresnel_rt(c, n1, n2)
                    Ts = tmm.coh_tmm("s", [n1, n2], [np.inf, np.inf], th, 0.5)["T"]
                    Tp = tmm.coh_tmm("p", [n1, n2], [np.inf, np.inf], th, 0.5)["T"]
                    assert float(T_) == pytest.approx((Ts + Tp) / 2, abs=1e-12)
