"""`FitResult`, the result of the index fits (`fit_eta`, and per wavelength `fit_dispersion`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._core._result import result


@result
class FitResult:
    """Result of `fit_eta`, a pytree usable under `jit` and `vmap`. Batch shape `(...)` is that of
    the curves.

    **Fields:**

    - `eta`: fitted index, `(...)`; real, or complex `n + ik` on the physical branch `n > 0, k >= 0`
      for `absorbing=True`.
    - `stderr`: standard error of `eta`, `(...)`: real; for complex fits, complex with the standard
      error of `n` as real part and that of `k` as imaginary part (see `corr_nk`). It is `inf` for a
      parameter the data do not constrain to first order (e.g. `k` fitted as exactly 0: `R` depends
      on `k` only quadratically there).
    - `covariance`: `(..., p, p)` covariance of the parameters (`eta`, or `(n, k)`), from the
      Jacobian at the solution: `(J^T J)^-1` with residuals scaled by `1/sigma` when `sigma` is given
      (times `max(1, chi2_reduced)`, so data inconsistent with their `sigma` widen the errors),
      times the reduced chi-square `RSS / (m - p)` when it is not.
    - `converged`: `(...)` bool: the solver reported success, the estimate is finite and its error
      is not NaN.
    - `residual_rms`: `(...)` root mean square of the unweighted residuals `R_model - R`.
    - `chi2_reduced`: `(...)` `sum(((R_model - R) / sigma)^2) / (m - p)` (with `sigma = 1` when
      not given); about 1 for a good model with correct `sigma`.
    - `num_steps`: `(...)` solver iterations.
    - `eta_alt`: `(...)` the other branch's index where the data cannot tell it from `eta`, else
      NaN (always NaN for complex fits). Below the critical angle a medium less dense than the
      incident one (`eta2 < eta1`) and a denser one give similar curves; where the data stop short
      of what separates them (the TIR plateau, large angles) both fit. Both branches are solved,
      `eta` is the one with the smaller chi-square, and where the other is within
      `Delta chi2 < 9` (three standard deviations: not excluded by the data) it is reported here
      and `stderr` includes the distance to it (`sqrt(stderr_local^2 + (eta - eta_alt)^2)`, the
      covariance likewise): the data do not determine the index better than that.
    """

    eta: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    converged: jax.Array
    residual_rms: jax.Array
    chi2_reduced: jax.Array
    num_steps: jax.Array
    eta_alt: jax.Array

    @property
    def corr_nk(self):
        """Correlation of the errors of `n` and `k` (complex fits), `(...)`."""
        c = self.covariance
        return c[..., 0, 1] / jnp.sqrt(c[..., 0, 0] * c[..., 1, 1])
