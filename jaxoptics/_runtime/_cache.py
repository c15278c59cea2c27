"""Compiled programs kept between processes: `enable_cache` turns on JAX's persistent
compilation cache and, beside it, a store of the fits' compiled executables.

JAX's persistent compilation cache skips XLA's compilation in a later process, but every new
process still traces and lowers the program in Python first: for the fits that is most of a warm
run (`fit --example`: 0.8 s of tracing and 0.2 s of lowering, against 0.1 s to load the compiled
program). The store keeps each fit's compiled executable (`<key2>.xlaexec`, serialized by
`jax.experimental.serialize_executable`) under a key that names everything it was traced from
plus the backend's platform and version and the processor's model and instruction-set
extensions, since XLA compiles for the host's. A later process on the same machine loads it and
calls it: no tracing, no lowering and no compilation-cache lookup.

Where no executable is stored, the program is traced, lowered and compiled once, and its
executable written. A program whose caller gives symbolic shapes for its inputs (`call`'s
`poly`: `fit_eta`'s batched solve, for any number of angles and curves in a range) is traced
for those instead, and that traced program stored under a key of its own: a process that meets
new shapes in the range lowers and compiles it without tracing. The package ships such programs
for the command line's fits (`_SHIPPED`, written by `jaxoptics.tools.make_programs`); they are
found under the same keys, so only by the source and library versions they were traced with.
With the store off, a call that gives `poly` still compiles its shipped program, if there is one,
and keeps it for the process (`_shipped_or`).

Where the backend cannot serialize an executable, or where JAX's persistent compilation cache
supplied it (serialized again, such an executable is incomplete: see `_compile_and_store`), the
traced program is stored instead (`<key>.jaxexport`, StableHLO serialized by `jax.export`): a
later process deserializes it and hands it to `jit`, which compiles it (or JAX's persistent
cache serves it); a process whose executable is missing or foreign but whose traced program is
stored does the same (and stores its executable). A file that fails to load is deleted and
written again, and so is an executable whose first call in a process fails (that call is waited
for). An executable that calls custom kernels other than LAPACK's is not stored (their
libraries' set-up happens when a program is lowered, which loading skips); for LAPACK's, loading
sets them up (`_initialize_lapack`). Like JAX's compilation cache, whose entries are also
machine code, the store trusts its directory: it is the user's own.

The key is a SHA-256 of: the jaxoptics source (every `.py` file of the package, so an edited
checkout never reuses a stale program), the versions of jax and jaxlib, the backend, the
configuration that changes tracing (`jax_enable_x64`, the default matmul precision, the dtype
promotion and rank promotion modes), the compiler options, the traced function's module and
name, and a canonical text of its arguments: array leaves by shape, dtype and weak type, every
other leaf by value. An argument without a stable text (a lambda, a local function, an object
whose repr holds a memory address) makes the call uncacheable, and it runs as a plain `jit` call.
A program that can be stored neither way (host callbacks) is compiled and kept in this process only.

Stored files are `<key2>.xlaexec` and `<key>.jaxexport` in the compilation cache's directory (JAX's
own entries end in `-cache`). They are written to a temporary name and renamed, so processes sharing
the directory never read a partial file, and the least recently used are deleted beyond
`MAX_BYTES`.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import io
import logging
import os
import pickle
import re
import tempfile
import threading
import types
from pathlib import Path

import jax
import numpy as np

from ._options import known_options

_log = logging.getLogger(__name__)

MAX_BYTES = 256 * 2**20
_SUFFIX = ".jaxexport"
_dir: list[Path | None] = [None]


def default_cache_dir() -> Path | None:
    """The cache directory of the command line, or None when turned off: `$JAXOPTICS_CACHE_DIR`
    if set (an empty value or `off` turns the cache off), else `$XDG_CACHE_HOME/jaxoptics/xla`
    (`~/.cache/jaxoptics/xla` by default)."""
    env = os.environ.get("JAXOPTICS_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxoptics" / "xla"


def enable_cache(*, path: str | os.PathLike | None = None) -> Path | None:
    """Keep compiled programs between processes, in `path` (default: `$JAXOPTICS_CACHE_DIR`, or
    `~/.cache/jaxoptics/xla`; `JAXOPTICS_CACHE_DIR=off` leaves the cache off).

    A later process that runs the same fits (same shapes and options) then neither traces nor
    compiles them: `fit_eta` and `fit_stack` load their executables (or, where a backend cannot
    serialize executables, their traced programs) from the directory, and JAX's persistent
    compilation cache, turned on here for every program of the process (JAX's default keeps only
    those that took a second or more to compile), loads the compiled ones. The directory is capped
    at 1 GiB of JAX's entries and 256 MiB of the fits' executables and traced programs, least
    recently used first out; JAX guards its entries with a file lock and the fits' files are
    written atomically, so processes can share the directory. Deleting it is always safe.

    The compilation cache is a setting of the whole process (`jax.config`); call this once, at
    the start, before anything is compiled. The command line (`python -m jaxoptics fit`,
    `fit-stack`, `demo`) calls it unless given `--no-cache`.

    **Returns:** the directory used, or None when the cache stays off.
    """
    path = default_cache_dir() if path is None else Path(path).expanduser()
    if path is None:
        return None
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", 2**30)
    enable_store(path)
    return path


def enable_store(path) -> None:
    """Keep traced programs in `path` (created if missing) for this process, without touching the
    compilation cache."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    _dir[0] = path
    _in_process.clear()


