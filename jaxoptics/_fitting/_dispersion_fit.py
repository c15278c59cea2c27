"""Fit a dispersion law n(lambda) to reflectance-versus-angle curves at several wavelengths."""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._core import _validate as V
from .._core._numerics import materialize
from .._core._result import result, static
from .._films._materials import cauchy, sellmeier
from ._index import _warn_if_x64_off, check_curves, fit_eta
from ._index_model import POLARIZATIONS, _model
from ._index_solver import _tol
from ._index_stages import _is_concrete

if TYPE_CHECKING:
    from jaxtyping import ArrayLike, Float

MODELS = ("cauchy", "sellmeier")
DEFAULT_TERMS = 3  # Sellmeier terms or Cauchy coefficients
# Starting poles for Sellmeier fits (micrometres squared): typical of optical glasses and silica,
# two in the ultraviolet and one in the infrared. The B terms then follow by linear least squares.
_SELLMEIER_POLES = {1: (0.01,), 2: (0.01, 100.0), 3: (0.0047, 0.0135, 97.9)}


def _index(model, p, lam, terms):
    if model == "cauchy":
        return cauchy(lam, p)
    return sellmeier(lam, p[:terms], p[terms:])


# A Sellmeier pole beyond the longest measured wavelength is fitted through `(a, b) = (B/C, 1/C)`,
# in which its term reads `a lambda^2 / (b lambda^2 - 1)`. Data that end well short of the pole see
# only its tail, `-a lambda^2 (1 + b lambda^2 + ...)`: in `(B, C)` the best fit then lies at
# infinity (C grows with B/C fixed) and the solver walks down a valley without end, while in
# `(a, b)` it is a finite point with `b` near zero and an honest error. Poles at shorter
# wavelengths keep `(B, C)`, whose limit C -> 0 is a finite point already. `far` marks the terms
# fitted through the reciprocal; it is decided from the starting poles.

def _far_poles(model, terms, p0, lam):
    if model == "cauchy":
        return jnp.zeros((terms,), bool)
    return p0[terms:] > jnp.max(lam) ** 2


def _reciprocal(model, terms, p, far):
    """`(B, C) -> (B/C, 1/C)` on the `far` terms, identity on the others: from the coefficients to
    the fitted parameters, and back (the map is its own inverse)."""
    if model == "cauchy":
        return p
    x, y = p[:terms], p[terms:]
    ys = jnp.where(far, y, 1)
    return jnp.concatenate([jnp.where(far, x / ys, x), jnp.where(far, 1 / ys, y)])


def _internal_index(model, q, lam, terms, far):
    if model == "cauchy":
        return cauchy(lam, q)
    a, b, far = q[None, :terms], q[None, terms:], far[None, :]
    l2 = (lam * lam)[:, None]
    den = jnp.where(far, b * l2 - 1, l2 - b)
    return jnp.sqrt(1 + jnp.sum(a * l2 / den, axis=-1))


