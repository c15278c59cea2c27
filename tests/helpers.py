"""The test oracle: 50-digit mpmath transcriptions of the textbook formulas (`jaxoptics.tools.mpref`,
which calls no kernel: it is an independent transcription, shared with the stress test)."""

from jaxoptics.tools.mpref import backward_bound, fresnel_ref, fresnel_specials, mpc, mpf, refract_ref, spacing, stack_ref  # noqa: F401
