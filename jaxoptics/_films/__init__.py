"""Thin films and materials: the multilayer kernel and ellipsometry (`_stack`, with its layer
recursion in `_layers` and elementary functions in `_elementary`), dispersion models with free
parameters (`_dispersion`, and the oscillator models of ellipsometry software in `_oscillators`),
effective-medium mixtures (`_ema`), graded layers (`_graded`), published dispersion laws
(`_materials`), refractiveindex.info materials (`_rii`), the layered sample with its roughness
layer (`_sample`), and the measurement's non-idealities (`_instrument`).

May import: `_core`, `_interface`.
"""
