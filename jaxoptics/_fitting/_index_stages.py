"""The index fit's follow-ups in JAX (the Levenberg-Marquardt refit of curves Gauss-Newton did
not converge on, the second branch of ambiguous internal-reflection curves, the restart of
absorbing fits), the fit's derivatives by the implicit function theorem, and the per-device fits
of a sharded batch.

The follow-ups are masked solves (`_solve_masked`): the curves that need one are gathered to the
front and solved a block at a time in a `lax.while_loop` whose trip count is the number of such
curves over the block size. No curve is picked on the host, so `fit_eta` gives the same result
eagerly, under `jax.jit` and under `jax.vmap` (see `_solve` for when each stage is compiled).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime._compile import filter_jit
from .._runtime._shard import from_blocks
from ._index_model import _reflectance
from ._index_result import FitResult
from ._index_starts import _of_curve, _per_curve


# `_index_solver` (and with it optimistix, lineax and equinox) loads when a program is traced: a
# process that loads its compiled fit from the store (`_cache`) does not import them.
def _fit_batch(*args, **kwargs):
    from ._index_solver import _fit_batch

    return _fit_batch(*args, **kwargs)


def _fit_block(*args, **kwargs):
    from ._index_solver import _fit_block

    return _fit_block(*args, **kwargs)


def _errors(*args, **kwargs):
    from ._index_solver import _errors

    return _errors(*args, **kwargs)

# Curves whose start on the other branch fits within this factor of the solution's sum of
# squares (on the start's 16 angles) are solved on that branch too (see `_second_branch`).
# Measured (noise 1e-3 and 1e-4; internal and external reflection; angles 0-15, 0-30, 0-60, 0-85,
# 20-70 and 40-80 degrees; the other branch's minimum found from three starts, one of them the
# true index): every curve whose other branch fits within Delta chi2 < 9 had a ratio below 2.5
# (below 3.5 for Delta chi2 < 16). No curve is flagged at 0-60, 0-85 or 40-80 degrees.
_BRANCH_RATIO = 4.0
_AMBIGUOUS_DCHI2 = 9.0

# Curves per block of a follow-up solve. A vmapped solve runs until its slowest member stops, and
# a block is solved whole even when only some of its curves need it.
_FOLLOWUP_BLOCK = 64


def _where(mask, a, b):
    """`a` where `mask` (one flag per curve) else `b`, leaf by leaf of two pytrees."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(mask.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)


def _take(polarization, idx):
    """The polarization of the curves `idx`: a name stays, per-curve weights are gathered."""
    return polarization if _per_curve(polarization) is None else polarization[idx]


def _solve_masked(mask, starts, res, theta, R, w, eta1, solver, lm, kw):
    """The curves where `mask` solved again from `starts` (with `solver`, then with `lm` where that
    does not converge, when `lm` is given): a `FitResult` over the whole batch, equal to `res`
    where `mask` is false.

    The masked curves are gathered to the front (one stable argsort) and solved `_FOLLOWUP_BLOCK`
    at a time in a `while_loop` that runs `ceil(count / block)` times: the cost follows the number
    of curves that need the solve, and is a sort and a reduction when none does.
    """
    B = R.shape[0]
    K = min(B, _FOLLOWUP_BLOCK)
    order = jnp.argsort(~mask, stable=True)
    count = jnp.sum(mask)

    def block(idx):
        kw_idx = dict(kw, polarization=_take(kw["polarization"], idx))
        sub = _fit_block(theta, R[idx], w[idx], eta1, starts[idx], solver=solver, use_init=True, **kw_idx)[0]
        if lm is None:
            return sub
        again = lambda: _where(sub.converged, sub, _fit_block(theta, R[idx], w[idx], eta1, starts[idx], solver=lm,
                                                                use_init=True, **kw_idx)[0])
        return jax.lax.cond(jnp.all(sub.converged), lambda: sub, again)

    def body(carry):
        i, out = carry
        pos = i * K + jnp.arange(K)
        sel = pos < count
        idx = order[jnp.minimum(pos, B - 1)]
        sub = block(idx)
        dst = jnp.where(sel, idx, B)  # out of bounds: dropped
        return i + 1, jax.tree_util.tree_map(lambda a, b: a.at[dst].set(b, mode="drop"), out, sub)

    n_blocks = (count + K - 1) // K
    return jax.lax.while_loop(lambda c: c[0] < n_blocks, body, (jnp.zeros((), count.dtype), res))[1]


