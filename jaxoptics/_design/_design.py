"""`design`: refine a coating's thicknesses to meet `Target`s from many starts at once, and
optionally grow it by needle synthesis; `merit` of a sample; `thickness_errors`, its yield.

The method:

1. **Refinement** (every call): the free thicknesses of the sample are the variables, each within
   its `Free` bounds and `[min_thickness_nm, max_thickness_nm]`. `starts` designs (the sample's
   own values first, then random thicknesses uniform within the bounds; where a layer has no
   upper bound, up to the larger of twice its value and half the longest target wavelength) are
   refined together by Levenberg-Marquardt (optimistix) on the merit's residuals, in one compiled
   call; the design of lowest merit is kept.
2. **Needle synthesis** (`needle=True`): the needle function of every candidate material at every
   sampled depth (`jaxoptics._design._needle`) in one gradient pass; a needle of the best material
   at the best depth (the most negative derivative) is inserted, a quarter of the depth spacing
   thick (with `needles=k`, at the `k` depths where the needle function has its most negative
   local minima, each of the best material there: the deepest inserted first, so that the depths
   above stay where they were sampled); the design is refined with lower bounds of zero; free layers thinner than 0.1 nm are
   removed and neighbours of one material merged; and again, until no needle lowers the merit (a needle derivative below `1e-4 MF^2` per spacing),
   a round lowers it by less than `1e-3` of itself, the next needle would exceed `max_layers`
   slots, or the total physical thickness reaches `max_total_nm`. A last refinement keeps every
   free layer within `[min_thickness_nm, max_thickness_nm]`: layers thinner than
   `min_thickness_nm` are either removed or grown to it, whichever refines to the lower merit
   (a thin layer that the rounds keep may grow useful in a later round, so the limit is applied
   once, at the end). Every round runs the same two
   compiled programs: the design lives in `max_layers` slots, unused ones of zero thickness.
   **Gradual evolution** (`gradual > 0`): where the rounds stall, every free layer is made
   `1 + gradual` times thicker (not refined: that would take it back to where the rounds stalled)
   and needle rounds go on; a second stall before the merit beats the best so far ends the
   synthesis with the best design.
3. **Robust design** (`robust=ThicknessErrors(...)`): the refinements minimize the mean of `MF^2`
   over that set of random thickness errors (the same draws throughout) instead of `MF^2`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from .._films._dispersion import Constant
from .._films._sample import Sample
from . import _errors, _layers, _needle, _refine, _targets
from ._targets import Target

_THINNEST = 0.1  # nm: free layers thinner than this are removed between needle rounds at least
_NEEDLE_T = 0.25  # a new needle's thickness, in needle spacings
_MIN_GAIN = 1e-3  # a round must lower the merit by this fraction of itself
_MIN_SLOPE = 1e-4  # a needle's predicted decrease of MF^2 per spacing, relative to MF^2


@dataclasses.dataclass(frozen=True, eq=False)
class Design:
    """Result of `design`.

    **Fields:** `sample`, the designed `Sample` (every thickness fixed at its designed value);
    `names` and `values`, the layers' thickness parameters (`layer1.thickness_nm`, ...) and their
    values in nm, top layer first; `merit`, the design's merit (`MF`, 1 where every target is met
    to its tolerance on average); `history`, the merit after the refinement of the starts and
    after each needle round; `merits` `(starts,)`, the merit each start refined to; `layers`, the
    number of layers; `materials`, each layer's material."""

    sample: Sample
    names: list
    values: np.ndarray
    merit: float
    history: np.ndarray
    merits: np.ndarray
    layers: int
    materials: list

    def __getitem__(self, name):
        return float(self.values[self.names.index(name)])

    def table(self) -> str:
        rows = [f"{self.layers} layers, total {float(np.sum(self.values)):.1f} nm, merit {self.merit:.4g}"]
        rows += [f"{n:24s} {v:10.3f}  {_label(m)}" for n, v, m in zip(self.names, self.values, self.materials)]
        return "\n".join(rows)


def _label(m) -> str:
    """A material's short name for tables: its `name`, or its index where it is a constant."""
    if getattr(m, "name", None):
        return str(m.name)
    if isinstance(m, Constant):
        return f"n = {m.n:g}" + (f" + {m.k:g}i" if m.k else "")
    return type(m).__name__


def _dtype():
    return np.float64 if jax.config.read("jax_enable_x64") else np.float32


def _check_int(v, what, low):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
        raise ValueError(f"design: {what} must be an int >= {low}, got {v!r}")
    return int(v)


