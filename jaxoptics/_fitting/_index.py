"""Fit the refractive index to reflectance-versus-angle curves, with optimistix.

One curve or thousands: every curve of a batch is fitted in one compiled, vmapped call. Results are
a `FitResult` pytree (estimate, standard error from the Jacobian at the solution, convergence flag),
never an exception from inside the solver.

The fit is spread over files by concern: `_index_model` (the reflectance model and its
derivatives), `_index_starts` (starting points), `_index_solver` (the batched optimistix solve and
the standard errors), `_index_stages` (refits, second branches, restarts in JAX; derivatives of fits),
`_index_result` (`FitResult`); this file holds the checks of the data and `fit_eta` itself.
"""

from __future__ import annotations

import functools
import warnings
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _validate as V
from .._runtime._shard import _trim, batch_mesh, shard_batch
from ._index_model import POLARIZATIONS, S_WEIGHT
from ._index_result import FitResult
from ._index_stages import _batch_shards, _fit_differentiable, _fit_per_shard, _is_concrete, _solve_stages

if TYPE_CHECKING:
    from collections.abc import Sequence

    import optimistix as optx
    from jax.sharding import Mesh
    from jaxtyping import ArrayLike, Float, Inexact


def _check_theta(theta, R_shape, n_params, at):
    """Checks of the (small) shared angle array and of R's shape against it; returns theta."""
    th = np.asarray(theta, dtype=np.float64)
    if th.ndim != 1:
        raise ValueError(f"theta must be one-dimensional (shared by all curves), got shape {th.shape}{at}")
    if len(R_shape) < 1 or R_shape[-1] != th.shape[0]:
        raise ValueError(f"R must have shape (..., {th.shape[0]}) to match theta, got {tuple(R_shape)}{at}")
    if th.shape[0] < n_params + 1:
        raise ValueError(
            f"{th.shape[0]} angle(s){at}: fitting {n_params} parameter(s) with an uncertainty needs at least "
            f"{n_params + 1} angles"
        )
    bad = np.argwhere(~np.isfinite(th))
    if bad.size:
        raise ValueError(f"theta[{bad[0][0]}] = {th[bad[0][0]]} is not finite{at}")
    out = np.argwhere((th < 0) | (th > np.pi / 2 + 1e-12))
    if out.size:
        k = out[0][0]
        raise ValueError(f"theta[{k}] = {th[k]} rad ({np.rad2deg(th[k]):.4g} deg) is outside [0, pi/2]{at}")
    return th


@jax.jit
def _curve_flags(R):
    return jnp.all(jnp.isfinite(R)), jnp.any(jnp.max(R, axis=-1) == jnp.min(R, axis=-1))


def check_curves(theta, R, sigma, *, n_params: int, where: str = "") -> None:
    """Value checks on concrete data, before any solving: a clear ValueError for degenerate input.

    A `jax.Array` (possibly sharded over devices or hosts) is checked with reductions where it
    lives; only when a check fails is the offending entry located on the host."""
    at = f" in {where}" if where else ""
    th = _check_theta(theta, np.shape(R), n_params, at)
    if isinstance(R, jax.Array):
        finite, const = (bool(x) for x in _curve_flags(R))
        if finite and not const:  # all good; no copy of a possibly large, sharded array to the host
            return _check_sigma(sigma, at)
    _check_R_parts(R, th.shape[0], at)
    _check_sigma(sigma, at)


def _check_sigma(sigma, at):
    if sigma is not None:
        V.first_bad(sigma, lambda s, _: ~(np.isfinite(s) & (s > 0)),
                    lambda idx, v: f"sigma{idx} = {v} must be finite and positive{at}")


def _check_R_parts(R, m, at):
    """Locate a non-finite value or a constant curve of `R` in the parts this process holds."""
    V.first_bad(R, lambda r, _: ~np.isfinite(r), lambda idx, v: f"R{idx} = {v} is not finite{at}")
    for start, part in V.local_parts(R):
        flat = np.asarray(part, np.float64).reshape(-1, part.shape[-1])
        const_rows = np.flatnonzero(np.ptp(flat, axis=-1) == 0) if part.shape[-1] == m else np.array([], int)
        if const_rows.size:
            k = [int(i) + s for i, s in zip(np.unravel_index(const_rows[0], part.shape[:-1]), start)] if part.ndim > 1 else []
            raise ValueError(
                f"curve {k}{at} has the same reflectance {flat[const_rows[0], 0]} at every angle: "
                "a constant curve carries no information on the index"
            )
    if isinstance(R, jax.Array):  # the flags saw a bad value in a part another process holds
        raise ValueError(f"R holds a value that is not finite or a curve that is constant{at}, in a part another "
                         "process holds")


def _prepared(xp, x, name: str) -> jax.Array | np.ndarray:
    """`x` checked to be real (`_validate.as_real`), as an array of `xp` (NumPy or jax.numpy)."""
    return xp.asarray(V.check_real(x, name))


