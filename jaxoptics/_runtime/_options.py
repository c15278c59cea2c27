"""The compiler options of the programs the fits compile.

`QUICK_COMPILE`, for small fits (one curve, one spectrum: the fits choose it by the size of the
problem, `_fitting._index_stages`, `_fitting._stack_fit`), where compiling is most of the time a fit takes:

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