def _starts(s: _layers.Slots, starts, wl_max, rng) -> np.ndarray:
    """`(B, S)` start thicknesses (module docstring, step 1)."""
    free = np.flatnonzero(s.free)
    if isinstance(starts, (int, np.integer)) and not isinstance(starts, bool):
        B = _check_int(starts, "starts", 1)
        D = np.repeat(s.d[None], B, axis=0)
        hi = np.where(np.isfinite(s.hi), s.hi, np.maximum(2 * s.d, wl_max / 2))
        D[1:, free] = rng.uniform(s.lo[free], hi[free], (B - 1, free.size))
        return D
    given = np.asarray(starts, dtype=float)
    if given.ndim != 2 or given.shape[1] != free.size:
        raise ValueError(f"design: starts as an array must be (starts, {free.size}) thicknesses of the free "
                         f"layers, got shape {given.shape}")
    if not np.all(np.isfinite(given) & (given >= s.lo[free]) & (given <= s.hi[free])):
        raise ValueError("design: every start thickness must be finite and within its layer's bounds")
    D = np.repeat(s.d[None], given.shape[0], axis=0)
    D[:, free] = given
    return D


def design(sample: Sample, targets: Sequence[Target], *, starts: Any = 1, needle: bool = False, materials: Sequence[Any] | None = None,
           max_layers: int | None = None, min_thickness_nm: float = 0.0, max_thickness_nm: float | None = None,
           max_total_nm: float | None = None, max_rounds: int = 40, max_steps: int = 200,
           robust: _errors.ThicknessErrors | None = None, gradual: float = 0.0, needles: int = 1, seed: int = 0,
           progress: bool = False) -> Design:
    """Design the free thicknesses of `sample` to meet `targets` (see the module docstring for the
    method).

    **Arguments:**

    - `sample`: a `Sample`; its free (`Free`) thicknesses are designed, its fixed ones kept; every
      index parameter must be fixed.
    - `targets`: a list of `Target`.
    - `starts`: the number of starts refined together (the sample's values and random ones), or a
      `(starts, free layers)` array of start thicknesses.
    - `needle`, `materials`: needle synthesis with these candidate materials (`Dispersion`s,
      numbers, or built-in names such as `"SiO2"`, `"Si3N4"`, `"Al2O3"`); with `needle=False`,
      `materials` is ignored.
    - `max_layers`: the layer budget (default: the sample's layers; with `needle`, 40).
    - `min_thickness_nm`, `max_thickness_nm`: bounds of every designable layer (inserted ones too).
    - `max_total_nm`: needle synthesis inserts no needle once the total thickness reaches it.
    - `max_rounds`, `max_steps`: needle rounds; Levenberg-Marquardt steps per refinement.
    - `robust`: `ThicknessErrors` whose mean merit is minimized instead of the merit.
    - `gradual`: gradual evolution: when needle rounds stall, the free layers are made this fraction
      thicker and needle rounds go on (0, the default, stops at the first stall).
    - `needles`: needles inserted per round, at the most negative local minima of the needle
      function over depth (fewer where fewer minima lower the merit or the layer budget is short).
    - `seed`: of the random starts. `progress`: print a line per needle round.

    **Returns:** a `Design`.
    """
    lay, arrays = _targets.layout(targets)
    dtype = _dtype()
    if min_thickness_nm < 0 or not math.isfinite(min_thickness_nm):
        raise ValueError(f"design: min_thickness_nm must be finite and >= 0, got {min_thickness_nm}")
    if max_thickness_nm is not None and not max_thickness_nm > min_thickness_nm:
        raise ValueError(f"design: max_thickness_nm={max_thickness_nm} must exceed min_thickness_nm={min_thickness_nm}")
    cands = [_layers.as_material(m, "design materials") for m in (materials or [])]
    if needle and not cands:
        raise ValueError("design: needle=True needs candidate materials (materials=[...])")
    n_layers = len(sample.layers) if isinstance(sample, Sample) else 0
    budget = max_layers if max_layers is not None else (max(40, n_layers + 2) if needle else None)
    if budget is not None:
        _check_int(budget, "max_layers", 1)
    max_steps = _check_int(max_steps, "max_steps", 1)
    needles = _check_int(needles, "needles", 1)
    if isinstance(gradual, bool) or not isinstance(gradual, (int, float)) or not 0 <= gradual < 10:
        raise ValueError(f"design: gradual must be a number in [0, 10), got {gradual!r}")
    # during needle rounds, layers may thin to zero (and are removed); the last refinement applies min_thickness_nm
    s = _layers.from_sample(sample, cands if needle else [], budget, 0.0 if needle else min_thickness_nm, max_thickness_nm)
    if not s.free.any() and not needle:
        raise ValueError("design: the sample has no free thickness to design (make one Free)")
    wl_all = np.concatenate([arrays["wl_plain"], arrays["wl_disp"]])
    errors = None if robust is None else _errors.robust_draws(robust, s.size, dtype)
    problem = _refine.make_problem(s, lay, arrays, dtype, errors)
    rng = np.random.default_rng(seed)
    D, mf2, _ = _refine.refine(problem, s, _starts(s, starts, float(wl_all.max()), rng), max_steps)
    merits = np.sqrt(mf2)
    best = int(np.nanargmin(mf2))
    s = s.replace(d=D[best])
    history = [float(merits[best])]
    if needle:
        cand_ids = [_layers.Slots.index(s, c) for c in cands]
        s, history = _synthesize(problem, s, cand_ids, history, float(wl_all.min()) * _needle.NEEDLE_SPACING,
                                 _THINNEST, max_total_nm, max_rounds, max_steps, progress, gradual, needles)
        s = _within_limits(problem, s, min_thickness_nm, max_thickness_nm, max_steps)
        history.append(math.sqrt(_refine.merit2(problem, s)))
    return _result(s, sample, history, merits)


