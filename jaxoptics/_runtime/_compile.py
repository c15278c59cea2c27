"""`filter_jit`: a function compiled as `eqx.filter_jit` does it, with the fits' compiler options
(`_options`), and kept between processes by the program store (`_cache`)."""

from __future__ import annotations

import functools

import jax
import numpy as np

from . import _cache
from ._options import compiler_options, wanted_options


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