@result
class DispersionFit:
    """Result of `fit_dispersion`.

    **Fields:** `model` ("cauchy" or "sellmeier"), `terms`; `coefficients` (`(A, B, C, ...)` for
    Cauchy, `(B_1..B_k, C_1..C_k)` for Sellmeier, wavelengths in micrometres); `stderr` of each
    coefficient (huge for a coefficient the data do not determine, such as the split of `B`
    between two Sellmeier poles that merged); `covariance` of the coefficients over the
    combinations the data determine (the pseudo-inverse of the normal matrix, which leaves out
    the directions the data do not see at all: singular values of the column-scaled Jacobian at
    or below `eps max(m, p)` of the largest, numpy's rank tolerance; `index` propagates it, so
    the index's error is the same wherever along such a direction the fit stopped, and where
    nothing is left out `stderr` is the square root of its diagonal); `converged`; `residual_rms` of the reflectance;
    `chi2_reduced`; `num_steps`; `condition_number` of `J^T J` in the parameters the fit moves, scaled to unit
    diagonal (large for Sellmeier fits, whose coefficients are strongly correlated: judge the fit
    by `index(wavelength_um)` and its error, not by single coefficients); `covariance_factor`, a
    `(p, p)` matrix `F` with `covariance = F F^T` (a column per determined direction, zero
    columns for those left out), through which `index` propagates: with condition numbers up to
    `1e20`, `g^T (F F^T) g` formed from the matrix loses the variance to cancellation, while
    `|F^T g|^2` keeps it.

    A Sellmeier pole that starts beyond the longest measured wavelength is fitted through
    `(B/C, 1/C)`, in which a pole at infinity (the term `-B/C lambda^2`) is an ordinary point.
    Where the data see only the pole's tail, `1/C` comes out near zero, of either sign, and the
    reported `C` (and `B`) carry standard errors larger than their values: the pole is not
    located, while `index` stays determined. `covariance` is carried over to `(B, C)` to first
    order, which leaves the error of `index` as it is in the fitted parameters.
    """

    model: str = static()
    terms: int = static()
    coefficients: jax.Array
    covariance: jax.Array
    stderr: jax.Array
    converged: jax.Array
    residual_rms: jax.Array
    chi2_reduced: jax.Array
    num_steps: jax.Array
    condition_number: jax.Array
    covariance_factor: jax.Array

    def index(self, wavelength_um):
        """`(n, stderr)` at `wavelength_um`: the fitted law and its standard error, propagated from
        the coefficients' covariance to first order (the delta method, through
        `covariance_factor`)."""
        lam = jnp.asarray(wavelength_um, self.coefficients.dtype)
        f = lambda p, l: _index(self.model, p, l, self.terms)
        n = f(self.coefficients, lam)
        g = jax.vmap(jax.grad(f), in_axes=(None, 0))(self.coefficients, lam.reshape(-1))
        var = jnp.sum((g @ self.covariance_factor) ** 2, axis=-1).reshape(lam.shape)
        return n, jnp.sqrt(var)


def _initial(model, terms, lam, n):
    """Linear least squares for the coefficients, given per-wavelength indices (in JAX, so that
    `fit_dispersion` traces under `jit` and `vmap`)."""
    if model == "cauchy":
        A = jnp.stack([lam ** (-2 * k) for k in range(terms)], 1)
        return jnp.linalg.lstsq(A, n)[0]
    C = jnp.asarray(_SELLMEIER_POLES[terms], lam.dtype)
    l2 = lam[:, None] ** 2
    B = jnp.linalg.lstsq(l2 / (l2 - C[None, :]), n**2 - 1)[0]
    return jnp.concatenate([B, C])


def _residual_fn(theta, lam, R, w, eta1, far, *, model, terms, polarization):
    """`q -> r`: the weighted residuals of the law with fitted parameters `q` (see `_reciprocal`)."""
    cos_i = materialize(jnp.cos(theta))  # once, not in every loop over the residuals (see `_fit_batch`)

    def residual(q, _=None):
        n = _internal_index(model, q, lam, terms, far)
        return ((_model(cos_i[None, :], eta1, n[:, None], polarization) - R) * w).ravel()

    return residual


