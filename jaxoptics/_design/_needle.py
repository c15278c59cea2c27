"""Needle synthesis (Tikhonravov and Trubetskov): where inserting a thin layer of a candidate
material lowers the merit fastest, found for every depth and material in one gradient pass.

A layer of zero thickness leaves the stack unchanged, so the derivative of `MF^2` with respect
to the thickness of a zero-thickness layer of material `c` inserted at depth `z` is the needle
function `P(z, c)`. The design is cut at every sampled depth (spacing `NEEDLE_SPACING` times the
shortest target wavelength, at least three depths inside each layer, and every interface); at
each cut one zero-thickness layer per candidate material is inserted; one reverse-mode pass of
`MF^2` through that stack gives `P` at every cut and material. A needle of the same material as
the layer around it (or, at an interface, as a layer beside it) only thickens that layer, which
refinement already does: those are not candidates.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._layers import Slots
from ._refine import Problem, run

# depth between sampled needle positions, as a fraction of the shortest target wavelength
# (OpenFilters' default spacing; Larouche and Martinu, Appl. Opt. 47, C219 (2008))
NEEDLE_SPACING = 0.02
_MIN_PER_LAYER = 3


def positions(s: Slots, spacing: float) -> np.ndarray:
    """Sampled depths (nm from the top of the stack): every interface (the top and the
    substrate's surface included) and points inside each layer at most `spacing` apart, at
    least `_MIN_PER_LAYER` per layer."""
    d = s.d[:s.used]
    edges = np.concatenate([[0.0], np.cumsum(d)])
    out = [edges]
    for j, t in enumerate(d):
        k = max(_MIN_PER_LAYER, int(np.ceil(t / spacing)) - 1)
        out.append(edges[j] + t * np.arange(1, k + 1) / (k + 1))
    return np.unique(np.concatenate(out))


def expanded(s: Slots, depths: np.ndarray, candidates: list[int], size: int):
    """The design cut at `depths` with one zero-thickness layer of each candidate at each cut:
    `(ids, d)` padded to `size` slots, and `(where, ok)`: `(len(depths), C)` slot index of each
    needle and whether it is a candidate (module docstring)."""
    d = s.d[:s.used]
    ids_l = s.ids[:s.used]
    edges = np.concatenate([[0.0], np.cumsum(d)])
    rows_id, rows_d = [], []
    where = np.zeros((depths.size, len(candidates)), np.int64)
    ok = np.ones((depths.size, len(candidates)), bool)
    k = 0  # next depth
    for j in range(s.used + 1):  # layer j, then (j == used) the substrate's surface
        top = edges[j]
        bottom = edges[j + 1] if j < s.used else top
        cut = top
        while k < depths.size and depths[k] <= bottom + 1e-9 and (j < s.used or depths[k] <= top + 1e-9):
            z = depths[k]
            if j < s.used and z > cut:
                rows_id.append(ids_l[j])
                rows_d.append(z - cut)
                cut = z
            at_top = abs(z - top) <= 1e-9
            at_bottom = abs(z - bottom) <= 1e-9 and j < s.used
            if at_bottom:  # an interface below layer j: sampled with layer j + 1's top
                break
            around = {int(ids_l[j])} if j < s.used else set()
            if at_top and j > 0:
                around.add(int(ids_l[j - 1]))
            if at_top and j == s.used:
                around = {int(ids_l[j - 1])} if j > 0 else set()
            for c_i, c in enumerate(candidates):
                where[k, c_i] = len(rows_id)
                ok[k, c_i] = c not in around
                rows_id.append(c)
                rows_d.append(0.0)
            k += 1
        if j < s.used and bottom > cut:
            rows_id.append(ids_l[j])
            rows_d.append(bottom - cut)
    if len(rows_id) > size:
        raise ValueError(f"{len(rows_id)} > {size}")
    pad = size - len(rows_id)
    return (np.array(rows_id + [0] * pad, np.int32), np.array(rows_d + [0.0] * pad)), (where, ok)


def padded_size(n: int) -> int:
    """Slots of the expanded stack: `n` rounded up to a multiple of 64 (a program per size)."""
    return max(64, -(-n // 64) * 64)


def _gradient(problem: Problem, ids, d):
    f = lambda x: jnp.sum(problem.objective(ids, x) ** 2)
    return jax.value_and_grad(f)(d)


def needle_function(problem: Problem, s: Slots, candidates: list[int], spacing: float):
    """`(depths, P, ok, mf2)`: the sampled depths, `P[k, c]` the derivative of `MF^2` per nm of a
    needle of `candidates[c]` at `depths[k]`, where it is a candidate, and the merit squared."""
    z = positions(s, spacing)
    n = s.used + z.size * (1 + len(candidates)) + s.used + 1
    (ids, d), (where, ok) = expanded(s, z, candidates, padded_size(n))
    mf2, g = run(_gradient, problem, jnp.asarray(ids), jnp.asarray(d, problem.dtype))
    return z, np.asarray(g)[where], ok, float(mf2)
