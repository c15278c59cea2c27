"""The store of traced programs behind `jaxoptics.enable_cache`: a stored program gives the answer
the plain compiled call gives, a later process loads it instead of tracing, a damaged file is
traced again, and the key tells apart everything that changes the program (and refuses what it
cannot name)."""

import dataclasses
import functools
import logging
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxoptics as jo
from jaxoptics._fitting import _stack_fit
from jaxoptics._runtime import _cache


@pytest.fixture(autouse=True)
def _no_shipped_programs(monkeypatch):
    """The package's shipped programs (`_cache._SHIPPED`) off: these tests follow what the store
    traces, compiles and keeps (`test_shipped_programs...` turns them on)."""
    monkeypatch.setattr(_cache, "_SHIPPED", [None])


@pytest.fixture
def store(tmp_path):
    _cache.enable_store(tmp_path)
    try:
        yield tmp_path
    finally:
        _cache.disable_store()


def _fields(result):
    return {f.name: np.asarray(getattr(result, f.name)) for f in dataclasses.fields(result)}


def _assert_same(a, b):
    """The same program compiled from its stored form: equal to rounding."""
    fa, fb = _fields(a), _fields(b)
    assert fa.keys() == fb.keys()
    for k in fa:
        if fa[k].dtype.kind in "fc":
            np.testing.assert_allclose(fb[k], fa[k], rtol=1e-12, atol=0, err_msg=k)
        else:
            np.testing.assert_array_equal(fb[k], fa[k], err_msg=k)


def _fails(*args, **kwargs):
    pytest.fail("the program was traced again instead of loaded from the store")


@pytest.mark.slow
def test_fit_eta_stored_loaded_and_repaired(tmp_path, monkeypatch, caplog):
    c = jo.load_reflectance(jo.example_path()).curves()[0]
    fit = lambda: jo.fit_eta(c.theta, c.R, polarization=c.polarization, sigma=c.sigma)
    plain = fit()
    _cache.enable_store(tmp_path)
    try:
        first = fit()  # traced and lowered once, compiled, its executable stored
        (exe,) = tmp_path.glob("*.xlaexec")
        (for_all,) = tmp_path.glob("*.jaxexport")  # and the traced program, for any number of angles
        _cache._in_process.clear()  # as in a new process
        with monkeypatch.context() as m:  # the executable: neither traced nor lowered
            m.setattr(_cache, "_flat", _fails)
            m.setattr(_cache, "_export", _fails)
            m.setattr(_cache, "_load", _fails)
            loaded = fit()
        exe.write_bytes(b"not an executable")
        _cache._in_process.clear()
        with caplog.at_level(logging.WARNING, logger="jaxoptics._runtime._cache"):
            rebuilt = fit()  # dropped, traced and compiled again, stored again
        assert "unreadable stored executable" in caplog.text
        assert exe.read_bytes() != b"not an executable"
        # a backend that cannot serialize executables: the traced program is stored instead, and
        # a later process compiles it without tracing
        from jax.experimental import serialize_executable

        exe.unlink()
        for_all.unlink()
        _cache._in_process.clear()
        with monkeypatch.context() as m:
            m.setattr(serialize_executable, "serialize", _no_serialization)
            traces = _count_traces(m)
            traced = fit()
            assert traces and len(traces) == len(set(traces)), traces  # each program traced once
            (path,) = tmp_path.glob("*.jaxexport")
            assert not list(tmp_path.glob("*.xlaexec"))
            _cache._in_process.clear()
            m.setattr(_cache, "_flat", _fails)
            from_traced = fit()
        path.write_bytes(b"not a stored program")
        _cache._in_process.clear()
        caplog.clear()
        with monkeypatch.context() as m, caplog.at_level(logging.WARNING, logger="jaxoptics._runtime._cache"):
            m.setattr(serialize_executable, "serialize", _no_serialization)
            repaired = fit()
        assert "unreadable stored program" in caplog.text
        assert path.read_bytes() != b"not a stored program"
    finally:
        _cache.disable_store()
    for r in (first, loaded, rebuilt, traced, from_traced, repaired):
        _assert_same(plain, r)
    assert np.asarray(plain.converged).all()


