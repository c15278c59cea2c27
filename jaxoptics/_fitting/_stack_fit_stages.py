"""The stages of a film fit (`fit_stack`), as named functions of the fit's description
(`FitProblem`, built once per sample structure, data grid and batch size by `build_problem`):

1. `fringe_grid` (NumPy, when the fit is built): the grid of starts over the free thicknesses,
   and the subset of wavelengths it is scored on (`grid_subset`);
2. `grid_starts`: the fringe search of one spectrum, its best grid points;
3. `gauss_newton_passes`: Gauss-Newton from the starts of every spectrum, in one or two passes;
4. `levenberg_marquardt_rescue`: Levenberg-Marquardt for the spectra Gauss-Newton did not fit;
5. `error_estimate`: standard errors, covariance, correlation and flags of one spectrum, and
   `map_errors`, which gets the normal matrices they need for a whole map.

`first_stage`, `errors_stage` and `second_stage` chain them into the compiled calls `fit_stack`
makes (see its module docstring for the method). The model, its residuals and their Jacobian
are evaluated on "all" the data points or on the grid's "subset" (`points`).

optimistix (with equinox and lineax) is imported inside the stages, which run only where a
program is traced: a process that loads its compiled fit from the store does not import it.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._films._sample import Sample
from .._runtime._options import wanted_options
from ._stack_jacobian import _model_and_jacobian

# On the benchmark's map (film thickness and Cauchy A, B, C free) Gauss-Newton takes 5-8 steps
# (5.6 on average) on the grid's subset of wavelengths and 2-3 on all the data (both passes: 8 on
# the median, 99% within 14); a spectrum it has not fitted after 20 steps of a pass (about 1 in 300
# there) is handed to Levenberg-Marquardt, which takes 40-55 steps on those. Both run as pools of
# lanes refilled as problems stop (`_pool`): 64 lanes keep the vectorized stack kernel busy, and
# the few Levenberg-Marquardt problems run 8 at a time so that idle lanes cost little.
_GN_STEPS = 20
# Gauss-Newton also stops when its step is below 1e-3 standard errors (`gauss_newton_edm_stop`):
# the squared step in the metric of the covariance, `|J s|^2`, at most `_EDM_TOL` times the
# covariance's variance scale. `|J s|^2` is MINUIT's EDM (the predicted fall of chi^2), which
# Migrad takes below `0.002 * tol` with `tol = 0.1` by default: 2e-4.
_EDM_TOL = 1e-6
# The first of two Gauss-Newton passes (on a subset of the wavelengths, for maps) stops at a step
# below 0.1 standard errors of that subset's fit.
_EDM_TOL_SUBSET = 1e-2
_GN_LANES = 64
_LM_LANES = 8
# Fits of at most this many residuals (spectra x data points) are compiled with `QUICK_COMPILE`:
# 12-20 ms more run time per spectrum than the optimized program, for 3-4 s less compile time.
_QUICK_COMPILE_RESIDUALS = 2**14
# Spectra per block of the other batched passes (grid costs, chi^2, standard errors): a lax.map
# over blocks bounds the memory of a map of any size.
_FIRST_BLOCK = 64
# how far inside its bounds every start is moved, as a fraction of their width (`_Bound.inside`)
_INSIDE = 1e-3


def _quick(B, Q, P):
    """Whether a fit of `B` spectra of `Q` quantities at `P` points is small: compiled with
    `QUICK_COMPILE`, and with one Gauss-Newton pass (compile time matters more than run time)."""
    return B * Q * P <= _QUICK_COMPILE_RESIDUALS


def _options(B, Q, P):
    """The compiler options asked for a fit of `B` spectra of `Q` quantities at `P` points
    (`wanted_options`: those this XLA knows are used). A small fit is compiled with
    `QUICK_COMPILE`: on the bundled example (one spectrum, 846 residuals) the first call takes
    6.9-8.4 s against 11.7 s with XLA's defaults, and a later one 21-30 ms against 9.0 ms."""
    return wanted_options(_quick(B, Q, P))


