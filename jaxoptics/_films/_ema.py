"""Effective-medium materials: a mixture of two materials as one index (`EMA`; a surface
roughness layer, `jaxoptics._films._sample.roughness`, is such a mixture with void).

With `eps_h` the host's and `eps_i` the inclusion's dielectric function, `f` the inclusion's
volume fraction and `L` the depolarization factor of the inclusions (1/3 for spheres):

- Bruggeman (symmetric): `(1 - f)(eps_h - eps)/(eps + L(eps_h - eps)) + f(eps_i - eps)/(eps +
  L(eps_i - eps)) = 0`, a quadratic in `eps`: `(1 - L) eps^2 - b eps - L eps_h eps_i = 0` with
  `b = (1 - L)((1 - f) eps_h + f eps_i) - L((1 - f) eps_i + f eps_h)`. Of its two roots the
  physical one is the one with the larger imaginary part (a passive medium has `Im eps >= 0`;
  the other root has `Im eps <= 0` or, for lossless constituents, a negative real part): it is
  continuous in `f`, equals `eps_h` at `f = 0` and `eps_i` at `f = 1`.
- Maxwell-Garnett (inclusions in a host): `eps = eps_h (eps_h + (L(1 - f) + f)(eps_i - eps_h)) /
  (eps_h + L(1 - f)(eps_i - eps_h))`.
- Looyenga: `eps^(1/3) = (1 - f) eps_h^(1/3) + f eps_i^(1/3)` (principal cube roots).
- Linear: `eps = (1 - f) eps_h + f eps_i`.

To first order in a small `f` all four agree: `eps = eps_h + f (eps_i - eps_h) c` with `c = 1`
(linear), `eps_h / (eps_h + L (eps_i - eps_h))` (Bruggeman and Maxwell-Garnett) and
`3 eps_h^(2/3) (eps_i^(1/3) - eps_h^(1/3)) / (eps_i - eps_h)` (Looyenga); the test suite checks
each against these closed forms, the limits and pyElli's implementation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp

from ._dispersion import Constant, Dispersion, Free

METHODS = ("bruggeman", "maxwell-garnett", "looyenga", "linear")


def _as_material(m, what):
    if isinstance(m, Dispersion):
        return m
    if isinstance(m, bool) or not isinstance(m, (int, float, complex, Free)):
        raise ValueError(f"{what}: a Dispersion model or a number, got {m!r}")
    if isinstance(m, Free):
        return Constant(n=m, k=0.0)
    m = complex(m)
    return Constant(n=m.real, k=m.imag)


@dataclasses.dataclass(frozen=True)
class EMA(Dispersion):
    """An effective medium of a `host` material with a volume `fraction` of an `inclusion`
    material (see the module docstring for the formulas).

    **Fields:**

    - `host`, `inclusion`: any materials (dispersion models with their own free parameters,
      built-in or database materials, or numbers `n + ik`).
    - `fraction`: the inclusion's volume fraction in `[0, 1]`, a number or `Free` (named
      `<layer>.fraction`; the constituents' parameters `<layer>.host.A`, ...).
    - `method`: `"bruggeman"` (default), `"maxwell-garnett"`, `"looyenga"` or `"linear"`.
    - `depolarization`: the inclusions' depolarization factor `L` in `(0, 1)`, 1/3 for spheres
      (Bruggeman and Maxwell-Garnett).

    The index is `sqrt(eps)` (principal root: `k >= 0` for `Im eps >= 0`). Gradients are finite
    at every fraction, 0 and 1 included.
    """

    host: Any = 1.0
    inclusion: Any = 1.0
    fraction: Any = 0.5
    method: str = "bruggeman"
    depolarization: float = 1 / 3
    _params = ("host", "inclusion", "fraction")

    def __post_init__(self):
        object.__setattr__(self, "host", _as_material(self.host, "EMA host"))
        object.__setattr__(self, "inclusion", _as_material(self.inclusion, "EMA inclusion"))
        if self.method not in METHODS:
            raise ValueError(f"EMA method={self.method!r}: one of {METHODS}")
        if not 0 < float(self.depolarization) < 1:
            raise ValueError(f"EMA depolarization={self.depolarization!r}: must lie in (0, 1)")
        f = self.fraction  # a number or Free here; inside a fit, the solver's value (not checked)
        if isinstance(f, Free) and not (f.lower >= 0 and f.upper <= 1):
            raise ValueError(f"EMA fraction: Free bounds must lie within [0, 1], got ({f.lower}, {f.upper})")
        if isinstance(f, (int, float)) and not 0 <= f <= 1:
            raise ValueError(f"EMA fraction={f!r}: must lie in [0, 1]")

    @property
    def range_um(self):
        """The constituents' common wavelength range (micrometres), or None."""
        rs = [r for r in (getattr(self.host, "range_um", None), getattr(self.inclusion, "range_um", None)) if r is not None]
        if not rs:
            return None
        return (max(r[0] for r in rs), min(r[1] for r in rs))

    def eps(self, wavelength_um):
        eh, ei = self.host.eps(wavelength_um), self.inclusion.eps(wavelength_um)
        eh, ei = jnp.asarray(eh), jnp.asarray(ei).astype(jnp.asarray(eh).dtype)
        f = jnp.asarray(self.fraction).astype(eh.dtype)  # complex, as strict promotion wants
        L = self.depolarization
        if self.method == "linear":
            return (1 - f) * eh + f * ei
        if self.method == "maxwell-garnett":
            d = ei - eh
            return eh * (eh + (L * (1 - f) + f) * d) / (eh + L * (1 - f) * d)
        if self.method == "looyenga":
            cube = lambda z: jnp.exp(jnp.log(z) / 3)  # principal cube root (z != 0 for a material)
            return ((1 - f) * cube(eh) + f * cube(ei)) ** 3
        b = (1 - L) * ((1 - f) * eh + f * ei) - L * ((1 - f) * ei + f * eh)
        q = jnp.sqrt(b * b + 4 * (1 - L) * L * eh * ei)
        r1, r2 = (b + q) / (2 * (1 - L)), (b - q) / (2 * (1 - L))
        return jnp.where(jnp.imag(r1) >= jnp.imag(r2), r1, r2)

    def nk(self, wavelength_um):
        return jnp.sqrt(self.eps(wavelength_um))
