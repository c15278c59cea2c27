"""Fit a dispersion law n(lambda) to reflectance-versus-angle curves at several wavelengths."""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from . import _validate as V
from ._fit import _warn_if_x64_off, check_curves, fit_eta
from ._fit_followups import _is_concrete
from ._fit_model import POLARIZATIONS, _model
from ._fit_solver import _tol
from ._fresnel import materialize
from ._materials import cauchy, sellmeier
from ._result import result, static

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
    directions the data do not see at all; `index` propagates it, and where nothing is left out
    `stderr` is the square root of its diagonal); `converged`; `residual_rms` of the reflectance;
    `chi2_reduced`; `num_steps`; `condition_number` of `J^T J` in the parameters the fit moves, scaled to unit
    diagonal (large for Sellmeier fits, whose coefficients are strongly correlated: judge the fit
    by `index(wavelength_um)` and its error, not by single coefficients).

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

    def index(self, wavelength_um):
        """`(n, stderr)` at `wavelength_um`: the fitted law and its standard error, propagated from
        the coefficients' covariance to first order (the delta method)."""
        lam = jnp.asarray(wavelength_um, self.coefficients.dtype)
        f = lambda p, l: _index(self.model, p, l, self.terms)
        n = f(self.coefficients, lam)
        g = jax.vmap(jax.grad(f), in_axes=(None, 0))(self.coefficients, lam.reshape(-1))
        var = jnp.einsum("ip,pq,iq->i", g, self.covariance, g).reshape(lam.shape)
        return n, jnp.sqrt(jnp.maximum(var, 0))


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


@eqx.filter_jit
def _solve(theta, lam, R, w, eta1, p0, *, model, terms, polarization, solver, max_steps, sigma_given):
    cos_i = materialize(jnp.cos(theta))  # once, not in every loop over the residuals (see `_fit_batch`)

    far = _far_poles(model, terms, p0, lam)

    def residual(q, _):
        n = _internal_index(model, q, lam, terms, far)
        return ((_model(cos_i[None, :], eta1, n[:, None], polarization) - R) * w).ravel()

    sol = optx.least_squares(residual, solver, _reciprocal(model, terms, p0, far), max_steps=max_steps, throw=False)
    q = sol.value
    r = residual(q, None)
    J = jax.jacfwd(residual)(q, None)
    JTJ = J.T @ J
    # Scale the normal matrix to unit diagonal before inverting (the coefficients differ by orders
    # of magnitude). Two inverses: the pseudo-inverse leaves out the directions the data do not see
    # at all (eigenvalues at rounding level: two Sellmeier poles that merged, whose B split any
    # way); it is the covariance of the combinations the data determine, which `index` propagates
    # (the index does not move along a left-out direction, and keeping one would let rounding in
    # its gradient, times an unbounded variance, swamp the error). The standard errors come from
    # the inverse with nothing left out (eigenvalues floored at eps^2 of the largest, as in
    # `fit_stack`): a coefficient the data do not determine gets a huge error, never a small one.
    d = jnp.sqrt(jnp.diagonal(JTJ))
    d = jnp.where(d > 0, d, 1)
    S = JTJ / (d[:, None] * d[None, :])
    ev, vec = jnp.linalg.eigh(S)
    eps, top = jnp.finfo(S.dtype).eps, jnp.maximum(ev[-1], jnp.finfo(S.dtype).tiny)
    cond = ev[-1] / jnp.maximum(ev[0], jnp.finfo(S.dtype).tiny)
    seen = ev > eps * S.shape[0] * top
    dd = d[:, None] * d[None, :]
    cov = (vec * jnp.where(seen, 1 / jnp.where(seen, ev, 1), 0)[None, :]) @ vec.T / dd
    cov_all = (vec / jnp.maximum(ev, eps**2 * top)[None, :]) @ vec.T / dd
    dof = r.shape[0] - q.shape[0]
    chi2 = jnp.sum(r * r) / dof
    scale = jnp.maximum(chi2, 1) if sigma_given else chi2  # as in fit_eta
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(jnp.diagonal(cov)))
    # report (B, C): the covariances carried over to first order, which leaves the delta-method
    # error of `DispersionFit.index` what it is in the fitted parameters
    p = _reciprocal(model, terms, q, far)
    T = jax.jacfwd(_reciprocal, argnums=2)(model, terms, q, far)
    cov = scale * (T @ cov @ T.T)
    se = jnp.sqrt(scale * jnp.abs(jnp.diagonal(T @ cov_all @ T.T)))
    rms = jnp.sqrt(jnp.mean((r / w.ravel()) ** 2))
    return p, cov, se, ok, rms, chi2, sol.stats["num_steps"], cond


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
    p, cov, se, ok, rms, chi2, steps, cond = _solve(
        theta, lam, R, w, jnp.asarray(eta1, dt), p0, model=model, terms=terms, polarization=polarization,
        solver=solver, max_steps=int(max_steps), sigma_given=sigma is not None)
    return DispersionFit(model, terms, p, cov, se, ok, rms, chi2, steps, cond)
