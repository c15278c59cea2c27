"""Starting points of the index fits: a data-independent grid of indices scored on a few angles
in one batched pass, and heuristics from the curve's shape (no single start may land on the
wrong side of eta1 or in a wrong local minimum)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._interface._fresnel import fresnel_sp
from ._index_model import _reflectance


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
    j = count_below(ths, first)
    mid = jnp.where(j > 0, 0.5 * (ths[jnp.maximum(j - 1, 0)] + first), first)
    onset = jnp.where(jnp.any(plateau), mid, jnp.nan)
    # Brewster's minimum (of R_p; the unpolarized minimum lies near it too)
    brewster = jnp.clip(theta[_first_argmin(R)], 1e-3, 1.5)
    h = jnp.stack([eta1 * (1 + s) / (1 - s), eta1 * (1 - s) / (1 + s), eta1 * jnp.sin(onset), eta1 * jnp.tan(brewster)])
    if absorbing:
        return jnp.stack([h, jnp.zeros_like(h)], -1)
    return h[:, None]


def count_below(sorted_x, v):
    """`jnp.searchsorted(sorted_x, v)` (a bisection); for a symbolic length, which
    `jnp.searchsorted` does not take, a count of the elements below `v` (a pass over all)."""
    if isinstance(sorted_x.shape[0], int):
        return jnp.searchsorted(sorted_x, v)
    return jnp.sum(sorted_x < v)


def _score_columns(m):
    """At most 16 of the m angles, evenly spread: where start candidates are ranked. For a symbolic
    m (a program traced for any number of angles, `_index_stages.angles_poly`: then m >= 16), the
    same 16 indices computed in the program."""
    if not isinstance(m, int):  # round(k (m - 1) / 15), k < 16 (never a tie: 2 k (m - 1) is even)
        return (jnp.arange(16) * (2 * m - 2) + 15) // 30
    return np.unique(np.linspace(0, m - 1, min(m, 16)).round().astype(int))


def _per_curve(polarization):
    """The weights of s-polarized light, one per curve, when `polarization` is not one name for
    all curves (see `_index_model._mix`); else None."""
    return None if isinstance(polarization, str) else polarization


def _of_curve(polarization, p1):
    """One curve's polarization inside a vmap over curves: its weight `p1` (vmapped from
    `_per_curve`), or the name all curves share (`p1` None)."""
    return polarization if p1 is None else p1


def _start(theta, cos_i, R, w, eta1, residual, absorbing, polarization):
    """Best starting point per curve (vmapped over curves): the shared grid is scored for all
    curves at once with matrix products (sum w^2 (Rg - R)^2 expanded), the few per-curve
    candidates (heuristics, the refined grid point) on at most 16 of the angles, evenly spread:
    the start only has to land in the right basin, and scoring them on every angle was a third of
    the whole fit's time (measured, 10^4 curves x 90 angles). All candidates are ranked on those
    same angles. `polarization`: a name, or the weight of s-polarized light per curve, `(B,)`;
    `residual(y, R1, w1, polarization, cols)` is one curve's residual on the angles `cols`."""
    grid = _grid(eta1, absorbing, R.dtype)
    eta_g = jax.lax.complex(grid[:, 0], grid[:, 1]) if absorbing else grid[:, 0]
    w2 = None if w is None else w * w
    per_curve = _per_curve(polarization)
    if per_curve is None:
        # the grid's curves, shared: (K, m)
        parts = ((_reflectance(cos_i[None, :], eta1, eta_g[:, None], polarization), None),)
    else:  # curve b's grid curves are a_b G_s + (1 - a_b) G_p
        G_s, G_p = fresnel_sp(cos_i[None, :], eta1, eta_g[:, None])
        a = per_curve[:, None]
        parts = ((G_s, a), (G_p, 1 - a))

    def grid_sse(cols):
        # sum_j w_j^2 (sum_i c_i G_ij - R_j)^2 expanded into matrix products over the grid
        R_, w2_ = R[:, cols], None if w2 is None else w2[:, cols]
        wsum = (lambda X: jnp.sum(X, -1)[None, :]) if w2_ is None else (lambda X: w2_ @ X.T)  # unit weights: one product fewer
        wR = R_ if w2_ is None else w2_ * R_
        sse = 0
        for i, (G_i, c_i) in enumerate(parts):
            for G_j, c_j in parts[i:]:
                term = wsum(G_i[:, cols] * G_j[:, cols])
                sse = sse + (term if c_i is None else (1 if G_j is G_i else 2) * c_i * c_j * term)
        for G_i, c_i in parts:
            term = wR @ G_i[:, cols].T
            sse = sse - 2 * (term if c_i is None else c_i * term)
        sse = sse + jnp.sum(wR * R_, -1, keepdims=True)
        return jnp.where(jnp.isfinite(sse), sse, jnp.inf)

    sub = _score_columns(theta.shape[0])
    score = lambda y, R1, w1, p1: jnp.sum(residual(y, R1[sub], None if w1 is None else w1[sub],
                                                   _of_curve(polarization, p1), sub) ** 2)
    score_all = jax.vmap(lambda ys, R1, w1, p1: jax.vmap(lambda y: score(y, R1, w1, p1))(ys))
    heur = jax.vmap(lambda R1: _heuristics(theta, R1, eta1, absorbing))(R)  # (B, 4, p)
    sse_heur = score_all(heur, R, w, per_curve)
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
        sse_ref = score_all(refined, R, w, per_curve)
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
