"""The fitters and their figures: the index fit of reflectance curves (`_index`, with its model
`_index_model`, starts `_index_starts`, batched solve `_index_solver`, follow-up stages and
derivatives `_index_stages`, and result `_index_result`), the dispersion-law fit
(`_dispersion_fit`), the film fit of layered samples (`_stack_fit`, its stages
`_stack_fit_stages`, its Jacobian `_stack_jacobian`, the pooled solver `_pool`, joint fits of
several data sets `_joint`, point-by-point n and k `_nk`, the statistics users compare with other programs, `_statistics`,
and reflectometry's absolute reflectance and Fourier-transform start, `_reflectometry`), and the
figures of all three (`_plot`).

May import: `_core`, `_runtime`, `_interface`, `_films`, `_io`.
"""
