"""Thickness errors of manufacture: Monte-Carlo draws, the yield of a design, each layer's
sensitivity, and the draws a robust design averages its merit over.

The error model is OpenFilters' pre-production one: each layer's thickness is off by a random
amount, relative to its thickness (`kind="relative"`, default 1 %) or absolute (`"absolute"`,
default 1 nm), normally (`size` the standard deviation) or uniformly (`size` the half-width)
distributed, independently per layer and draw. A thickness that an error would make negative
is taken as zero.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class ThicknessErrors:
    """Random thickness errors: `kind` `"relative"` (`size` a fraction of each thickness, default
    0.01) or `"absolute"` (`size` in nm, default 1.0); `distribution` `"normal"` (`size` the
    standard deviation) or `"uniform"` (`size` the half-width); `draws` designs drawn; `seed` of
    the draws (the same seed gives the same draws)."""

    kind: str = "relative"
    size: float | None = None
    distribution: str = "normal"
    draws: int = 100
    seed: int = 0

    def __post_init__(self):
        if self.kind not in ("relative", "absolute"):
            raise ValueError(f"ThicknessErrors kind {self.kind!r}: 'relative' or 'absolute'")
        if self.distribution not in ("normal", "uniform"):
            raise ValueError(f"ThicknessErrors distribution {self.distribution!r}: 'normal' or 'uniform'")
        if self.size is None:
            object.__setattr__(self, "size", 0.01 if self.kind == "relative" else 1.0)
        if not (isinstance(self.size, (int, float)) and math.isfinite(self.size) and self.size > 0):
            raise ValueError(f"ThicknessErrors size must be a number > 0, got {self.size!r}")
        if isinstance(self.draws, bool) or not isinstance(self.draws, int) or self.draws < 1:
            raise ValueError(f"ThicknessErrors draws must be an int >= 1, got {self.draws!r}")

    def sample(self, layers: int, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
        """`(relative, absolute)` errors, each `(draws, layers)`: `d * (1 + relative) + absolute`."""
        rng = np.random.default_rng(self.seed)
        shape = (self.draws, layers)
        e = rng.standard_normal(shape) if self.distribution == "normal" else rng.uniform(-1.0, 1.0, shape)
        e = (float(self.size or 0.0) * e).astype(dtype)
        z = np.zeros(shape, dtype)
        return (e, z) if self.kind == "relative" else (z, e)


@dataclasses.dataclass(frozen=True, eq=False)
class ErrorAnalysis:
    """What thickness errors do to a design (`jaxoptics.thickness_errors`).

    **Fields:** `merit`, the design's own merit; `merits` `(draws,)`, the merit of each drawn
    design; `yield_fraction`, the fraction of draws with merit at most `threshold`; `threshold`;
    `sensitivity` `(layers,)`, per layer the root-mean-square increase of the merit over the same
    draws when only that layer is off; `expected_merit`, `sqrt(mean(merits^2))`."""

    merit: float
    merits: np.ndarray
    yield_fraction: float
    threshold: float
    sensitivity: np.ndarray
    expected_merit: float

    def table(self, names=None) -> str:
        names = names or [f"layer{j + 1}" for j in range(self.sensitivity.size)]
        rows = [f"merit {self.merit:.4g}; under errors: expected {self.expected_merit:.4g}, median "
                f"{np.median(self.merits):.4g}, yield (merit <= {self.threshold:g}) {100 * self.yield_fraction:.1f} %",
                "layer  RMS merit increase from its errors alone"]
        rows += [f"{n}  {s:.4g}" for n, s in zip(names, self.sensitivity)]
        return "\n".join(rows)


def analyse(merit2, ids, d, used, errors: ThicknessErrors, threshold: float) -> ErrorAnalysis:
    """Evaluate `merit2(ids, D)` (`(B, S)` thicknesses to `(B,)` merit squared) on the drawn
    designs, all at once, and on the designs where one layer at a time is off."""
    S = d.size
    rel, ab = errors.sample(used, d.dtype)
    pad = lambda e: np.concatenate([e, np.zeros((e.shape[0], S - used), e.dtype)], axis=1)
    rel, ab = pad(rel), pad(ab)
    D = np.maximum(d * (1 + rel) + ab, 0)
    # one layer off at a time: (used * draws, S)
    eye = np.eye(S, dtype=bool)[:used]
    D1 = np.where(eye[:, None, :], D[None], d[None, None]).reshape(-1, S)
    allD = np.concatenate([d[None], D, D1])
    m = np.sqrt(np.asarray(merit2(ids, jnp.asarray(allD))))
    m0, md, m1 = float(m[0]), m[1:1 + errors.draws], m[1 + errors.draws:].reshape(used, errors.draws)
    sens = np.sqrt(np.mean((m1 - m0) ** 2, axis=1))
    return ErrorAnalysis(m0, md, float(np.mean(md <= threshold)), float(threshold), sens, float(np.sqrt(np.mean(md ** 2))))


def robust_draws(errors: ThicknessErrors, slots: int, dtype) -> tuple:
    """The draws as JAX arrays `(draws, slots)` for `Problem.errors`."""
    rel, ab = errors.sample(slots, dtype)
    return jax.device_put(rel), jax.device_put(ab)