@pytest.mark.slow
def test_new_numbers_of_angles_and_curves_compile_the_stored_program_without_tracing(store, monkeypatch):
    """The batched solve is stored as one traced program for every number of angles from 16 to
    4096 and of curves up to 32 (`_fit_followups.angles_poly`): data of another size in that range
    is compiled from it, not traced, and fits as the plain call does. Outside the range the
    program is traced for the shapes given."""
    rng = np.random.default_rng(7)
    theta = np.deg2rad(np.linspace(4, 86, 120))
    Rs, Rp = (np.asarray(x) for x in jo.fresnel_sp(np.cos(theta), 1.0, 1.52))
    R = np.stack([Rs, Rp, 0.5 * (Rs + Rp)]) + 2e-3 * rng.standard_normal((3, theta.size))
    pols = ("s", "p", "unpolarized")

    def fit(step, curves):
        return jo.fit_eta(theta[::step], R[:curves, ::step], polarization=pols[:curves], sigma=2e-3)

    sizes = [(1, 2), (3, 2), (2, 3), (9, 2)]  # (40, 2), (60, 3) and (14, 2): angles and curves
    _cache.disable_store()
    plain = [fit(*s) for s in sizes]
    _cache.enable_store(store)
    first = fit(*sizes[0])
    (stored,) = store.glob("*.jaxexport")
    for size, expected in zip(sizes, plain):
        _cache._in_process.clear()  # as in a new process
        with monkeypatch.context() as m:
            traces = _count_traces(m)
            got = fit(*size)
        m_angles = theta[::size[0]].size
        assert traces == ([] if m_angles >= 16 else ["jaxoptics._fitting._index_stages._first"]), (size, traces)
        _assert_same(expected, got)
        assert np.asarray(got.converged).all()
    assert list(store.glob("*.jaxexport")) == [stored]  # 14 angles: its executable only
    _assert_same(plain[0], first)


def _count_traces(m) -> list:
    """Patch `_cache._flat` so that each trace of a program appends its name to the returned list."""
    traces: list = []
    real = _cache._flat

    def counting(fn, name, in_tree):
        flat, out_tree = real(fn, name, in_tree)

        def counted(*xs):
            traces.append(name)
            return flat(*xs)

        counted.__name__ = counted.__qualname__ = flat.__name__
        return counted, out_tree

    m.setattr(_cache, "_flat", counting)
    return traces


def _no_serialization(*args, **kwargs):
    raise NotImplementedError("this backend does not serialize executables")