# ---- bounds: x(u) and its inverse -------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Bound:
    lo: float
    hi: float

    def inside(self, v, frac=_INSIDE):
        """`v` moved inside the bounds by `frac` of their width (of `max(1, |bound|)` where one
        is infinite) if it lies closer to one. A start on a bound is a stationary point of the
        change of variables (`dx/du = 0`): the solvers would never move that parameter and would
        report the point as converged though the data pull it inside."""
        lo, hi = self.lo, self.hi
        if math.isfinite(lo) and math.isfinite(hi):
            eps = frac * (hi - lo)
            return min(max(v, lo + eps), hi - eps)
        if math.isfinite(lo):
            return max(v, lo + frac * max(1.0, abs(lo)))
        if math.isfinite(hi):
            return min(v, hi - frac * max(1.0, abs(hi)))
        return v

    def x(self, u):
        lo, hi = self.lo, self.hi
        if math.isfinite(lo) and math.isfinite(hi):
            return lo + (hi - lo) * (1 + jnp.sin(u)) / 2
        if math.isfinite(lo):
            return lo - 1 + jnp.sqrt(u * u + 1)
        if math.isfinite(hi):
            return hi + 1 - jnp.sqrt(u * u + 1)
        return u

    def u(self, x):
        lo, hi = self.lo, self.hi
        if math.isfinite(lo) and math.isfinite(hi):
            return jnp.arcsin(jnp.clip(2 * (x - lo) / (hi - lo) - 1, -1, 1))
        if math.isfinite(lo):
            return jnp.sqrt(jnp.maximum((x - lo + 1) ** 2 - 1, 0))
        if math.isfinite(hi):
            return jnp.sqrt(jnp.maximum((hi - x + 1) ** 2 - 1, 0))
        return x


def _wrap_deg(d):
    """`d` (degrees) less the nearest multiple of 360: in `[-180, 180]`, within an ulp of `d` of
    the exact remainder. (`jnp.mod` is a scalar library call per element on the CPU, a twentieth
    of a fit's time; this vectorizes.)"""
    return d - 360 * jnp.round(d / 360)


# ---- the fit's description --------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class FitProblem:
    """What the stages of one fit are built from (compared by identity: one per compiled fit).

    `sample` with its `free` parameters (`p` of them) and their `bounds`, the starts `x0` (moved
    inside the bounds); the data's layout: `B` spectra of the quantities `kinds` (`Q`) at `P`
    points (wavelengths `wl` in nm and angles `ang` in radians, and the same in NumPy as `lam`);
    the grid of starts (`grid`, `(n_grid, p)`, None without a global start) and the points `sub`
    it is scored on; `starts` per spectrum; `two_pass` (Gauss-Newton on `sub` first); the fit's
    `dtype`, its solvers' tolerance `tol`, `sigma_given`, `max_steps` of Levenberg-Marquardt and
    `progress`."""

    sample: Sample
    kinds: tuple
    B: int
    Q: int
    P: int
    p: int
    dtype: np.dtype
    lam: np.ndarray
    wl: jax.Array
    ang: jax.Array
    is_delta: np.ndarray
    free: tuple
    bounds: tuple
    x0: np.ndarray
    grid: np.ndarray | None
    sub: np.ndarray
    starts: int
    two_pass: bool
    sigma_given: bool
    max_steps: int
    progress: bool
    tol: float

    @property
    def M(self) -> int:
        """The number of least-squares problems: one per (spectrum, start)."""
        return self.B * self.starts

    def points(self, which: str):
        """`(wl, ang)` of "all" the data points or of the grid's "subset"."""
        return (self.wl, self.ang) if which == "all" else (self.wl[self.sub], self.ang[self.sub])


def grid_subset(wl_nm, n_max, d_max):
    """Indices of a subset of points whose wavenumbers sample the fringes of a film of optical
    thickness `n_max * d_max` at least four times per period (all angles of a kept wavelength)."""
    sigma = 1 / np.asarray(wl_nm)
    period = 1 / (2 * n_max * max(d_max, 1e-9))
    uniq = np.unique(sigma)[::-1]
    kept, last = [], None
    for s in uniq:
        if last is None or last - s >= period / 4:
            kept.append(s)
            last = s
    kept = np.asarray(kept)
    return np.flatnonzero(np.isin(sigma, kept))


