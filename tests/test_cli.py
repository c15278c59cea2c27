"""The command line as a user runs it, in fresh processes: what `import jaxoptics` loads, and the
compilation cache of `python -m jaxoptics fit`."""

import os
import subprocess
import sys

import pytest


def _run(args, **env):
    e = dict(os.environ)
    e.update(env)
    return subprocess.run([sys.executable, *args], env=e, capture_output=True, text=True, timeout=900, check=True)


def test_import_loads_only_what_the_kernels_need():
    """`import jaxoptics` does not load the fitting stack (optimistix, equinox, lineax), plotting,
    SciPy or the tools' dependencies, and neither does naming a fit: the fitting stack loads when
    a fit traces its program (`tests/test_cache.py`: not at all when it is loaded from the store)."""
    heavy = ("optimistix", "equinox", "lineax", "matplotlib", "scipy", "mpmath", "tqdm", "jaxoptics.tools")
    code = ("import sys, jaxoptics as jo; mods = set(sys.modules); "
            f"print(sorted(m for m in mods if m.split('.')[0] in {heavy!r} or m.startswith('jaxoptics.tools'))); "
            "jo.fit_eta, jo.fit_stack; print('optimistix' in sys.modules)")
    out = _run(["-c", code]).stdout.split("\n")
    assert out[0] == "[]", out[0]
    assert out[1] == "False"


def _shipped_programs_apply() -> bool:
    from jaxoptics._runtime import _cache
    from jaxoptics.tools import make_programs

    manifest = make_programs.read_manifest()
    return manifest["versions"] == _cache.library_versions() and manifest["source"] == _cache.source_hash()


@pytest.mark.slow
def test_fit_keeps_compiled_programs_between_runs(tmp_path):
    """A first run fills the cache directory (compiled programs and the fit's executable), a
    second run gives the same answer from it without tracing the fit; `--no-cache` and
    `JAXOPTICS_CACHE_DIR=off` write nothing."""
    cache = tmp_path / "cache"
    fit = ["-m", "jaxoptics", "fit", "--example"]
    first = _run(fit, JAXOPTICS_CACHE_DIR=str(cache), JAX_LOG_COMPILES="1")
    entries = sorted(p.name for p in cache.iterdir())
    assert any(n.endswith("-cache") for n in entries), entries
    assert any(n.endswith(".xlaexec") for n in entries), entries
    # traced, unless the package's shipped program of this form is for the installed libraries
    assert ("Finished tracing _first" in first.stderr) != _shipped_programs_apply()
    second = _run(fit, JAXOPTICS_CACHE_DIR=str(cache), JAX_LOG_COMPILES="1")
    assert second.stdout == first.stdout
    assert "Finished tracing _first" not in second.stderr
    compiled = second.stderr.count("\nCompiling ") + second.stderr.startswith("Compiling ")
    assert compiled == second.stderr.count("Persistent compilation cache hit"), second.stderr  # none compiled
    first = first.stdout
    off = tmp_path / "off"
    _run(["-m", "jaxoptics", "fit", "--example", "--no-cache"], JAXOPTICS_CACHE_DIR=str(off))
    assert not off.exists()
    home = tmp_path / "home"
    _run(["-m", "jaxoptics", "demo"], JAXOPTICS_CACHE_DIR="off", HOME=str(home), XDG_CACHE_HOME=str(home / "xdg"))
    assert not (home / "xdg").exists()


@pytest.mark.slow
def test_command_ends_with_its_output_exit_code_and_exit_handlers(tmp_path):
    """`python -m jaxoptics` ends its process without the interpreter's teardown (`_exit_now`):
    output written to a file (block-buffered) is complete, exit handlers run after the command, and
    an error's exit code is kept."""
    code = ("import atexit, runpy, sys; atexit.register(lambda: print('exit handler ran')); "
            "sys.argv = ['jaxoptics', 'demo']; runpy.run_module('jaxoptics', run_name='__main__'); "
            "print('not reached')")
    out = tmp_path / "out.txt"
    with open(out, "w") as f:
        e = dict(os.environ, JAXOPTICS_CACHE_DIR="off")
        res = subprocess.run([sys.executable, "-c", code], env=e, stdout=f, stderr=subprocess.PIPE, text=True,
                             timeout=900)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = out.read_text().splitlines()
    assert lines[-1] == "exit handler ran"
    assert lines[-2].split()[0] == "90.00" and lines[-2].split()[-1] == "yes"  # the table's last row
    assert "not reached" not in lines
    bad = subprocess.run([sys.executable, "-m", "jaxoptics", "fit", str(tmp_path / "missing.csv"), "--no-cache"],
                         capture_output=True, text=True, timeout=900)
    assert bad.returncode == 2
    assert "missing.csv: no such file" in bad.stderr



_DEFAULT_EMITTERS = """
import warnings
import numpy as np, jax, jax.numpy as jnp, tmm
jax.config.update("jax_enable_x64", True)
import jaxoptics as jo
rng = np.random.default_rng(5)
K, L = 16, 6
n = rng.uniform(1.2, 2.6, (K, L)) + 1j * np.where(rng.random((K, L)) < 0.4, rng.uniform(0, 0.4, (K, L)), 0)
n[:, 0] = 1.0
d = rng.uniform(5, 400, (K, L - 2)); d[:, 1] = 5e3
wl, th = rng.uniform(350, 1000, K), rng.uniform(0, 1.5, K)
for inc, coh in (((), ["i", "c", "c", "c", "c", "i"]), ((1,), ["i", "c", "i", "c", "c", "i"])):
    res = jax.jit(lambda *a: jo.stack(*a, incoherent=inc))(n, d, wl, np.cos(th))
    for k in range(K):
        for pol, R in (("s", res.R_s), ("p", res.R_p)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ref = tmm.inc_tmm(pol, list(n[k]), [np.inf, *d[k], np.inf], coh, th[k], wl[k])["R"]
            assert abs(float(R[k]) - ref) < 1e-10, (inc, k, pol, float(R[k]), ref)
g = jax.jit(jax.grad(lambda d: jnp.sum(jo.stack(jnp.asarray(n), d, wl, np.cos(th), incoherent=(1,)).R)))(d)
assert np.all(np.isfinite(np.asarray(g)))
c = np.linspace(0, 1, 101)
s, ct = np.sqrt(1 - c**2), np.sqrt(1 - (np.sqrt(1 - c**2) / 1.5) ** 2)
rs, rp = (c - 1.5 * ct) / (c + 1.5 * ct), (ct - 1.5 * c) / (ct + 1.5 * c)
assert np.allclose(np.asarray(jo.fresnel(c, 1.0, 1.5)), (rs**2 + rp**2) / 2, rtol=1e-13, atol=1e-15)
print("DEFAULTS OK")
"""


@pytest.mark.slow
def test_kernels_under_xla_default_emitters():
    """The suite compiles with XLA's classic CPU emitters at optimization level 0 (`conftest.py`);
    users run XLA's defaults. Here, in a process with the defaults: stacks with and without an incoherent layer against
    tmm's `inc_tmm` (1e-10), finite gradients, and the Fresnel reflectance against its closed form."""
    from helpers import xla_flags_without

    flags = xla_flags_without("xla_cpu_use_fusion_emitters", "xla_backend_optimization_level")
    out = _run(["-c", _DEFAULT_EMITTERS], XLA_FLAGS=flags)
    assert "DEFAULTS OK" in out.stdout