def _covariances(J):
    """`(factor, cov_all, cond)` of the fitted parameters from the Jacobian `J` (`(m, p)`) of the
    weighted residuals, at unit variance scale.

    `J` is scaled to unit column norms (the coefficients differ by orders of magnitude) and
    decomposed by its singular values `s` (not through `J^T J`, which would square the condition
    number and leave directions below `sqrt(eps)` to rounding). Directions with
    `s <= eps max(m, p) s_max` (the rank tolerance of `numpy.linalg.matrix_rank` and `lstsq`) are
    those the data do not see at all: two Sellmeier poles that merged, whose `B` split any way.
    Along such a direction neither the residuals nor any quantity the law determines (the index
    at a wavelength) move, to first order, and its computed singular value and the gradients'
    component along it are both rounding. `cov`, which `DispersionFit.index` propagates, leaves
    these directions out (it is `factor factor^T`, `factor` a column per direction kept): the
    index error is then the same wherever along them the solve stopped, and the same eagerly and
    under `jit`. Every direction above the tolerance is kept,
    however weakly determined: its share of a determined quantity's variance (its leverage) does
    not shrink with its singular value, so no threshold above rounding could drop it without
    changing that variance. `cov_all` leaves nothing out (singular values floored at
    `eps s_max`), for the coefficients' own standard errors: a coefficient the data do not
    determine gets a huge error, never a small one. `cond` is the condition number of the scaled
    `J^T J`."""
    m, p = J.shape
    d = jnp.linalg.norm(J, axis=0)
    d = jnp.where(d > 0, d, 1)
    _, s, vt = jnp.linalg.svd(J / d[None, :], full_matrices=False)
    eps, tiny = jnp.finfo(J.dtype).eps, jnp.finfo(J.dtype).tiny
    top = jnp.maximum(s[0], tiny)
    seen = s > eps * max(m, p) * top
    v = vt.T / d[:, None]  # back to the unscaled parameters
    factor = v * jnp.where(seen, 1 / jnp.where(seen, s, 1), 0)[None, :]
    cov_all = (v / jnp.maximum(s, eps * top)[None, :] ** 2) @ v.T
    cond = (top / jnp.maximum(s[-1], tiny)) ** 2
    return factor, cov_all, cond


def _estimate(residual, q, far, *, model, terms, sigma_given):
    """What `fit_dispersion` reports at the fitted parameters `q`: the coefficients `(B, C)`, their
    covariance over the determined directions with its factor, and standard errors
    (`_covariances`, scaled as in `fit_eta`: by the reduced chi-square, at least 1 with `sigma`),
    the residuals, the reduced chi-square and the condition number."""
    r = residual(q)
    J = jax.jacfwd(residual)(q)
    factor, cov_all, cond = _covariances(J)
    dof = r.shape[0] - q.shape[0]
    chi2 = jnp.sum(r * r) / dof
    scale = jnp.maximum(chi2, 1) if sigma_given else chi2
    # report (B, C): the covariances carried over to first order, which leaves the delta-method
    # error of `DispersionFit.index` what it is in the fitted parameters
    p = _reciprocal(model, terms, q, far)
    T = jax.jacfwd(_reciprocal, argnums=2)(model, terms, q, far)
    factor = jnp.sqrt(scale) * (T @ factor)
    se = jnp.sqrt(scale * jnp.abs(jnp.diagonal(T @ cov_all @ T.T)))
    return p, factor @ factor.T, factor, se, r, chi2, cond


@eqx.filter_jit
def _solve(theta, lam, R, w, eta1, p0, *, model, terms, polarization, solver, max_steps, sigma_given):
    far = _far_poles(model, terms, p0, lam)
    residual = _residual_fn(theta, lam, R, w, eta1, far, model=model, terms=terms, polarization=polarization)
    sol = optx.least_squares(residual, solver, _reciprocal(model, terms, p0, far), max_steps=max_steps, throw=False)
    q = sol.value
    p, cov, factor, se, r, chi2, cond = _estimate(residual, q, far, model=model, terms=terms, sigma_given=sigma_given)
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(jnp.diagonal(cov)))
    rms = jnp.sqrt(jnp.mean((r / w.ravel()) ** 2))
    return p, cov, se, ok, rms, chi2, sol.stats["num_steps"], cond, factor


