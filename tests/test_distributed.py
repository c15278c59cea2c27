"""JAX's multi-process runtime (`jax.distributed`): 2 processes on localhost with 2 CPU devices
each, one global mesh of 4 devices. Kernels and fits take arrays that span both processes (made
from each process's own data), every process computes its own shards, and each shard equals the
single-process answer for its rows. Both processes run under a time limit and are ended by the
test."""

import os
import socket
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.slow  # the quick subset (-m "not slow") leaves this file out

WORKER = textwrap.dedent('''
    import sys
    import jax
    jax.config.update("jax_enable_x64", True)
    pid, port = int(sys.argv[1]), sys.argv[2]
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=pid,
                               initialization_timeout=120)
    import jax.numpy as jnp
    import numpy as np
    import jaxoptics as jo
    from jax.sharding import NamedSharding, PartitionSpec as P

    assert jax.process_count() == 2 and len(jax.devices()) == 4 and len(jax.local_devices()) == 2
    mesh = jo.batch_mesh()
    spec = lambda a: NamedSharding(mesh, P("batch", *([None] * (np.ndim(a) - 1))))
    # every process knows the whole batch here only to check its answer; the global array is made
    # from the rows each process holds, as a host would make it from its own files
    glob = lambda a: jax.make_array_from_callback(np.shape(a), spec(a), lambda idx: a[idx])

    def check_local(out, ref, rtol, atol, what):
        """`out` spans the mesh; each of this process's shards equals `ref` (NumPy, whole) there."""
        assert out.shape == np.shape(ref) and not out.is_fully_addressable, (what, out.shape)
        assert out.sharding.spec[0] == "batch", (what, out.sharding)
        for s in out.addressable_shards:
            np.testing.assert_allclose(np.asarray(s.data), np.asarray(ref)[s.index], rtol=rtol, atol=atol, err_msg=what)

    rng = np.random.default_rng(0)
    # ---- kernels ---------------------------------------------------------------------------------
    L, N = 5, 64
    nn = np.concatenate([np.ones((N, 1)), rng.uniform(1.3, 2.4, (N, L - 2)) + 1j * rng.uniform(0, 0.1, (N, L - 2)),
                         np.full((N, 1), 3.9 + 0.02j)], 1)
    d, wl, ci = rng.uniform(10, 300, (N, L - 2)), rng.uniform(300, 900, N), rng.uniform(0.2, 1.0, N)
    args = [glob(a) for a in (nn, d, wl, ci)]
    check_local(jo.stack(*args).R_p, jo.stack(nn, d, wl, ci).R_p, 1e-12, 1e-14, "stack")
    check_local(jo.ellipsometry(*args).delta, jo.ellipsometry(nn, d, wl, ci).delta, 1e-12, 1e-14, "ellipsometry")
    i = rng.normal(size=(N, 3)); i /= np.linalg.norm(i, axis=1, keepdims=True)
    up = jnp.array([0.0, 0.0, 1.0])
    hit = jax.jit(lambda i: jo.interface(i, up, 1.0, 1.5))
    check_local(hit(glob(i)).R, hit(i).R, 1e-13, 1e-15, "interface")
    kind = np.arange(N) % 5
    scene_spec = jo.SceneSpec(kinds=("mirror", "dielectric", "conductor", "thin_dielectric", "coated_dielectric"),
                              wavelengths=(630.0, 532.0, 465.0))
    eta2 = np.where(kind == 2, 0.2 + 3.0j, 1.5 + 0j)
    scene = jax.jit(lambda i, k, e: jo.scene_interface(i, up, k, 1.0, e, scene=scene_spec, film_eta=1.38,
                                                       film_d=120.0).R)
    check_local(scene(glob(i), glob(kind), glob(eta2)), scene(i, kind, eta2), 1e-12, 1e-15, "scene_interface")

    # ---- fits ------------------------------------------------------------------------------------
    th = np.linspace(0.05, 1.4, 60)
    R = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(1), jnp.linspace(1.3, 1.8, 64), jnp.asarray(th),
                                            noise=1e-3))
    mine = slice(32 * pid, 32 * pid + 32)  # this process's rows of the global batch
    single = jo.fit_eta(th, R[mine], eta1=1.0)
    res = jo.fit_eta(th, glob(R), eta1=1.0)
    ref = lambda x: np.concatenate([np.zeros_like(x)] * pid + [x] + [np.zeros_like(x)] * (1 - pid))
    check_local(res.eta, ref(np.asarray(single.eta)), 1e-12, 0, "fit_eta")
    check_local(res.stderr, ref(np.asarray(single.stderr)), 1e-9, 0, "fit_eta stderr")
    res = jo.fit_eta_sharded(th, glob(R), mesh=mesh)
    check_local(res.eta, ref(np.asarray(single.eta)), 1e-12, 0, "fit_eta_sharded")
    bad = R.copy(); bad[40, 3] = np.nan  # in the second process's rows: both processes refuse
    try:
        jo.fit_eta(th, glob(bad), eta1=1.0)
        raise AssertionError("a NaN in the data was not refused")
    except ValueError as e:
        assert ("R[40, 3] = nan" if pid == 1 else "a part another process holds") in str(e), e

    lam = np.linspace(0.4, 1.0, 8)
    Rl = np.asarray(jo.synthetic_reflectance(jax.random.PRNGKey(2), jnp.asarray(1.45 + 0.004 / lam**2),
                                             jnp.asarray(th), noise=1e-4))
    one = jo.fit_dispersion(lam, th, Rl, model="cauchy", terms=2, sigma=1e-4)
    many = jo.fit_dispersion(lam, th, glob(Rl), model="cauchy", terms=2, sigma=1e-4)
    assert bool(one.converged) and bool(many.converged)
    np.testing.assert_allclose(np.asarray(many.coefficients), np.asarray(one.coefficients), rtol=1e-9)

    # a map: each process fits its own two film sites (its "wafer files"), one per device
    wl_nm = np.linspace(400, 800, 41)
    d_true = np.array([95.0, 102.0, 110.0, 121.0])[2 * pid:2 * pid + 2]
    film = lambda t: jo.Sample([jo.Layer(jo.Cauchy(A=1.46, B=0.0035), t, name="film")], 3.9 + 0.02j)
    truth = np.stack([np.asarray(film(t).fixed().quantities(("psi_deg", "delta_deg"), jnp.asarray(wl_nm),
                                                              jnp.deg2rad(jnp.full(41, 70.0)))) for t in d_true])
    noise = 0.01 * np.random.default_rng(pid).normal(size=(2, 2, 41))
    spectra = jo.make_spectra(wl_nm, 70.0, {k: truth[:, q] + noise[q] for q, k in enumerate(("psi_deg", "delta_deg"))})
    model = film(jo.Free(100.0, 50.0, 200.0))
    fit = jo.fit_stack(model, spectra, mesh=mesh)
    assert fit.values.shape == (4, 1) and bool(np.all(np.asarray(fit.converged.addressable_shards[0].data)))
    alone = [jo.fit_stack(model, spectra._replace(values=spectra.values[j:j + 1])) for j in range(2)]
    for s in fit.values.addressable_shards:
        j = s.index[0].start - 2 * pid
        np.testing.assert_allclose(np.asarray(s.data), np.asarray(alone[j].values), rtol=1e-9, err_msg="fit_stack")
    assert np.all(np.abs(np.asarray(fit.values.addressable_shards[0].data)[:, 0] - d_true[0]) < 1.0)
    print(f"PROCESS {pid} OK", flush=True)
    jax.distributed.shutdown()
''')


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_kernels_and_fits_over_two_processes(tmp_path):
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu", JAXOPTICS_CACHE_DIR="off")
    port = str(_free_port())
    logs = [open(tmp_path / f"process{k}.log", "w+") for k in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(k), port], env=env, stdout=logs[k],
                              stderr=subprocess.STDOUT, text=True) for k in range(2)]
    try:
        codes = [p.wait(timeout=600) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    out = []
    for f in logs:
        f.seek(0)
        out.append(f.read())
        f.close()
    for k in range(2):
        assert codes[k] == 0 and f"PROCESS {k} OK" in out[k], f"process {k}:\n{out[k][-4000:]}"
