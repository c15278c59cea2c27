"""Dispersion laws n(lambda) and published coefficients for common materials.

Wavelengths are in micrometres (`wavelength_um`) everywhere, as in the catalogues.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import jax.numpy as jnp

from .._core import _validate as V

if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike, Float


def cauchy(wavelength_um: Float[ArrayLike, "*batch"], coefficients: Float[ArrayLike, " k"]) -> Float[Array, "*batch"]:
    r"""Cauchy's law `n = A + B / lambda^2 + C / lambda^4 + ...` (wavelength in micrometres).

    **Arguments:**

    - `wavelength_um`: wavelengths in micrometres, any shape.
    - `coefficients`: `(A, B)` or `(A, B, C, ...)`, a one-dimensional sequence or array.

    **Returns:** `n`, shaped like `wavelength_um`.

    **Edge cases:** a non-positive wavelength gives inf or NaN (the law is singular at 0).
    """
    lam = V.as_real(wavelength_um, "wavelength_um")
    coef = jnp.asarray(coefficients)
    if coef.ndim != 1 or coef.shape[0] < 1:
        raise ValueError(f"coefficients must be one-dimensional, (A, B, ...), got shape {coef.shape}")
    inv2 = 1 / (jnp.asarray(lam) ** 2)
    n = jnp.broadcast_to(coef[-1], inv2.shape)
    for k in range(coef.shape[0] - 2, -1, -1):  # Horner in 1/lambda^2
        n = coef[k] + inv2 * n
    return n


def sellmeier(wavelength_um: Float[ArrayLike, "*batch"], B: Float[ArrayLike, " k"],
              C: Float[ArrayLike, " k"]) -> Float[Array, "*batch"]:
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
    if B.ndim != 1 or B.shape != C.shape:
        raise ValueError(f"B and C must be one-dimensional and of equal length, got shapes {B.shape} and {C.shape}")
    l2 = (lam * lam)[..., None]
    lead = (1,) * lam.ndim
    n2 = 1 + jnp.sum(B.reshape(lead + B.shape) * l2 / (l2 - C.reshape(lead + C.shape)), axis=-1)
    return jnp.sqrt(n2)


class Material(NamedTuple):
    """Published dispersion of a material: `index(wavelength_um)` evaluates it.

    **Fields:** `name`; `model`, `"sellmeier"` or `"cauchy"`; `B`, `C`, the coefficients of
    `sellmeier` (`C` in micrometres squared) or, for Cauchy, `B` the coefficients of `cauchy`;
    `range_um`, the wavelength range the coefficients were fitted over (micrometres); `reference`,
    the source.
    """

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


def material_index(name: str, wavelength_um: Float[ArrayLike, "*batch"]) -> Float[Array, "*batch"]:
    """Refractive index of a catalogued material (a key of `MATERIALS`) at `wavelength_um`
    (micrometres, any shape; the dtype follows the input). Outside the material's `range_um` the
    law is extrapolated, not flagged. An unknown name raises a `ValueError` listing the known
    ones."""
    try:
        m = MATERIALS[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; known: {sorted(MATERIALS)}") from None
    return m.index(wavelength_um)
