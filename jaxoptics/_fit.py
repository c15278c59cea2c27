"""Fit the refractive index to reflectance-versus-angle curves, with optimistix.

One curve or thousands: every curve of a batch is fitted in one compiled, vmapped call. Results are
a `FitResult` pytree (estimate, standard error from the Jacobian at the solution, convergence flag),
never an exception from inside the solver.
"""

from __future__ import annotations

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree

from . import _validate as V
from ._fresnel import _own_loop, fresnel, fresnel_sp, materialize

POLARIZATIONS = ("unpolarized", "s", "p")


def _reflectance(cos_i, eta1, eta2, polarization):
    if polarization == "unpolarized":
        return fresnel(cos_i, eta1, eta2)
    R_s, R_p = fresnel_sp(cos_i, eta1, eta2)
    return R_s if polarization == "s" else R_p


def _kt_squared_plain(ki, eta1, eta2):
    """k_t^2 = eta2^2 - eta1^2 sin^2 in the two forms of `fresnel` (see `_kt_squared`), by one select."""
    return jnp.where(eta1 > 2 * eta2, eta2 * eta2 + (ki - eta1) * (ki + eta1), (eta2 - eta1) * (eta2 + eta1) + ki * ki)


def _reflectance_d_eta2(cos_i, eta1, eta2, polarization):
    r"""`d R / d eta2` for a real `eta2`, written so that XLA compiles it to one fused loop.

    With k_i = eta1 |c|, k_t = sqrt(q), q = eta2^2 - eta1^2 + k_i^2, D_s = k_i + k_t and
    D_p = eta2^2 k_i + eta1^2 k_t (the same closed form as `fresnel`'s derivative rule):

    $$\frac{dR_s}{d\eta_2} = \frac{-4 k_i \eta_2 (k_i - k_t)}{k_t D_s^3}, \qquad
    \frac{dR_p}{d\eta_2} = \frac{4 \eta_1^2 \eta_2 k_i (2 q - \eta_2^2)(\eta_2^2 k_i - \eta_1^2 k_t)}{k_t D_p^3}$$

    and 0 under TIR and at the critical angle (q <= 0), as in `fresnel`. Only what a fit needs:
    no guards for invalid input (the fit's index is |y| and its data are checked), one select at
    the end. The kernel's own rule shares its quotients with the reflectance and selects on
    several masks; XLA on the CPU (no multi-output fusion) then wrote five arrays over all
    (curves x angles) per solver step for this one column.
    """
    ki = eta1 * jnp.abs(cos_i)
    e1sq, e2sq = eta1 * eta1, eta2 * eta2
    q = _kt_squared_plain(ki, eta1, eta2)
    kt = jnp.sqrt(jnp.maximum(q, jnp.finfo(q.dtype).tiny))
    if polarization != "p":
        ds = ki + kt
        d_s = -4 * ki * eta2 * (ki - kt) / (kt * ds * ds * ds)
    if polarization != "s":
        dp = e2sq * ki + e1sq * kt
        d_p = 4 * e1sq * eta2 * ki * (2 * q - e2sq) * (e2sq * ki - e1sq * kt) / (kt * dp * dp * dp)
    d = {"s": lambda: d_s, "p": lambda: d_p, "unpolarized": lambda: 0.5 * (d_s + d_p)}[polarization]()
    return jnp.where(q > 0, d, 0)


def _reflectance_plain(cos_i, eta1, eta2, polarization):
    """The reflectance for a real `eta2 > 0` as one expression XLA compiles to one fused loop: the
    fits' model (residuals, start ranking).

    `fresnel` is accurate to a few ulps relative to R everywhere; a fit needs R to an absolute
    accuracy far below any measurement noise, and pays for the kernel's guards and branches in
    every solver step. Here: the textbook amplitudes on k_t^2 formed as in `fresnel` (exact
    `eta2 - eta1`; for `eta1 > 2 eta2` the form that cancels only at the scale of eta2^2), one
    select at the end. Absolute error at most 1e-15 (tested against 50-digit mpmath), except
    within rounding of the critical angle, where both are ill-conditioned. On the fits' shapes the
    careful kernel split into four loops in the start and was 14% of a 10^4-curve fit in the
    solver (measured).
    """
    shape = jnp.broadcast_shapes(jnp.shape(cos_i), jnp.shape(eta1), jnp.shape(eta2))
    cos_i, eta1, eta2 = (jnp.broadcast_to(x, shape) for x in (cos_i, eta1, eta2))
    ki = eta1 * jnp.abs(cos_i)
    e1sq, e2sq = eta1 * eta1, eta2 * eta2
    kt = jnp.sqrt(jnp.maximum(_kt_squared_plain(ki, eta1, eta2), 0))  # 0 under TIR: R = 1
    rs = (ki - kt) / (ki + kt)
    rp = (e2sq * ki - e1sq * kt) / (e2sq * ki + e1sq * kt)
    R = {"s": lambda: rs * rs, "p": lambda: rp * rp, "unpolarized": lambda: 0.5 * (rs * rs + rp * rp)}[polarization]()
    # 0/0 only at exact grazing incidence with k_t = 0: no interface if eta1 == eta2 (R = 0), else
    # the grazing limit under TIR (R = 1). Written as `== 0` so that a NaN candidate (the TIR-onset
    # estimate of a curve without a plateau) keeps R = NaN and is never chosen: `> 0` made its R
    # 0, the best fit to an index-matched curve.
    return jnp.where(ki + kt == 0, jnp.where(eta1 == eta2, 0, 1), R)