def fit_dispersion(wavelength_um: Float[ArrayLike, " w"], theta: Float[ArrayLike, " m"], R: Float[ArrayLike, "w m"], *,
                   model: str = "sellmeier", terms: int | None = None, eta1: float = 1.0,
                   polarization: str = "unpolarized", sigma: Float[ArrayLike, "#w #m"] | None = None,
                   init: Float[ArrayLike, " p"] | None = None, solver: optx.AbstractLeastSquaresSolver | None = None,
                   max_steps: int = 1024) -> DispersionFit:
    r"""Fit a dispersion law to reflectance curves measured at several wavelengths.

    **Arguments:**

    - `wavelength_um`: `(w,)` wavelengths in micrometres.
    - `theta`: `(m,)` angles of incidence in radians, shared by all wavelengths.
    - `R`: `(w, m)` reflectance, one curve per wavelength.
    - `model`: `"sellmeier"` (`n^2 = 1 + sum B_i lambda^2/(lambda^2 - C_i)`) or `"cauchy"`
      (`n = A + B/lambda^2 + C/lambda^4 + ...`).
    - `terms`: Sellmeier terms or Cauchy coefficients; default 3 for both. A 3-term Sellmeier law
      (6 coefficients, two poles in the ultraviolet and one in the infrared) is determined only by
      precise data over a wide wavelength range: with noisy data its coefficients move along flat
      valleys (two poles merge, the condition number is huge) and the fit often reports
      `converged=False`; use `terms=2` (or Cauchy) there.
    - `eta1`, `polarization`, `sigma`: as in `fit_eta` (`sigma` broadcastable to `(w, m)`).
    - `init`: starting coefficients (same layout as `DispersionFit.coefficients`). By default each
      wavelength is first fitted alone with `fit_eta` (batched), then the law is fitted to those
      indices by linear least squares (Sellmeier: with poles typical of glasses), and the result
      starts the joint fit to all the reflectance data.
    - `solver`: optimistix least-squares solver (default Levenberg-Marquardt).

    **Returns:** a `DispersionFit`; `fit.index(lambda)` gives `n(lambda)` with its standard error.

    **Errors:** as `fit_eta` (checked on every curve), plus an unknown `model` and a wavelength
    count that does not match `R`.
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if polarization not in POLARIZATIONS:
        raise ValueError(f"polarization must be one of {POLARIZATIONS}, got {polarization!r}")
    terms = DEFAULT_TERMS if terms is None else int(terms)
    if model == "sellmeier" and terms not in _SELLMEIER_POLES:
        raise ValueError(f"sellmeier terms must be 1, 2 or 3, got {terms}")
    n_par = terms if model == "cauchy" else 2 * terms
    lam = np.asarray(wavelength_um) if _is_concrete(wavelength_um) else wavelength_um
    if _is_concrete(theta, R, sigma, wavelength_um):
        check_curves(theta, R, sigma, n_params=1)
        lam_np = np.asarray(wavelength_um, np.float64)
        if lam_np.ndim != 1 or np.shape(R)[:-1] != lam_np.shape:
            raise ValueError(f"wavelength_um must have shape (w,) matching R's leading axis; got {lam_np.shape} and R {np.shape(R)}")
        if not np.all(np.isfinite(lam_np) & (lam_np > 0)):
            raise ValueError(f"wavelength_um must be finite and positive, got {lam_np}")
        if lam_np.size * np.shape(R)[-1] <= n_par:
            raise ValueError(f"{lam_np.size * np.shape(R)[-1]} data points cannot determine {n_par} coefficients")
        _warn_if_x64_off(theta, R)
    R = jnp.asarray(V.as_real(R, "R"))
    theta = jnp.asarray(V.as_real(theta, "theta"))
    dt = V.float_dtype(R, theta)
    R, theta, lam = R.astype(dt), theta.astype(dt), jnp.asarray(lam, dt)
    w = jnp.ones((), dt) if sigma is None else 1 / jnp.asarray(sigma, dt)
    w = jnp.broadcast_to(w, R.shape)
    if init is None:
        per = fit_eta(theta, R, eta1=eta1, polarization=polarization, sigma=sigma)
        p0 = _initial(model, terms, lam, per.eta).astype(dt)
    else:
        p0 = jnp.asarray(init, dt)
        if p0.shape != (n_par,):
            raise ValueError(f"init must have {n_par} coefficients for {model} with {terms} terms, got shape {p0.shape}")
    tol = _tol(dt)
    solver = optx.LevenbergMarquardt(rtol=tol, atol=tol) if solver is None else solver
    p, cov, se, ok, rms, chi2, steps, cond, factor = _solve(
        theta, lam, R, w, jnp.asarray(eta1, dt), p0, model=model, terms=terms, polarization=polarization,
        solver=solver, max_steps=int(max_steps), sigma_given=sigma is not None)
    return DispersionFit(model, terms, p, cov, se, ok, rms, chi2, steps, cond, factor)