def _within_limits(problem, s, min_t, max_t, max_steps):
    """The last refinement (module docstring, step 2), every free layer within `[min_t, max_t]`.
    Free layers thinner than `min_t` are either removed or grown to it, whichever refines to the
    lower merit."""
    def bounded(x):
        lo = np.where(x.free, np.maximum(x.lo, min_t), x.lo)
        hi = np.where(x.free, x.hi if max_t is None else np.minimum(x.hi, max_t), x.hi)
        x = x.replace(lo=lo, hi=np.maximum(hi, lo))
        D, m2, _ = _refine.refine(problem, x, np.clip(x.d, x.lo, x.hi)[None], max_steps)
        return x.replace(d=D[0]), float(m2[0])

    keep, m_keep = bounded(s)
    thin = s.free[:s.used] & (s.d[:s.used] < min_t)
    if not thin.any():
        return keep
    drop, m_drop = bounded(_layers.cleanup(s, min_t))
    return drop if m_drop < m_keep else keep


def needle_sites(P, ok, count, threshold):
    """`[(depth index, candidate index)]` of up to `count` needles, most negative first: the depths
    where the best candidate's needle function `min_c P[k, c]` (over candidates allowed there,
    `ok`) is a local minimum along depth (not above either neighbour) and below `threshold`, each
    with that best candidate. The first is the global minimum of `P` (the single-needle choice)."""
    P = np.where(ok, P, np.inf)
    best = np.min(P, axis=1)
    cand = np.argmin(P, axis=1)
    padded = np.concatenate([[np.inf], best, [np.inf]])
    local = (best <= padded[:-2]) & (best <= padded[2:]) & (best < threshold)
    ks = np.flatnonzero(local)
    ks = ks[np.argsort(best[ks], kind="stable")][:count]
    return [(int(k), int(cand[k])) for k in ks]


def _needle_step(problem, s, cand_ids, spacing, thinnest, max_steps, needles):
    """One needle round: the best needle(s) inserted (`needle_sites`, as many as `needles` and
    the free slots allow) and the design refined and cleaned up, with its merit; None where no
    needle lowers the merit."""
    z, P, ok, mf2 = _needle.needle_function(problem, s, cand_ids, spacing)
    room = (s.size - s.used) // 2  # each needle takes two slots (it splits a layer); `_synthesize` leaves room for one
    sites = needle_sites(P, ok, min(needles, room), -_MIN_SLOPE * mf2 / spacing)
    if not sites:
        return None
    trial = s
    for k, c in sorted(sites, key=lambda kc: -z[kc[0]]):  # deepest first: the depths above are unchanged
        trial = _layers.insert(trial, float(z[k]), cand_ids[c], _NEEDLE_T * spacing, 0.0, math.inf)
    D, m2, _ = _refine.refine(problem, trial, trial.d[None], max_steps)
    trial = _layers.cleanup(trial.replace(d=D[0]), thinnest)
    D, m2, _ = _refine.refine(problem, trial, trial.d[None], max_steps)
    return trial.replace(d=D[0]), float(np.sqrt(m2[0]))


