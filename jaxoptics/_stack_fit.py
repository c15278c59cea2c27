"""Fit the free parameters of a layered `Sample` to measured `Spectra`: one spectrum or a whole
map at once, in two compiled calls over the whole map (Gauss-Newton; then the standard errors, or
Levenberg-Marquardt and the standard errors, see `fit_stack`).

The method, per spectrum:

1. **Global start over thickness.** Reflectance and ellipsometric angles are periodic in each
   film's optical thickness, so a local solver started one fringe away converges to a wrong
   minimum with a good-looking fit. Every free thickness with a finite upper bound is searched on
   a grid from its lower to its upper bound, with a step of `1/8` of the shortest fringe period
   `lambda_min / (2 n_max)` (`n_max` the film's largest start index over the data), so that a
   grid point lies well inside the basin of the true minimum; the other free parameters sit at
   their starts. The grid is evaluated in one batched pass over all spectra, on a subset of the
   wavelengths that still samples the fringes of the thickest film at least four times per
   period. Several free thicknesses are searched on their product grid, which is coarsened to at
   most `max_grid` points.
2. **Gauss-Newton, then Levenberg-Marquardt** (optimistix) from the `starts` best grid points,
   least squares weighted by `sigma`; the lowest chi^2 wins. Gauss-Newton (at most 20 steps)
   stops when its step is below 1e-3 standard errors (`gauss_newton_edm_stop`) or below
   optimistix's relative tolerance, and fits nearly every spectrum. For a map (more residuals
   than a small fit's `QUICK_COMPILE` limit) whose grid subset holds at most half of the data,
   Gauss-Newton runs twice (at most 20 steps each): on the subset first, to a step below 0.1 of
   that fit's standard errors, then on all the data from there. Levenberg-Marquardt restarts from
   the grid's points for the spectra Gauss-Newton did not fit, in a second compiled call that is
   made (and compiled) only when there are such spectra.
   Bounds are kept by the usual change of variables (`x = lo + (hi - lo)(1 + sin u)/2` for two
   bounds, `lo - 1 + sqrt(u^2 + 1)` for one, as MINUIT and lmfit do); starts on a bound are
   moved inside it (`_Bound.inside`), where the slope of the change is not zero. The spectra
   of a map are solved by a pool of lanes that take the next spectrum as soon as theirs has converged
   (`jaxoptics._pool`), and the Jacobian is formed with as few passes through the stack as the
   model allows (`_jacobian_plan`).
3. **Uncertainties** from the Jacobian of the weighted residuals in the physical parameters at
   the solution (where Gauss-Newton stopped by its step test, the Jacobian of its last step, less
   than 1e-3 standard errors before the solution, and the chi^2 that step predicts: no further
   evaluation of the model; elsewhere evaluated at the solution): covariance `(J^T J)^-1`,
   inverted through the eigendecomposition of the correlation-scaled matrix, with no truncation: a direction the data do not determine gets an
   enormous standard error and correlations near +-1, never a small one. Without `sigma` the
   residuals' own scatter sets the scale (`cov * chi2_reduced`); with `sigma`, `cov *
   max(1, chi2_reduced)`.

Without sigma columns, quantities are weighted by nominal standard deviations (`DEFAULT_SIGMA`:
0.05 degrees for psi, 0.1 for delta, 0.002 for N, C, S, R and T) so that mixed quantities have
comparable weights; the overall scale is then estimated from the fit.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _cache
from . import _validate as V
from ._compile import known_options, wanted_options
from ._dispersion import Constant, Free, Tabulated, parameter_leaves
from ._fresnel import materialize
from ._result import result, static
from ._rii import RIIFormula
from ._sample import Sample, model_quantities
from ._spectra import Spectra
from ._stack import stack

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
DEFAULT_SIGMA = {"psi_deg": 0.05, "delta_deg": 0.1, "N": 0.002, "C": 0.002, "S": 0.002,
                 "R": 0.002, "R_s": 0.002, "R_p": 0.002, "T": 0.002, "T_s": 0.002, "T_p": 0.002}


@result
class StackFit:
    """Result of `fit_stack`: a pytree over the map's sites (leading axes `(...)`, the spectra's
    batch shape; `()` for one spectrum).

    **Fields:**

    - `names`: the free parameters, e.g. `("oxide.thickness_nm", "oxide.A")` (static).
    - `values`, `stderr`: `(..., p)`, the fitted values and their standard errors.
    - `covariance`, `correlation`: `(..., p, p)`.
    - `chi2_reduced`: `(...)`, `sum(r^2) / (m - p)` of the sigma-weighted residuals `r`.
    - `converged`: `(...)` bool, the solver met its tolerances within `max_steps` and every
      value is finite.
    - `at_bound`: `(..., p)` bool, a value within `1e-6` (relative to its range) of a bound:
      its standard error describes the curvature there, not a confidence interval.
    - `num_steps`: `(...)`, solver steps of the winning start (Gauss-Newton's, of both passes on
      a map, plus Levenberg-Marquardt's where the spectrum was refitted with it).
    - `sigma_given`: whether the data carried sigma (static).

    `fit["oxide.thickness_nm"]` is the value of one parameter; `fit.stderr_of(name)` its error;
    `fit.table()` a text table (one site: the first, or `site=i`).
    """

    names: tuple = static()
    values: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    correlation: jax.Array
    chi2_reduced: jax.Array
    converged: jax.Array
    at_bound: jax.Array
    num_steps: jax.Array
    sigma_given: bool = static()

    def _index(self, name):
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"{name!r} is not a free parameter; free: {', '.join(self.names)}") from None

    def __getitem__(self, name):
        return self.values[..., self._index(name)]

    def stderr_of(self, name):
        return self.stderr[..., self._index(name)]

    def table(self, site=None) -> str:
        """A text table of values, standard errors and flags for one site."""
        sl = (lambda a: a) if self.values.ndim == 1 else (lambda a: np.asarray(a).reshape((-1,) + a.shape[self.values.ndim - 1:])[site or 0])
        v, s, b = (np.asarray(sl(x)) for x in (self.values, self.stderr, self.at_bound))
        w = max(len(n) for n in self.names)
        rows = [f"{'parameter':<{w}}  {'value':>14}  {'stderr':>12}"]
        for i, n in enumerate(self.names):
            rows.append(f"{n:<{w}}  {v[i]:>14.6g}  {s[i]:>12.3g}" + ("  (at a bound)" if b[i] else ""))
        chi = float(np.asarray(sl(self.chi2_reduced[..., None]))[0])
        conv = bool(np.asarray(sl(self.converged[..., None]))[0])
        rows.append(f"chi2_reduced {chi:.4g}; converged {conv}; sigma {'from the data' if self.sigma_given else 'estimated from the fit'}")
        return "\n".join(rows)


# ---- bounds: x(u) and its inverse -------------------------------------------------------------


# how far inside its bounds every start is moved, as a fraction of their width (`_Bound.inside`)
_INSIDE = 1e-3


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


def _check_ranges(sample: Sample, spectra: Spectra):
    lam_um = np.asarray(spectra.wavelength_nm) / 1000
    for owner, model in sample._slots():
        tab = type(model).__name__ == "Tabulated" or getattr(model, "k_table", None) is not None
        rng = getattr(model, "range_um", None)
        if tab and rng is not None and (lam_um.min() < rng[0] - 1e-12 or lam_um.max() > rng[1] + 1e-12):
            raise ValueError(f"{owner}: the material's tabulated data cover {rng[0] * 1000:g}-{rng[1] * 1000:g} nm, "
                             f"the spectra {lam_um.min() * 1000:g}-{lam_um.max() * 1000:g} nm; tabulated data are not extrapolated")
    # every constant or tabulated medium's index at the data's wavelengths is one the stack takes:
    # finite, n > 0, k >= 0 (a database table or formula can give NaN beyond a k table, or gain)
    wl = np.unique(np.asarray(spectra.wavelength_nm))
    for owner, model in sample._slots():
        N = _data_index(model, wl / 1000)
        if N is None:
            continue
        bad = ~np.isfinite(N) | (N.real <= 0) | V.is_gain(N)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{owner}: its index at {wl[i]:g} nm is {complex(N[i]):.6g}; the stack takes finite "
                             "indices n + ik with n > 0 and k >= 0 (absorption)")


def _data_index(model, lam_um):
    """The index of a constant, tabulated or refractiveindex.info medium at `lam_um`, in NumPy
    (checked before compiling at no cost in JAX dispatch), or None for the other models."""
    value = lambda v: v.value if isinstance(v, Free) else v
    if isinstance(model, Constant):
        return np.full(lam_um.shape, complex(value(model.n), value(model.k)))
    interp = lambda tab: np.interp(lam_um, tab[0], tab[1], left=np.nan, right=np.nan)
    k = np.zeros(lam_um.shape) if getattr(model, "k_table", None) is None else interp(model.k_table)
    if isinstance(model, Tabulated):
        return interp(model.n_table) + 1j * k
    if isinstance(model, RIIFormula):
        kind, v = model._n2_or_n(lam_um)
        return (np.sqrt(v + 0j) if kind == "n2" else v + 0j) + 1j * k
    return None


def _grid_subset(wl_nm, n_max, d_max):
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


def fit_stack(sample: Sample, spectra: Spectra, *, global_start: bool = True, starts: int = 1,
              max_grid: int = 4096, max_steps: int = 200, progress: bool = False) -> StackFit:
    """Fit the `Free` parameters of `sample` to `spectra` (one spectrum or a map of them).

    **Arguments:**

    - `sample`: a `Sample` with at least one `Free` parameter.
    - `spectra`: `Spectra` (`load_spectra`, `make_spectra`); leading axes of its values are
      map sites, all fitted together (each compiled call covers the whole map).
    - `global_start`: search each free thickness with a finite upper bound on a grid first (see
      the module docstring); `False` starts from the `Free` values.
    - `starts`: how many of the best grid points to refine; the lowest chi^2 wins.
    - `max_grid`: the most grid points per spectrum (several free thicknesses share this budget).
    - `max_steps`: Levenberg-Marquardt steps per start.
    - `progress`: report on standard error how many spectra the Gauss-Newton stage has done
      (from inside the compiled call; for maps that take minutes).

    The fit runs in float64 when `jax_enable_x64` is on (recommended: the phase of a micrometre
    film is a few hundred radians), float32 otherwise.

    **Returns:** a `StackFit`.

    Raises `ValueError` before compiling when the sample has no free parameter, a tabulated
    material does not cover the data's wavelengths, a constant, tabulated or refractiveindex.info
    medium's index at a measured wavelength is not finite or has `n <= 0` or `k < 0` (below zero
    by more than `1e-12 |N|`, the rounding tolerance `stack` shares), or there
    are fewer data than parameters.
    """
    if not isinstance(sample, Sample):
        raise ValueError(f"sample must be a Sample, got {type(sample).__name__}")
    if not isinstance(spectra, Spectra):
        raise ValueError(f"spectra must be Spectra (load_spectra, make_spectra), got {type(spectra).__name__}")
    free = sample.free()
    if not free:
        raise ValueError("the sample has no Free parameter to fit")
    _check_ranges(sample, spectra)
    kinds = spectra.kinds
    Q, P = len(kinds), spectra.wavelength_nm.shape[0]
    p = len(free)
    if Q * P <= p:
        raise ValueError(f"{Q * P} data for {p} free parameters: a fit needs more data than parameters")
    dtype = jnp.dtype(jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32)
    batch = spectra.values.shape[:-2]
    B = math.prod(batch)
    V = jnp.asarray(spectra.values.reshape((B, Q, P)), dtype)
    sigma_given = spectra.sigma is not None
    if spectra.sigma is not None:
        S = jnp.asarray(spectra.sigma.reshape((B, Q, P)), dtype)
    else:
        S = jnp.broadcast_to(jnp.asarray([DEFAULT_SIGMA[k] for k in kinds], dtype)[:, None], (B, Q, P))
    key = (sample, kinds, tuple(map(float, spectra.wavelength_nm)), tuple(map(float, spectra.angle_deg)), B,
           dtype.name, sigma_given, bool(global_start), int(starts), int(max_grid), int(max_steps), bool(progress))
    try:
        hash(key)
    except TypeError:  # a model holding lists or arrays: compiled for this call only
        build: Callable[[], tuple] = functools.cache(lambda: _program.__wrapped__(*key))
    else:
        build = lambda: _program(*key)

    def stages():
        with jax.ensure_compile_time_eval():  # built on concrete values, also when called while tracing
            return build()

    options = _options(B, Q, P)

    def call(i, name, args):
        # The stages are built (optimistix imported, the grid computed) only when one is traced:
        # a stage whose executable is in the store (`_cache`) runs without them.
        run = lambda *a: stages()[i].run(*a)
        jitted = lambda *a: stages()[i].jitted(*a)
        if progress:  # a host callback, which `jax.export` cannot store
            return jitted(*args)
        return _cache.call(run, f"jaxoptics._stack_fit.{name}", args, static=key, options=options,
                           fallback=lambda: jitted(*args))

    # Two compiled calls: Gauss-Newton, then the standard errors, or, where Gauss-Newton left some
    # spectrum unfitted (one read from the device decides), Levenberg-Marquardt and the standard
    # errors. The Levenberg-Marquardt program is compiled only when needed: on the bundled example
    # it is not, and a first call compiles about a third less.
    state = call(0, "_first_stage", (V, S))
    if bool(np.all(np.asarray(state[3]))):
        out = call(1, "_errors_stage", (V, S, state))
    else:
        out = call(2, "_second_stage", (V, S, state))
    x, sd, cov, corr, chi2r, conv, at_b, steps = out
    shp = lambda a: a.reshape(batch + a.shape[1:])
    return StackFit(tuple(f.name for f in free), shp(x), shp(sd), shp(cov), shp(corr), shp(chi2r), shp(conv),
                    shp(at_b), shp(steps), sigma_given)


@functools.lru_cache(maxsize=16)
def _program(sample, kinds, wl_nm, angle_deg, B, dtype_name, sigma_given, global_start, starts, max_grid, max_steps, progress):
    """The fit for one sample structure, data grid and batch size as three stages (cached: a second
    `fit_stack` call with the same ones runs without tracing or compiling): `first(V, S) -> state`,
    the global start and Gauss-Newton (with the normal matrix of its last step where it ended by
    its step test); `errors_only(V, S, state) -> fit`, its standard errors; and
    `second(V, S, state) -> fit`, Levenberg-Marquardt for the spectra Gauss-Newton did not fit, then
    the standard errors. Where `first` fits every spectrum, `second` gives what `errors_only` gives
    (its loop runs zero times)."""
    dtype = jnp.dtype(dtype_name)
    free = sample.free()
    p = len(free)
    Q, P = len(kinds), len(wl_nm)
    lam = np.asarray(wl_nm)
    wl = jnp.asarray(lam, dtype)
    ang = jnp.asarray(np.deg2rad(np.asarray(angle_deg)), dtype)
    is_delta = np.asarray([k == "delta_deg" for k in kinds])
    has_delta = bool(is_delta.any())
    bounds = [_Bound(f.lower, f.upper) for f in free]
    x0 = np.asarray([b.inside(f.value) for f, b in zip(free, bounds)], np.float64)

    def model_x(x, wl, ang):
        """The model's quantities, quantity after quantity."""
        return sample.with_values([x[i] for i in range(p)]).quantities(kinds, wl, ang, flat=True)

    def weigh(model, V, S):
        """Weighted residuals of `model` against the data (`V`, `S` flattened the same way)."""
        diff = model - V
        if has_delta:
            diff = jnp.where(jnp.broadcast_to(jnp.repeat(is_delta, diff.shape[-1] // Q), diff.shape), _wrap_deg(diff), diff)
        return diff / S

    def residuals_x(x, wl, ang, V, S):
        """Weighted residuals, quantity after quantity."""
        return weigh(model_x(x, wl, ang), V, S)

    # Both are called at several places of the one program (the solvers' init and step, the
    # errors, the grid): as jitted functions they are traced once per shape, not at every call
    model_x = jax.jit(model_x)

    def residuals_and_jac_at(wl, ang):
        """`(x, V, S) -> (r, J)`: weighted residuals and their Jacobian at the points `(wl, ang)`."""
        model_and_jac = jax.jit(_model_and_jacobian(sample, kinds, wl, ang))

        def residuals_and_jac(x, V, S):
            m, J = model_and_jac(x)
            return weigh(m, V, S), J / S[:, None]  # the wrap of delta has derivative 1

        return residuals_and_jac

    residuals_and_jac = residuals_and_jac_at(wl, ang)

    def to_x(u):
        return jnp.stack([b.x(u[i]) for i, b in enumerate(bounds)])

    def to_u(x):
        return jnp.stack([b.u(x[i]) for i, b in enumerate(bounds)])

    # grid over the free thicknesses with finite upper bounds
    tidx = [i for i, f in enumerate(free) if f.is_thickness and math.isfinite(f.upper)] if global_start else []
    grid = None
    sub = np.arange(P)
    if tidx:
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
            axes.append((free[i].lower, free[i].upper, step))
        counts = [max(2, int(math.ceil((hi - lo) / st)) + 1) for lo, hi, st in axes]
        while math.prod(counts) > max_grid:
            j = int(np.argmax(counts))
            counts[j] = max(2, counts[j] * 3 // 4)
        pts = np.meshgrid(*[np.linspace(lo, hi, c) for (lo, hi, _), c in zip(axes, counts)], indexing="ij")
        G = np.stack([g.reshape(-1) for g in pts], -1)  # (n_grid, len(tidx))
        grid = np.broadcast_to(x0, (G.shape[0], p)).copy()
        grid[:, tidx] = G
        # keep the starts of the thicknesses strictly inside their bounds
        for k, i in enumerate(tidx):
            lo, hi = free[i].lower, free[i].upper
            eps = 1e-6 * (hi - lo)
            grid[:, i] = np.clip(grid[:, i], lo + eps, hi - eps)
        dmax = sum(free[i].upper for i in tidx)
        sub = _grid_subset(lam, nmax_all, dmax)
    starts = max(1, min(int(starts), 1 if grid is None else grid.shape[0]))

    import optimistix as optx

    from ._fit_solver import _tol
    from ._pool import gauss_newton_edm_stop, pooled_least_squares

    tol = _tol(dtype)
    gn = optx.GaussNewton(rtol=tol, atol=tol)

    def var_scale(m):
        """The variance scale of the reported covariance (`errors`) from the residuals of `m` data."""
        dof = m - p
        return (lambda r: jnp.maximum(jnp.sum(r * r) / dof, 1)) if sigma_given else (lambda r: jnp.sum(r * r) / dof)

    # the full-data pass keeps the normal matrix of its last step: the standard errors need no
    # further evaluation of the model where it ended by this test (`errors`)
    gn_stop = gauss_newton_edm_stop(_EDM_TOL, var_scale(Q * P), normal_matrix=True)
    # A map's Gauss-Newton runs in two passes where the grid's subset of wavelengths holds at most
    # half of the data: first on that subset, to a step below 0.1 of the subset's standard errors,
    # then on all the data from there, which then takes two or three steps. (A small fit, compiled
    # with `QUICK_COMPILE` for a short first call, runs one pass: a smaller program.)
    two_pass = sub.shape[0] <= P // 2 and not _quick(B, Q, P)
    if two_pass:
        Ps = sub.shape[0]
        gn_stop_sub = gauss_newton_edm_stop(_EDM_TOL_SUBSET, var_scale(Q * Ps))
    lm = optx.LevenbergMarquardt(rtol=tol, atol=tol)

    def residuals_u_at(wl, ang, residuals_and_jac):
        """`(u, V, S) -> r`, the weighted residuals at the points `(wl, ang)` in the solvers'
        variables `u`, with its Jacobian from `residuals_and_jac`."""

        @jax.custom_jvp
        def residuals_u(u, Vb, Sb):
            return residuals_x(to_x(u), wl, ang, Vb, Sb)

        @residuals_u.defjvp
        def _residuals_u_jvp(primals, tangents):
            # The Jacobian in one forward pass with p tangents (`jacfwd`), kept as a matrix: the
            # solvers linearize this function and then apply the linearization to p basis vectors,
            # which for the stack kernel would store and re-read every intermediate array; J @ du
            # is cheap.
            u, Vb, Sb = primals
            du, dV, dS = tangents
            x, dxdu = jax.jvp(to_x, (u,), (jnp.ones_like(u),))  # x_i depends on u_i alone
            r, J = residuals_and_jac(x, Vb, Sb)
            return r, J @ (dxdu * du) - dV / Sb - r * dS / Sb  # r = (model - V) / S is linear in V and 1/S

        return residuals_u

    residuals_u = residuals_u_at(wl, ang, residuals_and_jac)

    def starts_of(Vb, Sb, Mg):
        """The `starts` best grid points of one spectrum (or the `Free` values), in `u`."""
        if grid is None:
            return to_u(jnp.asarray(x0, dtype))[None]
        Vs = Vb.reshape(Q, P)[:, sub].reshape(-1)
        Ss = Sb.reshape(Q, P)[:, sub].reshape(-1)
        cost = jnp.sum(weigh(Mg, Vs[None], Ss[None]) ** 2, axis=-1)
        cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
        # (one start: the minimum, at half the cost of the sort on the benchmark's map)
        best = jnp.argmin(cost)[None] if starts == 1 else jnp.argsort(cost)[:starts]
        return jax.vmap(to_u)(jnp.asarray(grid, dtype)[best])

    def normal(x, Vb, Sb):
        """The normal matrix `J^T J` of the weighted residuals in `x`, and their sum of squares."""
        r, J = residuals_and_jac(x, Vb, Sb)
        return J.T @ J, jnp.sum(r * r)

    def normal_from_stop(info):
        """`normal` from the Gauss-Newton stop's `info` (`gauss_newton_edm_stop`): its normal
        matrix in `u`, at the point `u` where the last step began, taken to `x` by the chain rule
        (`J_x = J_u / (dx/du)` column by column: a product undone, exact to rounding while
        `dx/du` is not zero), and the sum of squares predicted after the step. That step is below
        1e-3 standard errors, so `J` differs from its value at the solution by as little."""
        u, Au, c2 = info
        dxdu = jax.jvp(to_x, (u,), (jnp.ones_like(u),))[1]
        A = Au / dxdu[:, None] / dxdu[None, :]
        usable = jnp.all(dxdu != 0) & jnp.all(jnp.isfinite(A)) & jnp.isfinite(c2)
        return A, c2, usable

    def errors(x, ok, A, c2):
        """Standard errors, covariance, correlation, chi^2/dof, flags from the normal matrix `A`
        and the sum of squares `c2` at `x`."""
        chi2r = c2 / (Q * P - p)
        dg = jnp.sqrt(jnp.diag(A))
        dsafe = jnp.where(dg > 0, dg, 1)
        # invert the correlation-scaled normal matrix through its eigendecomposition, without
        # truncation: an undetermined direction gets a huge variance, never a small one
        lam_, vec = jnp.linalg.eigh(A / dsafe[:, None] / dsafe[None, :])
        tiny = jnp.finfo(dtype).eps ** 2 * jnp.maximum(jnp.max(lam_), jnp.finfo(dtype).tiny)
        cov = (vec / jnp.maximum(lam_, tiny)[None, :]) @ vec.T / dsafe[:, None] / dsafe[None, :]
        cov = jnp.where((dg[:, None] > 0) & (dg[None, :] > 0), cov, jnp.where(jnp.eye(p, dtype=bool), jnp.inf, 0))
        cov = cov * (jnp.maximum(chi2r, 1) if sigma_given else chi2r)
        sd = jnp.sqrt(jnp.abs(jnp.diag(cov)))
        sdsafe = jnp.where(jnp.isfinite(sd) & (sd > 0), sd, 1)
        corr = cov / sdsafe[:, None] / sdsafe[None, :]
        lo = jnp.asarray([f.lower for f in free], dtype)
        hi = jnp.asarray([f.upper for f in free], dtype)
        span = jnp.where(jnp.isfinite(hi - lo), hi - lo, jnp.maximum(jnp.abs(x), 1))
        at_b = (jnp.abs(x - lo) <= 1e-6 * span) | (jnp.abs(hi - x) <= 1e-6 * span)
        conv = ok & jnp.all(jnp.isfinite(x)) & jnp.isfinite(chi2r)
        return sd, cov, corr, chi2r, conv, at_b

    def problems(V, S):
        """The least-squares problem of each (spectrum, start) pair, and its chi^2."""
        fn = lambda u, i: residuals_u(u, V[i], S[i])
        chi2 = lambda u, i: jnp.sum(residuals_x(to_x(u), wl, ang, V[i], S[i]) ** 2)
        return fn, chi2

    M = B * starts
    spec = jnp.arange(M) // starts  # the spectrum of each (spectrum, start) problem

    def best(u, c2, ok, steps, *more):
        """The lowest chi^2 among each spectrum's starts (and the arrays `more` of that start)."""
        x = jax.vmap(to_x)(u).reshape(B, starts, p)
        c2 = jnp.where(jnp.isfinite(c2), c2, jnp.inf).reshape(B, starts)
        ok = ok.reshape(B, starts) & jnp.isfinite(c2)
        k = jnp.argmin(jnp.where(ok, c2, jnp.inf), axis=1)
        pick = lambda a: jnp.take_along_axis(a, k.reshape((B, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]
        return (pick(x), pick(c2), pick(ok), pick(steps.reshape(B, starts))) + tuple(pick(a.reshape((B, starts) + a.shape[1:])) for a in more)

    def finish(x, ok, steps, V, S, A, c2, have):
        """The results: the normal matrix and sum of squares `A`, `c2` where `have`, evaluated at
        `x` for the other spectra (their number sets the cost: `_pending_map`)."""
        order = jnp.argsort(have, stable=True)
        A, c2 = _pending_map(normal, (x, V, S), order, jnp.sum(~have), _FIRST_BLOCK, (A, c2))
        sd, cov, corr, chi2r, conv, at_b = jax.vmap(errors)(x, ok, A, c2)
        return x, sd, cov, corr, chi2r, conv, at_b, steps

    def first(V, S):
        """The global start and Gauss-Newton from every start: the starts `U0`, and the best
        solution's `x`, `c2`, `ok`, `steps` per spectrum, with the normal matrix `A` of its last
        step where `have` (`c2` is then that step's prediction; see `finish`)."""
        V, S = V.reshape(B, -1), S.reshape(B, -1)
        fn, chi2 = problems(V, S)
        # the model on the grid does not depend on the data: evaluated once for the whole map, and
        # each spectrum only compares its data with it
        Mg = None if grid is None else jax.vmap(lambda x: model_x(x, wl[sub], ang[sub]))(jnp.asarray(grid, dtype))
        U0 = _blocked(jax.vmap(lambda Vb, Sb: starts_of(Vb, Sb, Mg)), (V, S), _FIRST_BLOCK).reshape(M, p)
        report = lambda what: (lambda done, _: _report(done // starts, B, what)) if progress else None
        U1, st0 = U0, 0
        if two_pass:
            ws, angs = wl[sub], ang[sub]
            fn_sub = residuals_u_at(ws, angs, residuals_and_jac_at(ws, angs))
            Vs = V.reshape(B, Q, P)[:, :, sub].reshape(B, -1)
            Ss = S.reshape(B, Q, P)[:, :, sub].reshape(B, -1)
            u0, _, st0, _, _ = pooled_least_squares(lambda u, i: fn_sub(u, Vs[i], Ss[i]), gn, U0, spec, jnp.arange(M), M,
                                                 lanes=_GN_LANES, max_steps=_GN_STEPS, early_stop=gn_stop_sub,
                                                 on_progress=report("first pass, on a subset of the wavelengths"))
            # the second pass starts where the first ended (from the start, where that is not finite)
            U1 = jnp.where(jnp.all(jnp.isfinite(u0), axis=-1, keepdims=True), u0, U0)
        u1, ok1, st1, _, (info, early) = pooled_least_squares(fn, gn, U1, spec, jnp.arange(M), M, lanes=_GN_LANES,
                                                              max_steps=_GN_STEPS, early_stop=gn_stop,
                                                              on_progress=report("Gauss-Newton stage"))
        A, c2e, usable = jax.vmap(normal_from_stop)(info)
        have = early & usable
        # chi^2 picks the best of several starts (with one, the stop's prediction or `finish` gives it)
        c21 = _blocked(jax.vmap(chi2), (u1, spec), _FIRST_BLOCK) if starts > 1 else c2e
        x, c2, ok, steps, A, have = best(u1, c21, ok1, st0 + st1, A, have)
        return U0, x, c2, ok, steps, A, have

    def errors_only(V, S, state):
        """The fit of `first`, with its standard errors: where Gauss-Newton fitted every spectrum."""
        V, S = V.reshape(B, -1), S.reshape(B, -1)
        _, x, c2, ok, steps, A, have = state
        return finish(x, ok, steps, V, S, A, c2, have)

    def second(V, S, state):
        """Levenberg-Marquardt from the same starts, for the spectra Gauss-Newton did not fit (the
        pending problems first, in `order`, so that its cost follows the number of failures); the
        better solution of the two per spectrum, and its standard errors."""
        V, S = V.reshape(B, -1), S.reshape(B, -1)
        fn, chi2 = problems(V, S)
        U0, x, c2, ok, steps, A, have = state
        pend = ~ok[spec]
        order = jnp.argsort(~pend, stable=True)
        count = jnp.sum(pend)
        u2, ok2, st2, touched, _ = pooled_least_squares(fn, lm, U0, spec, order, count, lanes=_LM_LANES,
                                                     max_steps=max_steps)
        c22 = _pending_map(chi2, (u2, spec), order, count, _LM_LANES, jnp.full(M, jnp.inf, dtype))
        x2, c22, ok2, st2 = best(u2, c22, ok2 & touched, st2)
        better = ok2 & (~ok | (c22 < c2))
        x = jnp.where(better[:, None], x2, x)
        c2 = jnp.where(better, c22, c2)
        steps = steps + st2
        ok = ok | ok2
        return finish(x, ok, steps, V, S, A, c2, have & ~better)

    options = known_options(_options(B, Q, P))
    return tuple(_Stage(f, jax.jit(f, compiler_options=options)) for f in (first, errors_only, second))


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


class _Stage(NamedTuple):
    run: object  # the stage's function
    jitted: object  # it under `jax.jit`, with the fit's compiler options


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


def _model_and_jacobian(sample, kinds, wl, ang):
    """`x -> (model, J)`: the quantities `kinds` at the points `(wl, ang)` (nm, radians), flat
    `(Q P,)`, and their Jacobian `(Q P, p)` in the free parameters `x`, by the chain rule through the
    stack's inputs (`_jacobian_plan`)."""
    plan = _jacobian_plan(sample)
    p, Q = len(plan.columns), len(kinds)
    inc = sample.incoherent
    cos_ang = jnp.cos(ang)
    inputs = lambda x: sample.with_values([x[i] for i in range(p)]).stack_inputs(wl)
    quantities = lambda n, d: model_quantities(stack(n, d, wl, cos_ang, incoherent=inc), kinds, True)

    def model_and_jac(x):
        basis = jnp.eye(p, dtype=x.dtype)
        (n, d), (dn, dd) = jax.vmap(lambda t: jax.jvp(inputs, (x,), (t,)), out_axes=(None, -1))(basis)
        tn, td = [], []
        for kind, j in plan.directions:
            if kind == "param":
                tn.append(dn[..., j])
                td.append(dd[..., j])
            else:
                tn.append(jnp.zeros_like(n).at[..., j].set(1 if kind == "re" else 1j))
                td.append(jnp.zeros_like(d))
        m, D = jax.vmap(lambda a, b: jax.jvp(quantities, (n, d), (a, b)), out_axes=(None, 1))(jnp.stack(tn), jnp.stack(td))
        # stored once: under `vmap` over the directions, XLA otherwise fuses the stack's last steps
        # into the loop that assembles the columns, where they run one element at a time (4x the
        # cost of the whole Jacobian, measured on a film's R_s)
        D = materialize(D)
        cols = []
        for i in range(p):
            src = plan.columns[i]
            if len(src) == 1:  # the parameter's own direction
                cols.append(D[:, src[0]])
            else:  # d/dx_i = d/dRe(n_j) Re(dn_j/dx_i) + d/dIm(n_j) Im(dn_j/dx_i), point by point
                k_re, k_im = src
                g = jnp.tile(dn[:, plan.medium[i], i], Q)
                col = D[:, k_re] * jnp.real(g)
                cols.append(col if k_im is None else col + D[:, k_im] * jnp.imag(g))
        return m, jnp.stack(cols, axis=1)

    return model_and_jac


class _Plan(NamedTuple):
    directions: tuple  # tangents through the stack: ("param", i), ("re", j) or ("im", j)
    columns: tuple  # per free parameter: (direction,) or (re direction, im direction or None)
    medium: tuple  # per free parameter: the medium it belongs to (None for a thickness)


def _jacobian_plan(sample):
    """How `fit_stack` builds the Jacobian of the model in the free parameters `x`.

    The model is `quantities(stack(n(x), d(x)))`: cheap per-point dispersion formulas `n(x)` of
    the `L` media and the thicknesses `d(x)`, then the stack, which costs nearly all the time. Its
    forward-mode derivative costs about one stack evaluation per tangent, so the tangents through
    the stack are kept few: a medium with more than two free parameters gets two (its index's real
    and imaginary part, at every point at once: each point depends on its own index only), or one
    where its index is real (the incident medium; a model whose `k` is held at zero, such as
    Cauchy's without an Urbach tail), and the derivative in each of its parameters is their
    point-by-point combination with the dispersion formula's derivatives. Every other parameter
    (a thickness, or a medium with one or two) is its own tangent. On the benchmark's film (Cauchy
    A, B, C and the thickness free) that is 2 tangents instead of 4."""
    medium, counts, real = [], [], []
    for j, (_, model) in enumerate(sample._slots()):
        k = sum(isinstance(leaf, Free) for _, leaf in parameter_leaves(model))
        medium += [j] * k
        counts.append(k)
        real.append(j == 0 or model._real())
    medium += [None] * sum(isinstance(layer.thickness_nm, Free) for layer in sample.layers)
    directions, columns, split = [], [], {}
    for i, j in enumerate(medium):
        if j is not None and counts[j] > 2:
            if j not in split:
                split[j] = (len(directions), None if real[j] else len(directions) + 1)
                directions += [("re", j)] + ([] if real[j] else [("im", j)])
            columns.append(split[j])
        else:
            columns.append((len(directions),))
            directions.append(("param", i))
    return _Plan(tuple(directions), tuple(columns), tuple(medium))


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
