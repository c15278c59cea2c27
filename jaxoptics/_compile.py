"""Compilation where the compile time is what a user waits for.

`QUICK_COMPILE` turns XLA's backend (LLVM) optimizations off. A small fit (one curve, one
spectrum) then compiles in about a third less time, and its solve runs a few milliseconds slower
at most; the fits choose it by the size of the problem (`_fit_followups`, `_stack_fit`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax

from . import _cache

QUICK_COMPILE = {"xla_backend_optimization_level": 0}


def filter_jit(fn):
    """`fn` compiled as `eqx.filter_jit` does it (arrays traced, everything else static), with
    `QUICK_COMPILE` when called with `quick=True` on concrete arrays (inside the caller's own
    `jit`, it is the caller's program that gets compiled, with the caller's options). Called on
    concrete arrays while the program store is enabled (the command line), the traced program is
    kept between processes (`_cache`)."""

    def compiled(options):
        def run(static, dynamic):
            args, kwargs = _combine(static, dynamic)
            return fn(*args, **kwargs)

        run.__name__ = run.__qualname__ = fn.__name__  # the program's name in JAX's logs and profiles
        return jax.jit(run, static_argnums=0, compiler_options=options)

    runs = {False: compiled(None), True: compiled(QUICK_COMPILE)}

    name = f"{fn.__module__}.{fn.__qualname__}"

    @functools.wraps(fn)
    def call(*args, quick=False, **kwargs):
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(static)
        quick = quick and not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(dynamic))
        static_key = (treedef, tuple(leaves))
        fallback = lambda: runs[quick](static_key, dynamic)
        if not _cache.enabled():
            return fallback()

        def combined(dynamic):
            args, kwargs = _combine(static_key, dynamic)
            return fn(*args, **kwargs)

        return _cache.call(combined, name, (dynamic,), static=static, options=QUICK_COMPILE if quick else None,
                              fallback=fallback)

    return call


def _combine(static, dynamic):
    treedef, leaves = static
    return eqx.combine(dynamic, jax.tree_util.tree_unflatten(treedef, leaves))