def _amplitudes_complex(cos_i, eta1, eta2):
    """k_i, k_t, the denominators D_s and D_p, eta1^2 and eta2^2 for a complex `eta2 = n + ik`,
    `k >= 0`: what the complex fits' model and its derivative are written in (plain expressions,
    see `_reflectance_plain`)."""
    shape = jnp.broadcast_shapes(jnp.shape(cos_i), jnp.shape(eta1), jnp.shape(eta2))
    cos_i, eta1, eta2 = (jnp.broadcast_to(x, shape) for x in (cos_i, eta1, eta2))
    e1 = eta1.astype(eta2.dtype)  # explicit casts: also under jax_numpy_dtype_promotion="strict"
    ki = e1 * jnp.abs(cos_i).astype(eta2.dtype)
    e1sq, e2sq = e1 * e1, eta2 * eta2
    kt = jnp.sqrt((eta2 - e1) * (eta2 + e1) + ki * ki)  # principal root: Im >= 0 for k >= 0
    ds, dp = ki + kt, e2sq * ki + e1sq * kt
    return ki, kt, ds, dp, e1sq, e2sq


def _reflectance_complex_plain(cos_i, eta1, eta2, polarization):
    """The reflectance for a complex `eta2`, as `_reflectance_plain` for a real one (absolute error
    about 1e-14 against mpmath)."""
    ki, kt, ds, dp, e1sq, e2sq = _amplitudes_complex(cos_i, eta1, eta2)
    rs, rp = (ki - kt) / ds, (e2sq * ki - e1sq * kt) / dp
    a2 = lambda z: jnp.real(z) ** 2 + jnp.imag(z) ** 2
    R = {"s": lambda: a2(rs), "p": lambda: a2(rp), "unpolarized": lambda: 0.5 * (a2(rs) + a2(rp))}[polarization]()
    return jnp.where(jnp.real(ds) == 0, jnp.where(eta1 == jnp.real(eta2), 0, 1), R)


def _reflectance_complex_grad(cos_i, eta1, eta2, polarization):
    """G with dR = Re(G d eta2): G = 2 conj(r) dr/deta2 for one polarization, the mean for both.
    dr_s/deta2 = -2 k_i eta2 / (k_t D_s^2), dr_p/deta2 = 2 eta1^2 eta2 k_i (2 k_t^2 - eta2^2) / (k_t D_p^2)."""
    ki, kt, ds, dp, e1sq, e2sq = _amplitudes_complex(cos_i, eta1, eta2)
    gs = jnp.conj((ki - kt) / ds) * (-2 * ki * eta2 / (kt * ds * ds))
    gp = jnp.conj((e2sq * ki - e1sq * kt) / dp) * (2 * e1sq * eta2 * ki * (2 * kt * kt - e2sq) / (kt * dp * dp))
    G = {"s": lambda: 2 * gs, "p": lambda: 2 * gp, "unpolarized": lambda: gs + gp}[polarization]()
    return jnp.where(jnp.abs(kt) > 0, G, 0)


def _reflectance_fit(cos_i, eta1, eta2, polarization):
    """The fits' model: `_reflectance_plain` for a real `eta2`, `_reflectance_complex_plain` for a
    complex one."""
    plain = _reflectance_complex_plain if jnp.iscomplexobj(eta2) else _reflectance_plain
    return plain(cos_i, eta1, eta2, polarization)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _model(cos_i, eta1, eta2, polarization):
    """`_reflectance_fit`, whose derivative in `eta2` is in closed form and compiles to a loop of
    its own.

    The solver linearizes the model at every step and needs the residuals and the Jacobian over all
    (curves x angles). Derived together, they share quotients, which XLA on the CPU writes to
    memory and reads back (the kernel's own derivative rule made five loops per step). Here the
    derivative comes from `_reflectance_d_eta2` (real `eta2`) or `_reflectance_complex_grad`
    (complex: `dR = Re(G d eta2)`), on inputs passed through an optimization barrier (`_own_loop`)
    so that no common subexpression ties it to the model's loop.
    """
    return _reflectance_fit(cos_i, eta1, eta2, polarization)


@functools.partial(_model.defjvp, symbolic_zeros=True)
def _model_jvp(polarization, primals, tangents):
    cos_i, eta1, eta2 = primals
    out = _model(cos_i, eta1, eta2, polarization)
    dc, de1, de2 = tangents
    if type(dc) is not SymbolicZero or type(de1) is not SymbolicZero:
        raise NotImplementedError("the fits' model is differentiated in eta2 only (angles and eta1 are data)")
    if type(de2) is SymbolicZero:
        return out, jnp.zeros_like(out)
    copies = _own_loop(cos_i, eta1, eta2)
    if jnp.iscomplexobj(eta2):
        G = _reflectance_complex_grad(*copies, polarization)
        return out, jnp.real(G) * jnp.real(de2) - jnp.imag(G) * jnp.imag(de2)
    return out, _reflectance_d_eta2(*copies, polarization) * de2


