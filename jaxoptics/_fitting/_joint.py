"""Joint fits: several data sets (angles, data types, instruments, samples), each with its own
sample model and weight, fitted together with parameters shared by name (`fit_joint`).

The method: each data set is first fitted alone by `fit_stack` (its global search over
thickness included), and each joint parameter starts from the data set that determines it best
(the smallest standard error); then one Levenberg-Marquardt solve (optimistix) of all data sets'
weighted residuals together, per site of a map (`jax.vmap`), with bounds kept by the same change
of variables as `fit_stack`'s; standard errors, correlations and chi^2 from the joint Jacobian at
the solution, as `fit_stack` forms them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
from typing import TYPE_CHECKING, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._films._sample import Sample
from .._io._spectra import Spectra
from . import _stack_fit_stages as _stages
from ._stack_jacobian import _model_and_jacobian

if TYPE_CHECKING:
    from ._stack_fit import StackFit


@dataclasses.dataclass(frozen=True, eq=False)
class Dataset:
    """One data set of a joint fit (`fit_joint([Dataset(...), ...])`).

    **Fields:**

    - `sample`: the `Sample` that models these data. Its free parameters are named as
      `Sample.free_names()` gives them (`oxide.thickness_nm`, `oxide.A`, ...); a name that
      appears in several data sets is one parameter of the joint fit (unless `shared=` says
      otherwise), any other is this data set's own, reported as `<name>:<parameter>`.
    - `spectra`: its `Spectra`. All data sets of a joint fit have the same map shape (sites fitted
      together). Data without sigma are weighted by nominal sigmas (0.05 degrees for Psi, 0.1 for
      Delta, 0.002 for N, C, S, R, T), and then the errors are scaled by the residual scatter.
    - `weight`: its chi^2 is multiplied by this (CompleteEASE's data-set weighting), default 1.
    - `name`: a label (default `data1`, `data2`, ...).
    """

    sample: Sample
    spectra: Spectra
    weight: float = 1.0
    name: str | None = None

    def __post_init__(self):
        if not isinstance(self.sample, Sample):
            raise ValueError(f"Dataset.sample must be a Sample, got {type(self.sample).__name__}")
        if not isinstance(self.spectra, Spectra):
            raise ValueError(f"Dataset.spectra must be Spectra, got {type(self.spectra).__name__}")
        if not (isinstance(self.weight, (int, float)) and math.isfinite(self.weight) and self.weight > 0):
            raise ValueError(f"Dataset.weight must be a finite number > 0, got {self.weight!r}")


def _plan(datasets, shared):
    """The joint parameters: their names, bounds (`ParameterInfo`s) and, per data set, the index
    of each of its free parameters in the joint vector. Raises on names that cannot be joined."""
    labels = [d.name or f"data{k + 1}" for k, d in enumerate(datasets)]
    if len(set(labels)) != len(labels):
        raise ValueError(f"data set names must differ, got {labels}")
    frees = [d.sample.free() for d in datasets]
    for lab, fr in zip(labels, frees):
        if not fr:
            raise ValueError(f"data set {lab}: its sample has no Free parameter")
    seen: dict[str, list[int]] = {}
    for k, fr in enumerate(frees):
        for f in fr:
            seen.setdefault(f.name, []).append(k)
    if shared is None:
        joint = {n for n, ks in seen.items() if len(ks) > 1}
    else:
        joint = set(shared)
        for n in joint:
            if n not in seen:
                raise ValueError(f"shared parameter {n!r} is no data set's free parameter; free: {sorted(seen)}")
            if len(seen[n]) < 2:
                raise ValueError(f"shared parameter {n!r} is free in data set {labels[seen[n][0]]} only")
    names: list[str] = []
    infos: list = []
    index = []
    for k, fr in enumerate(frees):
        idx = []
        for f in fr:
            g = f.name if f.name in joint else f"{labels[k]}:{f.name}"
            if g not in names:
                names.append(g)
                infos.append(dataclasses.replace(f, name=g))  # ParameterInfo is a frozen dataclass
            else:
                first = infos[names.index(g)]
                if (first.lower, first.upper) != (f.lower, f.upper):
                    raise ValueError(f"shared parameter {g!r} has bounds ({first.lower}, {first.upper}) in one data set "
                                     f"and ({f.lower}, {f.upper}) in {labels[k]}: give it the same bounds everywhere")
            idx.append(names.index(g))
        index.append(tuple(idx))
    return labels, names, infos, index


def fit_joint(datasets: Sequence[Dataset], *, shared: Sequence[str] | None = None, max_steps: int = 200) -> StackFit:
    """Fit several data sets together, with parameters shared by name (see the module docstring).

    **Arguments:**

    - `datasets`: `Dataset(sample, spectra, weight=1.0, name=None)`s: different angles, data
      types (ellipsometry and R/T), instruments, or samples. They cover the same map sites (or
      are single spectra).
    - `shared`: the free-parameter names (`Sample.free_names()`) that are one parameter across
      the data sets having them; every other parameter is its data set's own. Default: every name
      that is free in more than one data set. A shared parameter has the same bounds everywhere.
    - `max_steps`: Levenberg-Marquardt steps of the joint solve.

    **Returns:** a `StackFit` whose `names` are the shared names and `<data set>:<name>` for the
    others; `chi2_reduced` is over all data (each data set's chi^2 times its weight) with the
    joint number of parameters.

    Raises `ValueError` before compiling on data sets of different map shapes, a shared name that
    is not free in two data sets, different bounds of a shared parameter, or as `fit_stack` does
    for each data set.
    """
    from ._stack_fit import DEFAULT_SIGMA, StackFit, _check_ranges, fit_stack

    datasets = list(datasets)
    if not datasets or not all(isinstance(d, Dataset) for d in datasets):
        raise ValueError("a joint fit takes a list of jo.Dataset(sample, spectra, weight=..., name=...)")
    labels, names, infos, index = _plan(datasets, shared)
    batch = datasets[0].spectra.values.shape[:-2]
    for lab, d in zip(labels, datasets):
        if d.spectra.values.shape[:-2] != batch:
            raise ValueError(f"data set {lab} has map shape {d.spectra.values.shape[:-2]}, {labels[0]} has {batch}: "
                             "the data sets of a joint fit cover the same sites")
        _check_ranges(d.sample, d.spectra)
    # a data set without sigma is weighted by the nominal sigmas (`DEFAULT_SIGMA`); then the
    # covariance is scaled by chi2_reduced, as `fit_stack` does for data without sigma
    sigma_given = all(d.spectra.sigma is not None for d in datasets)
    dtype = jnp.dtype(jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32)
    B, p = math.prod(batch), len(names)
    m = sum(d.spectra.values.shape[-2] * d.spectra.values.shape[-1] for d in datasets)
    if m <= p:
        raise ValueError(f"{m} data for {p} free parameters: a fit needs more data than parameters")

    # starts: each data set fitted alone; a joint parameter from the data set with its smallest error
    x0 = np.tile(np.asarray([f.value for f in infos], np.float64), (B, 1))
    best = np.full((B, p), np.inf)
    for d, idx in zip(datasets, index):
        alone = fit_stack(d.sample, d.spectra)
        v = np.asarray(alone.values, np.float64).reshape(B, -1)
        e = np.asarray(alone.stderr, np.float64).reshape(B, -1)
        e = np.where(np.isfinite(e) & np.isfinite(v) & np.asarray(alone.converged).reshape(B, 1), e, np.inf)
        for j, g in enumerate(idx):
            take = (e[:, j] < best[:, g]) | ~np.isfinite(best[:, g]) & np.isfinite(e[:, j])
            x0[take, g], best[take, g] = v[take, j], e[take, j]
    bounds = tuple(_stages._Bound(f.lower, f.upper) for f in infos)
    x0 = np.stack([[b.inside(float(x)) for b, x in zip(bounds, row)] for row in x0])

    data = []
    for d in datasets:
        Q, P = d.spectra.values.shape[-2:]
        V = np.asarray(d.spectra.values, dtype).reshape(B, Q * P)
        S = (np.asarray(d.spectra.sigma, dtype).reshape(B, Q * P) if d.spectra.sigma is not None
             else np.broadcast_to(np.repeat(np.asarray([DEFAULT_SIGMA[k] for k in d.spectra.kinds], dtype), P), (B, Q * P)))
        data.append((jnp.asarray(V), jnp.asarray(S / math.sqrt(d.weight))))
    key = (tuple((d.sample, tuple(d.spectra.kinds), tuple(map(float, d.spectra.wavelength_nm)),
                  tuple(map(float, d.spectra.angle_deg))) for d in datasets), tuple(index), bounds, dtype.name,
           sigma_given, int(max_steps), tuple(infos))
    try:
        hash(key)
        program = _program(key)
    except TypeError:  # a model holding lists or arrays: compiled for this call only
        program = _program.__wrapped__(key)
    x, sd, cov, corr, chi2r, conv, at_b, steps = program(jnp.asarray(x0, dtype), tuple(data))
    shp = lambda a: a.reshape(batch + a.shape[1:])
    return StackFit(tuple(names), shp(x), shp(sd), shp(cov), shp(corr), shp(chi2r), shp(conv), shp(at_b), shp(steps),
                    sigma_given)


@functools.lru_cache(maxsize=8)
def _program(key):
    """The compiled joint solve and error estimate over a map's sites, for one plan."""
    import optimistix as optx

    parts, index, bounds, dtype_name, sigma_given, max_steps, infos = key
    dtype = jnp.dtype(dtype_name)
    p = len(bounds)
    m = sum(len(k) * len(w) for _, k, w, _ in parts)
    is_delta = [np.repeat(np.asarray([k == "delta_deg" for k in kinds]), len(wl)) for _, kinds, wl, _ in parts]
    pts = [(jnp.asarray(wl, dtype), jnp.deg2rad(jnp.asarray(ang, dtype))) for _, _, wl, ang in parts]
    to_x = lambda u: jnp.stack([b.x(u[i]) for i, b in enumerate(bounds)])
    to_u = lambda x: jnp.stack([b.u(x[i]) for i, b in enumerate(bounds)])

    mj = [_model_and_jacobian(sample, kinds, wl, ang) for (sample, kinds, _, _), (wl, ang) in zip(parts, pts)]

    def weighted(x, data):
        """The weighted residuals of all data sets at `x` and their Jacobian in `x` (each data
        set's by `_stack_jacobian`, placed in its parameters' columns)."""
        rs, Js = [], []
        for f, idx, dlt, (V, S) in zip(mj, index, is_delta, data):
            model, J = f(jnp.stack([x[i] for i in idx]))
            diff = model - V
            if dlt.any():
                diff = jnp.where(dlt, _stages._wrap_deg(diff), diff)
            rs.append(diff / S)
            Js.append(jnp.zeros((J.shape[0], p), J.dtype).at[:, list(idx)].set(J / S[:, None]))  # delta's wrap: slope 1
        return jnp.concatenate(rs), jnp.concatenate(Js)

    @jax.custom_jvp
    def residuals_u(u, data):
        return weighted(to_x(u), data)[0]

    @residuals_u.defjvp
    def _jvp(primals, tangents):
        # the Jacobian in one forward pass per data set, kept as a matrix (as `fit_stack`'s
        # residuals do): the solver then applies it to its tangents at the cost of a product
        u, data = primals
        du, ddata = tangents
        x, dxdu = jax.jvp(to_x, (u,), (jnp.ones_like(u),))  # x_i depends on u_i alone
        r, J = weighted(x, data)
        # r = (model - V) / S is linear in V and 1/S
        rr = jnp.split(r, np.cumsum([V.shape[0] for V, _ in data])[:-1])
        dr = jnp.concatenate([-dV / S - ri * dS / S for (dV, dS), (V, S), ri in zip(ddata, data, rr)])
        return r, J @ (dxdu * du) + dr

    tol = _stages._solver_tol(dtype)
    solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    prob = types.SimpleNamespace(p=p, dtype=dtype, Q=1, P=m, sigma_given=sigma_given, free=infos)

    def one(x0, data):
        sol = optx.least_squares(residuals_u, solver, to_u(x0), args=data, max_steps=max_steps, throw=False)
        x = to_x(sol.value)
        r, J = weighted(x, data)
        ok = sol.result == optx.RESULTS.successful
        sd, cov, corr, chi2r, conv, at_b = _stages.error_estimate(prob, x, ok, J.T @ J, jnp.sum(r * r))
        return x, sd, cov, corr, chi2r, conv, at_b, sol.stats["num_steps"]

    return jax.jit(jax.vmap(one))


_DATASET_KEYS = ("name", "data", "model", "weight", "format", "delta_convention", "delta_range", "mueller_s3_sign",
                 "angle_deg", "quantity", "scale", "wavelength_unit")


def is_joint_file(path) -> bool:
    """Whether a TOML file describes a joint fit (`[[dataset]]` tables) rather than one sample."""
    import tomllib
    from pathlib import Path

    try:
        return "dataset" in tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError):
        return False


def load_joint(path) -> tuple[list[Dataset], tuple | None]:
    """Read a joint fit's description from TOML: `[[dataset]]` tables, each with `data` (a
    measurement file, any format `load_spectra` reads), `model` (a sample model file, the format
    of `load_sample`), optional `name`, `weight`, `format` and `load_spectra`'s convention and
    photometric options; an optional top-level `shared = [...]` (parameter names). Paths are
    relative to the TOML file. Returns the `Dataset`s and `shared` (None when not given). Errors
    name the file and the key (`dataset[1].model`)."""
    from pathlib import Path

    from .._io._load import load_spectra
    from .._io._model_file import load_sample, read_toml, tables

    path = Path(path)
    doc = read_toml(path)
    unknown = set(doc) - {"dataset", "shared", "title"}
    if unknown:
        raise ValueError(f"{path}: unknown top-level keys {sorted(unknown)} (known: dataset, shared, title)")
    entries = doc.get("dataset")
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: no [[dataset]] tables")
    shared = doc.get("shared")
    if shared is not None and not (isinstance(shared, list) and all(isinstance(s, str) for s in shared)):
        raise ValueError(f"{path}: shared must be a list of parameter names, got {shared!r}")
    out = []
    for where, entry in tables(entries, path, "dataset", _DATASET_KEYS):
        for key in ("data", "model"):
            if not isinstance(entry.get(key), str):
                raise ValueError(f"{where}.{key}: give the {'measurement' if key == 'data' else 'sample model'} file's path")
        opts = {k: entry[k] for k in _DATASET_KEYS[4:] if k in entry}
        try:
            spectra = load_spectra(path.parent / entry["data"], **opts)
            sample = load_sample(path.parent / entry["model"])
            out.append(Dataset(sample, spectra, float(entry.get("weight", 1.0)), entry.get("name")))
        except (ValueError, TypeError) as err:
            raise ValueError(f"{where}: {err}") from None
    return out, (None if shared is None else tuple(shared))
