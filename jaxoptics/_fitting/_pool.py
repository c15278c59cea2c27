"""Many independent least-squares problems solved by one optimistix solver, a pool of `K` at a
time, each lane taking the next problem as soon as its own has stopped.

Why not `jax.vmap(optx.least_squares)`: a vmapped `while_loop` runs until its slowest member
stops, so a batch in which one problem needs 20 steps and the rest 9 costs 20 steps for every
problem. On a wafer map the step counts spread (5 to 20 Gauss-Newton steps, about one percent of
spectra at the cap), and every block of a vmapped solve ran to the cap. Here one loop iteration
is one solver step on `K` lanes; a lane whose problem has terminated writes its result and is
refilled with the next waiting problem (a fresh `solver.init`), so the work follows the sum of the
step counts, not `K` times their maximum. Memory is that of `K` problems, for a map of any size.

The loop follows optimistix's own `iterative_solve` (`init`, then `step` until `terminate` or
`max_steps`, a non-finite iterate ending the solve), through the solvers' public
`init`/`step`/`terminate` interface; the solver's state is split into its arrays (carried,
batched over lanes) and its static part (one for all lanes, as in optimistix).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx


def pooled_least_squares(fn, solver, y0, args, order, count, *, lanes: int, max_steps: int, on_progress=None,
                         early_stop=None):
    """Solve problems `order[:count]` of a set of `M` least-squares problems.

    **Arguments:**

    - `fn(y, args) -> residuals`: one problem (unbatched); `args` one problem's data.
    - `solver`: an optimistix least-squares solver (`GaussNewton`, `LevenbergMarquardt`, ...).
    - `y0`: `(M, p)` starts; `args`: a pytree of arrays with leading axis `M`.
    - `order`: `(M,)` int, the problems in the order to solve them; `count`: how many of them
      (traced; the rest are not touched).
    - `lanes`: problems in flight at once; `max_steps`: solver steps per problem.
    - `on_progress(done, count)`: an optional host callback after each loop iteration.
    - `early_stop(y, state) -> (stop, y_final, info)`: an optional further termination test,
      called after each step with the step's `y` and the solver's new state (traced, one problem);
      where `stop`, the problem ends as converged with the value `y_final`, and `info` (a pytree
      of arrays, or None) is kept for it (see `gauss_newton_edm_stop`).

    **Returns:** `(y, ok, steps, touched, info)`: `(M, p)` solutions (`y0` where not solved),
    `(M,)` bool converged (the solver terminated successfully with a finite iterate), `(M,)` steps
    taken, `(M,)` bool whether the problem was solved at all, and `(info, early)`: the `info` of
    `early_stop` where a problem ended by it (leading axis `M`; zeros elsewhere) and `(M,)` bool
    `early`, whether it did (`None` without `early_stop` or `info`).
    """
    M = y0.shape[0]
    K = max(1, min(lanes, M))
    options: dict = {}
    tags: frozenset = frozenset()
    f_struct = jax.eval_shape(lambda y, a: fn(y, a), y0[0], jax.tree.map(lambda a: a[0], args))
    wrapped = lambda y, a: (fn(y, a), None)
    first_state = solver.init(wrapped, y0[0], jax.tree.map(lambda a: a[0], args), options, f_struct, None, tags)
    _, static = eqx.partition(first_state, eqx.is_array)

    def init_dyn(y, a):
        return eqx.partition(solver.init(wrapped, y, a, options, f_struct, None, tags), eqx.is_array)[0]

    def step_dyn(y, a, dyn):
        state = eqx.combine(static, dyn)
        y_new, state, _ = solver.step(wrapped, y, a, options, state, tags)
        term, res = solver.terminate(wrapped, y_new, a, options, state, tags)
        e_stop, info = jnp.asarray(False), None
        if early_stop is not None:
            e_stop, y_early, info = early_stop(y_new, state)
            e_stop = e_stop & ~term & (res == optx.RESULTS.successful) & jnp.all(jnp.isfinite(y_early))
            y_new = jnp.where(e_stop, y_early, y_new)
            term = term | e_stop
        finite = jnp.all(jnp.isfinite(y_new))
        stop = term | (res != optx.RESULTS.successful) | ~finite
        ok = term & (res == optx.RESULTS.successful) & finite
        return y_new, eqx.partition(state, eqx.is_array)[0], stop, ok, (info, e_stop & finite)

    take = lambda tree, idx: jax.tree.map(lambda a: a[idx], tree)

    # lanes 0..K-1 start on problems order[0..K-1] (those beyond `count` are idle from the start)
    item = order[:K]
    active = jnp.arange(K) < count
    y = y0[item]
    dyn = jax.vmap(init_dyn)(y, take(args, item))
    out_y, out_ok = y0, jnp.zeros(M, bool)
    out_steps, touched = jnp.zeros(M, jnp.int32), jnp.zeros(M, bool)
    # the early stop's `info` of each problem, and whether it ended the problem
    info_struct = None if early_stop is None else jax.eval_shape(lambda: early_stop(y0[0], first_state)[2])
    out_info = (jax.tree.map(lambda s: jnp.zeros((M,) + s.shape, s.dtype), info_struct), jnp.zeros(M, bool))
    carry = (y, dyn, item, active, jnp.zeros(K, jnp.int32), jnp.minimum(count, K), out_y, out_ok, out_steps, touched, out_info)

    def body(carry):
        y, dyn, item, active, nst, nxt, out_y, out_ok, out_steps, touched, out_info = carry
        a = take(args, item)
        y, dyn, stop, ok, info = jax.vmap(step_dyn)(y, a, dyn)
        nst = nst + 1
        done = active & (stop | (nst >= max_steps))
        # write the finished problems (lanes not done scatter out of range and are dropped)
        dst = jnp.where(done, item, M)
        out_y = out_y.at[dst].set(y, mode="drop")
        out_ok = out_ok.at[dst].set(ok, mode="drop")
        out_steps = out_steps.at[dst].set(nst, mode="drop")
        touched = touched.at[dst].set(True, mode="drop")
        out_info = jax.tree.map(lambda o, v: o.at[dst].set(v, mode="drop"), out_info, info)
        # refill: the finished lanes take the next waiting problems, in lane order
        slot = nxt + jnp.cumsum(done) - 1
        refill = done & (slot < count)
        new_item = order[jnp.clip(slot, 0, M - 1)]
        y_new = y0[new_item]
        dyn_new = jax.vmap(init_dyn)(y_new, take(args, new_item))
        sel = lambda new, old: jnp.where(refill.reshape((K,) + (1,) * (old.ndim - 1)), new, old)
        y = sel(y_new, y)
        dyn = jax.tree.map(sel, dyn_new, dyn)
        item = jnp.where(refill, new_item, item)
        nst = jnp.where(refill, 0, nst)
        active = (active & ~done) | refill
        nxt = jnp.minimum(nxt + jnp.sum(done), count)
        if on_progress is not None:
            jax.debug.callback(on_progress, jnp.sum(touched), count)
        return y, dyn, item, active, nst, nxt, out_y, out_ok, out_steps, touched, out_info

    carry = jax.lax.while_loop(lambda c: jnp.any(c[3]), body, carry)
    info, early = carry[10]
    return carry[6], carry[7], carry[8], carry[9], (None if early_stop is None or info is None else (info, early))


def gauss_newton_edm_stop(tol, scale, *, normal_matrix=False):
    """An `early_stop` for `optx.GaussNewton`: stop where the step Gauss-Newton has just computed,
    `s`, would lower the sum of squares by `|J s|^2 <= tol * scale(r)` (the estimated distance to
    the minimum, MINUIT's EDM criterion), and return the point after that step.

    With `normal_matrix`, its `info` is `(y, J^T J, |r + J s|^2)`: the point `y` where `J` was
    evaluated, the normal matrix there (in the solver's variables), and the sum of squares that
    the linearization predicts after the step (`|r|^2 - |J s|^2`: the step solves `J s = -r` in
    least squares), from which the caller forms the covariance without evaluating the model
    again. Otherwise `info` is None.

    With sigma-weighted residuals the covariance of the parameters is `scale * (J^T J)^-1`, so
    `|J s|^2 / scale` is the squared length of the step in standard errors, in any
    parametrization: `tol = 1e-6` stops when the step is below 1e-3 standard errors, and the point
    after it is closer still (Gauss-Newton's steps shrink at least linearly near a minimum). The
    Cauchy test of optimistix asks for steps below `rtol` relative in every parameter and residual,
    which takes two or three more steps than this where the residuals are noise.

    Reads the Gauss-Newton state's last evaluation (`f_info`: the residuals `r` and the
    linearization `J` at the step's `y`) and the next point it proposes (`y_eval`)."""

    def stop(y, state):
        s = state.y_eval - y
        r = state.f_info.residual
        Js = state.f_info.jac.mv(s)
        edm = jnp.sum(Js**2)
        info = None
        if normal_matrix:
            J = state.f_info.jac.as_matrix()
            info = (y, J.T @ J, jnp.sum((r + Js) ** 2))
        return edm <= tol * scale(r), state.y_eval, info

    return stop
