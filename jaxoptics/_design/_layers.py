"""A design as the optimizers see it: a fixed budget of layer slots, each holding an index into
a list of materials and a thickness, unused slots (at the bottom) of zero thickness.

A layer of zero thickness is an exact no-op of the stack kernel (its characteristic matrix is
the identity), so every design of up to `slots` layers is the same compiled program: needle
synthesis inserts and removes layers without recompiling. The materials are `Dispersion`
models evaluated once per wavelength; the slots gather their indices.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from .._films._dispersion import Cauchy, Dispersion, Free, Sellmeier, parameter_leaves
from .._films._graded import Graded
from .._films._materials import MATERIALS
from .._films._rii import builtin_materials, material
from .._films._sample import Layer, Sample


def as_material(m, what) -> Dispersion:
    """A candidate material: a `Dispersion`, a built-in name (`builtin_materials()` or a key of
    `MATERIALS`), or a number `n` / `n + ik`."""
    if isinstance(m, str):
        if m in builtin_materials():
            return material(m)
        if m in MATERIALS:
            c = MATERIALS[m]
            if c.model == "sellmeier":
                return Sellmeier(B=tuple(c.B), C=tuple(c.C))
            return Cauchy(*c.B)
        raise ValueError(f"{what}: unknown material {m!r}; built in: {', '.join(builtin_materials() + sorted(MATERIALS))}")
    return Layer(m, 0.0).material


def _position(materials, m) -> int | None:
    """Where `m` (or a material equal to it) stands in `materials`, or None."""
    return next((i for i, x in enumerate(materials) if x is m or x == m), None)


@dataclasses.dataclass(frozen=True, eq=False)
class Slots:
    """`ids[j]` (index into `materials`) and `d[j]` (nm) of slot `j`, top first; `free[j]` whether
    the optimizer may change its thickness, within `[lo[j], hi[j]]`; `used` the number of slots in
    use (the rest have zero thickness and are not free)."""

    materials: tuple
    ambient: Dispersion
    substrate: Dispersion
    ids: np.ndarray
    d: np.ndarray
    free: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    used: int

    @property
    def size(self) -> int:
        return self.ids.size

    def index(self, m) -> int:
        """The position of material `m` in `materials`."""
        i = _position(self.materials, m)
        if i is None:
            raise ValueError(f"{m!r} is not among the design's materials")
        return i

    def replace(self, **kw) -> Slots:
        return dataclasses.replace(self, **kw)

    def n_table(self, wavelength_nm):
        """`(P, L)` indices of the whole stack (ambient, slots, substrate) at `(P,)` wavelengths."""
        lam = wavelength_nm / 1000
        sub = jnp.asarray(self.substrate.nk(lam))
        table = jnp.stack([jnp.asarray(m.nk(lam)) for m in self.materials]) if self.materials else \
            jnp.zeros((1,) + sub.shape, sub.dtype)  # (M, P)
        sub = sub.astype(table.dtype)
        amb = jnp.real(jnp.asarray(self.ambient.nk(lam))).astype(table.dtype)
        return lambda ids: jnp.concatenate([amb[:, None], table[ids].T, sub[:, None]], axis=1)

    def to_sample(self, names=None) -> Sample:
        """The design as a `Sample` whose thicknesses are all fixed at their values."""
        layers = [Layer(self.materials[int(self.ids[j])], float(self.d[j]), name=None if names is None else names[j])
                  for j in range(self.used)]
        return Sample(tuple(layers), self.substrate, self.ambient)


def from_sample(sample: Sample, candidates, slots: int | None, min_t: float, max_t: float | None) -> Slots:
    """The slots of `sample` (its free thicknesses are designable, bounded by their own bounds and
    by `[min_t, max_t]`), with `candidates` appended to its layers' materials, in `slots` slots
    (default: as many as the sample has layers)."""
    if not isinstance(sample, Sample):
        raise ValueError(f"design: the sample must be a jaxoptics.Sample, got {type(sample).__name__}")
    if sample.instrument is not None:
        raise ValueError("design: the sample has an Instrument; a design is computed for the ideal coating")
    mats: list = []

    def index_of(m):
        i = _position(mats, m)
        if i is None:
            mats.append(m)
            i = len(mats) - 1
        return i

    for owner, model in sample._slots():
        free = [p for p, leaf in parameter_leaves(model) if isinstance(leaf, Free)]
        if free:
            raise ValueError(f"design: {owner}.{free[0]} is Free; design varies thicknesses, so every index "
                             "parameter must be fixed (fit it first with fit_stack)")
    ids, d, fr, lo, hi = [], [], [], [], []
    for nm, layer in zip(sample.layer_names, sample.layers):
        if layer.incoherent or isinstance(layer.material, Graded):
            raise ValueError(f"design: layer {nm} is {'incoherent' if layer.incoherent else 'graded'}; "
                             "designs are coherent stacks of homogeneous layers")
        ids.append(index_of(layer.material))
        t = layer.thickness_nm
        if isinstance(t, Free):
            a, b = max(t.lower, min_t), min(t.upper, math.inf if max_t is None else max_t)
            if not a < b:
                raise ValueError(f"design: layer {nm}'s bounds [{t.lower}, {t.upper}] leave nothing within "
                                 f"min_thickness_nm={min_t}, max_thickness_nm={max_t}")
            d.append(min(max(t.value, a), b))
            fr.append(True)
            lo.append(a)
            hi.append(b)
        else:
            d.append(float(t))
            fr.append(False)
            lo.append(float(t))
            hi.append(float(t))
    for c in candidates:
        index_of(c)
    n = len(ids)
    size = n if slots is None else slots
    if size < n:
        raise ValueError(f"design: max_layers={slots} is fewer than the sample's {n} layers")
    pad = size - n
    return Slots(tuple(mats), sample.ambient, sample.substrate,
                 np.array(ids + [0] * pad, np.int32), np.array(d + [0.0] * pad), np.array(fr + [False] * pad),
                 np.array(lo + [0.0] * pad), np.array(hi + [0.0] * pad), n)


def insert(s: Slots, depth_nm: float, material_id: int, thickness: float, lo: float, hi: float) -> Slots:
    """`s` with a layer of `material_id` and `thickness` inserted at `depth_nm` below the top of
    the stack (splitting the layer there in two, or between two layers). Needs two free slots."""
    ids, d, fr, lo_, hi_ = (list(a[:s.used]) for a in (s.ids, s.d, s.free, s.lo, s.hi))
    edges = np.concatenate([[0.0], np.cumsum(d)])
    j = int(np.searchsorted(edges, depth_nm, side="right")) - 1  # the layer that holds depth_nm
    new = (material_id, thickness, True, lo, hi)
    if j >= len(d) or depth_nm - edges[j] <= 1e-9 or edges[j + 1] - depth_nm <= 1e-9:
        at = len(d) if j >= len(d) else (j if depth_nm - edges[j] <= 1e-9 else j + 1)
        rows = list(zip(ids, d, fr, lo_, hi_))
        rows.insert(at, new)
    else:
        rows = list(zip(ids, d, fr, lo_, hi_))
        top = rows[j][:1] + (depth_nm - edges[j],) + rows[j][2:]
        bottom = rows[j][:1] + (edges[j + 1] - depth_nm,) + rows[j][2:]
        rows[j:j + 1] = [top, new, bottom]
    return _from_rows(s, rows)


def _from_rows(s: Slots, rows) -> Slots:
    if len(rows) > s.size:
        raise ValueError(f"{len(rows)} layers do not fit in {s.size} slots")
    pad = [(0, 0.0, False, 0.0, 0.0)] * (s.size - len(rows))
    cols = list(zip(*(rows + pad)))
    return s.replace(ids=np.array(cols[0], np.int32), d=np.array(cols[1], float), free=np.array(cols[2], bool),
                     lo=np.array(cols[3], float), hi=np.array(cols[4], float), used=len(rows))


def cleanup(s: Slots, thinnest: float) -> Slots:
    """`s` without its free layers thinner than `thinnest` nm, and with neighbouring free layers
    of the same material merged (their thicknesses added, within the upper bound of the first)."""
    rows = [r for r in zip(s.ids[:s.used], s.d[:s.used], s.free[:s.used], s.lo[:s.used], s.hi[:s.used])
            if not (r[2] and r[1] < thinnest)]
    merged: list = []
    for r in rows:
        if merged and merged[-1][0] == r[0] and merged[-1][2] and r[2]:
            m = merged[-1]
            merged[-1] = (m[0], min(m[1] + r[1], m[4]), True, m[3], m[4])
        else:
            merged.append(r)
    return _from_rows(s, merged)