def _second_branch(res, alt, ratio, theta, R, w, eta1, solver, lm, kw):
    """Solve the curves whose other branch may fit as well, and report honestly when it does.

    Below the critical angle, internal-reflection curves (eta2 < eta1) and curves of a denser
    medium (eta2 > eta1) look alike. Where the data stop short of what tells them apart, the start
    can pick the branch that fits worse, and Gauss-Newton then converges to that branch's minimum
    with a small, local standard error: a confident wrong answer (2.5% of noisy internal-reflection
    fits over 20-70 degrees, |z| up to 27, are of this kind without this solve). Curves whose
    other-branch start fits within `_BRANCH_RATIO` of the solution are solved from it (none where
    the branches are told apart, e.g. 0-85 degrees). The smaller chi-square wins; where the other
    is within `Delta chi2 < 9`, it becomes `eta_alt` and the standard error includes the distance
    to it. (With `Delta chi2 < 4`, 1% of noisy fits at 0-30 degrees still had |z| up to 385: the
    branch the data preferred by a chi-square of 5 was the wrong one.)
    """
    amb = _needs_branch(ratio, False)
    sub = _solve_masked(amb, alt, res, theta, R, w, eta1, solver, lm, kw)
    mine = res
    other = amb & sub.converged & ((sub.eta < eta1) != (mine.eta < eta1))
    dof = R.shape[-1] - 1
    # chi-square in units of the noise: the reduced chi-square estimates it without sigma; with
    # sigma, data scattering more than stated widen it as in `_covariance`
    scale = mine.chi2_reduced if not kw["sigma_given"] else jnp.maximum(mine.chi2_reduced, 1)
    dchi2 = (sub.chi2_reduced - mine.chi2_reduced) * dof / jnp.where(other, scale, 1)
    swap = other & (~mine.converged | (dchi2 < 0))
    near = other & mine.converged & (jnp.abs(dchi2) < _AMBIGUOUS_DCHI2)
    win = _where(swap, sub, mine)
    lose_eta = jnp.where(swap, mine.eta, sub.eta)
    gap2 = jnp.where(near, (win.eta - lose_eta) ** 2, 0)
    import equinox as eqx

    win = eqx.tree_at(lambda r: (r.eta_alt, r.stderr, r.covariance), win,
                      (jnp.where(near, lose_eta, jnp.nan).astype(win.eta_alt.dtype), jnp.sqrt(win.stderr ** 2 + gap2),
                       win.covariance + gap2[:, None, None]))
    return _where(swap | near, win, res)


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
    again = _needs_branch(ratio, True)
    sub = _solve_masked(again, alt, res, theta, R, w, eta1, solver, lm, kw)
    better = again & sub.converged & (~res.converged | (sub.chi2_reduced < res.chi2_reduced))
    return _where(better, sub, res)


# Fits over at most this many points (curves x angles) are compiled with `QUICK_COMPILE`, where
# compiling is most of the time a fit takes. Measured on the bundled example (two curves of 33
# angles), against XLA's defaults: first call 1.6-1.9 s against 2.7 s, later calls 1.2 against
# 1.1 ms. (For 100 curves, one program of the batched solve ran in 4.6 against 0.7 ms with the
# LLVM optimizations off; for 1000 curves, 3 against 9 ms, a repeated call would lose what the
# first one gains.)
_QUICK_COMPILE_POINTS = 4096


def _quick(R):
    return R.shape[0] * R.shape[1] <= _QUICK_COMPILE_POINTS


# The batched solve is stored (`_cache`) as one traced program for any number of angles in this
# range and of curves up to `_POLY_CURVES` (`_BLOCK_POINTS / 4096 = 32`: one block, as
# `_index_solver._fit_batch` assumes for symbolic shapes), so that a process meeting data of a new
# size compiles it without tracing (tracing is most of a first fit: optimistix's loops under
# `vmap`). Below 16 angles the starts' scoring uses every angle, a number of its own.
_POLY_ANGLES = (16, 4096)
_POLY_CURVES = 32


@functools.cache
def _poly_dims():
    lo, hi = _POLY_ANGLES
    return jax.export.symbolic_shape("b, m", constraints=(f"b <= {_POLY_CURVES}", f"m >= {lo}", f"m <= {hi}"))


def angles_poly(dynamic):
    """The specs of `_first`'s array arguments with the numbers of curves `b` and of angles `m`
    symbolic, and a text naming their range (`filter_jit`'s `poly`); None outside `_POLY_CURVES`
    and `_POLY_ANGLES`."""
    (theta, R, w, eta1, y_init), kwargs = dynamic
    B, m = R.shape
    if not (_POLY_ANGLES[0] <= m <= _POLY_ANGLES[1] and B <= _POLY_CURVES):
        return None
    Bs, M = _poly_dims()

    def spec(x, *dims):
        return jax.ShapeDtypeStruct(dims, x.dtype, weak_type=getattr(x, "weak_type", False))

    args = (spec(theta, M), spec(R, Bs, M), spec(w, Bs, M if w.shape[-1] == m else 1), spec(eta1),
            spec(y_init, Bs, y_init.shape[-1]))
    kwargs = jax.tree_util.tree_map(lambda x: spec(x, Bs), kwargs)  # per-curve polarization weights
    text = f"b curves, m angles: b <= {_POLY_CURVES}, {_POLY_ANGLES[0]} <= m <= {_POLY_ANGLES[1]}"
    return (args, kwargs), text