def _check_polarization(polarization, batch):
    """The one name of all curves' polarization, or, where they differ, the names broadcast to the
    batch shape (a NumPy array)."""
    if isinstance(polarization, str):
        if polarization not in POLARIZATIONS:
            raise ValueError(f"polarization must be one of {POLARIZATIONS}, got {polarization!r}")
        return str(polarization)
    names = np.asarray(polarization, dtype=object)
    for k, x in np.ndenumerate(names):
        if not isinstance(x, str) or x not in POLARIZATIONS:
            raise ValueError(f"polarization{list(k)} must be one of {POLARIZATIONS}, got {x!r}")
    try:
        names = np.broadcast_to(names, batch)
    except ValueError:
        raise ValueError(f"polarization has shape {names.shape}, which does not broadcast to the batch shape "
                         f"{tuple(batch)} of R") from None
    return str(names.flat[0]) if names.size and np.all(names == names.flat[0]) else names


def _warn_if_x64_off(*xs):
    if not jax.config.jax_enable_x64 and any(np.asarray(x).dtype == np.float64 for x in xs if not isinstance(x, jax.Array)):
        warnings.warn(
            "jax_enable_x64 is off, so float64 data are fitted in float32 (about 1e-6 relative accuracy). "
            "Call jax.config.update('jax_enable_x64', True) first to fit in float64.",
            stacklevel=3,
        )


