"""The fused, scene-specialized interface kernel: equal to the separate kernels, and only what
the spec asks for is computed."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxoptics as jo


def _rays(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    a = np.cross(nrm, rng.normal(size=(n, 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    th = rng.uniform(0, np.pi / 2, n)
    i = np.sin(th)[:, None] * a - np.cos(th)[:, None] * nrm
    return i, nrm * rng.choice([-1.0, 1.0], size=(n, 1)), rng.uniform(0.6, 2.5, n)


def test_full_interface_equals_separate_kernels():
    i, n, e2 = _rays()
    x = jax.jit(lambda i, n, e2: jo.interface(i, n, 1.3, e2))(i, n, e2)
    t, tir = jax.jit(lambda i, n, e2: jo.refract(i, n, 1.3, e2))(i, n, e2)
    np.testing.assert_array_equal(np.asarray(x.tir), np.asarray(tir))
    np.testing.assert_allclose(np.asarray(x.t), np.asarray(t), atol=1e-15)
    np.testing.assert_allclose(np.asarray(x.r), np.asarray(jo.reflect(i, n)), atol=4e-16)
    # R and T against fresnel_rt at the same cosine, away from the critical angle's rounding
    c = np.abs(np.einsum("ij,ij->i", i, n))
    R, T = jo.fresnel_rt(c, 1.3, e2)
    away = np.abs(1.3 * np.sqrt(1 - c**2) - e2) > 1e-6
    np.testing.assert_allclose(np.asarray(x.R)[away], np.asarray(R)[away], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(x.T)[away], np.asarray(T)[away], rtol=1e-12, atol=1e-15)
    assert x.R_s is None and x.R_p is None


@pytest.mark.parametrize("fresnel,ref", [("schlick", jo.schlick), ("schlick_tir", jo.schlick_tir)])
def test_schlick_models(fresnel, ref):
    i, n, e2 = _rays(seed=1)
    x = jo.interface(i, n, 1.3, e2, spec=jo.InterfaceSpec(outputs=("R", "T"), fresnel=fresnel))
    c = np.abs(np.einsum("ij,ij->i", i, n))
    away = np.abs(1.3 * np.sqrt(1 - c**2) - e2) > 1e-6
    np.testing.assert_allclose(np.asarray(x.R)[away], np.asarray(ref(c, 1.3, e2))[away], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(x.R + x.T), 1, atol=1e-15)


@pytest.mark.slow
def test_only_requested_outputs_are_traced():
    i, n, e2 = _rays(100)
    spec = jo.InterfaceSpec(outputs=("R",))
    x = jo.interface(i, n, 1.0, e2, spec=spec)
    assert x.t is None and x.r is None and x.tir is None
    def flops(f):
        cost = jax.jit(f).lower(i, n, e2).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        return cost["flops"]

    full = flops(lambda i, n, e: jo.interface(i, n, 1.0, e))
    only_r = flops(lambda i, n, e: jo.interface(i, n, 1.0, e, spec=spec))
    lean = flops(lambda i, n, e: jo.interface(i, n, 1.0, e, spec=jo.InterfaceSpec(outputs=("R",), fresnel="schlick",
                                                                                     check_inputs=False)))
    assert lean < only_r < full, (lean, only_r, full)
    no_tir = jo.InterfaceSpec(outputs=("t", "R"), tir_possible=False, check_inputs=False)
    e_dense = 1.0 + e2  # every ray enters a denser medium
    y = jo.interface(i, n, 1.0, e_dense, spec=no_tir)
    z = jo.interface(i, n, 1.0, e_dense)
    np.testing.assert_allclose(np.asarray(y.t), np.asarray(z.t), atol=1e-15)
    np.testing.assert_allclose(np.asarray(y.R), np.asarray(z.R), atol=1e-15)


def test_conductor_and_polarized_outputs():
    i, n, e2 = _rays(500, seed=2)
    eta = jax.lax.complex(jnp.asarray(e2), 2.0 * jnp.asarray(e2))
    x = jo.interface(i, n, 1.0, eta, spec=jo.InterfaceSpec(outputs=("r", "R", "R_s", "R_p"), complex_index=True))
    c = np.abs(np.einsum("ij,ij->i", i, n))
    R_s, R_p = jo.fresnel_sp(c, 1.0, eta)
    np.testing.assert_allclose(np.asarray(x.R_s), np.asarray(R_s), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(x.R_p), np.asarray(R_p), rtol=1e-12)
    with pytest.raises(ValueError, match="no transmitted direction"):
        jo.interface(i, n, 1.0, eta, spec=jo.InterfaceSpec(outputs=("t",), complex_index=True))
    with pytest.raises(ValueError, match="unknown outputs"):
        jo.interface(i, n, 1.0, e2, spec=jo.InterfaceSpec(outputs=("X",)))


@pytest.mark.slow
def test_scene_interface_selects_by_material():
    i, n, e2 = _rays(1200, seed=3)
    kinds = ("mirror", "dielectric", "conductor", "thin_dielectric")
    k = np.arange(1200) % 4
    eta = e2 * (1 + 0.5j)
    h = jax.jit(lambda i, n, k, e: jo.scene_interface(i, n, k, 1.0, e, scene=jo.SceneSpec(kinds=kinds)))(i, n, k, eta)
    c = np.abs(np.einsum("ij,ij->i", i, n))
    np.testing.assert_array_equal(np.asarray(h.R)[k == 0], 1.0)
    np.testing.assert_allclose(np.asarray(h.R)[k == 1], np.asarray(jo.fresnel(c, 1.0, e2))[k == 1], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(h.R)[k == 2], np.asarray(jo.fresnel(c, 1.0, eta))[k == 2], rtol=1e-12)
    R1 = np.asarray(jo.fresnel(c, 1.0, e2))[k == 3]
    np.testing.assert_allclose(np.asarray(h.R)[k == 3], 2 * R1 / (1 + R1), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(h.t)[k == 3], i[k == 3], atol=1e-15)
    np.testing.assert_allclose(np.asarray(h.R + h.T)[k != 2], 1, atol=1e-15)
    bad = jo.scene_interface(i[:2], n[:2], np.array([7, 1]), 1.0, e2[:2], scene=jo.SceneSpec(kinds=("mirror", "dielectric")))
    assert np.isnan(float(bad.R[0])) and np.isfinite(float(bad.R[1]))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("outputs", [("r", "t", "tir", "R", "T"), ("t", "R", "T"), ("R", "T")])
def test_jitted_R_plus_T_is_one(dtype, outputs):
    """R and T come from separate loops (XLA on the CPU has no multi-output fusion); they must still
    read the same k_t^2, cos_i and sin^2, or near the critical angle R + T - 1 grows to hundreds of
    eps (seen: 244 eps in float32 when R shared a loop with the refracted direction). Random
    directions and indices, both sides of every interface, jitted."""
    rng = np.random.default_rng(3)
    N = 100_000
    i, n = rng.normal(size=(N, 3)).astype(dtype), rng.normal(size=(N, 3)).astype(dtype)
    e1, e2 = rng.uniform(0.5, 3, N).astype(dtype), rng.uniform(0.5, 3, N).astype(dtype)
    x = jax.jit(lambda i, n, a, b: jo.interface(i, n, a, b, spec=jo.InterfaceSpec(outputs=outputs)))(i, n, e1, e2)
    assert float(jnp.max(jnp.abs(x.R + x.T - 1))) <= 2 * np.finfo(dtype).eps


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_outputs_agree_on_tir_within_ulps_of_the_critical_angle(dtype):
    """Jitted, at 0 to 4 ulps around the critical cosine: every output makes the same TIR decision
    as the returned mask (R = 1 and T = 0 exactly, t the reflected direction; elsewhere Snell's law
    holds). XLA recomputes shared values in each fused loop and may contract multiply-adds
    differently in each; before k_t^2 was materialized once, R came out below 1 under a TIR mask
    (570 of 10^6 stress-test inputs, in both dtypes)."""
    rng = np.random.default_rng(5)
    m = 4000
    e1 = np.exp(rng.uniform(np.log(0.5), np.log(3.0), m)).astype(dtype)
    e2 = (e1 * np.exp(rng.uniform(np.log(1e-3), np.log(0.999), m))).astype(dtype)
    cc = (np.sqrt((e1.astype(np.float64) - e2) * (e1.astype(np.float64) + e2)) / e1).astype(dtype)
    k = rng.integers(-4, 5, m)
    c = np.array([np.nextafter(x, dtype(np.inf) if s > 0 else dtype(0)) if s else x for x, s in zip(cc, np.sign(k))], dtype)
    for _ in range(3):  # up to 4 ulps away
        step = np.abs(k) > 1 + _
        c = np.where(step, np.nextafter(c, np.where(k > 0, dtype(np.inf), dtype(0))), c).astype(dtype)
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    a = np.cross(nrm, rng.normal(size=(m, 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    c64 = c.astype(np.float64)
    i = (np.sqrt(1 - c64**2)[:, None] * a - c64[:, None] * nrm).astype(dtype)
    n = (nrm * rng.choice([-1.0, 1.0], size=(m, 1))).astype(dtype)
    x = jax.jit(jo.interface)(i, n, e1, e2)
    tir = np.asarray(x.tir)
    assert 0 < tir.sum() < m  # both sides of the critical angle are exercised
    R, T, t, r = (np.asarray(v, np.float64) for v in (x.R, x.T, x.t, x.r))
    assert np.all(R[tir] == 1) and np.all(T[tir] == 0)
    eps = float(np.finfo(dtype).eps)
    np.testing.assert_allclose(t[tir], r[tir], rtol=0, atol=2 * eps)  # r may be rounded apart in its own loop
    i64, n64 = i.astype(np.float64), n.astype(np.float64)
    sin_i = np.linalg.norm(np.cross(i64, n64), axis=1) / np.linalg.norm(i64, axis=1)
    sin_t = np.linalg.norm(np.cross(t, n64), axis=1)
    snell = np.abs(e1 * sin_i - e2 * sin_t) / np.maximum(e1, e2)
    assert np.max(snell[~tir]) < 16 * eps


@pytest.mark.slow
def test_scene_interface_coated_kinds_against_tmm():
    """Coated dielectric and conductor: R and T per wavelength are those of the three-medium
    stack (checked against tmm, unpolarized), directions and the TIR mask as without the film,
    uncoated kinds repeat their value over the spectral axis."""
    import tmm

    rng = np.random.default_rng(4)
    N = 12
    i = rng.normal(size=(N, 3))
    i /= np.linalg.norm(i, axis=-1, keepdims=True)
    n = np.tile([0.0, 0.0, 1.0], (N, 1))
    kind = np.arange(N) % 3
    kinds = ("dielectric", "coated_dielectric", "coated_conductor")
    wls = (450.0, 550.0, 650.0)
    eta1 = np.where(np.arange(N) % 2 == 0, 1.0, 1.6)  # some hits from the denser side: TIR
    eta2 = np.where(kind == 2, 0.2 + 3.0j, 1.2 + 0j)
    film_eta = rng.uniform(1.3, 2.4, N) + 1j * rng.uniform(0, 0.05, N)
    film_d = rng.uniform(0, 400, N)
    scene = jo.SceneSpec(kinds=kinds, wavelengths=wls)
    h = jax.jit(lambda *a: jo.scene_interface(*a, scene=scene, film_eta=film_eta, film_d=film_d))(i, n, kind, eta1, eta2)
    assert h.R.shape == (N, 3) and h.T.shape == (N, 3)
    plain = jo.scene_interface(i, n, kind, eta1, eta2.real, scene=jo.SceneSpec(kinds=("dielectric",) * 3))
    for k in range(N):
        th = np.arccos(abs(i[k] @ n[k]))
        if kind[k] == 0:
            np.testing.assert_allclose(np.asarray(h.R[k]), float(plain.R[k]), rtol=1e-15)
            continue
        for w, wl in enumerate(wls):
            args = ([eta1[k], film_eta[k], eta2[k]], [np.inf, film_d[k], np.inf], th, wl)
            R = 0.5 * (tmm.coh_tmm("s", *args)["R"] + tmm.coh_tmm("p", *args)["R"])
            T = 0.5 * (tmm.coh_tmm("s", *args)["T"] + tmm.coh_tmm("p", *args)["T"])
            np.testing.assert_allclose(float(h.R[k, w]), R, atol=1e-12)
            np.testing.assert_allclose(float(h.T[k, w]), 0.0 if kind[k] == 2 else T, atol=1e-12)
        if kind[k] == 1:  # directions and TIR of the bare dielectric
            np.testing.assert_allclose(np.asarray(h.t[k]), np.asarray(plain.t[k]), atol=1e-15)
            assert bool(h.tir[k]) == bool(plain.tir[k])
    assert np.any(np.asarray(h.tir))
    g = jax.grad(lambda fd: jo.scene_interface(i, n, kind, eta1, eta2, scene=scene, film_eta=film_eta, film_d=fd).R.sum())(film_d)
    assert np.all(np.isfinite(np.asarray(g)))


def test_scene_interface_coating_errors():
    i, n = np.array([[0.0, 0.6, -0.8]]), np.array([[0.0, 0.0, 1.0]])
    coated = jo.SceneSpec(kinds=("coated_dielectric",), wavelengths=(550.0,))
    with pytest.raises(ValueError, match="need SceneSpec.wavelengths"):
        jo.scene_interface(i, n, np.array([0]), 1.0, 1.5, scene=coated._replace(wavelengths=()), film_eta=1.38, film_d=100.0)
    with pytest.raises(ValueError, match="need film_eta and film_d"):
        jo.scene_interface(i, n, np.array([0]), 1.0, 1.5, scene=coated)
    with pytest.raises(ValueError, match="no coated kind"):
        jo.scene_interface(i, n, np.array([0]), 1.0, 1.5, film_eta=1.38, film_d=100.0)
    with pytest.raises(ValueError, match=r"film_d\[0\] = -1.0"):
        jo.scene_interface(i, n, np.array([0]), 1.0, 1.5, scene=coated, film_eta=1.38, film_d=np.array([-1.0]))