def fringe_grid(sample, free, x0, lam, dtype, max_grid, window=None):
    """`(grid, sub)`: the grid of starts over the free thicknesses with finite upper bounds and the
    indices of the data points it is scored on, or `(None, all points)` where there is no such
    thickness.

    Each such thickness is sampled from its lower to its upper bound with a step of `1/8` of the
    shortest fringe period `lambda_min / (2 n_max)` (`n_max` its layer's largest start index over
    the data), so that a grid point lies well inside the basin of the true minimum; several share
    a product grid, coarsened to at most `max_grid` points. The other parameters sit at `x0`. The
    subset of points samples the fringes of all the films together at least four times per
    period (`grid_subset`). `window = (i, low, high)` searches free thickness `i` over that range
    instead of its bounds (the Fourier-transform start, `_reflectometry.fft_window`)."""
    P, p = lam.shape[0], len(free)
    span = {i: (f.lower, f.upper) for i, f in enumerate(free)}
    if window is not None:
        span[window[0]] = (window[1], window[2])
    tidx = [i for i, f in enumerate(free) if f.is_thickness and math.isfinite(span[i][1])]
    if not tidx:
        return None, np.arange(P)
    fixed = sample.fixed()
    axes = []
    nmax_all = 1.0
    for i in tidx:
        layer_name = free[i].name.rsplit(".", 1)[0]
        li = sample.layer_names.index(layer_name)
        N = np.asarray(fixed.layers[li].material.nk(jnp.asarray(lam / 1000, dtype)))
        nmax = float(np.nanmax(np.abs(N))) if np.any(np.isfinite(N)) else 2.0
        nmax_all = max(nmax_all, nmax)
        step = lam.min() / (2 * nmax) / 8
        axes.append((span[i][0], span[i][1], step))
    counts = [max(2, int(math.ceil((hi - lo) / st)) + 1) for lo, hi, st in axes]
    while math.prod(counts) > max_grid:
        j = int(np.argmax(counts))
        counts[j] = max(2, counts[j] * 3 // 4)
    pts = np.meshgrid(*[np.linspace(lo, hi, c) for (lo, hi, _), c in zip(axes, counts)], indexing="ij")
    G = np.stack([g.reshape(-1) for g in pts], -1)  # (n_grid, len(tidx))
    grid = np.broadcast_to(x0, (G.shape[0], p)).copy()
    grid[:, tidx] = G
    # keep the starts of the thicknesses strictly inside their bounds
    for i in tidx:
        lo, hi = free[i].lower, free[i].upper
        eps = 1e-6 * (hi - lo)
        grid[:, i] = np.clip(grid[:, i], lo + eps, hi - eps)
    dmax = sum(span[i][1] for i in tidx)
    return grid, grid_subset(lam, nmax_all, dmax)


def build_problem(sample, kinds, wl_nm, angle_deg, B, dtype_name, sigma_given, global_start, starts, max_grid,
                  max_steps, progress) -> FitProblem:
    """The `FitProblem` of `fit_stack`'s arguments (concrete values; the grid is computed here)."""
    dtype = jnp.dtype(dtype_name)
    free = tuple(sample.free())
    p = len(free)
    Q, P = len(kinds), len(wl_nm)
    lam = np.asarray(wl_nm)
    bounds = tuple(_Bound(f.lower, f.upper) for f in free)
    x0 = np.asarray([b.inside(f.value) for f, b in zip(free, bounds)], np.float64)
    window = global_start[1:] if isinstance(global_start, tuple) else None  # ("window", i, low, high)
    grid, sub = fringe_grid(sample, free, x0, lam, dtype, max_grid, window) if global_start else (None, np.arange(P))
    # A map's Gauss-Newton runs in two passes where the grid's subset of wavelengths holds at most
    # half of the data: first on that subset, to a step below 0.1 of the subset's standard errors,
    # then on all the data from there, which then takes two or three steps. (A small fit, compiled
    # with `QUICK_COMPILE` for a short first call, runs one pass: a smaller program.)
    two_pass = sub.shape[0] <= P // 2 and not _quick(B, Q, P)
    return FitProblem(
        sample=sample, kinds=tuple(kinds), B=B, Q=Q, P=P, p=p, dtype=dtype, lam=lam, wl=jnp.asarray(lam, dtype),
        ang=jnp.asarray(np.deg2rad(np.asarray(angle_deg)), dtype),
        is_delta=np.asarray([k == "delta_deg" for k in kinds]), free=free, bounds=bounds, x0=x0, grid=grid, sub=sub,
        starts=max(1, min(int(starts), 1 if grid is None else grid.shape[0])), two_pass=two_pass,
        sigma_given=sigma_given, max_steps=int(max_steps), progress=progress, tol=_solver_tol(dtype))


def _solver_tol(dtype):
    from ._index_solver import _tol

    return _tol(dtype)


# ---- the model, its residuals and their Jacobian ----------------------------------------------

# Each is called at several places of the one program (the solvers' init and step, the errors, the
# grid): jitted, it is traced once per shape, not at every call.


def to_x(prob: FitProblem, u):
    """The physical parameters `x` of the solvers' variables `u` (the bounds' change of variables)."""
    return jnp.stack([b.x(u[i]) for i, b in enumerate(prob.bounds)])


def to_u(prob: FitProblem, x):
    return jnp.stack([b.u(x[i]) for i, b in enumerate(prob.bounds)])


@functools.partial(jax.jit, static_argnums=(0, 1))
def model_at(prob: FitProblem, points: str, x):
    """The model's quantities at `points` ("all" or "subset"), quantity after quantity."""
    wl, ang = prob.points(points)
    return prob.sample.with_values([x[i] for i in range(prob.p)]).quantities(prob.kinds, wl, ang, flat=True)


@functools.partial(jax.jit, static_argnums=(0, 1))
def model_and_jacobian(prob: FitProblem, points: str, x):
    """The model at `points` and its Jacobian in `x` (`_stack_jacobian`)."""
    wl, ang = prob.points(points)
    return _model_and_jacobian(prob.sample, prob.kinds, wl, ang)(x)


def weigh(prob: FitProblem, model, V, S):
    """Weighted residuals of `model` against the data (`V`, `S` flattened the same way); delta's
    differences wrapped into `[-180, 180]`."""
    diff = model - V
    if prob.is_delta.any():
        is_delta = np.repeat(prob.is_delta, diff.shape[-1] // prob.Q)
        diff = jnp.where(jnp.broadcast_to(is_delta, diff.shape), _wrap_deg(diff), diff)
    return diff / S


def residuals_x(prob: FitProblem, points: str, x, V, S):
    """Weighted residuals at `points` in the physical parameters `x`."""
    return weigh(prob, model_at(prob, points, x), V, S)


def residuals_and_jacobian(prob: FitProblem, points: str, x, V, S):
    """`(r, J)`: the weighted residuals at `points` and their Jacobian in `x`."""
    m, J = model_and_jacobian(prob, points, x)
    return weigh(prob, m, V, S), J / S[:, None]  # the wrap of delta has derivative 1


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def residuals_u(prob: FitProblem, points: str, u, V, S):
    """Weighted residuals at `points` in the solvers' variables `u`, with the Jacobian of
    `residuals_and_jacobian` as their derivative."""
    return residuals_x(prob, points, to_x(prob, u), V, S)


@residuals_u.defjvp
def _residuals_u_jvp(prob, points, primals, tangents):
    # The Jacobian in one forward pass with p tangents (`jacfwd`), kept as a matrix: the solvers
    # linearize this function and then apply the linearization to p basis vectors, which for the
    # stack kernel would store and re-read every intermediate array; J @ du is cheap.
    u, V, S = primals
    du, dV, dS = tangents
    x, dxdu = jax.jvp(functools.partial(to_x, prob), (u,), (jnp.ones_like(u),))  # x_i depends on u_i alone
    r, J = residuals_and_jacobian(prob, points, x, V, S)
    return r, J @ (dxdu * du) - dV / S - r * dS / S  # r = (model - V) / S is linear in V and 1/S


def spectrum_residuals(prob: FitProblem, points: str, V, S, u, i):
    """`residuals_u` of problem `i`'s spectrum (`V`, `S`: `(B, ...)` at `points`): the function the
    pooled solvers call with a problem's `u` and its spectrum index `i`."""
    return residuals_u(prob, points, u, V[i], S[i])


def spectrum_chi2(prob: FitProblem, V, S, u, i):
    """chi^2 on all the data of spectrum `i` at `u`."""
    return jnp.sum(residuals_x(prob, "all", to_x(prob, u), V[i], S[i]) ** 2)


def _variance_scale(prob: FitProblem, m, r):
    """The variance scale of the reported covariance (`error_estimate`) from the residuals `r` of
    `m` data: the reduced chi-square, at least 1 where the data carried sigma."""
    chi2 = jnp.sum(r * r) / (m - prob.p)
    return jnp.maximum(chi2, 1) if prob.sigma_given else chi2


# ---- the stages -------------------------------------------------------------------------------


def grid_starts(prob: FitProblem, Mg, Vb, Sb):
    """The fringe search of one spectrum: the `starts` grid points whose model `Mg` (`(n_grid, Q
    |sub|)`, evaluated once for the whole map) fits its data on the subset best (or the `Free`
    values, without a grid), in the solvers' variables `u`."""
    if prob.grid is None:
        return to_u(prob, jnp.asarray(prob.x0, prob.dtype))[None]
    Q, P = prob.Q, prob.P
    Vs = Vb.reshape(Q, P)[:, prob.sub].reshape(-1)
    Ss = Sb.reshape(Q, P)[:, prob.sub].reshape(-1)
    cost = jnp.sum(weigh(prob, Mg, Vs[None], Ss[None]) ** 2, axis=-1)
    cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
    # (one start: the minimum, at half the cost of the sort on the benchmark's map)
    best = jnp.argmin(cost)[None] if prob.starts == 1 else jnp.argsort(cost)[:prob.starts]
    return jax.vmap(functools.partial(to_u, prob))(jnp.asarray(prob.grid, prob.dtype)[best])


def map_starts(prob: FitProblem, V, S):
    """`grid_starts` of every spectrum, `(M, p)` (`V`, `S`: `(B, Q P)`); the model on the grid does
    not depend on the data, so it is evaluated once for the whole map."""
    Mg = None
    if prob.grid is not None:
        Mg = jax.vmap(functools.partial(model_at, prob, "subset"))(jnp.asarray(prob.grid, prob.dtype))
    starts = _blocked(jax.vmap(functools.partial(grid_starts, prob, Mg)), (V, S), _FIRST_BLOCK)
    return starts.reshape(prob.M, prob.p)


def gauss_newton_passes(prob: FitProblem, U0, V, S):
    """Gauss-Newton (at most `_GN_STEPS` steps a pass) from the starts `U0` of every problem, as a
    pool of lanes (`_pool`); for a `two_pass` fit, first on the subset of points to a step below
    0.1 of its standard errors, then on all the data from there. The full-data pass stops at a
    step below 1e-3 standard errors (`gauss_newton_edm_stop`) and keeps the normal matrix of its
    last step.

    **Returns:** `(u, ok, steps, A, c2, have)` per problem: the solution, whether Gauss-Newton
    converged, the steps of both passes, and where `have` the normal matrix `A` in `x` and the
    sum of squares `c2` its last step predicts (`normal_from_stop`)."""
    import optimistix as optx

    from ._pool import gauss_newton_edm_stop, pooled_least_squares

    M, Q = prob.M, prob.Q
    gn: optx.AbstractLeastSquaresSolver = optx.GaussNewton(rtol=prob.tol, atol=prob.tol)
    spec = jnp.arange(M) // prob.starts  # the spectrum of each (spectrum, start) problem
    U1, st0 = U0, 0
    if prob.two_pass:
        sub = prob.sub
        Vs = V.reshape(prob.B, Q, prob.P)[:, :, sub].reshape(prob.B, -1)
        Ss = S.reshape(prob.B, Q, prob.P)[:, :, sub].reshape(prob.B, -1)
        stop = gauss_newton_edm_stop(_EDM_TOL_SUBSET, functools.partial(_variance_scale, prob, Q * sub.shape[0]))
        u0, _, st0, _, _ = pooled_least_squares(functools.partial(spectrum_residuals, prob, "subset", Vs, Ss), gn, U0,
                                                spec, jnp.arange(M), M, lanes=_GN_LANES, max_steps=_GN_STEPS,
                                                early_stop=stop,
                                                on_progress=_progress(prob, "first pass, on a subset of the wavelengths"))
        # the second pass starts where the first ended (from the start, where that is not finite)
        U1 = jnp.where(jnp.all(jnp.isfinite(u0), axis=-1, keepdims=True), u0, U0)
    # the full-data pass keeps the normal matrix of its last step: the standard errors need no
    # further evaluation of the model where it ended by this test (`error_estimate`)
    stop = gauss_newton_edm_stop(_EDM_TOL, functools.partial(_variance_scale, prob, Q * prob.P), normal_matrix=True)
    u1, ok1, st1, _, (info, early) = pooled_least_squares(functools.partial(spectrum_residuals, prob, "all", V, S), gn,
                                                          U1, spec, jnp.arange(M), M, lanes=_GN_LANES,
                                                          max_steps=_GN_STEPS, early_stop=stop,
                                                          on_progress=_progress(prob, "Gauss-Newton stage"))
    A, c2, usable = jax.vmap(functools.partial(normal_from_stop, prob))(info)
    return u1, ok1, st0 + st1, A, c2, early & usable


def levenberg_marquardt_rescue(prob: FitProblem, V, S, U0, x, c2, ok, steps):
    """Levenberg-Marquardt (optimistix, `max_steps` a start) from the same starts `U0`, for the
    spectra Gauss-Newton did not fit (`~ok`; those problems first, so that the cost follows their
    number), as a pool of `_LM_LANES` lanes; per spectrum, the better solution of the two. A
    spectrum that neither fitted keeps the point of lower chi^2: Levenberg-Marquardt's (which only
    takes steps that lower chi^2) unless Gauss-Newton's, which can wander off, ended lower.

    **Returns:** `(x, c2, ok, steps, better)`, `better` where Levenberg-Marquardt's won."""
    import optimistix as optx

    from ._pool import pooled_least_squares

    M = prob.M
    lm: optx.AbstractLeastSquaresSolver = optx.LevenbergMarquardt(rtol=prob.tol, atol=prob.tol)
    spec = jnp.arange(M) // prob.starts
    pend = ~ok[spec]
    order = jnp.argsort(~pend, stable=True)
    count = jnp.sum(pend)
    u2, ok2, st2, touched, _ = pooled_least_squares(functools.partial(spectrum_residuals, prob, "all", V, S), lm, U0,
                                                    spec, order, count, lanes=_LM_LANES, max_steps=prob.max_steps)
    c22 = _pending_map(functools.partial(spectrum_chi2, prob, V, S), (u2, spec), order, count, _LM_LANES,
                       jnp.full(M, jnp.inf, prob.dtype))
    x2, c22, ok2, st2 = best_start(prob, u2, c22, ok2 & touched, st2)
    # chi^2 at Gauss-Newton's point where it did not converge (its `c2` there is the prediction
    # of its last step, not the value at `x`), for those spectra only
    B = prob.B
    left = jnp.argsort(ok, stable=True)
    c2_x = _pending_map(lambda xb, b: jnp.sum(residuals_x(prob, "all", xb, V[b], S[b]) ** 2), (x, jnp.arange(B)), left,
                        jnp.sum(~ok), _LM_LANES, c2)
    better = ok2 & (~ok | (c22 < c2)) | (~ok & ~ok2 & (c22 < jnp.where(jnp.isnan(c2_x), jnp.inf, c2_x)))
    return (jnp.where(better[:, None], x2, x), jnp.where(better, c22, c2), ok | ok2, steps + st2, better)


def normal(prob: FitProblem, x, Vb, Sb):
    """The normal matrix `J^T J` of the weighted residuals in `x`, and their sum of squares."""
    r, J = residuals_and_jacobian(prob, "all", x, Vb, Sb)
    return J.T @ J, jnp.sum(r * r)


def normal_from_stop(prob: FitProblem, info):
    """`normal` from the Gauss-Newton stop's `info` (`gauss_newton_edm_stop`): its normal matrix in
    `u`, at the point `u` where the last step began, taken to `x` by the chain rule (`J_x = J_u /
    (dx/du)` column by column: a product undone, exact to rounding while `dx/du` is not zero), and
    the sum of squares predicted after the step. That step is below 1e-3 standard errors, so `J`
    differs from its value at the solution by as little. Also whether it is usable."""
    u, Au, c2 = info
    dxdu = jax.jvp(functools.partial(to_x, prob), (u,), (jnp.ones_like(u),))[1]
    A = Au / dxdu[:, None] / dxdu[None, :]
    usable = jnp.all(dxdu != 0) & jnp.all(jnp.isfinite(A)) & jnp.isfinite(c2)
    return A, c2, usable


def error_estimate(prob: FitProblem, x, ok, A, c2):
    """Standard errors, covariance, correlation, chi^2/dof, convergence and at-bound flags of one
    spectrum from the normal matrix `A` and the sum of squares `c2` at `x`.

    The covariance is `(J^T J)^-1`, inverted through the eigendecomposition of the correlation-
    scaled matrix without truncation (eigenvalues floored at `eps^2` of the largest): a direction
    the data do not determine gets an enormous standard error and correlations near +-1, never a
    small one. It is scaled by chi^2/dof (at least 1 where the data carried sigma)."""
    p, dtype = prob.p, prob.dtype
    chi2r = c2 / (prob.Q * prob.P - p)
    dg = jnp.sqrt(jnp.diag(A))
    dsafe = jnp.where(dg > 0, dg, 1)
    lam_, vec = jnp.linalg.eigh(A / dsafe[:, None] / dsafe[None, :])
    tiny = jnp.finfo(dtype).eps ** 2 * jnp.maximum(jnp.max(lam_), jnp.finfo(dtype).tiny)
    cov = (vec / jnp.maximum(lam_, tiny)[None, :]) @ vec.T / dsafe[:, None] / dsafe[None, :]
    cov = jnp.where((dg[:, None] > 0) & (dg[None, :] > 0), cov, jnp.where(jnp.eye(p, dtype=bool), jnp.inf, 0))
    cov = cov * (jnp.maximum(chi2r, 1) if prob.sigma_given else chi2r)
    sd = jnp.sqrt(jnp.abs(jnp.diag(cov)))
    sdsafe = jnp.where(jnp.isfinite(sd) & (sd > 0), sd, 1)
    corr = cov / sdsafe[:, None] / sdsafe[None, :]
    lo = jnp.asarray([f.lower for f in prob.free], dtype)
    hi = jnp.asarray([f.upper for f in prob.free], dtype)
    span = jnp.where(jnp.isfinite(hi - lo), hi - lo, jnp.maximum(jnp.abs(x), 1))
    at_b = (jnp.abs(x - lo) <= 1e-6 * span) | (jnp.abs(hi - x) <= 1e-6 * span)
    conv = ok & jnp.all(jnp.isfinite(x)) & jnp.isfinite(chi2r)
    return sd, cov, corr, chi2r, conv, at_b


def best_start(prob: FitProblem, u, c2, ok, steps, *more):
    """The lowest chi^2 among each spectrum's converged starts (and the arrays `more` of that
    start); where none converged, the lowest chi^2 among all of them."""
    B, starts, p = prob.B, prob.starts, prob.p
    x = jax.vmap(functools.partial(to_x, prob))(u).reshape(B, starts, p)
    c2 = jnp.where(jnp.isfinite(c2), c2, jnp.inf).reshape(B, starts)
    ok = ok.reshape(B, starts) & jnp.isfinite(c2)
    k = jnp.where(jnp.any(ok, axis=1), jnp.argmin(jnp.where(ok, c2, jnp.inf), axis=1), jnp.argmin(c2, axis=1))
    pick = lambda a: jnp.take_along_axis(a, k.reshape((B, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]
    return (pick(x), pick(c2), pick(ok), pick(steps.reshape(B, starts))) + tuple(
        pick(a.reshape((B, starts) + a.shape[1:])) for a in more)


def map_errors(prob: FitProblem, x, ok, steps, V, S, A, c2, have):
    """The fit's results for every spectrum (`error_estimate`): the normal matrix and sum of
    squares `A`, `c2` where `have`, evaluated at `x` for the other spectra (their number sets the
    cost: `_pending_map`)."""
    order = jnp.argsort(have, stable=True)
    A, c2 = _pending_map(functools.partial(normal, prob), (x, V, S), order, jnp.sum(~have), _FIRST_BLOCK, (A, c2))
    sd, cov, corr, chi2r, conv, at_b = jax.vmap(functools.partial(error_estimate, prob))(x, ok, A, c2)
    return x, sd, cov, corr, chi2r, conv, at_b, steps


# ---- the compiled calls -----------------------------------------------------------------------


def first_stage(prob: FitProblem, V, S):
    """The fringe search and Gauss-Newton from every start: the starts `U0`, and the best
    solution's `x`, `c2`, `ok`, `steps` per spectrum, with the normal matrix `A` of its last step
    where `have` (`c2` is then that step's prediction; see `map_errors`)."""
    V, S = V.reshape(prob.B, -1), S.reshape(prob.B, -1)
    U0 = map_starts(prob, V, S)
    u1, ok1, steps, A, c2e, have = gauss_newton_passes(prob, U0, V, S)
    # chi^2 picks the best of several starts (with one, the stop's prediction or `map_errors` gives it)
    spec = jnp.arange(prob.M) // prob.starts
    c21 = _blocked(jax.vmap(functools.partial(spectrum_chi2, prob, V, S)), (u1, spec), _FIRST_BLOCK) if prob.starts > 1 else c2e
    x, c2, ok, steps, A, have = best_start(prob, u1, c21, ok1, steps, A, have)
    return U0, x, c2, ok, steps, A, have


def errors_stage(prob: FitProblem, V, S, state):
    """The fit of `first_stage`, with its standard errors: where Gauss-Newton fitted every spectrum."""
    V, S = V.reshape(prob.B, -1), S.reshape(prob.B, -1)
    _, x, c2, ok, steps, A, have = state
    return map_errors(prob, x, ok, steps, V, S, A, c2, have)


def second_stage(prob: FitProblem, V, S, state):
    """`levenberg_marquardt_rescue` for the spectra Gauss-Newton did not fit, then the standard
    errors (where every spectrum was fitted, what `errors_stage` gives: its loop runs zero times)."""
    V, S = V.reshape(prob.B, -1), S.reshape(prob.B, -1)
    U0, x, c2, ok, steps, A, have = state
    x, c2, ok, steps, better = levenberg_marquardt_rescue(prob, V, S, U0, x, c2, ok, steps)
    return map_errors(prob, x, ok, steps, V, S, A, c2, have & ~better)


STAGES = (first_stage, errors_stage, second_stage)


# ---- batching helpers and progress ------------------------------------------------------------


def _pending_map(f, args, order, count, size, init):
    """`out[order[i]] = f(*args[order[i]])` for `i < count` (traced), `size` at a time, the rest of
    `init` (an array, or a pytree of them like `f`'s output) unchanged: the work follows `count`,
    not the length of `args`."""
    M = order.shape[0]
    size = min(size, M)

    def body(c):
        i, out = c
        idx = jax.lax.dynamic_slice(jnp.concatenate([order, order[:size]]), (i,), (size,))
        val = jax.vmap(f)(*(a[idx] for a in args))
        dst = jnp.where(i + jnp.arange(size) < count, idx, M)
        return i + size, jax.tree.map(lambda o, v: o.at[dst].set(v, mode="drop"), out, val)

    return jax.lax.while_loop(lambda c: c[0] < count, body, (jnp.asarray(0), init))[1]


def _blocked(f, args, size):
    """`f` (batched over the leading axis) over blocks of `size` along that axis, one block after
    another (`lax.map`); the last block is padded by repeating the final element. Each block's
    intermediate arrays (a few spectra x all their points) then stay in the CPU's caches, where
    the whole batch at once would stream every linearization residual through memory."""
    B = args[0].shape[0]
    if B <= size:
        return f(*args)
    nb = -(-B // size)
    pad = lambda a: jnp.concatenate([a, jnp.broadcast_to(a[-1:], (nb * size - B,) + a.shape[1:])]).reshape((nb, size) + a.shape[1:])

    out = jax.lax.map(lambda xs: f(*xs), tuple(pad(a) for a in args))
    return jax.tree.map(lambda y: y.reshape((nb * size,) + y.shape[2:])[:B], out)


def _progress(prob: FitProblem, what: str):
    """The pooled solver's `on_progress` for a fit with `progress`, else None."""
    return functools.partial(_report_lanes, prob.starts, prob.B, what) if prob.progress else None


def _report_lanes(starts, total, what, done, _count):
    _report(done // starts, total, what)


_last_report = [0.0]


def _report(done, total, what):
    """Progress on standard error, at most twice a second and once at the end."""
    import sys
    import time

    done, total = int(done), int(total)
    now = time.monotonic()
    if done < total and now - _last_report[0] < 0.5:
        return
    _last_report[0] = now
    end = "\n" if done >= total else ""
    print(f"\rfit_stack: {done} of {total} spectra fitted ({what})", end=end, file=sys.stderr, flush=True)
