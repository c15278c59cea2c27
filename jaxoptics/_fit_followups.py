"""Follow-up solves of the index fits on concrete data: the Levenberg-Marquardt refit of
curves Gauss-Newton did not converge on, the second branch of ambiguous internal-reflection
curves, the restart of absorbing fits, and the per-device fits of a sharded batch."""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from ._fit_solver import _fit_batch


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
