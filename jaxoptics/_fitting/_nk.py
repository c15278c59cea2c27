"""Point-by-point n and k (`fit_nk`): one layer's index fitted at every wavelength on its own,
the rest of the sample held at the values of a parametric fit.

Each wavelength's data (all its angles and quantities) make a two-parameter least-squares problem
in `n` and `k`, solved by Levenberg-Marquardt for all wavelengths at once (a `vmap` of optimistix's
solver); its start is the layer's index from the parametric model (a dispersion law, a B-spline)
at that wavelength, which keeps each solution on the branch the parametric fit chose. With
`smoothness > 0` the wavelengths are then solved together from there, with the penalty rows
`smoothness (x_{j+1} - 2 x_j + x_{j-1}) / sigma_x` for `n` and `k` added to the residuals
(`sigma_x` the median standard error of the independent solutions: at `smoothness = 1` a second
difference of one standard error costs as much as one standard deviation of the data), a
Tikhonov regularization of the curvature. It biases a curve whose true curvature between
neighbouring wavelengths exceeds the data's errors: it suits densely sampled, noisy spectra, and
its weight is the user's choice (a value near 0.1 is a mild one). The standard errors are each
wavelength's own, from the Jacobian of its data at the solution (`(J^T J)^-1`, scaled by
chi^2/dof, at least 1 where the data carried sigma); with smoothness they leave out what the
penalty adds, so they are an upper bound.

`n = 1e-3 - 1 + sqrt(u^2 + 1)` and `k = -1 + sqrt(v^2 + 1)` keep `n > 0` and `k >= 0` (gain is
not a layer material), as `fit_stack` does its bounds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._films._dispersion import Constant, Tabulated
from .._films._sample import Sample
from .._io._spectra import Spectra
from ._stack_fit_stages import _Bound, _solver_tol, _wrap_deg

if TYPE_CHECKING:
    from jaxtyping import ArrayLike

_N_MIN = 1e-3


@dataclasses.dataclass(frozen=True)
class NKFit:
    """Result of `fit_nk`, one row per wavelength (increasing).

    **Fields:** `wavelength_nm`, `n`, `k`, `n_err`, `k_err` (standard errors), `chi2_reduced`
    (per wavelength; of the whole problem with smoothness), `converged`; all NumPy arrays. `layer`
    names the fitted layer.

    `material()` is the result as a `Tabulated` material (for a `Sample` or `fit_stack`);
    `save_yaml(path)` writes it as a refractiveindex.info YAML file (`tabulated nk`, micrometres),
    which `load_rii_yaml` reads back.
    """

    layer: str
    wavelength_nm: np.ndarray
    n: np.ndarray
    k: np.ndarray
    n_err: np.ndarray
    k_err: np.ndarray
    chi2_reduced: np.ndarray
    converged: np.ndarray

    def material(self, name: str | None = None) -> Tabulated:
        lam = self.wavelength_nm / 1000
        return Tabulated((lam, self.n), (lam, self.k), name=name or f"{self.layer} (point by point)",
                         reference="jaxoptics fit_nk")

    def save_yaml(self, path: str | Path, *, reference: str = "jaxoptics fit_nk, point-by-point fit") -> None:
        rows = "\n".join(f"        {w / 1000:.9g} {n:.9g} {k:.9g}" for w, n, k in zip(self.wavelength_nm, self.n, self.k))
        ref = reference.replace('"', "'")
        Path(path).write_text(f'REFERENCES: "{ref}"\nCOMMENTS: "layer {self.layer}"\nDATA:\n  - type: tabulated nk\n'
                              f"    data: |\n{rows}\n", encoding="utf-8")


# n > 0 and k >= 0 through `fit_stack`'s change of variables for a lower bound
_BOUNDS = (_Bound(_N_MIN, math.inf), _Bound(0.0, math.inf))


def _to_nk(u):
    return jnp.stack([b.x(u[i]) for i, b in enumerate(_BOUNDS)])


def _from_nk(n, k):
    """The solver's variables of starts `n`, `k`, moved inside the bounds (on a bound the change of
    variables has derivative 0: the solver would not move it)."""
    n = np.maximum(n, _N_MIN * 1.001)
    k = np.maximum(k, 1e-6)
    return jnp.stack([_BOUNDS[0].u(jnp.asarray(n)), _BOUNDS[1].u(jnp.asarray(k))], -1)


def fit_nk(sample: Sample, spectra: Spectra, layer: str, *, values: ArrayLike | None = None, smoothness: float = 0.0,
           max_steps: int = 256) -> NKFit:
    """Fit the index `n + ik` of one layer of `sample` at every wavelength of `spectra` on its own.

    **Arguments:**

    - `sample`: the `Sample`; `values`: its free parameters' values (a `fit_stack` result's
      `values` for one spectrum, in `sample.free_names()` order), or None for the `Free` starts.
      The thicknesses and every other medium are held there.
    - `layer`: the name of the layer whose index is fitted (`"substrate"` for the substrate). Its
      model at `values` gives each wavelength's start.
    - `spectra`: one spectrum (no map axes); each wavelength needs at least two data (angles times
      quantities) for its two unknowns.
    - `smoothness`: 0 (each wavelength independent) or the weight of the penalty on the
      second differences of `n` and `k` between neighbouring wavelengths (module docstring).
    - `max_steps`: Levenberg-Marquardt steps.

    **Returns:** an `NKFit`. Raises `ValueError` before any tracing for a map, an unknown layer, or
    a wavelength with fewer than two data.
    """
    from ._stack_fit import DEFAULT_SIGMA

    if not isinstance(sample, Sample) or not isinstance(spectra, Spectra):
        raise ValueError("fit_nk(sample: Sample, spectra: Spectra, layer: str)")
    if spectra.values.ndim != 2:
        raise ValueError(f"fit_nk fits one spectrum; these spectra have map axes {spectra.values.shape[:-2]}")
    names = sample.layer_names + ["substrate"]
    if layer not in names:
        raise ValueError(f"layer {layer!r} is not in the sample; its layers: {', '.join(names)}")
    if not (isinstance(smoothness, (int, float)) and smoothness >= 0):
        raise ValueError(f"smoothness must be a number >= 0, got {smoothness!r}")
    free = sample.free()
    vals = [f.value for f in free] if values is None else [float(v) for v in np.asarray(values).reshape(-1)]
    if len(vals) != len(free):
        raise ValueError(f"values has {len(vals)} entries for the sample's {len(free)} free parameters")
    dtype = jnp.dtype(jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32)
    resolved = sample.with_values(vals)
    kinds, Q = spectra.kinds, len(spectra.kinds)
    wl, ang = np.asarray(spectra.wavelength_nm), np.asarray(spectra.angle_deg)
    uw = np.unique(wl)
    counts = np.asarray([np.sum(wl == w) for w in uw])
    few = np.flatnonzero(counts * Q < 2)
    if few.size:
        raise ValueError(f"{uw[few[0]]:g} nm has {counts[few[0]] * Q} data for the two unknowns n and k")
    W, A = uw.size, int(counts.max())
    sigma_given = spectra.sigma is not None
    S_all = (np.asarray(spectra.sigma) if sigma_given
             else np.broadcast_to(np.asarray([DEFAULT_SIGMA[k] for k in kinds])[:, None], spectra.values.shape))
    # per wavelength, its angles padded to A (repeating its last one, with zero weight)
    idx = np.zeros((W, A), int)
    mask = np.zeros((W, A), bool)
    for j, w in enumerate(uw):
        ii = np.flatnonzero(wl == w)
        idx[j, :ii.size], idx[j, ii.size:] = ii, ii[-1]
        mask[j, :ii.size] = True
    Vw = jnp.asarray(np.moveaxis(np.asarray(spectra.values)[:, idx], 0, 1), dtype)  # (W, Q, A)
    Wt = jnp.asarray(np.moveaxis(np.where(mask[None], 1 / S_all[:, idx], 0.0), 0, 1), dtype)
    lam = jnp.asarray(uw, dtype)
    angr = jnp.asarray(np.deg2rad(ang[idx]), dtype)
    if layer == "substrate":
        seed_model = resolved.substrate
    else:
        seed_model = resolved.layers[sample.layer_names.index(layer)].material
    N0 = np.asarray(seed_model.nk(jnp.asarray(uw / 1000, dtype)))
    U0 = jnp.asarray(_from_nk(N0.real, N0.imag), dtype)  # (W, 2)
    x = jnp.asarray(vals, dtype)
    per = (lam, angr, Vw, Wt)
    m = jnp.asarray(counts * Q, dtype)
    prog = _programs(sample, layer, kinds, sigma_given, max_steps, dtype.name)
    U, ok = prog.solve(x, U0, per)
    X, err, chi2r, edm, fin = (np.asarray(a) for a in prog.errors(x, jax.vmap(_to_nk)(U), per, m))
    conv = (np.asarray(ok) | (edm < 1e-6)) & fin
    if smoothness > 0:
        # one problem over all wavelengths from the independent solutions: the data's residuals
        # and the differences between neighbours in units of the median standard errors
        scale = np.asarray([np.median(err[:, 0]), max(float(np.median(err[:, 1])), 1e-12)])
        Uf, ok1 = prog.joint(x, U.reshape(-1), per, jnp.asarray(smoothness / scale, dtype))
        X, err, chi2r, _, fin = (np.asarray(a) for a in prog.errors(x, jax.vmap(_to_nk)(Uf.reshape(W, 2)), per, m))
        conv = np.broadcast_to(np.asarray(ok1), (W,)) & fin
    return NKFit(layer, uw, X[:, 0], X[:, 1], err[:, 0], err[:, 1], chi2r, conv)


class _Programs(NamedTuple):
    solve: Callable  # (x, U0, per) -> (U, ok): each wavelength's Levenberg-Marquardt
    joint: Callable  # (x, U, per, weights) -> (U, ok): all wavelengths with the smoothness penalty
    errors: Callable  # (x, X, per, m) -> (X, err, chi2_reduced, edm, finite) per wavelength


@functools.lru_cache(maxsize=16)
def _programs(sample, layer, kinds, sigma_given, max_steps, dtype_name) -> _Programs:
    """The compiled calls of `fit_nk` for one sample, layer, list of quantities and solver
    setting: the sample's values, the data and the starts are their arguments, so that a later
    call (other values, other data of the same shapes) runs them without compiling again."""
    import optimistix as optx

    dtype = jnp.dtype(dtype_name)
    is_delta = np.asarray([k == "delta_deg" for k in kinds])[:, None]
    p = len(sample.free())
    li = None if layer == "substrate" else sample.layer_names.index(layer)

    def put(x, nk):
        """The sample at values `x` with the layer's index replaced by the constant `nk`."""
        resolved = sample.with_values([x[i] for i in range(p)])
        if li is None:
            return dataclasses.replace(resolved, substrate=Constant(nk[0], nk[1]))
        return dataclasses.replace(resolved, layers=tuple(
            dataclasses.replace(lay, material=Constant(nk[0], nk[1])) if i == li else lay
            for i, lay in enumerate(resolved.layers)))

    def residuals_nk(x, nk, j_args):
        """One wavelength's weighted residuals at `nk = (n, k)`."""
        lam_j, ang_j, V_j, W_j = j_args
        model = put(x, nk).quantities(kinds, jnp.broadcast_to(lam_j, ang_j.shape), ang_j)  # (Q, A)
        d = model - V_j
        d = jnp.where(jnp.asarray(is_delta), _wrap_deg(d), d)
        return (d * W_j).reshape(-1)

    tol = _solver_tol(dtype)
    lm: optx.AbstractLeastSquaresSolver = optx.LevenbergMarquardt(rtol=tol, atol=tol)

    @jax.jit
    def solve(x, U0, per):
        residuals = lambda u, j_args: residuals_nk(x, _to_nk(u), j_args)

        def one(u0, a):
            sol = optx.least_squares(residuals, lm, u0, a, max_steps=max_steps, throw=False)
            return sol.value, sol.result == optx.RESULTS.successful

        return jax.vmap(one)(U0, per)

    @jax.jit
    def joint(x, U, per, weights):
        W = per[0].shape[0]

        def all_residuals(Uf, _):
            U_ = Uf.reshape(W, 2)
            r = jax.vmap(lambda u, a: residuals_nk(x, _to_nk(u), a))(U_, per).reshape(-1)
            pen = weights[None, :] * jnp.diff(jax.vmap(_to_nk)(U_), 2, axis=0)
            return jnp.concatenate([r, pen.reshape(-1)])

        sol = optx.least_squares(all_residuals, lm, U, None, max_steps=max_steps, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful

    @jax.jit
    def errors(x, X, per, m):
        """Standard errors, chi^2/dof and MINUIT's EDM per wavelength from the Jacobian in
        `(n, k)` of each wavelength's own residuals at `X` (`m` data each)."""
        f = lambda nk, a: residuals_nk(x, nk, a)
        r = jax.vmap(f)(X, per)
        J = jax.vmap(jax.jacfwd(f))(X, per)  # (W, Q A, 2)
        chi2r = jnp.sum(r * r, axis=-1) / jnp.maximum(m - 2, 1)
        JtJ = jnp.einsum("wmi,wmj->wij", J, J)
        inv = jnp.linalg.pinv(JtJ)
        cov = inv * (jnp.maximum(chi2r, 1) if sigma_given else chi2r)[:, None, None]
        err = jnp.sqrt(jnp.abs(jnp.diagonal(cov, axis1=-2, axis2=-1)))
        # Converged (`fit_nk`): the solver met its tolerances, or the Gauss-Newton step left at
        # the solution would lower chi^2 by less than 1e-6 (MINUIT's EDM; at k = 0 with the step
        # pointing to k < 0, the step in n alone): near the bound k = 0 the solver's own test is
        # met slowly.
        g = jnp.einsum("wmi,wm->wi", J, r)
        step = -jnp.einsum("wij,wj->wi", inv, g)
        edm = jnp.einsum("wi,wij,wj->w", g, inv, g)
        at_bound = (X[:, 1] <= 1e-10) & (step[:, 1] < 0)
        edm = jnp.where(at_bound, g[:, 0] ** 2 / JtJ[:, 0, 0], edm)
        return X, err, chi2r, edm, jnp.all(jnp.isfinite(X), axis=-1)

    return _Programs(solve, joint, errors)
