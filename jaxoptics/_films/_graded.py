"""Graded layers: a film whose index or composition varies through its thickness (`Graded`).

The layer is sliced into `slices` sublayers of equal thickness; sublayer `j` (from the top, the
light side) takes the material at the depth of its middle, `z_j = (j + 1/2) / slices` of the
thickness. At depth `z` the profile's weight is `w(z)`, from 0 at the top to 1 at the bottom:
`z ** exponent` (linear for `exponent = 1`), or a tabulated `profile` of weights at equally spaced
depths `0, 1/m, ..., 1`, interpolated linearly. Then:

- index grading, `Graded(top, bottom)`: `N(z) = N_top + w(z) (N_bottom - N_top)`, the complex
  index (`n` and `k`) varying between the two materials';
- composition grading, `Graded(EMA(host, inclusion, f_top), fraction_bottom=f_bottom)`: the
  effective medium with the inclusion's fraction `f(z) = f_top + w(z) (f_bottom - f_top)`.

A staircase of `slices` steps converges to the continuous profile at second order: each doubling
of the slices cuts the error in R fourfold. For a 400 nm film whose index rises linearly by 0.3
(1.7 to 2.0 + 0.01i, on silicon, at 550 nm), the default 20 slices give R_s and R_p within 6e-4 of
the wave equation integrated through the continuous profile, 80 slices within 4e-5 (tests, at
normal incidence and at 65 degrees); the error grows with the index step and the film's optical
thickness, so steep or thick gradings want more slices. Every weight, fraction and exponent is
differentiable; so is the thickness, which each slice takes a `1/slices` share of.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._dispersion import Dispersion, Free
from ._ema import EMA, _as_material


@dataclasses.dataclass(frozen=True)
class Graded(Dispersion):
    """A material that varies through the layer's depth, from `top` (the light side) to `bottom`
    (see the module docstring for the profile and the slicing).

    **Fields:**

    - `top`, `bottom`: the materials at the top and the bottom (index grading), any models or
      numbers `n + ik`; or `top` an `EMA` and `fraction_bottom` its inclusion's fraction at the
      bottom (composition grading; `bottom` is then left out).
    - `fraction_bottom`: for composition grading, a number in `[0, 1]` or `Free`.
    - `exponent`: the profile `w(z) = z ** exponent` (`> 0`; 1 is linear), a number or `Free`
      (bounds within `[0, inf)`).
    - `profile`: instead of the power law, the weights `w` at equally spaced depths from the top
      (first) to the bottom (last), numbers or `Free` (at least two).
    - `slices`: the number of sublayers (default 20).

    Parameters are named `<layer>.top.A`, `<layer>.bottom.n`, `<layer>.top.fraction`,
    `<layer>.fraction_bottom`, `<layer>.exponent`, `<layer>.profile[2]`. `nk` gives the index at
    mid-depth (what the thickness search of `fit_stack` uses for the fringe period); the stack
    takes `nk_slices`. A graded layer cannot be incoherent.
    """

    top: Any = 1.0
    bottom: Any = None
    fraction_bottom: Any = None
    exponent: Any = 1.0
    profile: Any = None
    slices: int = 20
    _params = ("top", "bottom", "fraction_bottom", "exponent", "profile")

    def __post_init__(self):
        composition = self.fraction_bottom is not None
        object.__setattr__(self, "top", _as_material(self.top, "Graded top"))
        if composition:
            if self.bottom is not None:
                raise ValueError("Graded: give either bottom (index grading) or fraction_bottom with an EMA top "
                                 "(composition grading), not both")
            if not isinstance(self.top, EMA):
                raise ValueError(f"Graded fraction_bottom: composition grading needs an EMA top, got {type(self.top).__name__}")
            _check_fraction(self.fraction_bottom, "Graded fraction_bottom")
        else:
            if self.bottom is None:
                raise ValueError("Graded: give bottom (the material at the bottom) or, with an EMA top, fraction_bottom")
            object.__setattr__(self, "bottom", _as_material(self.bottom, "Graded bottom"))
        if isinstance(self.slices, bool) or not isinstance(self.slices, (int, np.integer)) or self.slices < 1:
            raise ValueError(f"Graded slices={self.slices!r}: a whole number >= 1")
        object.__setattr__(self, "slices", int(self.slices))
        if self.profile is not None:
            prof = tuple(self.profile)
            if len(prof) < 2:
                raise ValueError(f"Graded profile: at least two weights (top and bottom), got {len(prof)}")
            for i, v in enumerate(prof):
                if not _traced(v) and not isinstance(v, Free) and (isinstance(v, bool) or not isinstance(v, (int, float, np.number))
                                                                    or not np.isfinite(v)):
                    raise ValueError(f"Graded profile[{i}]: a finite number or Free, got {v!r}")
            object.__setattr__(self, "profile", prof)
        e = self.exponent
        if not _traced(e):
            ok = (e.value > 0 and e.lower >= 0) if isinstance(e, Free) else \
                (not isinstance(e, bool) and isinstance(e, (int, float, np.number)) and e > 0)
            if not ok:
                raise ValueError(f"Graded exponent={e!r}: must be > 0 (a Free one's lower bound >= 0)")

    @property
    def range_um(self):
        """The constituents' common wavelength range (micrometres), or None."""
        parts = [self.top] + ([self.bottom] if self.bottom is not None else [])
        rs = [r for r in (getattr(m, "range_um", None) for m in parts) if r is not None]
        return (max(r[0] for r in rs), min(r[1] for r in rs)) if rs else None

    def weights(self, z):
        """The profile's weight `w` at relative depths `z` (NumPy or JAX array in `[0, 1]`)."""
        z = jnp.asarray(z)
        if self.profile is None:
            return z ** jnp.asarray(self.exponent, z.dtype)
        w = jnp.stack([jnp.asarray(v, z.dtype) for v in self.profile])
        return jnp.interp(z, jnp.linspace(0.0, 1.0, len(self.profile), dtype=z.dtype), w)

    def depths(self):
        """The relative depths of the slices' middles, top first."""
        return (np.arange(self.slices) + 0.5) / self.slices

    def _at(self, wavelength_um, w):
        """The index at weights `w` (the shape of the wavelengths)."""
        if self.fraction_bottom is None:
            N0, N1 = self.top.nk(wavelength_um), self.bottom.nk(wavelength_um)
            N0 = jnp.asarray(N0)
            N1 = jnp.asarray(N1).astype(N0.dtype)
            return N0 + w.astype(N0.dtype) * (N1 - N0)
        f0 = self.top.fraction
        f = f0 + w * (jnp.asarray(self.fraction_bottom, w.dtype) - jnp.asarray(f0, w.dtype))
        return dataclasses.replace(self.top, fraction=f).nk(wavelength_um)

    def nk_slices(self, wavelength_um):
        """`(..., slices)` indices of the sublayers (top first) at wavelengths `(...)`."""
        lam = jnp.asarray(wavelength_um)
        w = self.weights(jnp.asarray(self.depths(), _real_dtype(lam)))
        shape = lam.shape + (self.slices,)
        return self._at(jnp.broadcast_to(lam[..., None], shape), jnp.broadcast_to(w, shape))

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        return self._at(lam, jnp.broadcast_to(self.weights(jnp.asarray(0.5, _real_dtype(lam))), lam.shape))


def _real_dtype(lam):
    """The real floating dtype of the wavelengths' computation."""
    return jnp.real(jnp.zeros((), jnp.result_type(lam, float))).dtype


def _traced(v) -> bool:
    """A value the model is given inside a fit or a transformation (a JAX array or tracer): the
    solver keeps it within the bounds, and nothing is checked."""
    return isinstance(v, jax.Array)


def _check_fraction(f, what):
    if _traced(f):
        return
    if isinstance(f, Free):
        if not (f.lower >= 0 and f.upper <= 1):
            raise ValueError(f"{what}: Free bounds must lie within [0, 1], got ({f.lower}, {f.upper})")
    elif isinstance(f, bool) or not isinstance(f, (int, float, np.number)) or not 0 <= f <= 1:
        raise ValueError(f"{what}={f!r}: must lie in [0, 1]")