@pytest.mark.slow
def test_fit_stack_stored_and_loaded(store, monkeypatch):
    wl = np.linspace(400.0, 900.0, 60)
    truth = jo.Sample([jo.Layer(1.46, 250.0)], jo.material("Si")).fixed()
    q = np.asarray(truth.quantities(("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.full(60, np.radians(70.0))))
    sp = jo.make_spectra(wl, 70.0, {"psi_deg": q[0], "delta_deg": q[1]})
    model = jo.Sample([jo.Layer(1.46, jo.Free(100.0, 0.0, 600.0), name="film")], jo.material("Si"))
    first = jo.fit_stack(model, sp)
    assert len(list(store.glob("*.xlaexec"))) == 2  # Gauss-Newton fitted it: its stage and the errors
    _cache._in_process.clear()
    _stack_fit._program.cache_clear()  # nothing of the first call stays in memory
    with monkeypatch.context() as m:
        m.setattr(_cache, "_flat", _fails)
        m.setattr(_cache, "_export", _fails)
        loaded = jo.fit_stack(model, sp)
    _cache.disable_store()
    plain = jo.fit_stack(model, sp)
    _assert_same(plain, first)
    _assert_same(plain, loaded)
    assert float(plain["film.thickness_nm"]) == pytest.approx(250.0, abs=1e-6)


def _user_function(x):
    return x


def test_key_tells_apart_what_changes_the_program():
    key = lambda static, args=(): _cache._key("jaxoptics.f", static, args, None)
    x32 = jnp.zeros(3, jnp.float32)
    # static values by value (arrays too), traced arrays by shape and dtype only
    assert key((1.0, "s")) == key((1.0, "s"))
    assert key((1.0, "s")) != key((1.0 + 1e-15, "s")) != key((1.0, "p"))
    assert key(np.array([1.0, 2.0])) == key(np.array([1.0, 2.0])) != key(np.array([1.0, 3.0]))
    assert key(None, (x32,)) == key(None, (x32 + 1,))
    assert key(None, (x32,)) != key(None, (jnp.zeros(4, jnp.float32),)) != key(None, (jnp.zeros(3, jnp.float64),))
    assert key(None, (x32,)) != key(None, ({"a": x32},))
    assert key(jo.Cauchy(1.45, 0.004)) != key(jo.Cauchy(1.45, 0.005))
    assert key(functools.partial(jnp.sum, axis=0)) != key(functools.partial(jnp.sum, axis=1))
    assert _cache._key("jaxoptics.f", None, (), None) != _cache._key("jaxoptics.g", None, (), None)
    assert _cache._key("jaxoptics.f", None, (), None) != _cache._key("jaxoptics.f", None, (), {"xla_backend_optimization_level": 0})
    default = key(None, (x32,))
    with jax.numpy_rank_promotion("warn"):
        assert key(None, (x32,)) != default
    # what has no stable text is not stored: lambdas, local and user functions, opaque objects
    for unstable in (lambda x: x, _user_function, object(), (1.0, object())):
        assert key(unstable) is None, unstable

    def local(x):
        return x

    assert key(local) is None


def test_store_is_off_unless_enabled(tmp_path):
    assert not _cache.enabled()
    c = jo.load_reflectance(jo.example_path()).curves()[0]
    jo.fit_eta(c.theta, c.R, polarization=c.polarization, sigma=c.sigma)
    assert not list(tmp_path.iterdir())


def test_prune_keeps_the_most_recently_used(tmp_path, monkeypatch):
    monkeypatch.setattr(_cache, "MAX_BYTES", 2500)
    for k in range(5):
        p = tmp_path / f"{k}{_cache._SUFFIX}"
        p.write_bytes(bytes(1000))
        os.utime(p, (1000 + k, 1000 + k))
    _cache._prune(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{k}{_cache._SUFFIX}" for k in (3, 4)]


def test_compiler_options_xla_does_not_know_are_left_out(monkeypatch, tmp_path):
    from jaxoptics._runtime import _options as _compile

    bogus = {"xla_no_such_option_for_jaxoptics": True}
    monkeypatch.setattr(_compile, "QUICK_COMPILE", {**_compile.QUICK_COMPILE, **bogus})
    assert not _compile._known(tuple(bogus.items()))
    assert _compile._known((("xla_backend_optimization_level", 0),))
    options = _compile.compiler_options(True)
    assert options == {k: v for k, v in _compile.QUICK_COMPILE.items() if _compile._known(((k, v),))}
    assert "xla_no_such_option_for_jaxoptics" not in options and options["xla_backend_optimization_level"] == 0
    assert _compile.compiler_options(False) is None
    # through the store, which keys a program by the options asked for: compiled without the
    # unknown one, stored and loaded
    theta = np.radians(np.linspace(5.0, 80.0, 12))
    R = np.asarray(jo.fresnel(np.cos(theta), 1.0, 1.5))
    _cache.enable_store(tmp_path)
    try:
        first = jo.fit_eta(theta, R)
        assert list(tmp_path.glob("*" + _cache._EXE_SUFFIX))
        _cache._in_process.clear()
        again = jo.fit_eta(theta, R)
    finally:
        _cache.disable_store()
    assert float(first.eta) == float(again.eta) == pytest.approx(1.5, rel=1e-6)


class _Planted:
    def __reduce__(self):
        return (os.system, ("echo planted",))


def test_a_planted_file_runs_nothing(tmp_path, caplog):
    """A stored file is unpickled with only JAX's tree structure and jaxoptics' result classes
    allowed: a file that would call anything else is refused (and deleted) before it runs."""
    import pickle

    path = tmp_path / ("0" * 64 + _cache._SUFFIX)
    path.write_bytes(pickle.dumps((b"", _Planted())))
    with caplog.at_level(logging.WARNING, logger="jaxoptics._runtime._cache"):
        assert _cache._load(path) is None
    assert "is not part of a stored program" in caplog.text
    assert not path.exists()


def test_executable_key_names_the_machine_and_the_devices(monkeypatch):
    """A stored executable is machine code for the host's processor and the devices its inputs
    lived on: its key adds the backend, the processor's model and instruction-set extensions and
    the arguments' placement to the program's key."""
    key = "0" * 64
    here = _cache._executable_key(key, "cpu:0")
    assert here != _cache._executable_key("1" * 64, "cpu:0")
    assert here != _cache._executable_key(key, "cpu:1")
    if os.path.exists("/proc/cpuinfo"):
        assert "flags" in _cache._machine() or "Features" in _cache._machine()  # x86, Arm
    monkeypatch.setattr(_cache, "_machine", lambda: "another processor")
    assert _cache._executable_key(key, "cpu:0") != here
    # a NumPy array and a JAX array on the default device are the same placement
    assert _cache._placement([np.ones(2), jnp.ones(2), 3.0]) == _cache._placement([np.ones(2)]) == "cpu:0"


_NO_SHIPPED = "from jaxoptics._runtime import _cache; _cache._SHIPPED[0] = None  # this process traces what the store misses\n"
_WARM = _NO_SHIPPED + """
import sys, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import jaxoptics as jo
jo.enable_cache(path=sys.argv[1])
c = jo.load_reflectance(jo.example_path()).curves()[0]
r = jo.fit_eta(c.theta, c.R, polarization=c.polarization)
probed = jo._runtime._options._known.cache_info().currsize > 0  # XLA asked which compiler options it knows
print(float(r.eta), bool(r.converged), *(m in sys.modules for m in ("optimistix", "equinox", "lineax")), probed)
"""


@pytest.mark.slow
def test_warm_process_calls_the_stored_executable_without_the_solver_stack(tmp_path):
    """A process whose fit is in the store loads its executable: it traces and compiles nothing,
    so it does not import optimistix, equinox or lineax, nor ask XLA which compiler options it
    knows (the first process, which traces and compiles, does all of these)."""
    import subprocess
    import sys

    run = lambda: subprocess.run([sys.executable, "-c", _WARM, str(tmp_path)], capture_output=True, text=True,
                                 check=True).stdout.split()
    first, warm = run(), run()
    assert first[2:] == ["True", "True", "True", "True"], first
    assert warm[2:] == ["False", "False", "False", "False"], warm
    assert warm[:2] == first[:2] and first[1] == "True"


@pytest.mark.slow
def test_program_found_in_jax_cache_is_stored_in_a_form_a_later_process_runs(tmp_path):
    """A process whose executable is missing from the store (deleted, pruned, or stored under the
    key of another jaxoptics version) but whose program JAX's persistent compilation cache holds
    gets it from there; what it stores must run in a later process (an executable loaded from JAX's
    cache and serialized again lacks its kernels: "Function ..._kernel not found"). It does not
    store that executable; it and the later processes compile the stored traced program (for all
    numbers of angles), which JAX's cache serves: they trace nothing."""
    import subprocess
    import sys

    run = lambda: subprocess.run([sys.executable, "-c", _WARM, str(tmp_path)], capture_output=True, text=True)
    first = run()
    assert first.returncode == 0, first.stderr[-2000:]
    for f in tmp_path.glob("*" + _cache._EXE_SUFFIX):
        f.unlink()
    assert list(tmp_path.glob("jit_call-*-cache"))  # JAX's own entry stays
    for _ in range(3):
        later = run()
        assert later.returncode == 0, later.stderr[-2000:]
        assert later.stdout.split()[:2] == first.stdout.split()[:2]
        assert later.stdout.split()[2:5] == ["False", "False", "False"], later.stdout  # nothing traced


@pytest.mark.slow
def test_stored_executable_that_fails_to_run_is_dropped_and_compiled_again(tmp_path):
    """An executable that loads but fails when run (here: one written the way that lost its
    kernels, by a process that does not watch for JAX's cache hits) is deleted, with a warning,
    and the program compiled again: the answer is the same, and the next process runs from the
    store."""
    import subprocess
    import sys

    run = lambda script=_WARM: subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True,
                                              text=True)
    first = run()
    assert first.returncode == 0, first.stderr[-2000:]
    for f in tmp_path.glob("*" + _cache._EXE_SUFFIX):
        f.unlink()
    unwatched = "from jaxoptics._runtime import _cache; _cache._listening.append(True)\n" + _WARM
    assert run(unwatched).returncode == 0
    assert list(tmp_path.glob("*" + _cache._EXE_SUFFIX))  # written from JAX's cache hit: incomplete
    mended = run()
    assert mended.returncode == 0, mended.stderr[-2000:]
    assert "dropping stored executable" in mended.stderr and "failed to run" in mended.stderr
    assert mended.stdout.split()[:2] == first.stdout.split()[:2]
    later = run()
    assert later.returncode == 0 and "dropping" not in later.stderr, later.stderr[-2000:]
    assert later.stdout.split()[:2] == first.stdout.split()[:2]


_WARM_STACK = _NO_SHIPPED + """
import sys, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, jaxoptics as jo
jo.enable_cache(path=sys.argv[1])
wl = np.linspace(400.0, 900.0, 40)
truth = jo.Sample([jo.Layer(1.46, 250.0)], jo.material("Si")).fixed()
q = np.asarray(truth.quantities(("psi_deg", "delta_deg"), jnp.asarray(wl), jnp.full(40, np.radians(70.0))))
sp = jo.make_spectra(wl, 70.0, {"psi_deg": q[0], "delta_deg": q[1]})
model = jo.Sample([jo.Layer(1.46, jo.Free(100.0, 0.0, 600.0), name="film")], jo.material("Si"))
print(repr(float(jo.fit_stack(model, sp)["film.thickness_nm"])), len(list(__import__("pathlib").Path(sys.argv[1]).glob("*.xlaexec"))))
print(*(m in sys.modules for m in ("optimistix", "equinox", "lineax")), jo._runtime._options._known.cache_info().currsize > 0)
"""


@pytest.mark.slow
def test_warm_process_runs_a_stored_executable_that_calls_lapack(tmp_path):
    """`fit_stack`'s program calls LAPACK (QR, eigh), whose kernels jaxlib sets up when it lowers a
    linear-algebra operation; a process that only loads the executable sets them up itself (it
    would crash otherwise). It builds no program either, so it does not import optimistix,
    equinox or lineax, nor ask XLA which compiler options it knows (the first process does)."""
    import subprocess
    import sys

    run = lambda: subprocess.run([sys.executable, "-c", _WARM_STACK, str(tmp_path)], capture_output=True, text=True)
    first, warm = run(), run()
    assert first.returncode == 0 and warm.returncode == 0, (first.returncode, warm.returncode, warm.stderr[-2000:])
    (value, stored), modules = first.stdout.splitlines()[0].split(), first.stdout.splitlines()[1].split()
    assert stored == "2" and modules == ["True", "True", "True", "True"], first.stdout  # two stages stored
    assert warm.stdout.splitlines() == [f"{value} {stored}", "False False False False"], (first.stdout, warm.stdout)
    assert float(value) == pytest.approx(250.0, abs=1e-6)


def test_shipped_programs_are_those_of_the_source():
    """The programs shipped in `jaxoptics/data/programs` were traced from this source, one for each
    form of the command line's `fit` calls (`python -m jaxoptics.tools.make_programs` writes them)."""
    from jaxoptics.tools import make_programs

    manifest = make_programs.read_manifest()
    assert manifest["source"] == _cache.source_hash(), (
        "the shipped programs are of another source: run python -m jaxoptics.tools.make_programs")
    assert [p["form"] for p in manifest["programs"]] == [name for name, _ in make_programs.forms()]
    files = sorted(p["file"] for p in manifest["programs"])
    assert files == sorted(f.name for f in make_programs.OUT.glob("*" + _cache.SHIPPED_SUFFIX))
    assert len(set(files)) == len(files) == 16


_SHIPPED_RUN = """
import sys, jax
from jaxoptics._runtime import _cache
if sys.argv[2] == "off":
    _cache._SHIPPED[0] = None
from jaxoptics.__main__ import main
main(["fit", "--example"])  # (enables the cache in $JAXOPTICS_CACHE_DIR)
print("traced:", "optimistix" in sys.modules, len(list(_cache._dir[0].glob("*" + _cache._SUFFIX))))
"""


@pytest.mark.slow
def test_first_command_line_fit_compiles_a_shipped_program_without_tracing(tmp_path):
    """With an empty cache, `fit --example` compiles the shipped program of its form instead of
    tracing (it does not import optimistix, and stores no traced program of its own), and prints
    the fit that tracing gives. Shipped programs are found only with the library versions they
    were traced with."""
    import subprocess
    import sys

    from jaxoptics.tools import make_programs

    manifest = make_programs.read_manifest()
    if manifest["versions"] != _cache.library_versions():
        pytest.skip(f"shipped programs are of {manifest['versions']}, installed: {_cache.library_versions()}")

    def run(shipped, cache):
        env = dict(os.environ, JAXOPTICS_CACHE_DIR=str(tmp_path / cache))
        out = subprocess.run([sys.executable, "-c", _SHIPPED_RUN, "", shipped], capture_output=True, text=True,
                             env=env)
        assert out.returncode == 0, out.stderr[-2000:]
        table, _, tail = out.stdout.rpartition("traced:")
        return table, tail.split()

    table, tail = run("on", "shipped")
    table_traced, tail_traced = run("off", "traced")
    assert tail == ["False", "0"], tail
    assert tail_traced == ["True", "1"], tail_traced
    assert table == table_traced


_SHIPPED_NO_STORE = """
import sys
from jaxoptics._runtime import _cache
if sys.argv[2] == "off":
    _cache._SHIPPED[0] = None
from jaxoptics.__main__ import main
main(["fit", "--example", "--no-cache", *sys.argv[3:]])
print("imported:", "optimistix" in sys.modules, "scipy.linalg" in sys.modules, _cache.enabled())
"""


@pytest.mark.slow
@pytest.mark.parametrize("form", [[], ["--absorbing"]], ids=["real index", "complex index"])
def test_fit_without_the_store_compiles_a_shipped_program_without_tracing(form):
    """With the store off (`--no-cache`, or a library call without `enable_cache`), a fit whose
    form the package ships compiles the shipped batched solve in the process instead of tracing
    it, and prints the fit that tracing gives. A program without LAPACK calls (a real index) is
    lowered without jax's LAPACK set-up, which imports scipy.linalg; one with them (a complex
    index: QR) gets it, and runs. (The complex example also needs a follow-up stage, which is
    traced: only the batched solve is shipped.)"""
    import subprocess
    import sys

    from jaxoptics.tools import make_programs

    manifest = make_programs.read_manifest()
    if manifest["versions"] != _cache.library_versions():
        pytest.skip(f"shipped programs are of {manifest['versions']}, installed: {_cache.library_versions()}")

    def run(shipped):
        env = {k: v for k, v in os.environ.items() if k != "JAXOPTICS_CACHE_DIR"}
        env["JAX_LOG_COMPILES"] = "1"
        out = subprocess.run([sys.executable, "-c", _SHIPPED_NO_STORE, "", shipped, *form], capture_output=True,
                             text=True, env=env)
        assert out.returncode == 0, out.stderr[-2000:]
        table, _, tail = out.stdout.rpartition("imported:")
        return table, tail.split(), "Finished tracing _first " in out.stderr

    table, imported, traced = run("on")
    table_traced, imported_traced, traced_traced = run("off")
    assert not traced and traced_traced
    assert imported[1:] == [str(bool(form)), "False"], imported
    if not form:
        assert imported[0] == "False", imported  # nothing traced: optimistix not even imported
    assert table == table_traced
