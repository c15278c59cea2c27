"""The fit statistics ellipsometry users compare between programs: WVASE's MSE, CompleteEASE's
N, C, S MSE, 90% confidence limits, and the counts they are formed from (`fit_statistics`).

Definitions (`docs/layered-fits.md#fit-statistics` gives the sources), for one spectrum of `N`
points `(wavelength, angle)`, `m` data (quantity values) and `M` free parameters:

- `mse`: WVASE's mean squared error, `sqrt(sum_j ((model_j - data_j) / sigma_j)^2 / (m - M))`;
  for Psi/Delta data `m = 2N` and this is `sqrt(1/(2N - M) sum [(dPsi/sigma_Psi)^2 +
  (dDelta/sigma_Delta)^2])`. It equals `sqrt(chi2_reduced)`; it needs the data's sigma (NaN
  without).
- `mse_ncs`: CompleteEASE's, `1000 sqrt(sum (dN^2 + dC^2 + dS^2) / (q N - M))` over the `q` of
  N, C, S the data determine (3 for Psi/Delta, N, C, S or a Mueller matrix; 2 for N, C of folded
  data), unweighted, with the data's N, C, S formed from its Psi and Delta where it gives those.
  NaN for photometric data.
- `ci90`: the 90% confidence limits `1.65 sqrt(mse C_ii)` with `C = (J^T W J)^-1` the
  covariance of the sigma-weighted fit before any scaling by chi^2 (`StackFit.covariance`
  divided by `max(1, chi2_reduced)`); without sigma, `1.65` times the standard error (which is
  then scaled by the residual scatter).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from .._films._sample import Sample
    from .._io._spectra import Spectra
    from ._stack_fit import StackFit

_NCS = ("N", "C", "S")


class FitStatistics(NamedTuple):
    """What `fit_statistics` returns; arrays over the map's sites (leading axes, `()` for one
    spectrum).

    **Fields:** `mse` and `mse_ncs` `(...)`; `chi2_reduced` `(...)`; `ci90` `(..., M)` in the
    parameters' units; `correlation` `(..., M, M)`; `names` (the free parameters); `n_points` `N`,
    `n_data` `m`, `n_params` `M`, `n_ncs` (the `q N` data of the N, C, S MSE, 0 without them).
    """

    names: tuple
    mse: np.ndarray
    mse_ncs: np.ndarray
    chi2_reduced: np.ndarray
    ci90: np.ndarray
    correlation: np.ndarray
    n_points: int
    n_data: int
    n_params: int
    n_ncs: int

    def table(self, site: int | None = None) -> str:
        """The statistics of one site (the first, or `site=i`) as text."""
        k = site or 0
        pick = lambda a: np.asarray(a).reshape((-1,) + np.shape(a)[np.ndim(self.mse):])[k]
        rows = [f"MSE (WVASE, sigma-weighted, {self.n_data} - {self.n_params} dof) {float(pick(self.mse)):.4g}; "
                f"MSE (CompleteEASE N,C,S x1000, {self.n_ncs} - {self.n_params} dof) {float(pick(self.mse_ncs)):.4g}"]
        w = max(len(n) for n in self.names)
        for n, c in zip(self.names, pick(self.ci90)):
            rows.append(f"{n:<{w}}  90% confidence +-{float(c):.3g}")
        return "\n".join(rows)


def _data_ncs(spectra):
    """The data's N, C, S `(..., q, P)` and which of them (names), from its Psi/Delta or N, C, S
    quantities; None for photometric data."""
    V, kinds = np.asarray(spectra.values, np.float64), tuple(spectra.kinds)
    got = {k: V[..., kinds.index(k), :] for k in _NCS if k in kinds}
    if "psi_deg" in kinds and "delta_deg" in kinds:
        p2 = np.radians(2 * V[..., kinds.index("psi_deg"), :])
        d = np.radians(V[..., kinds.index("delta_deg"), :])
        got = {"N": np.cos(p2), "C": np.sin(p2) * np.cos(d), "S": np.sin(p2) * np.sin(d), **got}
    if not got:
        return None, ()
    names = tuple(k for k in _NCS if k in got)
    return np.stack([got[k] for k in names], axis=-2), names


@functools.lru_cache(maxsize=16)
def _model_ncs(sample, names):
    """`(X, wavelength_nm, angle_rad) -> N, C, S` of `sample` for parameter rows `X` `(B, M)`, one
    compiled program per sample."""
    import jax

    one = lambda x, w, a: sample.with_values(list(x)).quantities(names, w, a)
    return jax.jit(jax.vmap(one, in_axes=(0, None, None)))


def fit_statistics(sample: Sample, spectra: Spectra, fit: StackFit) -> FitStatistics:
    """WVASE's and CompleteEASE's MSE, 90% confidence limits and the correlation matrix of a
    `fit_stack` result (see the module docstring for the definitions), for every site of a map.

    **Arguments:** the `sample` and `spectra` given to `fit_stack`, and its result `fit`.

    **Returns:** a `FitStatistics`. The N, C, S MSE evaluates the model at the fitted values (one
    compiled program per sample, kept for the next call).
    """
    import jax.numpy as jnp

    batch = tuple(spectra.values.shape[:-2])
    Q, N = spectra.values.shape[-2:]
    M = len(fit.names)
    chi = np.asarray(fit.chi2_reduced, np.float64)
    mse = np.sqrt(chi) if fit.sigma_given else np.full(chi.shape, np.nan)
    data, names = _data_ncs(spectra)
    if data is None:
        mse_ncs = np.full(batch, np.nan)
        n_ncs = 0
    else:
        X = np.asarray(fit.values, np.float64).reshape(-1, M)
        f = _model_ncs(sample, names)
        model = np.asarray(f(jnp.asarray(X), jnp.asarray(spectra.wavelength_nm), jnp.deg2rad(jnp.asarray(spectra.angle_deg))))
        d = model.reshape(batch + model.shape[1:]) - data
        n_ncs = len(names) * N
        mse_ncs = 1000 * np.sqrt(np.sum(d * d, axis=(-2, -1)) / max(n_ncs - M, 1))
    sd = np.asarray(fit.stderr, np.float64)
    if fit.sigma_given:  # the unscaled covariance: StackFit's is scaled by max(1, chi2_reduced)
        ci90 = 1.65 * sd / np.sqrt(np.maximum(1.0, chi))[..., None] * np.sqrt(mse)[..., None]
    else:
        ci90 = 1.65 * sd
    return FitStatistics(tuple(fit.names), mse, mse_ncs, chi, ci90, np.asarray(fit.correlation), N, Q * N, M, n_ncs)