def disable_store() -> None:
    _dir[0] = None
    _in_process.clear()


def enabled() -> bool:
    return _dir[0] is not None


class _Uncacheable(Exception):
    pass


_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _canon(x, traced: bool) -> str:
    """A text that two processes give for equal values, or `_Uncacheable`. Arrays are described
    by shape and dtype where they are `traced` (the program's inputs), by value elsewhere."""
    canon = functools.partial(_canon, traced=traced)
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        return repr(x)
    if isinstance(x, jax.ShapeDtypeStruct):  # a program's input of symbolic shape (`call`'s `poly`)
        weak = ", weak" if x.weak_type else ""
        return f"array({x.dtype}[{', '.join(str(d) for d in x.shape)}]{weak})"
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        weak = ", weak" if getattr(x, "weak_type", False) else ""
        if traced:
            return f"array({x.dtype}{list(np.shape(x))}{weak})"
        value = np.asarray(x)
        return f"value({value.dtype}{list(value.shape)}{weak},{hashlib.sha256(value.tobytes()).hexdigest()})"
    if isinstance(x, enum.Enum):
        return f"{type(x).__module__}.{type(x).__qualname__}.{x.name}"
    if isinstance(x, tuple) and hasattr(x, "_fields"):
        return _name(type(x)) + "(" + ",".join(f"{k}={canon(v)}" for k, v in zip(x._fields, x)) + ")"
    if isinstance(x, (tuple, list, frozenset, set)):
        items = [canon(v) for v in x]
        if isinstance(x, (frozenset, set)):
            items.sort()
        return type(x).__name__ + "(" + ",".join(items) + ")"
    if isinstance(x, dict):
        return "dict(" + ",".join(sorted(f"{canon(k)}:{canon(v)}" for k, v in x.items())) + ")"
    if isinstance(x, np.dtype):
        return f"dtype({x})"
    if isinstance(x, type):
        return "type:" + _name(x)
    if dataclasses.is_dataclass(x):  # equinox modules (optimistix solvers, bound methods) too
        fields = ",".join(f"{f.name}={canon(getattr(x, f.name))}" for f in dataclasses.fields(x))
        return f"{_name(type(x))}({fields})"
    if isinstance(x, functools.partial):
        return f"partial({canon(x.func)},{canon(x.args)},{canon(x.keywords)})"
    if isinstance(x, types.MethodType):
        return f"method({_name(x.__func__)},{canon(x.__self__)})"
    if isinstance(x, (types.FunctionType, types.BuiltinFunctionType)) or hasattr(x, "__wrapped__"):
        return "fn:" + _name(x)
    if isinstance(x, jax.tree_util.PyTreeDef):
        return _checked(str(x))
    raise _Uncacheable(f"no canonical text for a {type(x).__name__}")  # a repr need not show all state