def fit_eta(theta: Float[ArrayLike, " m"], R: Float[ArrayLike, "*batch m"], *, eta1: float = 1.0,
            polarization: str | Sequence[str] = "unpolarized", sigma: Float[ArrayLike, "*#batch #m"] | None = None,
            init: Inexact[ArrayLike, "*#batch"] | None = None, absorbing: bool = False,
            solver: optx.AbstractLeastSquaresSolver | None = None, max_steps: int = 256) -> FitResult:
    r"""Fit the index of the reflecting medium to reflectance-versus-angle data.

    **Arguments:**

    - `theta`: angles of incidence in radians, shape `(m,)`, shared by all curves.
    - `R`: measured reflectance, `(m,)` for one curve or `(..., m)` for a batch; every curve is
      fitted independently, all in one compiled, batched call.
    - `eta1`: known (real) index of the incident medium. It may exceed the fitted index (internal
      reflection data with a TIR plateau).
    - `polarization`: `"unpolarized"`, `"s"` or `"p"`; or one of these per curve (a sequence or
      array of names broadcastable to the batch shape), e.g. `("s", "p")` for an s and a p curve
      in `R` of shape `(2, m)`: curves in different polarizations are fitted in one compiled call.
    - `sigma`: standard deviation of each measurement (scalar, `(m,)` or `(..., m)`). Given, the
      residuals are weighted by `1/sigma` and the errors are absolute; not given, the errors are
      scaled by the residual scatter (reduced chi-square).
    - `init`: starting value(s), broadcastable to the batch shape (complex for `absorbing=True`).
      Not needed: by default each curve starts from the best of a log grid of indices (and of
      `(n, k)` pairs for `absorbing=True`) and of the physical estimates (normal-incidence
      inversion on both branches, the onset of a TIR plateau, the Brewster minimum).
    - `absorbing`: fit a complex index `n + ik` (metals, absorbing media).
    - `solver`: an optimistix least-squares solver. Default: `optimistix.GaussNewton` for a real
      index, with `OneColumnLeastSquares` as its linear solver (curves it does not converge on are
      refitted with `optimistix.LevenbergMarquardt` in the same compiled call),
      `optimistix.LevenbergMarquardt` for a complex one; tolerances from the dtype. The choice was
      measured: see `_default_solver`.
    - `max_steps`: solver iteration cap; hitting it gives `converged=False`.

    **Returns:** a `FitResult` (see its fields) with the batch shape of `R`.

    **Two branches (real fits):** a medium less dense than the incident one (`eta2 < eta1`) and a
    denser one can give similar curves below the critical angle. Curves whose other branch may fit
    as well are solved on it too, in the same compiled call (over just those curves); the smaller
    chi-square wins, and where the other is within `Delta chi2 < 9` it is reported as `eta_alt` and
    included in `stderr` (see `FitResult`).

    **Errors:** degenerate data raise a `ValueError` before any solving: fewer than `p + 1` angles,
    non-finite values, angles outside `[0, pi/2]`, a constant curve, non-positive `sigma`, unknown
    polarization, shapes that do not match. (Under an outer `jit` only shapes are checked; NaN data
    then give `converged=False`.) Failures of the solver are reported as `converged=False`, never
    raised.

    **Inside JAX programs:** the fit, with its Levenberg-Marquardt refit and its second-branch
    solves, is pure JAX: called eagerly, under `jax.jit` or under `jax.vmap` it runs the same
    solves on the same curves and agrees to the solver's tolerance. (Eagerly, a follow-up stage is
    compiled only when some curve needs it.) It is differentiable in `R`, `theta`, `eta1` and
    `sigma` by the implicit function theorem at the solution; where `converged` is false the
    derivatives are NaN.

    **Dtype:** the fit runs in the floating dtype of `R`; with `jax_enable_x64` off, float64 NumPy
    data are fitted in float32 and a warning says so.
    """
    polarization = _check_polarization(polarization, np.shape(R)[:-1])
    p = 2 if absorbing else 1
    concrete = _is_concrete(theta, R, sigma)
    if concrete:
        _warn_if_x64_off(theta, R)  # looks at the dtype the caller passed, before conversion
    # Plain NumPy or Python input is prepared in NumPy: each small eager JAX operation here would be
    # a program of its own, compiled (or looked up in the compilation cache) on a first call.
    xp = jnp if any(isinstance(x, jax.Array) for x in (theta, R, sigma, init, eta1)) or not concrete else np
    R_given = V.check_real(R, "R")
    if concrete:  # the caller's arrays, where they are (a jax.Array by one compiled reduction), never
        check_curves(theta, R_given, sigma, n_params=p)  # a constant staged into the caller's trace
    R = _prepared(xp, R_given, "R")
    if not np.isscalar(eta1) and np.ndim(eta1) != 0:
        raise ValueError(f"eta1 must be a scalar, got shape {np.shape(eta1)}")
    theta = _prepared(xp, theta, "theta")
    dt = V.float_dtype(R, theta)
    R, theta = R.astype(dt), theta.astype(dt)
    batch, m = R.shape[:-1], R.shape[-1]
    Rf = R.reshape(-1, m)
    if sigma is None:
        w = xp.ones((Rf.shape[0], 1), dt)
    else:
        w = xp.broadcast_to(1 / _prepared(xp, sigma, "sigma").astype(dt), R.shape).reshape(-1, m)
    use_init = init is not None
    if use_init:
        init = xp.broadcast_to(xp.asarray(init), batch).reshape(-1)
        y_init = (xp.stack([xp.real(init), xp.imag(init)], -1) if absorbing else xp.real(init)[:, None]).astype(dt)
    else:
        y_init = xp.zeros((Rf.shape[0], p), dt)
    retry = solver is None and not absorbing
    # the default solvers by name (`_index_solver._solver`): optimistix is imported only to trace
    spec: object = ("default", np.dtype(dt).name, bool(absorbing)) if solver is None else solver
    lm = ("lm", np.dtype(dt).name) if retry else None
    if not isinstance(polarization, str):  # per curve: the weight of s-polarized light, data of the one program
        polarization = xp.asarray(np.vectorize(S_WEIGHT.get, otypes=[float])(polarization).reshape(-1), dt)
    kw = dict(polarization=polarization, absorbing=absorbing, max_steps=int(max_steps), sigma_given=sigma is not None,
              solver=spec, lm=lm, use_init=use_init)
    eta1_arr = xp.asarray(eta1, dt)
    shards = _batch_shards(Rf)
    if shards is None:
        # concrete: nothing to differentiate, the follow-up stages compiled only when needed
        fit = _solve_stages if _is_concrete(theta, Rf, w, eta1_arr, y_init) else _fit_differentiable
        res = fit(theta, Rf, w, eta1_arr, y_init, kw)
    else:
        res = _fit_per_shard(shards, theta, Rf, w, eta1_arr, y_init, kw)
    return res if batch == (len(Rf),) else _reshaped(res, batch)


@functools.partial(jax.jit, static_argnums=1)
def _reshaped(res, batch):
    """Every field of a fit result with the batch shape: one program for all fields."""
    return jax.tree_util.tree_map(lambda x: x.reshape(batch + x.shape[1:]), res)


def fit_eta_sharded(theta: Float[ArrayLike, " m"], R: Float[ArrayLike, "B m"], *, mesh: Mesh | None = None,
                    keep_padding: bool = False, **kwargs) -> FitResult:
    """`fit_eta` on a batch of curves `R` (shape `(B, m)`) spread over the devices of `mesh`.

    Pads the batch to a multiple of the device count (with copies of the last curve), fits all
    curves where they live in one compiled call, and returns a `FitResult` of batch size `B`.
    Keyword arguments are those of `fit_eta`; `sigma`, if an array, must be shared or `(m,)`.
    `keep_padding` as in `sharded_map`.
    """
    mesh = batch_mesh() if mesh is None else mesh
    R = jnp.asarray(R)
    if R.ndim != 2:
        raise ValueError(f"R must have shape (B, m) for fit_eta_sharded, got {R.shape}")
    Rs, n = shard_batch(R, mesh=mesh)
    return _trim(fit_eta(theta, Rs, **kwargs), n, Rs.shape[0], keep_padding)
