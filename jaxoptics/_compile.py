"""The compiler options of the programs the fits compile, and `filter_jit` with them.

`QUICK_COMPILE`, for small fits (one curve, one spectrum: the fits choose it by the size of the
problem, `_fit_followups`, `_stack_fit`), where compiling is most of the time a fit takes:

- XLA's backend (LLVM) optimizations off: about a third less compile time, and a solve a few
  milliseconds slower at most;
- loops emitted by XLA's LLVM IR emitters rather than its (default) MLIR fusion emitters: a
  one-curve `fit_eta` program compiles in 0.43 s against 1.04 s, the bundled `fit-stack` example's
  first call takes 7.1 s against 8.8 s, with the same estimates (measured side by side, float64).

Large batches keep XLA's defaults, whose run time matters more: with the IR emitters, 3000
complex (`absorbing=True`) fits compiled in 6.3 s against 8.0 s but ran in 0.96 s against 0.67 s.
An XLA that does not know an option compiles without it (`compiler_options`).
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from . import _cache

QUICK_COMPILE = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


def wanted_options(quick: bool) -> dict | None:
    """The options a program is compiled with where this XLA knows them all: `QUICK_COMPILE` for
    `quick`, else None (XLA's defaults). No compilation: the program store (`_cache`) keys its
    programs by these, so a process that loads its executables never probes XLA."""
    return dict(QUICK_COMPILE) if quick else None


def compiler_options(quick: bool) -> dict | None:
    """`wanted_options(quick)` without the options this XLA does not know."""
    return known_options(wanted_options(quick))


def known_options(options: dict | None) -> dict | None:
    """`options` without those this XLA does not know (a trivial compilation per option set, once
    per process: about 40 ms)."""
    if options is None:
        return None
    wanted = tuple(options.items())
    return dict(wanted) if _known(wanted) else {k: v for k, v in wanted if _known(((k, v),))}


@functools.cache
def _known(options: tuple) -> bool:
    """Whether XLA accepts the compiler options (one trivial compilation, once per process)."""
    try:
        jax.jit(lambda x: x, compiler_options=dict(options)).lower(np.float32(0)).compile()
    except Exception:  # XLA's "No such compile option" (its exception type varies across jax versions)
        return False
    return True


def filter_jit(fn=None, *, poly=None):
    """`fn` compiled as `eqx.filter_jit` does it (arrays traced, everything else static), with
    `compiler_options(quick)` on concrete arrays (inside the caller's own `jit`, it is the
    caller's program that gets compiled, with the caller's options). Called on concrete arrays
    while the program store is enabled (`jaxoptics.enable_cache`), the traced program is kept
    between processes (`_cache`).

    `poly(dynamic)`: for the array arguments `dynamic` (a tree `(args, kwargs)` with None in the
    places of the other arguments), the same tree of `jax.ShapeDtypeStruct` with symbolic
    dimensions (`jax.export`) and a text naming their range, or None. The store then keeps one
    traced program for all the shapes it covers (`_cache.call`)."""
    if fn is None:
        return functools.partial(filter_jit, poly=poly)

    def run(static, dynamic):
        args, kwargs = _combine(static, dynamic)
        return fn(*args, **kwargs)

    run.__name__ = run.__qualname__ = fn.__name__  # the program's name in JAX's logs and profiles
    inner = jax.jit(run, static_argnums=0)  # inside the caller's program

    @functools.cache
    def compiled(quick):
        return jax.jit(run, static_argnums=0, compiler_options=compiler_options(quick))

    name = f"{fn.__module__}.{fn.__qualname__}"

    @functools.wraps(fn)
    def call(*args, quick=False, **kwargs):
        dynamic, static = _partition((args, kwargs))
        leaves, treedef = jax.tree_util.tree_flatten(static)
        static_key = (treedef, tuple(leaves))
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(dynamic)):
            return inner(static_key, dynamic)
        fallback = lambda: compiled(bool(quick))(static_key, dynamic)
        if not _cache.enabled() and poly is None:
            return fallback()
        return _cache.call(functools.partial(run, static_key), name, (dynamic,), static=static,
                           options=wanted_options(bool(quick)), fallback=fallback,
                           poly=None if poly is None else _poly_args(poly, dynamic))

    return call


def _poly_args(poly, dynamic):
    """`((specs,), text)` from `poly(dynamic)` for `_cache.call`, whose arguments are `(dynamic,)`."""
    got = poly(dynamic)
    return None if got is None else ((got[0],), got[1])


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic))


def _partition(tree):
    """(arrays, everything else) of `tree`, each with None in the other's places: equinox's
    `partition(tree, is_array)`, without importing equinox (a process that loads its compiled fits
    from the store does not need it)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    pick = lambda want: jax.tree_util.tree_unflatten(treedef, [x if _is_array(x) == want else None for x in leaves])
    return pick(True), pick(False)


def _combine(static, dynamic):
    """The inverse of `_partition`: `dynamic` with the leaves of `static` in its None places."""
    treedef, leaves = static
    rest = jax.tree_util.tree_unflatten(treedef, leaves)
    is_none = lambda x: x is None
    return jax.tree_util.tree_map(lambda a, b: b if a is None else a, dynamic, rest, is_leaf=is_none)