# Code whose version is part of the key (`_environment`): a function or class from anywhere else
# (the user's own) could change between runs under the same name.
_VERSIONED = ("jaxoptics", "optimistix", "equinox", "lineax", "jax", "jaxlib", "numpy", "builtins")


def _name(obj) -> str:
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if module is None or qualname is None or "<lambda>" in qualname or "<locals>" in qualname:
        raise _Uncacheable(f"no stable name for {obj!r}")
    if module.split(".")[0] not in _VERSIONED:
        raise _Uncacheable(f"{module}.{qualname} is not versioned code")
    return f"{module}.{qualname}"


def _checked(text: str) -> str:
    if _ADDRESS.search(text):
        raise _Uncacheable(text)
    return text


_LIBRARIES = ("jax", "jaxlib", "optimistix", "equinox", "lineax", "numpy")


@functools.cache
def source_hash() -> str:
    """SHA-256 of the package's source: every `.py` file, by path and content."""
    package = Path(__file__).parents[1]
    h = hashlib.sha256()
    for f in sorted(package.rglob("*.py")):
        h.update(str(f.relative_to(package)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def library_versions() -> dict:
    import importlib.metadata

    return {d: importlib.metadata.version(d) for d in _LIBRARIES}


@functools.cache
def _environment() -> str:
    """What a stored program depends on besides its arguments (computed once per process)."""
    return "|".join([source_hash(), *library_versions().values(), jax.default_backend()])


def _key(name: str, static, args, options) -> str | None:
    try:
        text = _canon((name, static, options), False) + "|" + _canon(args, True)
    except _Uncacheable as e:
        _log.debug("not stored: %s", e)
        return None
    try:
        environment = _environment()
    except Exception as e:  # e.g. a library without its package metadata: nothing is stored
        _log.debug("not stored: %s", e)
        return None
    config = [str(getattr(jax.config, k)) for k in
              ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion")]
    return hashlib.sha256("|".join([environment, *config, text]).encode()).hexdigest()


def call(fn, name: str, args: tuple, *, static=None, options=None, fallback, poly=None):
    """`fn(*args)` compiled with the compiler `options` (those this XLA knows: `_options.known_options`,
    asked only when something is compiled), through the store when it is enabled and every leaf of
    `args` is concrete; `fallback()` (the caller's own `jit` call) otherwise. `name` names `fn` (its
    module and qualified name) and `static` is whatever else `fn` was made from: both are part of
    the key, as are the `options` asked for.

    `poly`: None, or `(specs, text)`: `args` with `jax.ShapeDtypeStruct` leaves of symbolic shape
    (`jax.export.symbolic_shape`) that `fn` traces for, and a text naming their range. The traced
    program is then kept for all those shapes, under a key of its own (of `specs` and `text`, not
    of the compiler options), and a process that meets a new shape in the range compiles it
    without tracing. Executables stay keyed by the concrete shapes."""
    leaves, in_tree = jax.tree_util.tree_flatten(args)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return fallback()
    place = _placement(leaves)
    if place is None:
        return fallback()
    if _dir[0] is None:
        return _shipped_or(fallback, name, static, args, leaves, options, poly, place)
    key = _key(name, static, args, options)
    if key is None:
        return fallback()
    here = f"{key}|{place}"  # an executable runs on the devices it was compiled for
    if here not in _in_process:
        if poly is not None:
            poly_key = _poly_key(name, static, poly)
            poly = None if poly_key is None else (poly_key, jax.tree_util.tree_leaves(poly[0]))
        run, out_tree, loaded_from = _stored_or_compiled(fn, name, in_tree, leaves, key, place, options, poly=poly)
        if loaded_from is not None:
            # The first call of a loaded executable is waited for: one that loads but cannot run
            # (damaged, or written incomplete) is deleted, and the program compiled again.
            try:
                out = jax.block_until_ready(run(*leaves))
            except jax.errors.JaxRuntimeError as e:
                _log.warning("jaxoptics: dropping stored executable %s, which failed to run (%s)", loaded_from.name, e)
                loaded_from.unlink(missing_ok=True)
                run, out_tree, _ = _stored_or_compiled(fn, name, in_tree, leaves, key, place, options, load=False, poly=poly)
            else:
                _in_process[here] = run, out_tree
                return jax.tree_util.tree_unflatten(out_tree, out)
        _in_process[here] = run, out_tree
    run, out_tree = _in_process[here]
    return jax.tree_util.tree_unflatten(out_tree, run(*leaves))


def _placement(leaves) -> str | None:
    """Where the arrays among `leaves` live, which a compiled executable is tied to: one text per
    array (its devices by platform and id, and for a sharded array its mesh and partition spec);
    a NumPy array counts as living on JAX's default device, where a program compiled for it runs.
    Nothing here assumes a device: the same call on another device, a GPU, or a sharded array
    compiles (or loads) the program for that placement. None for a sharding without a stable
    text (its repr holds an address): such a call is not stored."""
    default = _default_device()
    texts = set()
    for x in leaves:
        if isinstance(x, jax.Array):
            texts.add(_sharding_text(x.sharding))
        elif isinstance(x, (np.ndarray, np.generic)):
            texts.add(default)
    try:
        return _checked(";".join(sorted(texts)))
    except _Uncacheable:
        return None


def _default_device() -> str:
    device = getattr(jax.config, "jax_default_device", None) or jax.devices()[0]
    if isinstance(device, str):  # a platform name: its first device
        device = jax.devices(device)[0]
    return _device_text(device)


def _device_text(d) -> str:
    return f"{d.platform}:{d.id}"


def _sharding_text(sh) -> str:
    if isinstance(sh, jax.sharding.SingleDeviceSharding):
        return _device_text(next(iter(sh.device_set)))
    if isinstance(sh, jax.sharding.NamedSharding):
        mesh = sh.mesh
        devices = ",".join(_device_text(d) for d in np.asarray(mesh.devices).ravel())
        return f"mesh({dict(zip(mesh.axis_names, mesh.devices.shape))} [{devices}]) {sh.spec} {sh.memory_kind}"
    return repr(sh)


def _shipped_or(fallback, name, static, args, leaves, options, poly, place):
    """Without the store: the program the package ships for all shapes of `poly` (see `call`),
    compiled once in this process for these shapes and the devices the arguments live on
    (`place`; no tracing); `fallback()` where none is shipped for this call (another form, other
    library versions, no `poly`)."""
    if poly is None or _SHIPPED[0] is None:
        return fallback()
    key = _key(name, static, args, options)
    if key is None or key in _not_shipped:
        return fallback()
    here = f"{key}|{place}"
    if here not in _in_process:
        poly_key = _poly_key(name, static, poly)
        got = None if poly_key is None else _load_shipped(poly_key)
        if got is None:
            _not_shipped.add(key)
            return fallback()
        exported, out_tree = got
        compiled = _ExportedJit(exported, known_options(options)).lower(*leaves).compile()
        _in_process[here] = compiled, out_tree
    run, out_tree = _in_process[here]
    return jax.tree_util.tree_unflatten(out_tree, run(*leaves))


_not_shipped: set[str] = set()  # keys of calls without a shipped program, looked for once


def _poly_key(name, static, poly) -> str | None:
    """The key of the program traced for all shapes of `poly = (specs, text)` (see `call`): of the
    specs and the range's text, not of the compiler options."""
    specs, text = poly
    return _key(name, (static, "for all shapes", text), specs, None)


def _stored_or_compiled(fn, name, in_tree, leaves, key, place, options, load=True, poly=None):
    """`(run, out_tree, loaded_from)` for the program of `key`: its executable loaded from the
    store (`loaded_from`: its file; unless not `load`); else its traced program loaded from the
    store and compiled (the one for these shapes, or, with `poly = (poly_key, spec_leaves)`, the
    one for all shapes of the specs); else `fn` traced and compiled here, once: for the specs'
    shapes where `poly` is given and that trace succeeds (the program is stored), else for these
    shapes (one trace and one lowering). What is compiled is stored as its executable, or, where
    that cannot be serialized, as its traced program (`loaded_from` None). Executables are kept
    per placement of the arguments (`place`, `_placement`); traced programs run anywhere."""
    exe_path = _dir[0] / (_executable_key(key, place) + _EXE_SUFFIX)
    loaded = _load_executable(exe_path) if load else None
    if loaded is not None:
        return (*loaded, exe_path)
    options = known_options(options)
    path = _dir[0] / (key + _SUFFIX)
    poly_path = None if poly is None else _dir[0] / (poly[0] + _SUFFIX)
    exported_tree = _load(path)
    if exported_tree is None and poly is not None:
        exported_tree = _load(poly_path) or _load_shipped(poly[0])
    if exported_tree is not None:  # for all shapes, or stored by a machine or backend without this executable
        exported, out_tree = exported_tree
        run, _ = _compile_and_store(_ExportedJit(exported, options), leaves, lambda: out_tree, exe_path)
        return run, out_tree, None
    flat, out_trees = _flat(fn, name, in_tree)
    if poly is not None:
        exported = _export_for_all_shapes(flat, out_trees, poly[1], poly_path)
        if exported is not None:
            run, _ = _compile_and_store(_ExportedJit(exported, options), leaves,
                                        lambda: out_trees[0], exe_path)
            return run, out_trees[0], None
    jitted = jax.jit(flat, compiler_options=options)
    run, stored = _compile_and_store(jitted, leaves, lambda: out_trees[0], exe_path)
    if not stored:
        _export(jitted, out_trees[0], leaves, path)  # the same `jit`: its trace is reused
    return run, out_trees[0], None


_EXE_SUFFIX = ".xlaexec"


@functools.cache
def _machine() -> str:
    """What a compiled executable depends on besides its program: the backend's platform and
    version, and on the CPU the processor's model and instruction-set extensions (XLA compiles
    for the host's)."""
    import platform

    dev = jax.devices()[0]
    parts = [dev.platform, dev.device_kind, dev.client.platform_version, platform.machine()]
    try:
        with open("/proc/cpuinfo") as f:
            info = f.read()
        wanted = ("model name", "flags", "Features", "CPU implementer", "CPU part")  # x86; Arm
        seen: dict = {}
        for line in info.splitlines():
            name = line.split(":")[0].strip()
            if name in wanted:
                seen.setdefault(name, line)
        parts += seen.values()
    except OSError:
        parts.append(platform.processor())
    return "|".join(parts)


def _executable_key(key: str, place: str) -> str:
    return hashlib.sha256(f"{key}|{place}|{_machine()}".encode()).hexdigest()


_jax_cache_hits = [0]
_listening: list[bool] = []


def _count_jax_cache_hits(event: str, **kwargs) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _jax_cache_hits[0] += 1


def _compile_and_store(jitted, leaves, out_tree, path: Path):
    """`(compiled, stored)`: `jitted` compiled for `leaves`, and whether its executable was written
    to `path` (with the output tree `out_tree()`).

    An executable that JAX's persistent compilation cache supplied is not written: serialized
    again, it lacks its kernels (jaxlib 0.10 on the CPU: a process that loads it fails when it
    runs it, "Function ..._kernel not found"). That happens where the store misses a program
    JAX's cache holds: its file deleted or pruned, or stored under the key of another jaxoptics
    version. Its traced program is stored instead (`_export`, or already stored for all shapes):
    the next process compiles that, and stores its executable unless JAX's cache supplied that
    one too (for a program stored for all shapes, which is what the first process compiled, it
    does: such processes compile the stored program from JAX's cache, without tracing)."""
    from jax.experimental import serialize_executable

    if not _listening:
        jax.monitoring.register_event_listener(_count_jax_cache_hits)
        _listening.append(True)
    lowered = jitted.lower(*leaves)  # (programs run while tracing are compiled, and counted, here)
    hits = _jax_cache_hits[0]
    compiled = lowered.compile()
    if _jax_cache_hits[0] != hits:
        _log.debug("executable not stored: it came from JAX's compilation cache")
        return compiled, False
    try:
        targets = sorted(set(_CUSTOM_CALL.findall(compiled.as_text() or "")))
        if any(not t.startswith("lapack_") for t in targets):
            raise _Uncacheable(f"custom calls {targets}")  # their libraries' set-up is unknown here
        blob = pickle.dumps((serialize_executable.serialize(compiled), out_tree(), targets))
    except Exception as e:  # a backend without executable serialization
        _log.debug("executable not stored: %s", e)
        return compiled, False
    _write(path, blob)
    return compiled, True


_CUSTOM_CALL = re.compile(r'custom_call_target="([^"]+)"')


def _initialize_lapack() -> None:
    """Set up jaxlib's LAPACK kernels, which lowering a linear-algebra operation does and loading
    an executable does not: an executable that calls them before this crashes the process."""
    from jaxlib import lapack

    lapack.prepare_lapack_call("geqrf", np.float64)


def _load_executable(path: Path):
    def parse(blob):
        from jax.experimental import serialize_executable

        (payload, in_tree, exe_out_tree), out_tree, targets = pickle.loads(blob)
        if targets:  # LAPACK's only (`_compile_and_store`)
            _initialize_lapack()
        return serialize_executable.deserialize_and_load(payload, in_tree, exe_out_tree), out_tree

    return _read_stored(path, parse, "executable")


def _read_stored(path: Path, parse, what: str):
    """`parse(bytes of path)`, or None if there is no such file; a file that does not parse (damaged,
    or foreign) is deleted, so that it is written again."""
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    try:
        value = parse(blob)
    except Exception as e:
        _log.warning("jaxoptics: dropping unreadable stored %s %s (%s)", what, path.name, e)
        path.unlink(missing_ok=True)
        return None
    try:
        os.utime(path)  # least recently used first out
    except OSError:  # pruned by another process meanwhile
        pass
    return value


_in_process: dict[str, tuple] = {}


class _ExportedJit:
    """`jax.jit(exported.call, compiler_options=options)`, lowered (`lower`) without jax's set-up
    of its LAPACK kernels where the program calls none.

    Lowering a `jax.export` program for the CPU sets those kernels up whatever the program calls
    (jax 0.10's `_call_exported_lowering`), and that set-up imports `scipy.linalg`: 0.35 s of a
    fresh process's first index fit, whose program (a real index) has no LAPACK call. Where the
    serialized program names no `lapack_` target, the set-up is skipped for that one lowering; a
    jax without the hook lowers as usual. The hook is swapped under a lock that every lowering
    here takes, so two threads of the package never see each other's swap (a `jax.export`
    program of another library lowered at that instant in another thread would; it is a window
    of one lowering)."""

    def __init__(self, exported, options):
        self.jitted = jax.jit(exported.call, compiler_options=options)
        self.lapack = b"lapack_" in bytes(exported.mlir_module_serialized)

    def lower(self, *leaves):
        try:
            from jax._src.export import _export as hook_module
        except ImportError:
            hook_module = None
        hook = getattr(hook_module, "_ensure_backends_initialized", None)
        with _LOWERING:
            if self.lapack or hook is None:
                return self.jitted.lower(*leaves)
            hook_module._ensure_backends_initialized = lambda platforms: None
            try:
                return self.jitted.lower(*leaves)
            finally:
                hook_module._ensure_backends_initialized = hook


_LOWERING = threading.Lock()


def _parse_program(blob):
    data, out_tree = _Unpickler(io.BytesIO(blob)).load()
    return jax.export.deserialize(data), out_tree


def _load(path: Path):
    return _read_stored(path, _parse_program, "program")


# Traced programs shipped with the package, for all shapes (`call`'s `poly`), under the keys the
# store gives them: those of the command line's index fits (`jaxoptics.tools.make_programs`
# writes them and lists what they are in its manifest). Read only, and found only by a process
# whose key names the same package source and library versions. None: not looked at.
_SHIPPED: list[Path | None] = [Path(__file__).parents[1] / "data" / "programs"]


SHIPPED_SUFFIX = _SUFFIX + ".xz"  # LZMA-compressed


def _load_shipped(key: str):
    if _SHIPPED[0] is None:
        return None
    path = _SHIPPED[0] / (key + SHIPPED_SUFFIX)
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    try:
        import lzma

        return _parse_program(lzma.decompress(blob))
    except Exception as e:
        _log.warning("jaxoptics: unreadable shipped program %s (%s)", path.name, e)
        return None


class _Unpickler(pickle.Unpickler):
    """Unpickles only what a stored file holds: bytes and the output's tree structure (JAX's
    `PyTreeDef`, its registry and jaxoptics' result classes), nothing a planted file could run."""

    def find_class(self, module, name):
        root = module.split(".")[0]
        if (root in ("jax", "jaxlib") and name in ("PyTreeDef", "default_registry")) or root == "jaxoptics":
            obj = super().find_class(module, name)
            if root != "jaxoptics" or isinstance(obj, type):
                return obj
        raise pickle.UnpicklingError(f"{module}.{name} is not part of a stored program")


def _flat(fn, name, in_tree):
    """`fn` on the flat leaves of its arguments, returning the flat leaves of its output (whose
    tree structure is appended to the list returned with it when traced)."""
    out_tree = []

    def flat(*xs):
        out = fn(*jax.tree_util.tree_unflatten(in_tree, xs))
        ys, tree = jax.tree_util.tree_flatten(out)
        out_tree.append(tree)
        return ys

    flat.__name__ = flat.__qualname__ = name.rsplit(".", 1)[-1]  # the program's name in JAX's logs
    return flat, out_tree


def _traced(jitted, args):
    """`jax.export` of `jitted` for `args` (arrays, or specs of symbolic shape). Custom calls without
    JAX's cross-version guarantee (LAPACK's QR, ...) are allowed: a stored program is only ever
    loaded by the jax and jaxlib versions that wrote it (the key)."""
    return jax.export.export(jitted, disabled_checks=[jax.export.DisabledSafetyCheck.custom_call("ALL")])(*args)


def _store_traced(exported, out_tree, path: Path) -> None:
    """Write `exported` with its output tree to `path`; nothing where it cannot be serialized."""
    try:
        blob = pickle.dumps((bytes(exported.serialize()), out_tree))
    except Exception as e:  # not serializable (host callbacks, ...): not stored
        _log.debug("not stored: %s", e)
        return
    _write(path, blob)


def _export(jitted, out_tree, leaves, path: Path) -> None:
    """Store the traced program of `jitted` (a `jit` of a `_flat` function already lowered for
    `leaves`, so JAX's trace cache serves the trace) with its output tree."""
    try:
        exported = _traced(jitted, leaves)
    except Exception as e:  # not exportable (host callbacks, ...): not stored
        _log.debug("not stored: %s", e)
        return
    _store_traced(exported, out_tree, path)


def _export_for_all_shapes(flat, out_trees, specs, path: Path):
    """`flat` traced for the symbolic shapes of `specs` (`jax.export`), stored in `path` with its
    output tree; None where it cannot be traced so (then nothing is stored). A program that cannot
    be serialized is returned all the same (and compiled in this process only)."""
    try:
        exported = _traced(jax.jit(flat), specs)
    except Exception as e:  # a function that needs concrete shapes: traced for these shapes instead
        _log.debug("no program for all shapes: %s", e)
        return None
    _store_traced(exported, out_trees[0], path)
    return exported


def _write(path: Path, blob: bytes) -> None:
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
        _prune(path.parent)
    except OSError as e:  # a read-only or full disk: the program still runs
        _log.warning("jaxoptics: could not store the program (%s)", e)
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


def _prune(folder: Path) -> None:
    files = []
    for f in [*folder.glob("*" + _SUFFIX), *folder.glob("*" + _EXE_SUFFIX)]:
        try:
            st = f.stat()
        except OSError:
            continue
        files.append((st.st_mtime, st.st_size, f))
    total = sum(s for _, s, _ in files)
    for _, size, f in sorted(files, key=lambda t: t[0]):
        if total <= MAX_BYTES:
            break
        f.unlink(missing_ok=True)
        total -= size