@filter_jit(poly=angles_poly)
def _first(theta, R, w, eta1, y_init, **kw):
    """The batched solve, and whether any curve needs the refit or the branch stage."""
    res, start, alt, ratio = _fit_batch(theta, R, w, eta1, y_init, **kw)
    return res, start, alt, ratio, jnp.stack([~jnp.all(res.converged), jnp.any(_needs_branch(ratio, kw["absorbing"]))])


@filter_jit
def _refit_stage(res, start, theta, R, w, eta1, lm, kw):
    return _solve_masked(~res.converged, start, res, theta, R, w, eta1, lm, None, kw)


@filter_jit
def _branch_stage(res, alt, ratio, theta, R, w, eta1, solver, lm, kw):
    again = _absorbing_restart if kw["absorbing"] else _second_branch
    return again(res, alt, ratio, theta, R, w, eta1, solver, lm, kw)


def _needs_branch(ratio, absorbing):
    return ratio == 0 if absorbing else ratio <= _BRANCH_RATIO


def _solve(theta, R, w, eta1, y_init, *, solver, lm, use_init, first=None, **kw):
    """The batched fit and its follow-ups: the Levenberg-Marquardt refit (`lm`, from the same
    start) of curves Gauss-Newton did not converge on, and, for fits started from the grid, the
    second branch of ambiguous curves or the restart of absorbing ones.

    Traced (inside the caller's `jit` or `vmap`), every stage is part of the one program, and a
    stage's loop runs zero times when no curve needs it. Called on concrete arrays, each stage is
    its own compiled call, compiled and run only when some curve needs it (one scalar read on the
    host decides): the first call of a fit that needs no follow-up compiles only the batched
    solve. Both ways run the same solves on the same curves. `first`: the batched solve's output
    when already dispatched.
    """
    quick = _quick(R)
    res, start, alt, ratio, needs = first if first is not None else _first(theta, R, w, eta1, y_init, solver=solver,
                                                                           use_init=use_init, quick=quick, **kw)
    refit = branch = True
    if _is_concrete(theta, R, w, eta1, y_init):
        refit, branch = np.asarray(needs)  # one read from the device for both decisions
    if lm is not None and refit:
        res = _refit_stage(res, start, theta, R, w, eta1, lm, kw, quick=quick)
    if not use_init and branch:
        res = _branch_stage(res, alt, ratio, theta, R, w, eta1, solver, lm, kw, quick=quick)
    return res


def _solve_stages(theta, R, w, eta1, y_init, kw):
    return _solve(theta, R, w, eta1, y_init, **kw)


def _fit_differentiable(theta, R, w, eta1, y_init, kw):
    """`_solve`, with derivatives in the data (`theta`, `R`, `w`, `eta1`) by the implicit
    function theorem; no derivative passes through the solver's loops (see `_implicit_jvp`)."""
    fit = jax.custom_jvp(lambda theta, R, w, eta1, y_init: _solve(theta, R, w, eta1, y_init, **kw))
    fit.defjvp(lambda primals, tangents: _implicit_jvp(primals, tangents, kw))
    return fit(theta, R, w, eta1, y_init)


