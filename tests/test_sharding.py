"""Every public entry point that takes a batch, on 4 forced host devices: the batch sharded along
its first axis, the answer equal to the single-device one and (where the entry point keeps it)
sharded the same way. Run in a subprocess: the device count is fixed when JAX starts."""

import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.slow  # the quick subset (-m "not slow") leaves this file out

SCRIPT = textwrap.dedent('''
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import jaxoptics as jo
    from jax.sharding import NamedSharding, PartitionSpec as P

    assert len(jax.devices()) == 4, jax.devices()
    mesh = jo.batch_mesh()
    rng = np.random.default_rng(0)
    on_mesh = lambda x: jax.device_put(x, NamedSharding(mesh, P("batch", *([None] * (np.ndim(x) - 1)))))

    def same(a, b, rtol, atol=0.0, what=""):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and np.allclose(a, b, rtol=rtol, atol=atol, equal_nan=True), (what, a, b)

    def sharded(x, what):
        assert isinstance(x.sharding, NamedSharding) and x.sharding.spec[0] == "batch", (what, x.sharding)

    # ---- kernels: sharded in, sharded out, equal to the single-device result --------------------
    c = rng.uniform(0, 1, 400)
    cs, n = jo.shard_batch(c, mesh=mesh)
    for name, f in (("fresnel", lambda c: jo.fresnel(c, 1.0, 1.5)), ("fresnel_rt", lambda c: jo.fresnel_rt(c, 1.5, 1.0)[1]),
                    ("fresnel_amplitudes", lambda c: jo.fresnel_amplitudes(c, 1.0, 0.2 + 3j).r_p)):
        for g in (f, jax.jit(f)):
            out = g(cs)
            assert out.sharding.spec == P("batch"), (name, out.sharding)
            same(out, g(jnp.asarray(c)), 4e-16, 1e-300, name)
    i = rng.normal(size=(400, 3)); i /= np.linalg.norm(i, axis=1, keepdims=True)
    ish, _ = jo.shard_batch(i, mesh=mesh)
    refr = jax.jit(lambda i: jo.refract(i, jnp.array([0.0, 0.0, 1.0]), 1.5, 1.0))
    (t, tir), (t1, _) = refr(ish), refr(jnp.asarray(i))
    sharded(t, "refract"); sharded(tir, "refract")
    # The sharded program is compiled apart from the single-device one, and XLA may contract
    # multiply-adds into FMAs differently in each: equal to rounding, amplified only by the
    # conditioning near the critical angle (excluded within 1e-9 of it).
    away = np.abs(1.5 * np.hypot(i[:, 0], i[:, 1]) - 1.0) > 1e-9
    same(np.asarray(t)[away], np.asarray(t1)[away], 0, 1e-13, "refract")

    # a batch that is not a multiple of the device count: padded, computed, trimmed
    out = jo.sharded_map(lambda c: jo.fresnel(c, 1.0, 1.5), c[:398])
    same(out, jax.jit(lambda c: jo.fresnel(c, 1.0, 1.5))(c[:398]), 4e-16, 0, "sharded_map")
    padded = jo.sharded_map(lambda c: jo.fresnel(c, 1.0, 1.5), c[:398], keep_padding=True)
    assert padded.shape == (400,) and padded.sharding.spec == P("batch")

    # the fused kernels: interface and scene_interface
    up = jnp.array([0.0, 0.0, 1.0])
    metal = jo.InterfaceSpec(outputs=("r", "R", "R_s", "R_p"), complex_index=True)
    for f in (lambda i: jo.interface(i, up, 1.0, 1.5), lambda i: jo.interface(i, up, 1.0, 0.2 + 3.0j, spec=metal)):
        hit, ref = jax.jit(f)(ish), jax.jit(f)(jnp.asarray(i))
        sharded(hit.R, "interface"); sharded(hit.r, "interface")
        same(hit.R, ref.R, 1e-13, 1e-15, "interface R")
    kind = np.arange(400) % 5
    spec = jo.SceneSpec(kinds=("mirror", "dielectric", "conductor", "thin_dielectric", "coated_dielectric"),
                        wavelengths=(630.0, 532.0, 465.0))
    eta2 = np.where(kind == 2, 0.2 + 3.0j, 1.5 + 0j)
    scene = lambda i, k, e: jo.scene_interface(i, up, k, 1.0, e, scene=spec, film_eta=1.38, film_d=120.0)
    h, ref = jax.jit(scene)(ish, on_mesh(kind), on_mesh(eta2)), jax.jit(scene)(jnp.asarray(i), kind, eta2)
    sharded(h.R, "scene_interface")
    same(h.R, ref.R, 1e-12, 1e-15, "scene_interface R")

    # stacks and ellipsometry: indices per point, sharded along the points
    L = 5
    nn = np.concatenate([np.ones((400, 1)), rng.uniform(1.3, 2.4, (400, L - 2)) + 1j * rng.uniform(0, 0.1, (400, L - 2)),
                         np.full((400, 1), 3.9 + 0.02j)], 1)
    d = rng.uniform(10, 300, (400, L - 2))
    wl = rng.uniform(300, 900, 400)
    ci = rng.uniform(0.2, 1.0, 400)
    args = [on_mesh(a) for a in (nn, d, wl, ci)]
    for name, f in (("stack", lambda *a: jo.stack(*a).R_p), ("ellipsometry", lambda *a: jo.ellipsometry(*a).delta)):
        for g in (f, jax.jit(f)):
            out = g(*args)
            sharded(out, name)
            same(out, g(nn, d, wl, ci), 1e-12, 1e-14, name)

    # ---- fits ------------------------------------------------------------------------------------
    # a batch of 64 curves of 60 angles, 16 per device: the size of a shipped program
    th = np.linspace(0.05, 1.4, 60)
    etas = np.linspace(1.3, 1.8, 64)
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(1), jnp.asarray(etas), jnp.asarray(th), noise=1e-3))
    single = jo.fit_eta(th, R, eta1=1.0)
    res = jo.fit_eta(th, on_mesh(R), eta1=1.0)
    for field in ("eta", "stderr", "covariance", "converged"):
        sharded(getattr(res, field), "fit_eta " + field)
    same(res.eta, single.eta, 1e-12, 0, "fit_eta")
    same(res.stderr, single.stderr, 1e-9, 0, "fit_eta stderr")
    res = jo.fit_eta_sharded(th, R[:63], mesh=mesh)  # 63 curves on 4 devices: padded, trimmed
    same(res.eta, single.eta[:63], 1e-12, 0, "fit_eta_sharded")
    kept = jo.fit_eta_sharded(th, R[:63], mesh=mesh, keep_padding=True)
    assert kept.eta.shape == (64,) and kept.eta.sharding.spec == P("batch")

    # a dispersion law over 8 wavelengths, the curves sharded along the wavelengths
    lam = np.linspace(0.4, 1.0, 8)
    n_lam = 1.45 + 0.004 / lam**2
    Rl = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(2), jnp.asarray(n_lam), jnp.asarray(th), noise=1e-4))
    one = jo.fit_dispersion(lam, th, Rl, model="cauchy", terms=2, sigma=1e-4)
    many = jo.fit_dispersion(lam, th, on_mesh(Rl), model="cauchy", terms=2, sigma=1e-4)
    assert bool(one.converged) and bool(many.converged)
    same(many.coefficients, one.coefficients, 1e-9, 0, "fit_dispersion")
    same(many.index(lam)[1], one.index(lam)[1], 1e-6, 0, "fit_dispersion stderr")

    # a map of 6 film sites over 2 devices, and 5 of them (padded to 6): the same fit as on one
    # device (each device compiles its own program: two devices show the path at half the cost;
    # the single-device answer fits the map's two halves, with the program of a device's block)
    wl_nm = np.linspace(400, 800, 41)
    d_true = np.array([95.0, 102.0, 110.0, 121.0, 133.0, 140.0])
    film = lambda t: jo.Sample([jo.Layer(jo.Cauchy(A=1.46, B=0.0035), t, name="film")], 3.9 + 0.02j)
    truth = np.stack([np.asarray(film(t).fixed().quantities(("psi_deg", "delta_deg"), jnp.asarray(wl_nm),
                                                              jnp.deg2rad(jnp.full(41, 70.0)))) for t in d_true])
    values = {k: truth[:, q] + 0.01 * rng.normal(size=(6, 41)) for q, k in enumerate(("psi_deg", "delta_deg"))}
    spectra = jo.make_spectra(wl_nm, 70.0, values)
    model = film(jo.Free(100.0, 50.0, 200.0))
    two = jo.batch_mesh(devices=jax.devices()[:2])
    halves = [jo.fit_stack(model, spectra._replace(values=spectra.values[h])) for h in (slice(0, 3), slice(3, 6))]
    a = jax.tree.map(lambda *x: jnp.concatenate(x), *halves)
    b = jo.fit_stack(model, spectra, mesh=two)
    assert bool(np.all(np.asarray(a.converged))) and bool(np.all(np.asarray(b.converged)))
    for field in ("values", "stderr", "covariance", "chi2_reduced", "converged"):
        sharded(getattr(b, field), "fit_stack " + field)
    sd = np.asarray(a.stderr)
    same(np.abs(np.asarray(b.values) - np.asarray(a.values)) <= 1e-3 * sd, np.ones_like(sd, bool), 0, 0, "fit_stack values")
    same(b.stderr, a.stderr, 1e-3, 0, "fit_stack stderr")
    five = spectra._replace(values=spectra.values[:5])
    c = jo.fit_stack(model, five, mesh=two)  # padded to 3 sites a device, trimmed
    assert c.values.shape == (5, 1)
    same(np.abs(np.asarray(c.values) - np.asarray(a.values)[:5]) <= 1e-3 * sd[:5], np.ones((5, 1), bool), 0, 0,
         "fit_stack padded")
    print("SHARDING OK")
''')


def test_every_batched_entry_point_on_four_devices():
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4".strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "SHARDING OK" in out.stdout
