r"""Fresnel reflection and transmission at a smooth interface.

Conventions (shared by every kernel in this package)
----------------------------------------------------
* ``cos_i`` is the cosine of the angle of incidence, ``|i . n|`` for a unit incident direction
  ``i`` and unit normal ``n``; its sign is ignored, so ``dot(i, n)`` can be passed as it is,
  whichever way the normal points.
* ``eta1`` is the (real, positive) index of the medium the light comes from, ``eta2`` the index of
  the medium it enters. ``eta2`` may be complex, ``n + ik`` with ``k >= 0`` absorbing (the tmm and
  refractiveindex.info convention).
* Amplitudes (Hecht's sign convention, the one tmm uses)::

      r_s = (eta1 cos_i - eta2 cos_t) / (eta1 cos_i + eta2 cos_t)
      r_p = (eta2 cos_i - eta1 cos_t) / (eta2 cos_i + eta1 cos_t)
      t_s = 2 eta1 cos_i / (eta1 cos_i + eta2 cos_t)
      t_p = 2 eta1 cos_i / (eta2 cos_i + eta1 cos_t)

  so that ``r_p = -r_s`` at normal incidence. ``eta2 cos_t`` is the square root of
  ``eta2**2 - eta1**2 sin_i**2`` on the branch whose wave decays into medium 2,
  ``Im(eta2 cos_t) >= 0`` (time dependence ``exp(-i omega t)``). Under total internal reflection
  ``eta2 cos_t = i kappa`` with ``kappa > 0``, so ``|r_s| = |r_p| = 1`` with the phase shifts that
  follow from these formulas.

How the values are kept accurate, and why the gradients are finite everywhere: see
`jaxoptics._interface._fresnel_terms`.

Out-of-domain values
--------------------
Nothing raises inside ``jit``. An element with a non-finite ``cos_i``, or an index that is not
finite and positive (for complex ``eta2``: real part > 0 and imaginary part >= 0), gives NaN in
every output. A complex ``eta2`` whose ``k`` lies below zero by at most ``1e-12 |eta2|`` is
rounding and is taken as ``k = 0``, as in `stack`. ``|cos_i|`` slightly above one (rounding in a dot product) is not clamped: the
formulas extend smoothly and stay finite.

References: B. de Greve, *Reflections and Refractions in Ray Tracing* (2006); E. Hecht, *Optics*,
ch. 4; T. Akenine-Moller et al., *Real-Time Rendering*; C. Schlick, *An Inexpensive BRDF Model for
Physically-based Rendering* (1994).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax.numpy as jnp

from .._core import _validate as V
from .._core._numerics import _abs2, _positive_finite, unpolarized
from .._core._program import program
from .._core._result import Unpacks, result
from ._fresnel_terms import (
    _abs_cos,
    _fresnel_real,
    _nan_where_invalid,
    _prepare,
    _q_real,
    _r_amplitudes,
    _rt_two_loops,
    _sp_rt,
    _t_amplitudes,
    _terms,
    _valid_index,
)

if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike, Float, Inexact


@result
class FresnelAmplitudes(Unpacks):
    """Complex amplitude coefficients of one interface (see the module conventions).

    **Fields:** ``r_s``, ``r_p``, ``t_s``, ``t_p``: complex arrays (``complex64`` for ``float32``
    inputs, ``complex128`` for ``float64``).

    Under total internal reflection ``|r_s| = |r_p| = 1`` and their arguments are the TIR phase
    shifts; ``t_s`` and ``t_p`` are then the amplitudes of the evanescent wave.
    """

    r_s: jnp.ndarray
    r_p: jnp.ndarray
    t_s: jnp.ndarray
    t_p: jnp.ndarray

    @property
    def R_s(self):
        """``|r_s|**2``."""
        return _abs2(self.r_s)

    @property
    def R_p(self):
        """``|r_p|**2``."""
        return _abs2(self.r_p)

    @property
    def R(self):
        """Unpolarized reflectance, ``(R_s + R_p) / 2``."""
        return unpolarized(self.R_s, self.R_p)


@program()
def fresnel(cos_i: Float[ArrayLike, "*batch"], eta1: Float[ArrayLike, "*#batch"],
            eta2: Inexact[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    r"""Unpolarized Fresnel reflectance ``R = (R_s + R_p) / 2`` of a smooth interface.

    **Arguments:**

    - `cos_i`: cosine of the angle of incidence, shape `(...)`; the sign is ignored.
    - `eta1`: real index of the incident medium, broadcastable with `cos_i`.
    - `eta2`: index of the medium entered; real, or complex `n + ik` with `k >= 0`.

    **Returns:** `R`, real, in the floating dtype of the inputs, shape the broadcast of the inputs.

    **Conventions:** see `jaxoptics` module docs: `eta1` is the medium the light comes from.

    **Edge cases:** `R = 1` under total internal reflection (gradient 0 there); `R = 0` at every
    angle, grazing included, when `eta1 == eta2`; `R = 1` at exact grazing incidence otherwise.
    An element with a non-finite `cos_i` or a non-positive / non-finite index gives NaN.

    **Accuracy:** within 4 ulps of the correctly rounded value, or within what a 2-ulp change of the
    inputs causes where the problem is ill-conditioned (near the critical angle), in float32 and
    float64, for index ratios 1e-3 to 1e3 (tested against 50-digit mpmath).

    Reference: Hecht, *Optics*, eqs. 4.34, 4.40; de Greve (2006), eqs. 25-27.
    """
    cos_i, eta1, eta2 = _prepare(cos_i, eta1, eta2, allow_complex=True)
    if not jnp.iscomplexobj(eta2):
        return _fresnel_real(cos_i, eta1, eta2, _q_real(cos_i, eta1, eta2))
    R_s, R_p, _, _ = _sp_rt(cos_i, eta1, eta2)
    return unpolarized(R_s, R_p)


@program()
def fresnel_sp(cos_i: Float[ArrayLike, "*batch"], eta1: Float[ArrayLike, "*#batch"],
               eta2: Inexact[ArrayLike, "*#batch"]) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    r"""Fresnel reflectances for s (TE) and p (TM) polarization, `(R_s, R_p)`.

    **Arguments:** as `fresnel`; `eta2` may be complex.

    **Returns:** a pair `(R_s, R_p)` of real arrays.

    **Edge cases:** both are 1 under TIR and at grazing incidence (unless `eta1 == eta2`, where
    both are 0); `R_p = 0` exactly at Brewster's angle `atan(eta2 / eta1)` (real indices).
    Invalid elements give NaN, as for `fresnel`.
    """
    cos_i, eta1, eta2 = _prepare(cos_i, eta1, eta2, allow_complex=True)
    R_s, R_p, _, _ = _sp_rt(cos_i, eta1, eta2)
    return R_s, R_p


@program()
def fresnel_rt(cos_i: Float[ArrayLike, "*batch"], eta1: Float[ArrayLike, "*#batch"],
               eta2: Inexact[ArrayLike, "*#batch"]) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    r"""Unpolarized reflectance and transmittance `(R, T)` computed together.

    `T` is the fraction of the incident power that crosses the interface (for an absorbing
    `eta2`, the power that enters the absorbing medium), so `R + T = 1` up to rounding; it is
    computed from shared intermediates as `4 k_i Re(k_t) / |k_i + k_t|^2` (and the p analogue),
    not as `1 - R`, so it keeps full relative accuracy at grazing incidence where `R -> 1`.
    `R` equals `fresnel`'s. For a real index, `R` and `T` are computed in two separate loops that
    share only `k_t^2` (XLA on the CPU would otherwise write every shared quotient to memory: 4x
    slower), so `|R + T - 1|` is within half an ulp, not exactly 0.

    **Edge cases:** `T = 0` under TIR; `T = 1` when `eta1 == eta2`; NaN for invalid elements.
    """
    cos_i, eta1, eta2 = _prepare(cos_i, eta1, eta2, allow_complex=True)
    if jnp.iscomplexobj(eta2):
        R_s, R_p, T_s, T_p = _sp_rt(cos_i, eta1, eta2)
        return unpolarized(R_s, R_p), unpolarized(T_s, T_p)
    return _rt_two_loops(cos_i, eta1, eta2)


@program()
def fresnel_amplitudes(cos_i: Float[ArrayLike, "*batch"], eta1: Float[ArrayLike, "*#batch"],
                       eta2: Inexact[ArrayLike, "*#batch"]) -> FresnelAmplitudes:
    r"""Complex Fresnel amplitude coefficients `r_s, r_p, t_s, t_p`, with phase.

    **Arguments:** as `fresnel`; `eta2` may be complex (metals, absorbing media).

    **Returns:** a `FresnelAmplitudes` named tuple of complex arrays (`complex64` for float32
    inputs, `complex128` for float64), with properties `R_s`, `R_p`, `R`.

    **Conventions:** the formulas and sign convention of the module docstring (Hecht's, as in tmm):
    `r_p = -r_s` at normal incidence; `eta2 cos_t` on the branch `Im >= 0` (decaying into medium 2).

    **Edge cases:** under TIR `|r_s| = |r_p| = 1` with phases
    `arg r_s = -2 atan(kappa / k_i)`, `arg r_p = -2 atan(eta1**2 kappa / (eta2**2 k_i))` where
    `kappa = sqrt(eta1**2 sin_i**2 - eta2**2)`; at grazing incidence `r_s = r_p = -1`;
    `eta1 == eta2` gives `r = 0`, `t = 1`. Invalid elements give NaN.
    """
    cos_i, eta1, eta2 = _prepare(cos_i, eta1, eta2, allow_complex=True)
    eta2 = jnp.asarray(eta2, V.complex_dtype(cos_i.dtype))
    t = _terms(cos_i, eta1, eta2)
    out = _r_amplitudes(t) + _t_amplitudes(t, eta2)
    return FresnelAmplitudes(*_nan_where_invalid(t.valid, *out))


def _schlick_from_r0(c, r0):
    x = 1 - c
    x2 = x * x
    return r0 + (1 - r0) * (x2 * x2 * x)


@program()
def schlick(cos_i: Float[ArrayLike, "*batch"], eta1: Float[ArrayLike, "*#batch"],
            eta2: Inexact[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    r"""Schlick's approximation `R0 + (1 - R0)(1 - cos_i)^5`, `R0 = ((eta1 - eta2)/(eta1 + eta2))^2`.

    **Arguments:** as `fresnel`; for a complex `eta2`, `R0 = |eta1 - eta2|^2 / |eta1 + eta2|^2`.

    **Accuracy:** exact at normal and grazing incidence; for `eta1 < eta2` (entering a denser
    medium) the error against `fresnel` stays below about 0.01 for glass-like indices, but it grows
    with the contrast. It knows nothing of TIR: for `eta1 > eta2` it is badly wrong past the
    critical angle (use `schlick_tir`). The power is computed by multiplications (4 multiplies),
    not `pow`.

    **Edge cases:** `R = 1` at grazing incidence, `R0` at normal incidence, `0` everywhere when
    `eta1 == eta2`; NaN for a non-finite `cos_i` or an index that is not finite and positive.

    Reference: Schlick (1994); Real-Time Rendering, 4th ed., eq. 9.16.
    """
    cos_i, eta1, eta2 = _prepare(cos_i, eta1, eta2, allow_complex=True)
    c = _abs_cos(cos_i)
    if V.is_complex(eta2):
        e1 = eta1.astype(eta2.dtype)
        r0 = _abs2(e1 - eta2) / _abs2(e1 + eta2)
        valid = _positive_finite(eta1) & _valid_index(eta2) & (c < jnp.inf)
    else:
        a = (eta1 - eta2) / (eta1 + eta2)
        r0 = a * a
        valid = _positive_finite(eta1) & _positive_finite(eta2) & (c < jnp.inf)
    return jnp.where(valid, _schlick_from_r0(c, r0), jnp.nan)


@program()
def schlick_tir(cos_i: Float[ArrayLike, "*batch"], eta1: Float[ArrayLike, "*#batch"],
                eta2: Float[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    r"""Schlick's approximation made aware of total internal reflection (de Greve 2006, eq. 30).

    When `eta1 > eta2` the cosine of the *transmitted* angle replaces `cos_i` (Schlick's formula is
    symmetric in that sense), and the result is 1 under TIR. For `eta1 <= eta2` it equals `schlick`.

    **Arguments:** real `cos_i`, `eta1`, `eta2` (complex indices are refused: TIR needs real ones).

    **Edge cases:** 1 under TIR (gradient 0); the square root at the critical angle is guarded by
    a double `where`, so gradients stay finite there. NaN for invalid elements.
    """
    cos_i, eta1, eta2 = _prepare(cos_i, eta1, eta2, allow_complex=False)
    t = _terms(cos_i, eta1, eta2)
    a = (eta1 - eta2) / (eta1 + eta2)
    r0 = a * a
    cos_t = t.kt / eta2
    c = jnp.where(eta1 > eta2, cos_t, t.c)
    R = jnp.where(t.tir, 1, _schlick_from_r0(c, r0))
    return jnp.where(t.valid, R, jnp.nan)
