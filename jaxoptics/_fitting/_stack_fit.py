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
   moved inside it (`_stack_fit_stages._Bound.inside`), where the slope of the change is not zero. The spectra
   of a map are solved by a pool of lanes that take the next spectrum as soon as theirs has converged
   (`jaxoptics._fitting._pool`), and the Jacobian is formed with as few passes through the stack as the
   model allows (`_stack_jacobian._jacobian_plan`).
3. **Uncertainties** from the Jacobian of the weighted residuals in the physical parameters at
   the solution (where Gauss-Newton stopped by its step test, the Jacobian of its last step, less
   than 1e-3 standard errors before the solution, and the chi^2 that step predicts: no further
   evaluation of the model; elsewhere evaluated at the solution): covariance `(J^T J)^-1`,
   inverted through the eigendecomposition of the correlation-scaled matrix, with no truncation: a direction the data do not determine gets an
   enormous standard error and correlations near +-1, never a small one. Without `sigma` the
   residuals' own scatter sets the scale (`cov * chi2_reduced`); with `sigma`, `cov *
   max(1, chi2_reduced)`.

Without sigma columns, quantities are weighted by nominal standard deviations (`DEFAULT_SIGMA`:
0.05 degrees for psi, 0.1 for delta, 0.002 for N, C, S, R, T and the depolarization) so that mixed quantities have
comparable weights; the overall scale is then estimated from the fit.

This file checks the input and drives the compiled calls; the stages themselves are named
functions in `_stack_fit_stages` (the fringe search, the Gauss-Newton passes, the
Levenberg-Marquardt rescue, the error estimate), and the Jacobian is `_stack_jacobian`'s.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _validate as V
from .._core._result import result, static
from .._films._dispersion import Constant, Free, Tabulated
from .._films._rii import RIIFormula
from .._films._sample import Sample
from .._io._spectra import Spectra
from .._runtime import _cache
from .._runtime._options import known_options
from .._runtime._shard import from_blocks

if TYPE_CHECKING:
    from jax.sharding import Mesh
from . import _stack_fit_stages as _stages

DEFAULT_SIGMA = {"psi_deg": 0.05, "delta_deg": 0.1, "N": 0.002, "C": 0.002, "S": 0.002,
                 "R": 0.002, "R_s": 0.002, "R_p": 0.002, "T": 0.002, "T_s": 0.002, "T_p": 0.002, "depolarization": 0.002}


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

    def table(self, site=None, statistics=None) -> str:
        """A text table of values, standard errors and flags for one site; with `statistics`
        (`fit_statistics(sample, spectra, fit)`) also the WVASE and CompleteEASE MSE and the 90%
        confidence limits."""
        sl = (lambda a: a) if self.values.ndim == 1 else (lambda a: np.asarray(a).reshape((-1,) + a.shape[self.values.ndim - 1:])[site or 0])
        v, s, b = (np.asarray(sl(x)) for x in (self.values, self.stderr, self.at_bound))
        w = max(len(n) for n in self.names)
        ci = None if statistics is None else np.asarray(sl(np.asarray(statistics.ci90)))
        rows = [f"{'parameter':<{w}}  {'value':>14}  {'stderr':>12}" + ("  90% limit" if ci is not None else "")]
        for i, n in enumerate(self.names):
            rows.append(f"{n:<{w}}  {v[i]:>14.6g}  {s[i]:>12.3g}" + (f"  +-{ci[i]:<8.3g}" if ci is not None else "")
                        + ("  (at a bound)" if b[i] else ""))
        chi = float(np.asarray(sl(self.chi2_reduced[..., None]))[0])
        conv = bool(np.asarray(sl(self.converged[..., None]))[0])
        rows.append(f"chi2_reduced {chi:.4g}; converged {conv}; sigma {'from the data' if self.sigma_given else 'estimated from the fit'}")
        if statistics is not None:
            mse = float(np.asarray(sl(np.asarray(statistics.mse)[..., None]))[0])
            ncs = float(np.asarray(sl(np.asarray(statistics.mse_ncs)[..., None]))[0])
            wvase = f"{mse:.4g}" if np.isfinite(mse) else "n/a (the data carry no sigma)"
            ce = f"{ncs:.4g}" if np.isfinite(ncs) else "n/a (no ellipsometric data)"
            rows.append(f"MSE {wvase} (WVASE: sigma-weighted, {statistics.n_data} data - {statistics.n_params}); "
                        f"MSE {ce} (CompleteEASE: N, C, S x1000, {statistics.n_ncs} data - {statistics.n_params})")
        return "\n".join(rows)


def _models(sample: Sample):
    """`(owner, model)` for every medium's model and the models inside it (an effective medium's
    constituents, named `owner.host`, ...)."""
    from .._films._dispersion import Dispersion

    def walk(owner, model):
        yield owner, model
        for f in model._params:
            v = getattr(model, f)
            if isinstance(v, Dispersion):
                yield from walk(f"{owner}.{f}", v)

    for owner, model in sample._slots():
        yield from walk(owner, model)


def _check_ranges(sample: Sample, spectra: Spectra):
    lam_um = np.asarray(spectra.wavelength_nm) / 1000
    for owner, model in _models(sample):
        tab = type(model).__name__ == "Tabulated" or getattr(model, "k_table", None) is not None
        rng = getattr(model, "range_um", None)
        if tab and rng is not None and (lam_um.min() < rng[0] - 1e-12 or lam_um.max() > rng[1] + 1e-12):
            raise ValueError(f"{owner}: the material's tabulated data cover {rng[0] * 1000:g}-{rng[1] * 1000:g} nm, "
                             f"the spectra {lam_um.min() * 1000:g}-{lam_um.max() * 1000:g} nm; tabulated data are not extrapolated")
    # every constant or tabulated medium's index at the data's wavelengths is one the stack takes:
    # finite, n > 0, k >= 0 (a database table or formula can give NaN beyond a k table, or gain)
    wl = np.unique(np.asarray(spectra.wavelength_nm))
    for owner, model in _models(sample):
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


def fit_stack(sample: Sample, spectra: Spectra, *, global_start: bool | str = True, starts: int = 1,
              max_grid: int = 4096, max_steps: int = 200, progress: bool = False, mesh: Mesh | None = None) -> StackFit:
    """Fit the `Free` parameters of `sample` to `spectra` (one spectrum or a map of them).

    **Arguments:**

    - `sample`: a `Sample` with at least one `Free` parameter.
    - `spectra`: `Spectra` (`load_spectra`, `make_spectra`); leading axes of its values are
      map sites, all fitted together (each compiled call covers the whole map).
    - `global_start`: search each free thickness with a finite upper bound on a grid first (see
      the module docstring); `False` starts from the `Free` values; `"fft"` (a thick film's
      reflectance or transmittance, one free thickness): search only around the thickness the
      Fourier transform of each spectrum gives (`fft_thickness`), over all sites' estimates
      widened by three resolutions and the film's dispersion, so that films of tens of
      micrometres, many hundreds of fringes, need a grid of tens of points.
    - `starts`: how many of the best grid points to refine; the lowest chi^2 wins.
    - `max_grid`: the most grid points per spectrum (several free thicknesses share this budget).
    - `max_steps`: Levenberg-Marquardt steps per start.
    - `progress`: report on standard error how many spectra the Gauss-Newton stage has done
      (from inside the compiled call; for maps that take minutes; on a `mesh`, each device
      reports its own block).
    - `mesh`: a one-dimensional device mesh (`batch_mesh()`) to fit a map over: its sites are
      split into one block per device, each device fits its own block with the same program
      compiled for it (no data move and no communication between devices while they fit; the
      devices' calls are all dispatched before any result is read), and every field of the
      result is sharded along the sites. A map whose number of sites is not a multiple of the
      device count is padded with copies of its last site for the fit, and the padding is
      dropped from the result (which then comes back unsharded, as JAX cannot shard an uneven
      length). On a mesh that spans several processes (`jax.distributed`), each process passes
      the spectra of its own sites (a one-dimensional map, the same number of sites per device in
      every process) and fits them on its own devices; the result is one array over the sites of
      all processes, its rows the devices' blocks in the mesh's order. Default: one device.

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
    V = np.asarray(spectra.values, dtype).reshape((B, Q, P))
    sigma_given = spectra.sigma is not None
    if spectra.sigma is not None:
        S = np.asarray(spectra.sigma, dtype).reshape((B, Q, P))
    else:
        S = np.broadcast_to(np.asarray([DEFAULT_SIGMA[k] for k in kinds], dtype)[:, None], (B, Q, P))
    devices = _mesh_devices(mesh)
    # the positions in the mesh of this process's devices (all of them but on a mesh that spans
    # several processes, `jax.distributed`: there each process fits its own sites on its own devices)
    local = [k for k, d in enumerate(devices) if d is None or d.process_index == jax.process_index()]
    multi = len(local) < len(devices)
    if multi:
        Bs = _sites_per_device(B, len(local), batch)
        Bp = Bs * len(devices)
    else:
        Bp = -(-B // len(devices)) * len(devices)  # sites padded to a multiple of the device count
        Bs = Bp // len(devices)  # the sites of one device's block
        pad = lambda a: np.concatenate([a, np.broadcast_to(a[-1:], (Bp - B,) + a.shape[1:])]) if Bp > B else a
        V, S = pad(V), pad(S)
    # the fit of one block of sites (the whole map without a mesh), the same on every device
    if global_start == "fft":
        from ._reflectometry import fft_window

        start: bool | tuple = ("window",) + fft_window(sample, spectra)
    elif isinstance(global_start, str):
        raise ValueError(f"global_start={global_start!r}: True, False or 'fft'")
    else:
        start = bool(global_start)
    key = (sample, kinds, tuple(map(float, spectra.wavelength_nm)), tuple(map(float, spectra.angle_deg)), Bs,
           dtype.name, sigma_given, start, int(starts), int(max_grid), int(max_steps), bool(progress))
    try:
        hash(key)
    except TypeError:  # a model holding lists or arrays: compiled for this call only
        build: Callable[[], tuple] = functools.cache(lambda: _program.__wrapped__(*key))
    else:
        build = lambda: _program(*key)

    def stages():
        with jax.ensure_compile_time_eval():  # built on concrete values, also when called while tracing
            return build()

    options = _stages._options(Bs, Q, P)

    def call(stage, args):
        # The stages are built (the grid computed, optimistix imported when traced) only when one
        # is traced: a stage whose executable is in the store (`_cache`) runs without them.
        i = _stages.STAGES.index(stage)
        run = lambda *a: stages()[i].run(*a)
        jitted = lambda *a: stages()[i].jitted(*a)
        if progress:  # a host callback, which `jax.export` cannot store
            return jitted(*args)
        return _cache.call(run, f"{stage.__module__}.{stage.__name__}", args, static=key, options=options,
                           fallback=lambda: jitted(*args))

    # Two compiled calls per block: Gauss-Newton, then the standard errors, or, where Gauss-Newton
    # left some spectrum of the block unfitted (one read from the device decides),
    # Levenberg-Marquardt and the standard errors. The Levenberg-Marquardt program is compiled only
    # when needed: on the bundled example it is not, and a first call compiles about a third less.
    # On a mesh, every device's calls are dispatched before any result is read, so the devices
    # fit at once.
    blocks = [(_put(V[j * Bs:(j + 1) * Bs], devices[k]), _put(S[j * Bs:(j + 1) * Bs], devices[k]))
              for j, k in enumerate(local)]
    states = [call(_stages.first_stage, blk) for blk in blocks]
    outs = [call(_stages.errors_stage if bool(np.all(np.asarray(st[3]))) else _stages.second_stage, blk + (st,))
            for blk, st in zip(blocks, states)]
    out = outs[0] if mesh is None else jax.tree.map(
        lambda *a: from_blocks({k * Bs: x for k, x in zip(local, a)}, Bp, mesh, mesh.axis_names[0]), *outs)
    x, sd, cov, corr, chi2r, conv, at_b, steps = out
    if multi:  # the sites of every process: one global array along the mesh
        batch = (Bp,)
    shp = lambda a: (a if Bp == B or multi else a[:B]).reshape(batch + a.shape[1:])
    return StackFit(tuple(f.name for f in free), shp(x), shp(sd), shp(cov), shp(corr), shp(chi2r), shp(conv),
                    shp(at_b), shp(steps), sigma_given)


def _sites_per_device(B: int, n_local: int, batch: tuple) -> int:
    """The sites of each device's block on a mesh that spans several processes: this process's `B`
    sites (a one-dimensional map) over its `n_local` devices, the same count in every process
    (checked across the processes: the result is one array over all their sites)."""
    from jax.experimental import multihost_utils

    if len(batch) != 1 or B % n_local:
        raise ValueError(f"on a mesh that spans several processes, each process fits a one-dimensional map of its own "
                         f"sites, a multiple of its {n_local} devices; this process has spectra of batch shape {batch}")
    counts = np.asarray(multihost_utils.process_allgather(np.array([B // n_local])))
    if np.any(counts != counts.ravel()[0]):
        raise ValueError(f"on a mesh that spans several processes every device fits as many sites; the processes' "
                         f"sites per device are {counts.ravel().tolist()}")
    return B // n_local


def _mesh_devices(mesh) -> list:
    """The devices of a one-dimensional `mesh`, in its order (one default device without a mesh)."""
    if mesh is None:
        return [None]
    if not isinstance(mesh, jax.sharding.Mesh) or len(mesh.axis_names) != 1:
        raise ValueError(f"mesh must be a one-dimensional jax.sharding.Mesh (jo.batch_mesh()), got {mesh!r}")
    return list(np.asarray(mesh.devices).ravel())


def _put(a, device):
    """`a` (NumPy) on `device`, or on the default device where `device` is None."""
    return jnp.asarray(a) if device is None else jax.device_put(a, device)


@functools.lru_cache(maxsize=16)
def _program(sample, kinds, wl_nm, angle_deg, B, dtype_name, sigma_given, global_start, starts, max_grid, max_steps, progress):
    """The fit for one sample structure, data grid and batch size (cached: a second `fit_stack`
    call with the same ones runs without tracing or compiling): its `FitProblem` and the three
    stages of `_stack_fit_stages.STAGES` on it, each with its compiled form: `first_stage(V, S)
    -> state`, the fringe search and Gauss-Newton; `errors_stage(V, S, state) -> fit`, its
    standard errors; `second_stage(V, S, state) -> fit`, Levenberg-Marquardt for the spectra
    Gauss-Newton did not fit, then the standard errors."""
    prob = _stages.build_problem(sample, kinds, wl_nm, angle_deg, B, dtype_name, sigma_given, global_start, starts,
                                 max_grid, max_steps, progress)
    options = known_options(_stages._options(B, len(kinds), len(wl_nm)))
    stages = [functools.partial(f, prob) for f in _stages.STAGES]
    return tuple(_Stage(f, jax.jit(f, compiler_options=options)) for f in stages)


class _Stage(NamedTuple):
    run: object  # the stage's function
    jitted: object  # it under `jax.jit`, with the fit's compiler options
