"""The test oracle: 50-digit mpmath transcriptions of the textbook formulas (`jaxoptics.tools.mpref`,
which calls no kernel: it is an independent transcription, shared with the stress test); and
`quick_jit`, for the tests' own programs around fits and models; `xla_flags_without`, for the
processes that run with XLA's defaults."""

import os

import jax

from jaxoptics._runtime._options import QUICK_COMPILE
from jaxoptics.tools.mpref import backward_bound, fresnel_ref, fresnel_specials, mpc, mpf, refract_ref, spacing, stack_ref  # noqa: F401


def quick_jit(fun, **kwargs):
    """`jax.jit` with the package's quick compiler options (`QUICK_COMPILE`, which the fits choose
    for small problems and a caller may choose too): for a test's own program around fits and
    models whose values it compares far above the rounding these options change (derivatives
    against finite differences, a Jacobian against jacfwd), which then compiles in about two
    thirds of the time. Not for the kernels' edge-case tests, where the rounding of XLA's default
    compilation is the property."""
    return jax.jit(fun, compiler_options=QUICK_COMPILE, **kwargs)


def xla_flags_without(*names: str) -> str:
    """The suite's `XLA_FLAGS` (`conftest.py`) without the flags named, for a process that runs
    with XLA's defaults for them."""
    return " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f.lstrip("-").split("=")[0] not in names)
