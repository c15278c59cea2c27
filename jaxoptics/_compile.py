"""Compilation where the compile time is what a user waits for.

`QUICK_COMPILE` turns XLA's backend (LLVM) optimizations off. A small fit (one curve, one
spectrum) then compiles in about a third less time, and its solve runs a few milliseconds slower
at most; the fits choose it by the size of the problem (`_fit_followups`, `_stack_fit`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax

QUICK_COMPILE = {"xla_backend_optimization_level": 0}


def filter_jit(fn):
    """`fn` compiled as `eqx.filter_jit` does it (arrays traced, everything else static), with
    `QUICK_COMPILE` when called with `quick=True` on concrete arrays (inside the caller's own
    `jit`, it is the caller's program that gets compiled, with the caller's options)."""

    def compiled(options):
        def run(static, dynamic):
            treedef, leaves = static
            args, kwargs = eqx.combine(dynamic, jax.tree_util.tree_unflatten(treedef, leaves))
            return fn(*args, **kwargs)

        run.__name__ = run.__qualname__ = fn.__name__  # the program's name in JAX's logs and profiles
        return jax.jit(run, static_argnums=0, compiler_options=options)

    runs = {False: compiled(None), True: compiled(QUICK_COMPILE)}

    @functools.wraps(fn)
    def call(*args, quick=False, **kwargs):
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(static)
        quick = quick and not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(dynamic))
        return runs[quick]((treedef, tuple(leaves)), dynamic)

    return call
