"""The compiler options of the programs the fits compile, and `filter_jit` with them.

`FAST_CODEGEN` has XLA's CPU backend emit its loop fusions with its LLVM IR emitters rather than
its (default) MLIR fusion emitters: the fits then compile in a third to a half less time and run
as fast. Measured side by side (float64, fresh processes): a one-curve `fit_eta` program 1.04 ->
0.43 s to compile; `fit_eta` on 10^4 curves, first call 2.77 -> 2.14 s, then 35.9 against 35.0 ms;
`fit_stack` on 1000 spectra, first call 17.0 -> 12.7 s, then 2.27 against 2.31 s; the same
estimates. An XLA that no longer knows the option compiles without it (`compiler_options`).

`QUICK_COMPILE` also turns XLA's backend (LLVM) optimizations off. A small fit (one curve, one
spectrum) then compiles in about a third less time, and its solve runs a few milliseconds slower
at most; the fits choose it by the size of the problem (`_fit_followups`, `_stack_fit`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import numpy as np

from . import _cache

FAST_CODEGEN = {"xla_cpu_use_fusion_emitters": False}
QUICK_COMPILE = {**FAST_CODEGEN, "xla_backend_optimization_level": 0}


def compiler_options(quick: bool) -> dict:
    """`QUICK_COMPILE` or `FAST_CODEGEN`, without the options this XLA does not know."""
    wanted = tuple((QUICK_COMPILE if quick else FAST_CODEGEN).items())
    return dict(wanted) if _known(wanted) else {k: v for k, v in wanted if _known(((k, v),))}


@functools.cache
def _known(options: tuple) -> bool:
    """Whether XLA accepts the compiler options (one trivial compilation, once per process)."""
    try:
        jax.jit(lambda x: x, compiler_options=dict(options)).lower(np.float32(0)).compile()
    except Exception:  # XLA's "No such compile option" (its exception type varies across jax versions)
        return False
    return True


def filter_jit(fn):
    """`fn` compiled as `eqx.filter_jit` does it (arrays traced, everything else static), with
    `compiler_options(quick)` on concrete arrays (inside the caller's own `jit`, it is the
    caller's program that gets compiled, with the caller's options). Called on concrete arrays
    while the program store is enabled (`jaxoptics.enable_cache`), the traced program is kept
    between processes (`_cache`)."""

    def run(static, dynamic):
        args, kwargs = _combine(static, dynamic)
        return fn(*args, **kwargs)

    run.__name__ = run.__qualname__ = fn.__name__  # the program's name in JAX's logs and profiles
    inner = jax.jit(run, static_argnums=0)  # inside the caller's program

    @functools.cache
    def compiled(quick):
        options = compiler_options(quick)
        return jax.jit(run, static_argnums=0, compiler_options=options), options

    name = f"{fn.__module__}.{fn.__qualname__}"

    @functools.wraps(fn)
    def call(*args, quick=False, **kwargs):
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(static)
        static_key = (treedef, tuple(leaves))
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(dynamic)):
            return inner(static_key, dynamic)
        jitted, options = compiled(bool(quick))
        fallback = lambda: jitted(static_key, dynamic)
        if not _cache.enabled():
            return fallback()
        return _cache.call(functools.partial(run, static_key), name, (dynamic,), static=static, options=options,
                           fallback=fallback)

    return call


def _combine(static, dynamic):
    treedef, leaves = static
    return eqx.combine(dynamic, jax.tree_util.tree_unflatten(treedef, leaves))