def _grow(problem, s, fraction):
    """Gradual evolution's step: every free layer made `1 + fraction` times thicker (within its
    upper bound), not refined (a refinement would take it back to the optimum the rounds stalled
    at): the next needle round starts from a thicker design."""
    d = np.where(s.free, np.minimum(s.d * (1 + fraction), s.hi), s.d)
    grown = s.replace(d=d)
    return grown, math.sqrt(_refine.merit2(problem, grown))


def _synthesize(problem, s, cand_ids, history, spacing, thinnest, max_total, max_rounds, max_steps, progress, gradual,
                needles):
    """The needle rounds (module docstring, step 2), with gradual evolution where `gradual > 0`:
    the best slots found and the merit history."""
    best, best_mf = s, history[-1]
    mf, grown = best_mf, False
    for rnd in range(max_rounds):
        room = s.used + 2 <= s.size and (max_total is None or float(np.sum(s.d)) < max_total)
        step = _needle_step(problem, s, cand_ids, spacing, thinnest, max_steps, needles) if room else None
        if step is not None and step[1] < mf * (1 - _MIN_GAIN):
            s, mf = step
            history.append(mf)
            if progress:
                print(f"needle round {rnd + 1}: {s.used} layers, merit {mf:.4g}", flush=True)
            if mf < best_mf * (1 - _MIN_GAIN):  # a new best: another stall may grow the design again
                best, best_mf, grown = s, mf, False
            continue
        # stalled: stop, or (gradual evolution) grow the design once and try needles again
        if gradual <= 0 or grown or not room:
            break
        s, mf = _grow(problem, s, gradual)
        grown = True
        history.append(mf)
        if progress:
            print(f"round {rnd + 1}, thickness grown: {s.used} layers, {float(np.sum(s.d)):.0f} nm, merit {mf:.4g}", flush=True)
    return best, history


def _result(s, sample, history, merits) -> Design:
    names = [f"layer{j + 1}.thickness_nm" for j in range(s.used)]
    return Design(s.to_sample(), names, np.asarray(s.d[:s.used], float), history[-1], np.asarray(history),
                  np.asarray(merits), s.used, [s.materials[int(i)] for i in s.ids[:s.used]])


def _evaluated(sample, targets):
    """The `Problem` of `targets` and the slots of `sample` (or a `Design`'s sample), as it is."""
    if isinstance(sample, Design):
        sample = sample.sample
    if not isinstance(sample, Sample):
        raise ValueError(f"expected a Sample or a Design, got {type(sample).__name__}")
    lay, arrays = _targets.layout(targets)
    s = _layers.from_sample(sample, [], None, 0.0, None)
    return _refine.make_problem(s, lay, arrays, _dtype()), s


def merit(sample: Sample | Design, targets: Sequence[Target]) -> float:
    """The merit `MF` of `sample` (its `Free` parameters at their values) for `targets`."""
    return math.sqrt(_refine.merit2(*_evaluated(sample, targets)))


def target_values(sample: Sample | Design, targets: Sequence[Target]) -> list[np.ndarray]:
    """What `sample` (or a `Design`'s sample) gives for each target: one array per target, at its
    wavelengths, in its quantity's unit (for plots and reports)."""
    problem, s = _evaluated(sample, targets)
    q = np.asarray(_refine.run(_refine.values_program, problem, jax.numpy.asarray(s.ids), jax.numpy.asarray(s.d, problem.dtype)))
    return [q[a:b] for a, b in _targets.spans(problem.lay)]


def thickness_errors(sample: Sample | Design, targets: Sequence[Target], *, errors: _errors.ThicknessErrors | None = None,
                     threshold: float = 1.0) -> _errors.ErrorAnalysis:
    """The merit of `sample` (or a `Design`'s sample) under random thickness errors (default
    `ThicknessErrors()`: 1 % relative, normal, 100 draws): every drawn design evaluated in one
    compiled call. **Returns:** an `ErrorAnalysis`: the merits, the yield (fraction of draws
    with merit at most `threshold`) and each layer's sensitivity."""
    errors = errors or _errors.ThicknessErrors()
    problem, s = _evaluated(sample, targets)
    m2 = lambda ids, D: _refine.run(_refine.merit2_program, problem, ids, D, starts=D.shape[0])
    return _errors.analyse(m2, jax.numpy.asarray(s.ids), s.d.astype(problem.dtype), s.used, errors, threshold)
