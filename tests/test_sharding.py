"""Sharding over devices: run in a subprocess with 4 forced host devices (the device count is fixed
when JAX starts, so it cannot be changed inside this test process)."""

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent('''
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import jaxoptics as jo
    from jax.sharding import PartitionSpec as P

    assert len(jax.devices()) == 4, jax.devices()
    mesh = jo.batch_mesh()
    rng = np.random.default_rng(0)

    # kernels: sharded in, sharded out, equal to the single-device result
    c = rng.uniform(0, 1, 4000)
    cs, n = jo.shard_batch(c, mesh=mesh)
    for f in (lambda c: jo.fresnel(c, 1.0, 1.5), lambda c: jo.fresnel_rt(c, 1.5, 1.0)[1],
              lambda c: jo.fresnel_amplitudes(c, 1.0, 0.2 + 3j).r_p):
        for g in (f, jax.jit(f)):
            single = g(jnp.asarray(c))  # the same program on one device
            out = g(cs)
            assert out.sharding.spec == P("batch"), out.sharding
            assert np.allclose(np.asarray(out)[:4000], np.asarray(single), rtol=4e-16, atol=1e-300)
    i = rng.normal(size=(4000, 3)); i /= np.linalg.norm(i, axis=1, keepdims=True)
    ish, _ = jo.shard_batch(i, mesh=mesh)
    t, tir = jax.jit(lambda i: jo.refract(i, jnp.array([0.0, 0.0, 1.0]), 1.5, 1.0))(ish)
    assert t.sharding.spec[0] == "batch" and tir.sharding.spec == P("batch")
    t1, _ = jax.jit(lambda i: jo.refract(i, jnp.array([0.0, 0.0, 1.0]), 1.5, 1.0))(jnp.asarray(i))
    # The sharded program is compiled apart from the single-device one, and XLA may contract
    # multiply-adds into FMAs differently in each: equal to rounding, amplified only by the
    # conditioning near the critical angle (excluded within 1e-9 of it).
    away = np.abs(1.5 * np.hypot(i[:, 0], i[:, 1]) - 1.0) > 1e-9
    assert np.allclose(np.asarray(t)[away], np.asarray(t1)[away], rtol=0, atol=1e-13)

    # a batch that is not a multiple of the device count: padded, computed, trimmed
    out = jo.sharded_map(lambda c: jo.fresnel(c, 1.0, 1.5), c[:3998])
    assert out.shape == (3998,)
    assert np.allclose(np.asarray(out), np.asarray(jax.jit(lambda c: jo.fresnel(c, 1.0, 1.5))(c[:3998])), rtol=4e-16)
    padded = jo.sharded_map(lambda c: jo.fresnel(c, 1.0, 1.5), c[:3998], keep_padding=True)
    assert padded.shape == (4000,) and padded.sharding.spec == P("batch")

    # the fused interface kernel through the helper: pad, shard, run, trim; padded form stays sharded
    hit = jo.sharded_map(lambda i: jo.interface(i, jnp.array([0.0, 0.0, 1.0]), 1.0, 1.5), i[:3998])
    assert hit.t.shape == (3998, 3) and hit.R.shape == (3998,)
    hit_p = jo.sharded_map(lambda i: jo.interface(i, jnp.array([0.0, 0.0, 1.0]), 1.0, 1.5), i[:3998], keep_padding=True)
    assert hit_p.R.sharding.spec == P("batch") and hit_p.t.sharding.spec[0] == "batch"
    ref = jax.jit(lambda i: jo.interface(i, jnp.array([0.0, 0.0, 1.0]), 1.0, 1.5))(jnp.asarray(i[:3998]))
    assert np.allclose(np.asarray(hit.R), np.asarray(ref.R), rtol=1e-13, atol=1e-15)

    # fitting: a sharded batch of curves stays sharded and equals the single-device fit
    th = np.deg2rad(np.linspace(0, 85, 90))
    etas = np.linspace(1.1, 3.0, 2003)
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(1), jnp.asarray(etas), jnp.asarray(th), noise=1e-3))
    single = jo.fit_eta(th, R)
    Rs, _ = jo.shard_batch(R[:2000], mesh=mesh)
    res = jo.fit_eta(th, Rs)
    assert res.eta.sharding.spec == P("batch") and res.stderr.sharding.spec == P("batch")
    assert res.covariance.sharding.spec[0] == "batch"
    assert np.allclose(np.asarray(res.eta), np.asarray(single.eta[:2000]), rtol=1e-12, atol=0)
    res = jo.fit_eta_sharded(th, R, mesh=mesh)  # 2003 curves on 4 devices
    assert res.eta.shape == (2003,) and bool(jnp.all(res.converged))
    kept = jo.fit_eta_sharded(th, R, mesh=mesh, keep_padding=True)
    assert kept.eta.shape == (2004,) and kept.eta.sharding.spec == P("batch")
    assert np.allclose(np.asarray(res.eta), np.asarray(single.eta), rtol=1e-12, atol=0)
    print("SHARDING OK")
''')


def test_sharded_kernels_and_fits_on_four_devices():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "SHARDING OK" in out.stdout
