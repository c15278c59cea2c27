"""Building blocks every other part uses: the result containers (`_result`), the checks of
arguments at trace time (`_validate`), and the numerical helpers written for XLA (`_numerics`:
values stored once, double-where square roots, the decaying branch of a complex root), and the
wrapper that runs a public kernel as one compiled program when called eagerly (`_program`).

May import: nothing of jaxoptics.
"""