def synthetic_reflectance(key, eta2, theta, *, eta1=1.0, polarization="unpolarized", noise=0.0):
    r"""Reflectance curves `R(theta)` for index `eta2`, with optional Gaussian noise.

    **Arguments:**

    - `key`: a `jax.random` key (used only when `noise > 0`).
    - `eta2`: index of the reflecting medium, real or complex (`n + ik`), shape `(...)`.
    - `theta`: angles of incidence in radians, shape `(m,)`.
    - `eta1`: index of the incident medium (keyword).
    - `polarization`: `"unpolarized"`, `"s"` or `"p"`.
    - `noise`: standard deviation of additive Gaussian noise (not clipped to [0, 1], so the noise
      stays unbiased).

    **Returns:** `R` of shape `(..., m)`.
    """
    if polarization not in POLARIZATIONS:
        raise ValueError(f"polarization must be one of {POLARIZATIONS}, got {polarization!r}")
    theta = jnp.asarray(V.as_real(theta, "theta"))
    eta2 = jnp.asarray(eta2)
    R = _reflectance(jnp.cos(theta), eta1, eta2[..., None], polarization)
    if noise:
        R = R + noise * jax.random.normal(key, R.shape, R.dtype)
    return R


class FitResult(eqx.Module):
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


def _grid(eta1, absorbing, dtype):
    """Data-independent starting points: a log grid of indices, or of (n, k) pairs."""
    if absorbing:
        n = eta1 * jnp.exp(jnp.linspace(jnp.log(0.03), jnp.log(8.0), 24)).astype(dtype)
        k = jnp.concatenate([jnp.zeros(1, dtype), eta1 * jnp.exp(jnp.linspace(jnp.log(1e-3), jnp.log(10.0), 19)).astype(dtype)])
        nn, kk = jnp.meshgrid(n, k, indexing="ij")
        return jnp.stack([nn.ravel(), kk.ravel()], -1)
    # log(eta / eta1) = -u ... u for u log-spaced in [1e-3, 2.1]: a range of 0.12 to 8 times eta1,
    # and fine near eta1, where a low-contrast curve changes fastest with the index
    u = jnp.exp(jnp.linspace(jnp.log(1e-3), jnp.log(2.1), 24))
    x = jnp.concatenate([-u[::-1], u])
    return (eta1 * jnp.exp(x)).astype(dtype)[:, None]


def _first_argmin(x):
    """`argmin` over the last axis (first index of the minimum; NaN is never chosen, all-NaN rows
    give 0) as two plain float reductions. XLA's CPU argmin, a reduction over (value, index)
    pairs, took 1.8 ms on (10^4, 90) float64 against 0.75 ms for this (measured)."""
    x = jnp.where(jnp.isnan(x), jnp.inf, x)
    n = x.shape[-1]
    k = jnp.arange(n, dtype=x.dtype)
    first = jnp.min(jnp.where(x == jnp.min(x, axis=-1, keepdims=True), k, n), axis=-1)
    return jnp.where(first < n, first, 0).astype(jnp.int32)


def _heuristics(theta, R, eta1, absorbing):
    """Per-curve physical estimates of a real index, shape (4, p)."""
    # normal-incidence inversion from the smallest angle (both branches: R0 is symmetric in eta2/eta1)
    # (s is kept off 0: eta2 == eta1 is a stationary point, dR/deta = 0, where Gauss-Newton stalls)
    k0 = jnp.argmin(theta)
    s = jnp.sqrt(jnp.clip(R[k0], 1e-6, 0.98))
    # onset of a TIR plateau (internal reflection): the critical angle lies between the smallest
    # angle with R near 1 and the largest angle below it; NaN (so never chosen) when there is no
    # plateau. The midpoint, not the onset angle itself: eta1 sin(theta_j) puts the critical angle
    # exactly on a data angle, where that residual's derivative is infinite, and Gauss-Newton
    # started there cannot leave it (measured: 8% of noisy internal-reflection curves were fitted
    # 5 to 30x the noise away, with standard errors of 1e-9).
    plateau = R >= 0.97
    first = jnp.min(jnp.where(plateau, theta, jnp.pi / 2))
    ths = jnp.sort(theta)  # shared by the curves: sorted once (under vmap), then a bisection
    j = jnp.searchsorted(ths, first)
    mid = jnp.where(j > 0, 0.5 * (ths[jnp.maximum(j - 1, 0)] + first), first)
    onset = jnp.where(jnp.any(plateau), mid, jnp.nan)
    # Brewster's minimum (of R_p; the unpolarized minimum lies near it too)
    brewster = jnp.clip(theta[_first_argmin(R)], 1e-3, 1.5)
    h = jnp.stack([eta1 * (1 + s) / (1 - s), eta1 * (1 - s) / (1 + s), eta1 * jnp.sin(onset), eta1 * jnp.tan(brewster)])
    if absorbing:
        return jnp.stack([h, jnp.zeros_like(h)], -1)
    return h[:, None]


def _score_columns(m):
    """At most 16 of the m angles, evenly spread: where start candidates are ranked."""
    return np.unique(np.linspace(0, m - 1, min(m, 16)).round().astype(int))