def _implicit_jvp(primals, tangents, kw):
    r"""Forward-mode derivative of the fit (reverse mode by transposition).

    The estimate q (eta, or n and k) is a minimum of `L(q, x) = sum(r^2) / 2` over the data
    x = (theta, R, 1/sigma, eta1), so `grad_q L(q(x), x) = 0` and, by the implicit function
    theorem, `dq = -H^{-1} (d grad_q L / dx) dx` with `H` the Hessian of L in q (exact, with the
    residuals' curvature: the data need not fit). It is evaluated at the solution with the exact
    reflectance kernel, so neither the start, nor the grid, nor the number of solver steps enters.
    The other fields (errors, covariance, chi-square, rms) are differentiated through their
    formulas at the estimate, with `dq` as the estimate's tangent; `eta_alt` has its own implicit
    derivative. The start `y_init` has none: the minimum does not depend on it. Where the fit did
    not converge, every tangent is NaN.
    """
    theta, R, w, eta1, y_init = primals
    dtheta, dR, dw, deta1, _ = tangents
    pol, absorbing, sg = kw["polarization"], kw["absorbing"], kw["sigma_given"]
    res = _solve(theta, R, w, eta1, y_init, **kw)
    to_q = lambda eta: jnp.stack([jnp.real(eta), jnp.imag(eta)], -1) if absorbing else eta[:, None]
    to_eta = lambda q: jax.lax.complex(q[..., 0], q[..., 1]) if absorbing else q[..., 0]

    per_curve = _per_curve(pol)  # vmapped with the curves when per-curve weights, else None

    def residuals(q, th, R1, w1, p1, e1):
        r = _reflectance(jnp.cos(th), e1, to_eta(q), _of_curve(pol, p1)) - R1
        return r * w1 if sg else r

    def grad_loss(q, th, R1, w1, p1, e1):
        return jax.grad(lambda q: 0.5 * jnp.sum(residuals(q, th, R1, w1, p1, e1) ** 2))(q)

    def dq_one(q, R1, w1, p1, dR1, dw1):
        H = jax.jacfwd(grad_loss)(q, theta, R1, w1, p1, eta1)
        dF = jax.jvp(lambda th, r1, v1, e1: grad_loss(q, th, r1, v1, p1, e1), (theta, R1, w1, eta1),
                     (dtheta, dR1, dw1, deta1))[1]
        return -jnp.linalg.solve(H, dF)

    q = to_q(res.eta)
    dq = jax.vmap(dq_one)(q, R, w, per_curve, dR, dw)
    has_alt = jnp.isfinite(res.eta_alt)
    q_alt = jnp.where(has_alt, res.eta_alt, res.eta)[:, None] if not absorbing else q
    dq_alt = (jnp.where(has_alt[:, None], jax.vmap(dq_one)(q_alt, R, w, per_curve, dR, dw), 0) if not absorbing
              else jnp.zeros_like(dq))

    def fields(q, q_alt, th, R, w, e1):
        one = lambda q1, R1, w1, p1: _errors(_reflectance, jnp.cos(th), R1, w1 if sg else None, e1, q1,
                                             polarization=_of_curve(pol, p1), absorbing=absorbing, sigma_given=sg)
        cov, se, rms, chi2 = jax.vmap(one)(q, R, w, per_curve)
        if absorbing:
            return jax.lax.complex(se[:, 0], se[:, 1]), cov, rms, chi2
        gap2 = jnp.where(has_alt, (q[:, 0] - q_alt[:, 0]) ** 2, 0)
        return jnp.sqrt(se[:, 0] ** 2 + gap2), cov + gap2[:, None, None], rms, chi2

    _, (d_se, d_cov, d_rms, d_chi2) = jax.jvp(fields, (q, q_alt, theta, R, w, eta1), (dq, dq_alt, dtheta, dR, dw, deta1))
    bad = ~res.converged
    # a product, not a select: it transposes to the same NaN factor, so reverse mode sees it too
    scale = jnp.where(bad, jnp.nan, 1.0).astype(res.residual_rms.dtype)
    nan = lambda t: t * scale.astype(t.dtype).reshape((-1,) + (1,) * (t.ndim - 1))
    zero = lambda x: np.zeros(x.shape, jax.dtypes.float0)
    tangent = FitResult(nan(to_eta(dq)), nan(d_se), nan(d_cov), zero(res.converged), nan(d_rms), nan(d_chi2),
                        zero(res.num_steps), nan(jnp.where(has_alt, dq_alt[:, 0], 0)))
    return res, tangent


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


def _fit_per_shard(shards, theta, R, w, eta1, y_init, kw):
    """Fit each device's block of curves on that device, then assemble the sharded result.

    Each device runs its own vmapped solver loop: no data move and no cross-device reduction in
    the loop (partitioning one vmapped loop over devices puts an all-reduce of the loop predicate in
    every step, and with forced host devices that was seen to stall for a few thousand curves).
    """
    sh = R.sharding
    results = []
    def on_device(s):  # what the device of shard s fits: its curves' weights and polarizations, the rest copied
        sl = s.index[0]
        put = lambda x: jax.device_put(x, s.device)
        per_curve = _per_curve(kw["polarization"])
        kw_s = kw if per_curve is None else dict(kw, polarization=put(per_curve[sl]))
        return (put(theta), s.data, put(w[sl]), put(eta1), put(y_init[sl])), kw_s

    for s in shards:  # dispatch all first: the devices work concurrently
        args, kw_s = on_device(s)
        results.append(_first(*args, quick=_quick(args[1]), **{k: v for k, v in kw_s.items() if k != "lm"}))
    for k, s in enumerate(shards):
        args, kw_s = on_device(s)
        results[k] = _solve(*args, first=results[k], **kw_s)
    starts = [s.index[0].start or 0 for s in shards]
    assemble = lambda *leaves: from_blocks(dict(zip(starts, leaves)), R.shape[0], sh.mesh, sh.spec[0])
    return jax.tree_util.tree_map(assemble, *results)


def _is_concrete(*xs):
    return not any(isinstance(x, jax.core.Tracer) for x in xs)
