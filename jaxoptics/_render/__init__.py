"""The fused kernels for renderers: an interface kernel specialized to what a scene needs, and its
material-level form over mirrors, dielectrics, conductors and coated surfaces (`_scene`).

May import: `_core`, `_interface`, `_films`.
"""
