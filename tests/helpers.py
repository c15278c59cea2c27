"""The test oracle: 50-digit mpmath transcriptions of the textbook formulas (`jaxoptics.tools.mpref`,
which calls no kernel: it is an independent transcription, shared with the stress test); and
`quick_jit`, for the tests' own programs around fits and models."""

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
