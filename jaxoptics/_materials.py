"""Dispersion laws n(lambda) and published coefficients for common materials.

Wavelengths are in micrometres (`wavelength_um`) everywhere, as in the catalogues.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from . import _validate as V


def cauchy(wavelength_um, coefficients):
    r"""Cauchy's law `n = A + B / lambda^2 + C / lambda^4 + ...` (wavelength in micrometres).

    **Arguments:**

    - `wavelength_um`: wavelengths in micrometres, any shape.
    - `coefficients`: `(A, B)` or `(A, B, C, ...)`; a sequence or an array whose *last* axis holds
      the coefficients (so batches of coefficient sets broadcast against `wavelength_um[..., None]`
      style inputs).

    **Returns:** `n`, the broadcast of `wavelength_um` with the coefficients' leading axes.

    **Edge cases:** a non-positive wavelength gives inf or NaN (the law is singular at 0).
    """
    lam = V.as_real(wavelength_um, "wavelength_um")
    coef = jnp.asarray(coefficients)
    inv2 = 1 / (jnp.asarray(lam) ** 2)
    n = coef[..., -1]
    for k in range(coef.shape[-1] - 2, -1, -1):  # Horner in 1/lambda^2
        n = coef[..., k] + inv2 * n
    return n


def sellmeier(wavelength_um, B, C):
    r"""Sellmeier's law `n^2 = 1 + sum_i B_i lambda^2 / (lambda^2 - C_i)` (lambda in micrometres,
    `C_i` in micrometres squared).

    **Arguments:**

    - `wavelength_um`: wavelengths in micrometres, any shape.
    - `B`, `C`: sequences or arrays of equal length along their last axis.

    **Returns:** `n` (the positive root).

    **Edge cases:** at a pole (`lambda^2 == C_i`) the value is inf or NaN; where `n^2 < 0`
    (inside an absorption band, outside the law's range) NaN.

    Reference: W. Sellmeier (1871); coefficients as in the SCHOTT and refractiveindex.info catalogues.
    """
    lam = jnp.asarray(V.as_real(wavelength_um, "wavelength_um"))
    B = jnp.asarray(B)
    C = jnp.asarray(C)
    l2 = (lam * lam)[..., None]
    n2 = 1 + jnp.sum(B * l2 / (l2 - C), axis=-1)
    return jnp.sqrt(n2)


class Material(NamedTuple):
    """Published dispersion of a material: `index(wavelength_um)` evaluates it."""

    name: str
    model: str  # "sellmeier" or "cauchy"
    B: tuple
    C: tuple
    range_um: tuple
    reference: str

    def index(self, wavelength_um):
        """Refractive index at `wavelength_um` (micrometres)."""
        if self.model == "sellmeier":
            return sellmeier(wavelength_um, self.B, self.C)
        return cauchy(wavelength_um, self.B)


MATERIALS = {
    "fused_silica": Material(
        "fused silica (SiO2), 20 C",
        "sellmeier",
        (0.6961663, 0.4079426, 0.8974794),
        (0.0684043**2, 0.1162414**2, 9.896161**2),
        (0.21, 3.71),
        "I. H. Malitson, J. Opt. Soc. Am. 55, 1205 (1965); n(0.5893 um) = 1.458403",
    ),
    "N-BK7": Material(
        "SCHOTT N-BK7",
        "sellmeier",
        (1.03961212, 0.231792344, 1.01046945),
        (0.00600069867, 0.0200179144, 103.560653),
        (0.3, 2.5),
        "SCHOTT optical glass data sheet N-BK7; n_d (0.5876 um) = 1.5168",
    ),
    "water": Material(
        "water, 20 C",
        "sellmeier",
        (5.684027565e-1, 1.726177391e-1, 2.086189578e-2, 1.130748688e-1),
        (5.101829712e-3, 1.821153936e-2, 2.620722293e-2, 1.069792721e1),
        (0.182, 1.129),
        "M. Daimon and A. Masumura, Appl. Opt. 46, 3811 (2007), 20 C; n(0.5893 um) = 1.3333",
    ),
}


def material_index(name: str, wavelength_um):
    """Refractive index of a catalogued material (`MATERIALS`) at `wavelength_um` (micrometres)."""
    try:
        m = MATERIALS[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; known: {sorted(MATERIALS)}") from None
    return m.index(wavelength_um)
