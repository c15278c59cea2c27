"""The batched least-squares solve of the index fits: optimistix solvers (Gauss-Newton with a
one-column linear solver, Levenberg-Marquardt), standard errors from the Jacobian, and the
curves of a batch fitted in cache-sized blocks inside one compiled call."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from .._core._numerics import materialize
from ._index_model import _model, _reflectance_fit, _reflectance_plain
from ._index_result import FitResult
from ._index_starts import _first_argmin, _of_curve, _per_curve, _score_columns, _start, count_below


def _tol(dtype):
    # Step and loss tolerances of the solvers. Much tighter than 1e-10 in float64 and the steps
    # start to chase rounding noise (with sigma-weighted residuals of order 1, Gauss-Newton then
    # stalls on a few percent of noisy curves). Gauss-Newton stops one step after a step below the
    # tolerance, by when it has converged quadratically far beyond it: 1e-9 still recovers
    # noise-free indices to 2e-15, agrees with a 1e-12 Levenberg-Marquardt fit of noisy curves to
    # 1e-6 standard errors, and saves the batch one step of six against 1e-10 (measured on
    # 10^4 curves x 90 angles, the benchmark's).
    return max(1e-9, 100 * float(jnp.finfo(dtype).eps))


class _ColumnState(eqx.Module):
    col: jax.Array  # the operator's one column (or, transposed, its one row), flattened
    transposed: bool = eqx.field(static=True)
    in_structure: object = eqx.field(static=True)
    out_structure: object = eqx.field(static=True)


class OneColumnLeastSquares(lx.AbstractLinearSolver):
    """Least-squares solve `min |A x - b|` for a real operator with one column (`m x 1`), in
    closed form: `x = (a . b) / (a . a)`, and `x = 0` where `a = 0` (the pseudo-inverse).

    For one fitted parameter this is the whole Gauss-Newton linear algebra. The general solvers
    factor an `m x 1` matrix per curve: QR (the default) through batched LAPACK calls took 20 of the
    fit's 99 ms (10^4 curves x 90 angles, `jax.profiler` trace); this takes one product of the
    linearized residual and two dot products. The transposed operator (`1 x m`, used when
    differentiating through the solve) gets the minimum-norm solution `a c / (a . a)`.
    """

    def init(self, operator, options):
        del options
        if operator.in_size() != 1 and operator.out_size() != 1:
            raise ValueError(f"OneColumnLeastSquares needs an operator with one column or one row, "
                             f"got {operator.out_size()} x {operator.in_size()}")
        transposed = operator.in_size() != 1
        src = operator.T if transposed else operator
        one = jax.tree_util.tree_map(lambda s: jnp.ones(s.shape, s.dtype), src.in_structure())
        col, _ = ravel_pytree(src.mv(one))
        return _ColumnState(col, transposed, operator.in_structure(), operator.out_structure())

    def compute(self, state, vector, options):
        del options
        a = state.col
        aa = jnp.sum(a * a)
        inv = jnp.where(aa > 0, 1 / jnp.where(aa > 0, aa, 1), 0)
        b, _ = ravel_pytree(vector)
        x = a * (b[0] * inv) if state.transposed else jnp.sum(a * b, keepdims=True) * inv
        _, unflatten = ravel_pytree(jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), state.in_structure))
        return unflatten(x), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        return _ColumnState(state.col, not state.transposed, state.out_structure, state.in_structure), options

    def conj(self, state, options):
        return state, options  # real operators only

    def assume_full_rank(self):
        return False


def _solver(spec):
    """The optimistix solver `fit_eta` names by a spec (`("default", dtype name, absorbing)`,
    `("lm", dtype name)`), or `spec` itself when it is a solver the caller gave. Specs keep
    optimistix out of what `fit_eta` builds before calling its compiled program, so a process that
    loads the program from the store (`_cache`) does not import optimistix at all."""
    if not isinstance(spec, tuple):
        return spec
    kind, dtype, *rest = spec
    if kind == "default":
        return _default_solver(np.dtype(dtype), *rest)
    tol = _tol(np.dtype(dtype))
    return optx.LevenbergMarquardt(rtol=tol, atol=tol)


def _default_solver(dtype, absorbing):
    """Measured (`python -m jaxoptics bench`, fit section): for one real parameter started from
    the grid, Gauss-Newton converges in at most 5 steps on 10^4 noisy curves, 7x to 14x faster than
    Levenberg-Marquardt, which needs up to 24 damped steps. Its linear solve is
    `OneColumnLeastSquares` (closed form; lineax's default QR was a fifth of the fit's time).
    Complex fits (two parameters, a rougher landscape for metals) use Levenberg-Marquardt. Curves
    where Gauss-Newton fails are refitted with Levenberg-Marquardt (see `fit_eta`)."""
    tol = _tol(dtype)
    if absorbing:
        return optx.LevenbergMarquardt(rtol=tol, atol=tol)
    return optx.GaussNewton(rtol=tol, atol=tol, linear_solver=OneColumnLeastSquares())



def _weigh(r, w):
    return r if w is None else r * w


def _params_to_eta(y, absorbing):
    # The sign of n and k is irrelevant to the residual (|y| enters), so the solver can step through
    # zero freely; the result is reported on the physical branch n > 0, k >= 0.
    if absorbing:
        return jax.lax.complex(jnp.abs(y[0]), jnp.abs(y[1]))
    return jnp.abs(y[0])


def _covariance(J, r, sigma_given):
    """(J^T J)^-1 and the reduced chi-square.

    Without sigma the covariance is scaled by the reduced chi-square (the residual scatter
    estimates the noise). With sigma it is scaled by max(1, chi2_reduced), the Particle Data
    Group's scale factor: data that scatter more than their stated sigma (or that the model does
    not describe) widen the errors instead of leaving a confident wrong answer.
    """
    m, p = J.shape
    chi2 = jnp.sum(r * r) / (m - p)
    cov = _inverse_with_null_space(jnp.sum(J * J, axis=0, keepdims=True) if p == 1 else J.T @ J)
    return cov * (jnp.maximum(chi2, 1) if sigma_given else chi2), chi2


def _inverse_with_null_space(A):
    """Inverse of a symmetric positive semi-definite normal matrix, honest about what it cannot see.

    Directions the data do not constrain to first order (an eigenvalue below p * eps of the
    largest, after scaling to unit diagonal) get infinite variance: every parameter with a
    component along them has variance inf, the others the pseudo-inverse's finite value. Example:
    k exactly 0 in a complex fit, where R depends on k only quadratically, so d R / d k = 0.
    """
    p = A.shape[0]
    if p == 1:  # closed form: a batched 1x1 eigh costs more than the whole solve
        a = A[0, 0]
        return jnp.where(a > 0, 1 / jnp.where(a > 0, a, 1), jnp.inf).reshape(1, 1)
    d = jnp.sqrt(jnp.diagonal(A))
    d_ok = d > 0
    d = jnp.where(d_ok, d, 1)
    S = A / (d[:, None] * d[None, :])
    if p == 2:
        # S = [[1, rho], [rho, 1]] (where both diagonals are nonzero): eigenvalues 1 -+ |rho| with
        # eigenvectors (1, -+sign(rho)) / sqrt(2), in closed form (no batched LAPACK call).
        rho = S[0, 1]
        sgn = jnp.where(rho < 0, -1.0, 1.0).astype(A.dtype)
        lam = jnp.stack([1 - jnp.abs(rho), 1 + jnp.abs(rho)])
        h = jnp.sqrt(jnp.asarray(0.5, A.dtype))
        V = jnp.stack([jnp.stack([h, h]), jnp.stack([-sgn * h, sgn * h])])
        lam = jnp.where(d_ok[0] & d_ok[1], lam, jnp.where(d_ok[0] | d_ok[1], jnp.array([0.0, 1.0], A.dtype), 0))
        V = jnp.where(d_ok[0] & d_ok[1], V, jnp.where(d_ok[0], jnp.array([[0.0, 1.0], [1.0, 0.0]], A.dtype),
                                                      jnp.array([[1.0, 0.0], [0.0, 1.0]], A.dtype)))
    else:
        lam, V = jnp.linalg.eigh(S)
    good = lam > lam[-1] * A.shape[0] * jnp.finfo(A.dtype).eps
    inv_lam = jnp.where(good, 1 / jnp.where(good, lam, 1), 0)
    cov = (V * inv_lam[None, :]) @ V.T / (d[:, None] * d[None, :])
    unseen = (jnp.sum(jnp.where(good[None, :], 0, V * V), axis=1) > 1e-12) | ~d_ok
    diag = jnp.where(unseen, jnp.inf, jnp.diagonal(cov))
    return cov.at[jnp.diag_indices(A.shape[0])].set(diag)


def _fit_one(cos_i, R, w, eta1, y0, *, polarization, absorbing, solver, max_steps, sigma_given):

    def residual(y, _):
        return _weigh(_model(cos_i, eta1, _params_to_eta(y, absorbing), polarization) - R, w)

    sol = optx.least_squares(residual, _solver(solver), y0, max_steps=max_steps, throw=False)
    y = jnp.abs(sol.value)  # the physical branch
    cov, se, rms, chi2 = _errors(_model, cos_i, R, w, eta1, y, polarization=polarization, absorbing=absorbing,
                                 sigma_given=sigma_given)
    if absorbing:
        eta, stderr = jax.lax.complex(y[0], y[1]), jax.lax.complex(se[0], se[1])
    else:
        eta, stderr = y[0], se[0]
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(y)) & ~jnp.any(jnp.isnan(se))
    return FitResult(eta, stderr, cov, ok, rms, chi2, sol.stats["num_steps"], jnp.full_like(rms, jnp.nan))


def _errors(model, cos_i, R, w, eta1, y, *, polarization, absorbing, sigma_given):
    """Covariance, standard errors, residual rms and reduced chi-square of one curve at the
    physical parameters `y` (eta, or n and k), with `model(cos_i, eta1, eta2, polarization)`."""

    def res_phys(q):  # residuals as a function of the physical parameters (eta, or n and k)
        eta2 = jax.lax.complex(q[0], q[1]) if absorbing else q[0]
        return _weigh(model(cos_i, eta1, eta2, polarization) - R, w)

    # r and J from separate passes: a jvp returning both compiles to more loops, with the shared
    # terms materialized (measured: 74 against 57 ms for the whole fit of 10^4 curves)
    r = res_phys(y)
    J = jax.jacfwd(res_phys)(y)
    cov, chi2 = _covariance(J, r, sigma_given)
    if not absorbing:
        # Internal reflection: where the fitted critical angle sits on a data angle theta_j
        # (eta = eta1 sin theta_j, which can be the least-squares minimum when noise lifts that
        # point's R above 1), that residual's derivative is infinite and the linearized standard
        # error collapses (seen: 3e-10 for a fit 1.5e-5 off). The linearization does not hold
        # within such a point's reach, so the error comes from the other points: the (at most
        # two) points whose critical index is next to the estimate are left out of J^T J when it
        # is within 3 standard errors. (Found by bisection in the shared, sorted critical indices,
        # not by another pass over every residual: that cost 5% of a 10^4-curve fit.)
        crit = eta1 * jnp.sqrt(1 - cos_i * cos_i)  # eta2 that puts the critical angle on theta_j
        order = jnp.argsort(crit)
        pos = count_below(crit[order], y[0])
        m = crit.shape[0]
        nb = order[jnp.clip(jnp.stack([pos - 1, pos]), 0, m - 1)]
        nb_ok = (jnp.abs(crit[nb] - y[0]) < 3 * jnp.sqrt(cov[0, 0])) & jnp.array([True, nb[0] != nb[1]])
        near = jnp.sum(jnp.where(nb_ok, J[nb, 0] ** 2, 0))
        jtj = jnp.sum(J[:, 0] ** 2)
        rest = jtj - near
        cov = jnp.where(near > 0, jnp.where(rest > 0, cov * (jtj / jnp.where(rest > 0, rest, 1)), jnp.inf), cov)
    se = jnp.sqrt(jnp.diagonal(cov))
    rms = jnp.sqrt(jnp.mean((r if w is None else r / w) ** 2))
    return cov, se, rms, chi2


# Curves are fitted in blocks of about this many points (curves x angles), one block after the
# other inside the one compiled call (`lax.map`). The whole batch at once needs about 51 MB of
# temporaries for 10^4 curves x 90 angles: above glibc's largest mmap threshold (32 MiB), so every
# call got fresh pages from the kernel (13,000 page faults per call, counted) and each array
# streamed through memory. In blocks of ~1,500 curves, 0 faults and cache-sized arrays: 36 to
# 25-27 ms for the jitted batch (side by side in one process; blocks of 1000 to 2500 curves
# measured alike, 250 slower), and the same estimates to the bit.
_BLOCK_POINTS = 2 ** 17


def _fit_batch(theta, R, w, eta1, y_init, *, polarization, absorbing, solver, max_steps, use_init, sigma_given):
    """`polarization`: a name for all curves, or the weight of s-polarized light per curve, `(B,)`."""
    kw = dict(absorbing=absorbing, solver=solver, max_steps=max_steps, use_init=use_init, sigma_given=sigma_given)
    B, m = R.shape
    # number of blocks; one for symbolic shapes (`_index_stages.angles_poly` bounds B m by a block)
    k = -(-B // max(1, _BLOCK_POINTS // m)) if isinstance(m, int) else 1
    if k <= 1:
        return _fit_block(theta, R, w, eta1, y_init, polarization=polarization, **kw)
    C = -(-B // k)  # curves per block; the last block is padded with copies of the last curve
    pad = k * C - B
    blocks = lambda x: (jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x
                        ).reshape((k, C) + x.shape[1:])
    per_curve = _per_curve(polarization)
    out = jax.lax.map(lambda a: _fit_block(theta, a[0], a[1], eta1, a[2], polarization=_of_curve(polarization, a[3]), **kw),
                      (blocks(R), blocks(w), blocks(y_init), None if per_curve is None else blocks(per_curve)))
    return jax.tree_util.tree_map(lambda x: x.reshape((k * C,) + x.shape[2:])[:B], out)


def _fit_block(theta, R, w, eta1, y_init, *, polarization, absorbing, solver, max_steps, use_init, sigma_given):
    # Without sigma the residuals are not weighted at all (w is None): no array of ones is
    # broadcast, carried through the solver's loop and read in every step. (Keeping the ones
    # (B, 1) inside the vmapped solver measured about 2x slower than broadcasting them to (B, m):
    # the loop's fusions split differently.)
    w = jnp.broadcast_to(w, R.shape) if sigma_given else None
    # The m cosines, computed once and stored: left to itself XLA fused jnp.cos into the loops
    # over all (B, m) residuals after the solve and took 10^6 cosines in each.
    cos_i = materialize(jnp.cos(theta))
    per_curve = _per_curve(polarization)
    if use_init:
        y0 = y_init
    else:

        def residual(y, R1, w1, p1, cols):
            return _weigh(_reflectance_fit(cos_i[cols], eta1, _params_to_eta(y, absorbing), p1) - R1, w1)

        y0, alt = _start(theta, cos_i, R, w, eta1, residual, absorbing, polarization)
    one = lambda R1, w1, y1, p1: _fit_one(cos_i, R1, w1, eta1, y1, polarization=_of_curve(polarization, p1),
                                          absorbing=absorbing, solver=solver, max_steps=max_steps, sigma_given=sigma_given)
    res = jax.vmap(one)(R, w, y0, per_curve)
    if use_init:
        return res, y0, y_init, jnp.full(R.shape[:1], jnp.inf, R.dtype)
    if absorbing:  # k fitted as exactly 0: flagged with ratio 0 (see `_absorbing_restart`)
        return res, y0, alt, jnp.where(jnp.imag(res.eta) == 0, 0.0, jnp.inf).astype(R.dtype)
    # A start on the other branch (see `_second_branch`): the better of the grid's refined point
    # there and the mirror image eta1^2 / eta of the solution (the same normal-incidence
    # reflectance; the better start when the data cover small angles only), and its sum of squares
    # relative to the solution's. Both on the start's 16 angles: on every angle this took 8 ms of
    # a 40 ms fit of 10^4 curves (the kernel on (curves, 2, angles) splits into several loops).
    cols = _score_columns(R.shape[-1])
    cands = jnp.stack([res.eta[:, None], alt, (eta1 * eta1 / res.eta)[:, None]], axis=1)  # (B, 3, 1)
    pol = polarization if per_curve is None else per_curve[:, None, None]
    r = _weigh(_reflectance_plain(cos_i[cols], eta1, cands, pol) - R[:, None, cols],
               None if w is None else w[:, None, cols])
    sse = jnp.sum(r * r, axis=-1)  # (B, 3)
    k = 1 + _first_argmin(sse[:, 1:])
    alt = jnp.take_along_axis(cands, k[:, None, None], axis=1)[:, 0]
    return res, y0, alt, jnp.take_along_axis(sse, k[:, None], axis=1)[:, 0] / sse[:, 0]