def _start(theta, cos_i, R, w, eta1, residual, absorbing, polarization):
    """Best starting point per curve (vmapped over curves): the shared grid is scored for all
    curves at once with matrix products (sum w^2 (Rg - R)^2 expanded), the few per-curve
    candidates (heuristics, the refined grid point) on at most 16 of the angles, evenly spread:
    the start only has to land in the right basin, and scoring them on every angle was a third of
    the whole fit's time (measured, 10^4 curves x 90 angles). All candidates are ranked on those
    same angles."""
    grid = _grid(eta1, absorbing, R.dtype)
    eta_g = jax.lax.complex(grid[:, 0], grid[:, 1]) if absorbing else grid[:, 0]
    Rg = _reflectance(cos_i[None, :], eta1, eta_g[:, None], polarization)  # (K, m), shared
    w2 = None if w is None else w * w

    def grid_sse(cols):
        Rg_, R_ = Rg[:, cols], R[:, cols]
        if w is None:  # unit weights: one matrix product instead of two
            sse = jnp.sum(Rg_ * Rg_, -1)[None, :] - 2 * (R_ @ Rg_.T) + jnp.sum(R_ * R_, -1, keepdims=True)
        else:
            w2_ = w2[:, cols]
            sse = (w2_ @ (Rg_ * Rg_).T) - 2 * ((w2_ * R_) @ Rg_.T) + jnp.sum(w2_ * R_ * R_, -1, keepdims=True)
        return jnp.where(jnp.isfinite(sse), sse, jnp.inf)

    sub = _score_columns(theta.shape[0])
    score = lambda y, R1, w1: jnp.sum(residual(y, R1[sub], None if w1 is None else w1[sub], sub) ** 2)
    heur = jax.vmap(lambda R1: _heuristics(theta, R1, eta1, absorbing))(R)  # (B, 4, p)
    sse_heur = jax.vmap(lambda hs, w1, R1: jax.vmap(lambda y: score(y, R1, w1))(hs))(heur, w, R)
    sse_grid = grid_sse(sub)
    if not absorbing:
        # Refine the best grid point (scored on every angle) by the vertex of the parabola (in
        # log eta) through it and its neighbours: the start is then within a fraction of a percent
        # and Gauss-Newton needs 3 to 5 steps. Once on each branch (eta2 below and above eta1):
        # below the critical angle the two branches give similar curves, and the grid's spacing
        # can favour the wrong one (measured: with angles 20 to 70 degrees, eta1 = 1.5 and eta2
        # near 1.45, 4% of noisy fits landed near 1.58 on the other branch, 50 standard errors
        # off); the refined points of both compete (2.5% then).
        full = grid_sse(slice(None))
        K = grid.shape[0]  # K / 2 grid points on each side of eta1 (see `_grid`)
        x = jnp.log(grid[:, 0])

        def refine(lo, hi):
            k = jnp.clip(lo + _first_argmin(full[:, lo:hi]), lo + 1, hi - 2)
            s0, s1, s2 = (jnp.take_along_axis(full, (k + d)[:, None], axis=1)[:, 0] for d in (-1, 0, 1))
            x0, x1, x2 = x[k - 1], x[k], x[k + 1]
            # vertex of the parabola through (x0, s0), (x1, s1), (x2, s2)
            num = (x1 - x0) ** 2 * (s1 - s2) - (x1 - x2) ** 2 * (s1 - s0)
            den = (x1 - x0) * (s1 - s2) - (x1 - x2) * (s1 - s0)
            ok = (den != 0) & (s0 >= s1) & (s2 >= s1)
            xv = jnp.where(ok, x1 - 0.5 * num / jnp.where(ok, den, 1), x1)
            return jnp.exp(jnp.clip(xv, x0, x2))[:, None]

        refined = jnp.stack([refine(0, K // 2), refine(K // 2, K)], axis=1)  # (B, 2, 1)
        sse_ref = jax.vmap(lambda ys, R1, w1: jax.vmap(lambda y: score(y, R1, w1))(ys))(refined, R, w)
        cands = jnp.concatenate([jnp.broadcast_to(grid, (R.shape[0],) + grid.shape), heur, refined], axis=1)
        sse = jnp.concatenate([sse_grid, sse_heur, sse_ref], axis=1)
        y0 = jnp.take_along_axis(cands, _first_argmin(sse)[:, None, None], axis=1)[:, 0]
        # The other branch's refined point, and how close the branches' best grid scores are
        # (see `_second_branch`)
        return y0, jnp.where(y0 < eta1, refined[:, 1], refined[:, 0])
    cands = jnp.concatenate([jnp.broadcast_to(grid, (R.shape[0],) + grid.shape), heur], axis=1)
    sse = jnp.concatenate([sse_grid, sse_heur], axis=1)
    y0 = jnp.take_along_axis(cands, _first_argmin(sse)[:, None, None], axis=1)[:, 0]
    # The best grid point with k > 0, for curves whose fit ends at k = 0 (see `_absorbing_restart`)
    k_pos = jnp.where(grid[:, 1] > 0, sse_grid, jnp.inf)
    return y0, grid[_first_argmin(k_pos)]


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

    sol = optx.least_squares(residual, solver, y0, max_steps=max_steps, throw=False)
    y = jnp.abs(sol.value)  # the physical branch

    def res_phys(q):  # residuals as a function of the physical parameters (eta, or n and k)
        eta2 = jax.lax.complex(q[0], q[1]) if absorbing else q[0]
        return _weigh(_model(cos_i, eta1, eta2, polarization) - R, w)

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
        pos = jnp.searchsorted(crit[order], y[0])
        m = crit.shape[0]
        nb = order[jnp.clip(jnp.stack([pos - 1, pos]), 0, m - 1)]
        nb_ok = (jnp.abs(crit[nb] - y[0]) < 3 * jnp.sqrt(cov[0, 0])) & jnp.array([True, nb[0] != nb[1]])
        near = jnp.sum(jnp.where(nb_ok, J[nb, 0] ** 2, 0))
        jtj = jnp.sum(J[:, 0] ** 2)
        rest = jtj - near
        cov = jnp.where(near > 0, jnp.where(rest > 0, cov * (jtj / jnp.where(rest > 0, rest, 1)), jnp.inf), cov)
    se = jnp.sqrt(jnp.diagonal(cov))
    if absorbing:
        eta, stderr = jax.lax.complex(y[0], y[1]), jax.lax.complex(se[0], se[1])
    else:
        eta, stderr = y[0], se[0]
    rms = jnp.sqrt(jnp.mean((r if w is None else r / w) ** 2))
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(y)) & ~jnp.any(jnp.isnan(se))
    return FitResult(eta, stderr, cov, ok, rms, chi2, sol.stats["num_steps"], jnp.full_like(rms, jnp.nan))


# Curves are fitted in blocks of about this many points (curves x angles), one block after the
# other inside the one compiled call (`lax.map`). The whole batch at once needs about 51 MB of
# temporaries for 10^4 curves x 90 angles: above glibc's largest mmap threshold (32 MiB), so every
# call got fresh pages from the kernel (13,000 page faults per call, counted) and each array
# streamed through memory. In blocks of ~1,500 curves, 0 faults and cache-sized arrays: 36 to
# 25-27 ms for the jitted batch (side by side in one process; blocks of 1000 to 2500 curves
# measured alike, 250 slower), and the same estimates to the bit.
_BLOCK_POINTS = 2 ** 17


@eqx.filter_jit
def _fit_batch(theta, R, w, eta1, y_init, *, polarization, absorbing, solver, max_steps, use_init, sigma_given):
    kw = dict(polarization=polarization, absorbing=absorbing, solver=solver, max_steps=max_steps, use_init=use_init,
              sigma_given=sigma_given)
    B, m = R.shape
    k = -(-B // max(1, _BLOCK_POINTS // m))  # number of blocks
    if k <= 1:
        return _fit_block(theta, R, w, eta1, y_init, **kw)
    C = -(-B // k)  # curves per block; the last block is padded with copies of the last curve
    pad = k * C - B
    blocks = lambda x: (jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x
                        ).reshape((k, C) + x.shape[1:])
    out = jax.lax.map(lambda a: _fit_block(theta, a[0], a[1], eta1, a[2], **kw), (blocks(R), blocks(w), blocks(y_init)))
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
    if use_init:
        y0 = y_init
    else:

        def residual(y, R1, w1, cols):
            return _weigh(_reflectance_fit(cos_i[cols], eta1, _params_to_eta(y, absorbing), polarization) - R1, w1)

        y0, alt = _start(theta, cos_i, R, w, eta1, residual, absorbing, polarization)
    one = lambda R1, w1, y1: _fit_one(cos_i, R1, w1, eta1, y1, polarization=polarization, absorbing=absorbing,
                                      solver=solver, max_steps=max_steps, sigma_given=sigma_given)
    res = jax.vmap(one)(R, w, y0)
    if use_init:
        return res, y_init, jnp.full(R.shape[:1], jnp.inf, R.dtype)
    if absorbing:  # k fitted as exactly 0: flagged with ratio 0 (see `_absorbing_restart`)
        return res, alt, jnp.where(jnp.imag(res.eta) == 0, 0.0, jnp.inf).astype(R.dtype)
    # A start on the other branch (see `_second_branch`): the better of the grid's refined point
    # there and the mirror image eta1^2 / eta of the solution (the same normal-incidence
    # reflectance; the better start when the data cover small angles only), and its sum of squares
    # relative to the solution's. Both on the start's 16 angles: on every angle this took 8 ms of
    # a 40 ms fit of 10^4 curves (the kernel on (curves, 2, angles) splits into several loops).
    cols = _score_columns(R.shape[-1])
    cands = jnp.stack([res.eta[:, None], alt, (eta1 * eta1 / res.eta)[:, None]], axis=1)  # (B, 3, 1)
    r = _weigh(_reflectance_plain(cos_i[cols], eta1, cands, polarization) - R[:, None, cols],
               None if w is None else w[:, None, cols])
    sse = jnp.sum(r * r, axis=-1)  # (B, 3)
    k = 1 + _first_argmin(sse[:, 1:])
    alt = jnp.take_along_axis(cands, k[:, None, None], axis=1)[:, 0]
    return res, alt, jnp.take_along_axis(sse, k[:, None], axis=1)[:, 0] / sse[:, 0]


def _refit(res, theta, R, w, eta1, y_init, lm, use_init, kw):
    """Gauss-Newton is fast but undamped: refit whatever it did not converge on with
    Levenberg-Marquardt, in one more batched call over just those curves."""
    bad = np.flatnonzero(~np.asarray(res.converged))
    if not bad.size:
        return res
    pad = _bucket(bad)
    sub, _, _ = _fit_batch(theta, R[pad], w[pad], eta1, y_init[pad], solver=lm, use_init=use_init, **kw)
    return jax.tree_util.tree_map(lambda a, b: a.at[bad].set(b[:bad.size]), res, sub)


# Curves whose start on the other branch fits within this factor of the solution's sum of
# squares (on the start's 16 angles) are solved on that branch too (see `_second_branch`).
# Measured (noise 1e-3 and 1e-4; internal and external reflection; angles 0-15, 0-30, 0-60, 0-85,
# 20-70 and 40-80 degrees; the other branch's minimum found from three starts, one of them the
# true index): every curve whose other branch fits within Delta chi2 < 9 had a ratio below 2.5
# (below 3.5 for Delta chi2 < 16). No curve is flagged at 0-60, 0-85 or 40-80 degrees.
_BRANCH_RATIO = 4.0
_AMBIGUOUS_DCHI2 = 9.0


def _bucket(idx):
    """`idx` padded (with its first entry) to a power of two: subsets of a batch solved in a second
    call then reuse a few compiled shapes instead of compiling one per count."""
    n = 1 << max(int(idx.size) - 1, 0).bit_length()
    return np.concatenate([idx, np.full(n - idx.size, idx[0])])


def _solve_subset(res, idx, starts, theta, R, w, eta1, solver, lm, kw):
    """The curves `idx` solved again from `starts[idx]` in one batched call (padded, see `_bucket`;
    Levenberg-Marquardt refitting what Gauss-Newton does not converge on, when `lm` is given):
    (their new fits, their current fits), both as NumPy pytrees."""
    pad = _bucket(idx)
    sub, _, _ = _fit_batch(theta, R[pad], w[pad], eta1, starts[pad], solver=solver, use_init=True, **kw)
    if lm is not None:
        sub = _refit(sub, theta, R[pad], w[pad], eta1, starts[pad], lm, True, kw)
    return (jax.tree_util.tree_map(lambda a: np.asarray(a[:idx.size]), sub),
            jax.tree_util.tree_map(lambda a: np.asarray(a[idx]), res))


def _second_branch(res, alt, ratio, theta, R, w, eta1, solver, lm, kw):
    """Solve the curves whose other branch may fit as well, and report honestly when it does.

    Below the critical angle, internal-reflection curves (eta2 < eta1) and curves of a denser
    medium (eta2 > eta1) look alike. Where the data stop short of what tells them apart, the start
    can pick the branch that fits worse, and Gauss-Newton then converges to that branch's minimum
    with a small, local standard error: a confident wrong answer (measured before this: 2.5% of
    noisy internal-reflection fits over 20-70 degrees, |z| up to 27). Curves whose other-branch
    start fits within `_BRANCH_RATIO` of the solution are solved from it in one more batched call
    (none where the branches are told apart, e.g. 0-85 degrees). The smaller chi-square wins; where
    the other is within `Delta chi2 < 9`, it becomes `eta_alt` and the standard error includes the
    distance to it. (With `Delta chi2 < 4`, 1% of noisy fits at 0-30 degrees still had |z| up to
    385: the branch the data preferred by a chi-square of 5 was the wrong one.)
    """
    amb = np.flatnonzero(np.asarray(ratio) <= _BRANCH_RATIO)
    if not amb.size:
        return res
    sub, mine = _solve_subset(res, amb, alt, theta, R, w, eta1, solver, lm, kw)
    e1 = float(eta1)
    other = sub.converged & ((sub.eta < e1) != (mine.eta < e1))
    dof = R.shape[-1] - 1
    # chi-square in units of the noise: the reduced chi-square estimates it without sigma; with
    # sigma, data scattering more than stated widen it as in `_covariance`
    scale = mine.chi2_reduced if not kw["sigma_given"] else np.maximum(mine.chi2_reduced, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        dchi2 = (sub.chi2_reduced - mine.chi2_reduced) * dof / scale
    swap = other & (~mine.converged | (dchi2 < 0))
    near = other & mine.converged & (np.abs(dchi2) < _AMBIGUOUS_DCHI2)
    win = jax.tree_util.tree_map(lambda a, b: np.where(swap.reshape((-1,) + (1,) * (a.ndim - 1)), b, a), mine, sub)
    lose_eta = np.where(swap, mine.eta, sub.eta)
    gap2 = np.where(near, (win.eta - lose_eta) ** 2, 0)
    win = eqx.tree_at(lambda r: (r.eta_alt, r.stderr, r.covariance), win,
                      (np.where(near, lose_eta, np.nan), np.sqrt(win.stderr ** 2 + gap2),
                       win.covariance + gap2[:, None, None]))
    changed = swap | near
    if not changed.any():
        return res
    idx = amb[changed]
    return jax.tree_util.tree_map(lambda a, b: a.at[idx].set(b[changed]), res, win)


def _absorbing_restart(res, alt, ratio, theta, R, w, eta1, solver, lm, kw):
    """Complex fits that end at k = 0 exactly, solved once more from the best grid point with
    k > 0; the smaller chi-square wins.

    R depends on k only through k^2, so k = 0 is a stationary point the solver cannot leave. The
    physical estimates (normal-incidence inversion and the rest) are real, k = 0, and on a curve
    of a moderately absorbing medium the inversion's n matches the normal-incidence reflectance
    that n and k make together: it won the start, and the fit stayed at k = 0 with n far off
    (measured on 3000 noisy curves, n 0.1 to 3, k 0.5 to 6: 2.2% with |z| of n beyond 3, up to
    46, chi-square 20 to 150 times the noise; e.g. 3.36 + 0i for 2.97 + 1.01i). Curves whose data
    are of a non-absorbing medium come back to k near 0 and keep their first fit.
    """
    again = np.flatnonzero(np.asarray(ratio) == 0)
    if not again.size:
        return res
    sub, mine = _solve_subset(res, again, alt, theta, R, w, eta1, solver, lm, kw)
    better = sub.converged & (~mine.converged | (sub.chi2_reduced < mine.chi2_reduced))
    if not better.any():
        return res
    idx = again[better]
    return jax.tree_util.tree_map(lambda a, b: a.at[idx].set(b[better]), res, sub)


def _solve(theta, R, w, eta1, y_init, solver, lm, use_init, kw, first=None):
    """The batched fit and, on concrete data, its follow-ups: the Levenberg-Marquardt refit of
    curves Gauss-Newton did not converge on, and the second branch of ambiguous curves. `first`:
    the batched fit's output when already dispatched."""
    res, alt, ratio = first if first is not None else _fit_batch(theta, R, w, eta1, y_init, solver=solver,
                                                                  use_init=use_init, **kw)
    if not _is_concrete(R, w):
        return res
    if lm is not None:
        res = _refit(res, theta, R, w, eta1, y_init, lm, use_init, kw)
    if not use_init:
        again = _absorbing_restart if kw["absorbing"] else _second_branch
        res = again(res, alt, ratio, theta, R, w, eta1, solver, lm, kw)
    return res


def _batch_shards(R):
    """The addressable shards of `R` if it is sharded along its first axis only, over more than
    one device; else None."""
    sh = getattr(R, "sharding", None)
    if isinstance(R, jax.core.Tracer) or not isinstance(sh, jax.sharding.NamedSharding) or len(sh.device_set) == 1:
        return None
    spec = tuple(sh.spec) + (None,) * (R.ndim - len(sh.spec))
    if spec[0] is None or any(a is not None for a in spec[1:]):
        return None
    seen, shards = set(), []
    for s in R.addressable_shards:
        key = (s.index[0].start, s.index[0].stop)
        if key not in seen:  # replicas along other mesh axes: fit each block once
            seen.add(key)
            shards.append(s)
    return shards


def _fit_per_shard(shards, theta, R, w, eta1, y_init, solver, lm, use_init, kw):
    """Fit each device's block of curves on that device, then assemble the sharded result.

    Each device runs its own vmapped solver loop: no data move and no cross-device reduction in
    the loop (partitioning one vmapped loop over devices puts an all-reduce of the loop predicate in
    every step, and with forced host devices that was seen to stall for a few thousand curves).
    """
    sh = R.sharding
    results = []
    for s in shards:  # dispatch all first: the devices work concurrently
        sl = s.index[0]
        put = lambda x: jax.device_put(x, s.device)
        results.append(_fit_batch(put(theta), s.data, put(w[sl]), put(eta1), put(y_init[sl]), solver=solver,
                                  use_init=use_init, **kw))
    for k, s in enumerate(shards):
        sl = s.index[0]
        put = lambda x: jax.device_put(x, s.device)
        results[k] = _solve(put(theta), s.data, put(w[sl]), put(eta1), put(y_init[sl]), solver, lm, use_init, kw,
                            first=results[k])
    P = jax.sharding.PartitionSpec
    ax = sh.spec[0]

    def assemble(*leaves):
        shape = (R.shape[0],) + leaves[0].shape[1:]
        target = jax.sharding.NamedSharding(sh.mesh, P(ax, *([None] * (len(shape) - 1))))
        arrays = {s.device: leaf for s, leaf in zip(shards, leaves)}
        ordered = [arrays[d] for d in target.addressable_devices_indices_map(shape)]
        return jax.make_array_from_single_device_arrays(shape, target, ordered)

    return jax.tree_util.tree_map(assemble, *results)


def _is_concrete(*xs):
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


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
    if isinstance(R, jax.Array) and sigma is None:
        finite, const = (bool(x) for x in _curve_flags(R))
        if finite and not const:
            return  # all good; no copy of a possibly large, sharded array to the host
    Rv = np.asarray(R, dtype=np.float64)
    bad = np.argwhere(~np.isfinite(Rv))
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        raise ValueError(f"R{list(idx)} = {Rv[idx]} is not finite{at}")
    flat = Rv.reshape(-1, th.shape[0])
    const = np.flatnonzero(np.ptp(flat, axis=-1) == 0)
    if const.size:
        k = tuple(int(i) for i in np.unravel_index(const[0], Rv.shape[:-1])) if Rv.ndim > 1 else ()
        raise ValueError(
            f"curve {list(k)}{at} has the same reflectance {flat[const[0], 0]} at every angle: "
            "a constant curve carries no information on the index"
        )
    if sigma is not None:
        sv = np.asarray(sigma, dtype=np.float64)
        if not np.all(np.isfinite(sv) & (sv > 0)):
            k = tuple(int(i) for i in np.argwhere(~(np.isfinite(sv) & (sv > 0)))[0])
            raise ValueError(f"sigma{list(k)} = {sv[k]} must be finite and positive{at}")


def _warn_if_x64_off(*xs):
    if not jax.config.jax_enable_x64 and any(np.asarray(x).dtype == np.float64 for x in xs if not isinstance(x, jax.Array)):
        warnings.warn(
            "jax_enable_x64 is off, so float64 data are fitted in float32 (about 1e-6 relative accuracy). "
            "Call jax.config.update('jax_enable_x64', True) first to fit in float64.",
            stacklevel=3,
        )


def fit_eta(theta, R, *, eta1=1.0, polarization="unpolarized", sigma=None, init=None, absorbing=False,
            solver=None, max_steps=256) -> FitResult:
    r"""Fit the index of the reflecting medium to reflectance-versus-angle data.

    **Arguments:**

    - `theta`: angles of incidence in radians, shape `(m,)`, shared by all curves.
    - `R`: measured reflectance, `(m,)` for one curve or `(..., m)` for a batch; every curve is
      fitted independently, all in one compiled, batched call.
    - `eta1`: known (real) index of the incident medium. It may exceed the fitted index (internal
      reflection data with a TIR plateau).
    - `polarization`: `"unpolarized"`, `"s"` or `"p"`.
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
      refitted with `optimistix.LevenbergMarquardt` in a second batched call),
      `optimistix.LevenbergMarquardt` for a complex one; tolerances from the dtype. The choice was
      measured: see `_default_solver`.
    - `max_steps`: solver iteration cap; hitting it gives `converged=False`.

    **Returns:** a `FitResult` (see its fields) with the batch shape of `R`.

    **Two branches (real fits):** a medium less dense than the incident one (`eta2 < eta1`) and a
    denser one can give similar curves below the critical angle. Curves whose other branch may fit
    as well are solved on it too, in one more batched call over just those curves; the smaller
    chi-square wins, and where the other is within `Delta chi2 < 9` it is reported as `eta_alt` and
    included in `stderr` (see `FitResult`).

    **Errors:** degenerate data raise a `ValueError` before any solving: fewer than `p + 1` angles,
    non-finite values, angles outside `[0, pi/2]`, a constant curve, non-positive `sigma`, unknown
    polarization, shapes that do not match. (Under an outer `jit` only shapes are checked; NaN data
    then give `converged=False`; the Levenberg-Marquardt refit and the second-branch solve, which
    pick curves on the host, are skipped there.) Failures of the solver are reported as
    `converged=False`, never raised.

    **Dtype:** the fit runs in the floating dtype of `R`; with `jax_enable_x64` off, float64 NumPy
    data are fitted in float32 and a warning says so.
    """
    if polarization not in POLARIZATIONS:
        raise ValueError(f"polarization must be one of {POLARIZATIONS}, got {polarization!r}")
    p = 2 if absorbing else 1
    concrete = _is_concrete(theta, R, sigma)
    if concrete:
        _warn_if_x64_off(theta, R)  # looks at the dtype the caller passed, before conversion
    R = jnp.asarray(V.as_real(R, "R"))
    if concrete:  # checked where it will be fitted, by one compiled reduction
        check_curves(theta, R, sigma, n_params=p)
    if not np.isscalar(eta1) and np.ndim(eta1) != 0:
        raise ValueError(f"eta1 must be a scalar, got shape {np.shape(eta1)}")
    theta = jnp.asarray(V.as_real(theta, "theta"))
    dt = V.float_dtype(R, theta)
    R, theta = R.astype(dt), theta.astype(dt)
    batch, m = R.shape[:-1], R.shape[-1]
    Rf = R.reshape(-1, m)
    if sigma is None:
        w = jnp.ones((Rf.shape[0], 1), dt)
    else:
        w = jnp.broadcast_to(1 / jnp.asarray(V.as_real(sigma, "sigma"), dt), R.shape).reshape(-1, m)
    use_init = init is not None
    if use_init:
        init = jnp.broadcast_to(jnp.asarray(init), batch).reshape(-1)
        y_init = (jnp.stack([jnp.real(init), jnp.imag(init)], -1) if absorbing else jnp.real(init)[:, None]).astype(dt)
    else:
        y_init = jnp.zeros((Rf.shape[0], p), dt)
    retry = solver is None and not absorbing
    solver = _default_solver(dt, absorbing) if solver is None else solver
    kw = dict(polarization=polarization, absorbing=absorbing, max_steps=int(max_steps), sigma_given=sigma is not None)
    eta1 = jnp.asarray(eta1, dt)
    lm = optx.LevenbergMarquardt(rtol=_tol(dt), atol=_tol(dt)) if retry else None
    shards = _batch_shards(Rf)
    if shards is None:
        res = _solve(theta, Rf, w, eta1, y_init, solver, lm, use_init, kw)
    else:
        res = _fit_per_shard(shards, theta, Rf, w, eta1, y_init, solver, lm, use_init, kw)
    return jax.tree_util.tree_map(lambda x: x.reshape(batch + x.shape[1:]), res)
