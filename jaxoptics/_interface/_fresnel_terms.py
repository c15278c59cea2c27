r"""The terms of the Fresnel kernels (`_fresnel`): `k_t`, the quotients, the powers, and their
closed-form derivatives. The conventions are those of `_fresnel`'s docstring.

How the values are kept accurate
--------------------------------
Everything is written in terms of ``k_i = eta1 cos_i`` and ``k_t = eta2 cos_t`` with

    k_t**2 = (eta2 - eta1) * (eta2 + eta1) + k_i**2,

which has no ``1 - cos_i**2`` (that loses everything at grazing incidence when the indices are
close) and whose difference ``eta2 - eta1`` is exact by Sterbenz's lemma when the indices are
within a factor of two. The differences in the numerators are rationalized,

    k_i - k_t = (eta1**2 - eta2**2) / (k_i + k_t),

so no cancellation happens when ``eta1`` is close to ``eta2`` and ``eta1 == eta2`` gives exactly
``R = 0`` at every angle. The only remaining cancellation is the one the problem itself has (near
the critical angle and at Brewster's zero of ``r_p``); there the error stays within what a 2-ulp
change of the inputs causes (tested against 50-digit mpmath).

Gradients
---------
Every singular operation (the square root at the critical angle, the divisions that become 0/0 at
grazing incidence with ``eta1 == eta2``) is guarded by the double-``where`` pattern: the *input*
is replaced by a harmless value in the lanes where the result is not used, and the output is then
selected. A single ``where`` is not enough, because the unused lane's NaN or infinite derivative is
multiplied by zero, which still gives NaN. Gradients are therefore finite everywhere, including
under TIR (where ``R`` is constant and its gradient is zero), at the exact critical angle (the
gradient is the one-sided value from the TIR side, where ``k_t`` is zero) and at grazing incidence.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._core import _validate as V
from .._core._numerics import _abs2, _own_loop, _positive_finite, decaying_sqrt, sqrt_where, unpolarized

_HALF_SQRT2 = 0.7071067811865476  # |r| <= 1/sqrt(2): R <= 1/2
_SQRT2 = 1.4142135623730951


def _abs_cos(cos_i):
    # |cos_i| through a where rather than jnp.abs: jnp.abs has derivative sign(0) = 0 at grazing
    # incidence, which would zero d/dcos_i there; this gives the one-sided derivative from the
    # physical side (+1).
    return jnp.where(cos_i < 0, -cos_i, cos_i)


def _valid_index(eta):
    if jnp.iscomplexobj(eta):
        return _positive_finite(jnp.real(eta)) & (jnp.imag(eta) >= 0) & (jnp.imag(eta) < jnp.inf)
    return _positive_finite(eta)


def _prepare(cos_i, eta1, eta2, *, allow_complex: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Validate at trace time; return arrays in the computation dtype."""
    cos_i = V.as_real(cos_i, "cos_i")
    eta1 = V.as_index(eta1, "eta1", allow_complex=False)
    eta2 = V.as_index(eta2, "eta2", allow_complex=allow_complex)
    shape = V.broadcast_shapes(cos_i=jnp.shape(cos_i), eta1=jnp.shape(eta1), eta2=jnp.shape(eta2))
    dt = V.float_dtype(cos_i, eta1, eta2)
    cos_i = jnp.broadcast_to(jnp.asarray(cos_i, dt), shape)
    eta1 = jnp.broadcast_to(jnp.asarray(eta1, dt), shape)
    eta2 = V.without_rounding_k(jnp.asarray(eta2, V.complex_dtype(dt) if V.is_complex(eta2) else dt))
    return cos_i, eta1, jnp.broadcast_to(eta2, shape)


def _kt_squared(ki, eta1, eta2, sin_sq=None, q_given=None):
    """k_t^2 = eta2^2 - eta1^2 sin^2, with diff = eta2^2 - eta1^2 and m = k_i^2 - eta1^2.

    No `1 - cos^2` anywhere (it loses everything at grazing incidence). Two forms of k_t^2, each
    exact where the other is not, and an m consistent with the one used (m enters the numerator
    of r_p, and near the critical angle any disagreement between m and k_t^2 is amplified):

    * eta1 <= 2 eta2: k_t^2 = diff + k_i^2 with diff = (eta2 - eta1)(eta2 + eta1), where
      eta2 - eta1 is exact by Sterbenz's lemma. Grazing incidence with eta1 ~ eta2 keeps r = -1
      exactly, and near the critical angle the error is ulp(k_i^2), tiny against the scale on which
      k_t^2 changes. (Entering the denser medium, m is formed directly; leaving it, m = k_t^2 -
      eta2^2, exactly consistent.)
    * eta1 > 2 eta2: k_t^2 = eta2^2 + m with m = (k_i - eta1)(k_i + eta1). Here diff + k_i^2 would
      cancel at the scale ulp(eta1^2), far above eta2^2; this form cancels only at ulp(eta2^2), the
      same as moving eta2 by half an ulp.

    `refract` uses this same function (with sin^2 from a cross product, see there).
    """
    diff = (eta2 - eta1) * (eta2 + eta1)
    # m = -eta1^2 sin^2: from the given sin^2 (refract passes |i x n|^2, accurate near normal
    # incidence where a cosine has lost the angle), or from the rounded k_i
    m_direct = (ki - eta1) * (ki + eta1) if sin_sq is None else -(eta1 * eta1) * sin_sq
    e1r, e2r = (jnp.real(eta1), jnp.real(eta2)) if jnp.iscomplexobj(eta2) else (eta1, eta2)
    far = e1r > 2 * e2r
    q_close = diff + ki * ki
    q = jnp.where(far, eta2 * eta2 + m_direct, q_close)
    if q_given is not None:  # the same value, computed once elsewhere (see `_rt_two_loops`)
        q = q_close = q_given
    m = jnp.where(far | (e2r >= e1r), m_direct, q_close - eta2 * eta2)
    return q, diff, m


class _Terms(NamedTuple):
    e1: jnp.ndarray  # eta1 in the working dtype (complex on the complex path)
    e2: jnp.ndarray  # eta2
    c: jnp.ndarray  # |cos_i|, in the working dtype
    ki: jnp.ndarray  # eta1 cos_i
    kt: jnp.ndarray  # eta2 cos_t on the decaying branch (real path: 0 under TIR)
    diff: jnp.ndarray  # eta2**2 - eta1**2, as (eta2 - eta1)(eta2 + eta1)
    tir: jnp.ndarray  # total internal reflection (always false on the complex path)
    m: jnp.ndarray  # k_i^2 - eta1^2 = -eta1^2 sin^2
    ok: jnp.ndarray  # an interface: false only at grazing incidence with eta1 == eta2 (0/0)
    den_s: jnp.ndarray  # k_i + k_t, 1 where not ok
    den_p: jnp.ndarray  # eta2**2 k_i + eta1**2 k_t, 1 where not ok
    inv_s: jnp.ndarray  # 1 / den_s
    inv_p: jnp.ndarray  # 1 / den_p
    valid: jnp.ndarray


def _terms(cos_i, eta1, eta2, sin_sq=None, q_given=None, *, own_jvp=False) -> _Terms:
    """Shared intermediates; `eta2` real (fast real path) or complex. `sin_sq`, if given, is
    sin^2 of the angle of incidence from a cross product (see `_kt_squared`).

    `own_jvp`: the caller has a derivative rule of its own (`_sp_rt_real`, `_fresnel_real`) and
    does not differentiate these values, so they need no guards for autodiff: `abs` instead of
    `_abs_cos`, the square root of `k_t^2` clamped at 0 instead of `sqrt_where`, and the divisors
    left as they are where they vanish (the same values, with fewer instructions per element)."""
    c = jnp.abs(cos_i) if own_jvp else _abs_cos(cos_i)
    if jnp.iscomplexobj(eta2):
        valid = _positive_finite(eta1) & _valid_index(eta2) & (c < jnp.inf)
        # Explicit casts: the complex path is complex throughout (no implicit real/complex mixing,
        # so it also runs under jax_numpy_dtype_promotion="strict").
        c, eta1 = c.astype(eta2.dtype), eta1.astype(eta2.dtype)
    else:
        valid = _positive_finite(eta1) & _positive_finite(eta2) & (c < jnp.inf)
    ki = eta1 * c
    q, diff, m = _kt_squared(ki, eta1, eta2, sin_sq, q_given)
    if jnp.iscomplexobj(q):
        kt = decaying_sqrt(q)
        tir = jnp.zeros(jnp.shape(q), bool)
    else:
        tir = q < 0
        # k_t = 0 under TIR and at the critical angle
        # (the square root through `_one_reader`: it has many readers, see there)
        kt = _one_reader(jnp.sqrt(jnp.where(q > 0, q, 0))) if own_jvp else sqrt_where(q, q > 0)
    den_s = ki + kt
    den_p = eta2 * eta2 * ki + eta1 * eta1 * kt
    # Both denominators vanish together only at grazing incidence with eta1 == eta2 (0/0: no
    # interface). Squares are tested, not the values, because XLA flushes subnormals to zero: a
    # tiny nonzero k_i + k_t can have a square of exactly 0. The divisors themselves are replaced
    # (not only the quotients) so no NaN leaks into gradients.
    # The TIR mask is deliberately not folded in here: XLA may evaluate `q < 0` more than once,
    # in different fusions with different FMA contraction, so two copies can disagree when q is
    # within rounding of 0. Each output therefore selects on `tir` exactly once, at the end,
    # between two branches that both make sense there (at q ~ 0 both give R ~ 1).
    # With `own_jvp` nothing is differentiated, and every value computed from the divisors is
    # selected on `ok` before it is returned (the quotients themselves may then be inf or NaN).
    if own_jvp and not jnp.iscomplexobj(q):
        # the same test on the divisors themselves (both >= 0 here): a value's square is a
        # normal number exactly when the value is at least `_smallest_squarable`. Written as "not
        # below", so a NaN divisor counts as ok and its NaN reaches the result (`_fresnel_real`
        # relies on that for a non-finite cos_i): two comparisons per element instead of four
        # operations.
        t0 = _smallest_squarable(den_s.dtype)
        ok = ~((den_s < t0) | (den_p < t0))
    else:
        ok = (_abs2(den_s) > 0) & (_abs2(den_p) > 0)
    if not own_jvp:
        den_s = jnp.where(ok, den_s, 1)
        den_p = jnp.where(ok, den_p, 1)
    return _Terms(eta1, eta2, c, ki, kt, diff, tir, m, ok, den_s, den_p, 1 / den_s, 1 / den_p, valid)


@functools.cache
def _smallest_squarable(dtype) -> np.ndarray:
    """The smallest `x` of `dtype` whose square `x * x` is a normal number (not flushed to 0)."""
    tiny = np.finfo(dtype).tiny
    x = np.sqrt(tiny).astype(dtype)
    while x * x < tiny:
        x = np.nextafter(x, dtype.type(np.inf))
    return x


def _r_amplitudes(t: _Terms):
    """r_s, r_p in forms free of cancellation except the one the problem has.

    r_s = (k_i - k_t)/(k_i + k_t) = (eta1^2 - eta2^2)/(k_i + k_t)^2 (rationalized: exact zero and
    full relative accuracy when eta1 ~ eta2).

    r_p = (eta2^2 k_i - eta1^2 k_t)/D with D = eta2^2 k_i + eta1^2 k_t, and the numerator
    rewritten as (eta2^2 - eta1^2)(k_i k_t + m)/(k_i + k_t) with m = -eta1^2 sin^2, whose
    remaining difference vanishes only at Brewster's angle, where r_p itself does. m is the very
    term k_t^2 = eta2^2 + m was formed from: any other sin^2 (say from cos_i directly) would be
    inconsistent with k_t at the rounding level, and near the critical angle with eta1 >> eta2
    that inconsistency is amplified a thousandfold. (Rationalizing over D instead leaves
    cos^2 (eta1^2 + eta2^2) - eta1^2, which cancels catastrophically there.)
    """
    e1 = t.e1
    # Successive quotients, not products with reciprocals: one rounding fewer each (measured: the
    # worst float32 error of R_s over 10^6 inputs drops from 4.3 to 2.7 ulps beyond the bound).
    # Not x / (d * d) either: near 0/0 (grazing, eta1 == eta2) the derivative of that with respect
    # to d * d is x / (d * d)^2, which underflows to 0/0 = NaN in float32; x / d / d keeps it 0.
    r_s = -t.diff / t.den_s / t.den_s
    # x = k_i k_t + m = k_i (k_i + k_t) - eta1^2. Entering the denser medium (no critical angle, so
    # no consistency with k_t^2 to keep) the second form has fewer roundings; leaving it, the
    # first keeps m identical to the one k_t^2 was formed from.
    denser = (jnp.real(t.diff) if jnp.iscomplexobj(t.diff) else t.diff) >= 0
    x = jnp.where(denser, t.ki * t.den_s - e1 * e1, t.ki * t.kt + t.m)
    r_p = (t.diff * x) / t.den_s / t.den_p
    if not jnp.iscomplexobj(t.kt):
        # Where |r_p| > 1/3 the direct form (eta2^2 k_i - eta1^2 k_t) / D cancels by at most a
        # factor 3 and takes fewer roundings than the rationalized one: measured over 10^6 float32
        # inputs, the worst error of R_p beyond the 2-ulp backward bound drops from 5.2 to about 3 ulps
        # (near grazing incidence entering a denser medium, R_p just under 1/2). Both terms are
        # those of D, so this costs one subtraction and one division.
        # The test is on |u - v| against D/3, not on r_p itself: a quotient feeding both a
        # comparison and a select is materialized by XLA on the CPU (a separate loop, 4x slower).
        num = t.e2 * t.e2 * t.ki - e1 * e1 * t.kt
        r_p = jnp.where(3 * jnp.abs(num) > t.den_p, num / t.den_p, r_p)
    if jnp.iscomplexobj(t.kt):
        # Where Re(k_t^2) < 0 (TIR, or a metal) k_t is mostly imaginary and the direct forms have
        # no cancellation; under TIR they are ratios of complex conjugates, so |r| = 1 exactly up
        # to the rounding of one division (the rationalized forms assume k_t^2 = diff + k_i^2
        # holds exactly, which the rounding of k_t^2 breaks at grazing incidence).
        direct = jnp.real(t.kt * t.kt) < 0
        e2sq_ki = t.e2 * t.e2 * t.ki
        r_s = jnp.where(direct, (t.ki - t.kt) * t.inv_s, r_s)
        r_p = jnp.where(direct, (e2sq_ki - e1 * e1 * t.kt) * t.inv_p, r_p)
    r_s = jnp.where(t.ok, r_s, 0)
    r_p = jnp.where(t.ok, r_p, 0)
    return r_s, r_p


def _t_amplitudes(t: _Terms, eta2):
    # Divisions, not products with the reciprocals: with eta1 == eta2 the numerators equal the
    # denominators exactly, and x / x is 1 where x * (1 / x) need not be.
    t_s = jnp.where(t.ok, 2 * t.ki / t.den_s, 1)
    t_p = jnp.where(t.ok, 2 * (t.e1 * eta2 * t.ki) / t.den_p, 1)
    return t_s, t_p


def _nan_where_invalid(valid, *xs):
    return tuple(jnp.where(valid, x, jnp.nan) for x in xs)


def _power_pair(t: _Terms, refl, trans):
    """(R, T) of one polarization from |r|^2 and the directly computed transmittance.

    Each is taken directly where it is the smaller of the two and as one minus the other where it
    is the larger, so that both keep full accuracy near 0 and near 1 (at grazing incidence R -> 1
    and T is small; near normal incidence the reverse).
    """
    small = refl <= 0.5
    R = jnp.where(small, refl, 1 - trans)
    T = jnp.where(small, 1 - refl, trans)
    R = jnp.where(t.tir, 1, jnp.where(t.ok, R, 0))
    T = jnp.where(t.tir, 0, jnp.where(t.ok, T, 1))
    return R, T


def _one_reader(q):
    """`q` unchanged (a `reduce_precision` to the dtype's own exponent and mantissa, which XLA keeps
    and emits as no instruction), so that an expensive value read by several operations has
    exactly one reader. XLA on the CPU does not duplicate a division or a square root into the
    loops of several readers, and its greedy fusion then leaves such a value outside the loop: it
    gets a loop of its own and goes through memory, often with much of what it is computed from
    (checked on the compiled HLO; `tests/test_bench.py` pins one loop per kernel)."""
    fi = jnp.finfo(q.dtype)
    return jax.lax.reduce_precision(q, exponent_bits=fi.nexp, mantissa_bits=fi.nmant)


def _quotients_real(t: _Terms, eta1, eta2):
    """One quotient per polarization for a real eta2, and which quantity it is.

    The values of `_r_amplitudes` and `_power_pair` (each polarization takes the smaller of R and
    T directly and the larger as one minus it; R from the rationalized or the direct amplitude),
    but the form is chosen *before* dividing: numerator and denominator are selected, and the one
    quotient `q` is the amplitude where `small` (`R = q**2`, `T = 1 - q**2`) and the
    transmittance elsewhere (`T = q`, `R = 1 - q`):

        s:  q = -diff / D_s**2 (= r_s)          where R_s <= 1/2,
            q = 4 k_i k_t / D_s**2 (= T_s)      elsewhere;
        p:  q = diff x / (D_s D_p) (= r_p)      where 3 |num| <= D_p (rationalized),
            q = num / D_p (= r_p)               where R_p <= 1/2 otherwise (direct),
            q = 4 k_i k_t (eta1 eta2)**2 / D_p**2 (= T_p)  elsewhere.

    The choices are tested on division-free equivalents (`sqrt(2) |diff| <= D_s**2` for
    `R_s <= 1/2`), so the loop has two divisions and one square root, as the textbook formula has;
    divided form by form, it would have five, and a division is the slowest vector instruction
    here. Under TIR `k_t = 0`, so both quotients are transmittances equal to 0: `R = 1` and
    `T = 0` exactly, with no select on the TIR mask. Where `not t.ok` the quotients may be inf or
    NaN (`_terms(..., own_jvp=True)` leaves the divisors as they are); every caller selects on
    `t.ok`.
    """
    e1, e2, ki, kt, ds, dp, diff = t.e1, t.e2, t.ki, t.kt, t.den_s, t.den_p, t.diff
    kk4 = 4 * ki * kt
    ds2 = ds * ds
    small_s = _SQRT2 * jnp.abs(diff) <= ds2  # |diff| scaled, not ds2: a scalar for scalar indices
    q_s = _one_reader(jnp.where(small_s, -diff, kk4) / ds2)
    # r_p's rationalized numerator x (see `_r_amplitudes`) and the direct one
    x = jnp.where(diff >= 0, ki * ds - e1 * e1, ki * kt + t.m)
    num = e2 * e2 * ki - e1 * e1 * kt
    rational = 3 * jnp.abs(num) <= dp
    small_p = jnp.abs(num) <= _HALF_SQRT2 * dp  # true wherever `rational` is
    n_p = jnp.where(rational, diff * x, jnp.where(small_p, num, kk4 * (eta1 * eta2) ** 2))
    d_p = dp * jnp.where(rational, ds, jnp.where(small_p, 1, dp))  # D_s D_p, D_p or D_p**2
    q_p = _one_reader(n_p / d_p)
    return small_s, q_s, small_p, q_p


def _reflectance(small, q):
    return jnp.where(small, q * q, 1 - q)


def _at_grazing(t: _Terms):
    """R where the denominators vanish (`not t.ok`: grazing incidence, where k_i^2 and k_t^2 are
    below the smallest normal number): 1 under TIR, 0 where eta1 == eta2 (no interface). There
    k_t^2 = diff + k_i^2 has the sign of diff, so this is `diff < 0`, which costs nothing per
    element when the indices are scalars (the TIR mask would be a comparison per element)."""
    return (t.diff < 0).astype(t.ki.dtype)


def _powers_real(t: _Terms, eta1, eta2):
    """(R_s, R_p, T_s, T_p) for a real eta2 (no NaN mask), from `_quotients_real`."""
    small_s, q_s, small_p, q_p = _quotients_real(t, eta1, eta2)
    R0 = _at_grazing(t)

    def pair(small, q):
        T = jnp.where(small, 1 - q * q, q)
        return jnp.where(t.ok, _reflectance(small, q), R0), jnp.where(t.ok, T, 1 - R0)

    (R_s, T_s), (R_p, T_p) = pair(small_s, q_s), pair(small_p, q_p)
    return R_s, R_p, T_s, T_p


def _powers(t: _Terms, eta1, eta2):
    """(R_s, R_p, T_s, T_p) from the shared intermediates, for real or complex eta2 (no NaN mask)."""
    if not jnp.iscomplexobj(t.kt):
        return _powers_real(t, eta1, eta2)
    r_s, r_p = _r_amplitudes(t)
    # Power entering medium 2 (Poynting flux just past the interface), equal to 1 - R.
    ki = jnp.real(t.ki)
    Ts = 4 * ki * jnp.real(t.kt) * _abs2(t.inv_s)
    Tp = 4 * eta1 * eta1 * ki * jnp.real(eta2 * eta2 * jnp.conj(t.kt)) * _abs2(t.inv_p)
    R_s, T_s = _power_pair(t, _abs2(r_s), Ts)
    R_p, T_p = _power_pair(t, _abs2(r_p), Tp)
    return R_s, R_p, T_s, T_p


def _sp_rt(cos_i, eta1, eta2):
    """(R_s, R_p, T_s, T_p) for real or complex eta2, NaN for invalid elements."""
    if not jnp.iscomplexobj(eta2):
        return _sp_rt_real(cos_i, eta1, eta2, _q_real(cos_i, eta1, eta2))
    t = _terms(cos_i, eta1, eta2)
    return _nan_where_invalid(t.valid, *_powers(t, eta1, eta2))


def _q_real(cos_i, eta1, eta2):
    # the `|cos_i|` of `_terms(..., own_jvp=True)` (one instruction; its derivative is not used)
    return _kt_squared(eta1 * jnp.abs(cos_i), eta1, eta2)[0]


@jax.custom_jvp
def _sp_rt_real(cos_i, eta1, eta2, q):
    # q = k_t^2, computed by `_q_real` from the same inputs (passed in so that `_rt_two_loops` can
    # compute it once for two loops); it is not differentiated separately (the rule below covers
    # the whole dependence on cos_i, eta1 and eta2).
    t = _terms(cos_i, eta1, eta2, q_given=q, own_jvp=True)
    return _nan_where_invalid(t.valid, *_powers(t, eta1, eta2))


@jax.custom_jvp
def _fresnel_real(cos_i, eta1, eta2, q):
    """`fresnel` for a real eta2: `(R_s + R_p) / 2` from `_quotients_real`, with the grazing and
    invalid-element selects applied once to the sum instead of to each polarization. It ends in a
    select, as `unpolarized` does and for the same reason (a reduction that consumes it does not
    cut its loop)."""
    t = _terms(cos_i, eta1, eta2, q_given=q, own_jvp=True)
    small_s, q_s, small_p, q_p = _quotients_real(t, eta1, eta2)
    R = jnp.where(t.ok, 0.5 * (_reflectance(small_s, q_s) + _reflectance(small_p, q_p)), _at_grazing(t))
    # A non-finite cos_i needs no test of its own: it makes D_p's terms inf - inf or NaN, so `q_p`
    # and `R` are NaN, and `t.ok` lets that through (tested). Only the indices are tested, which
    # for scalar indices is no work per element.
    return jnp.where(_positive_finite(eta1) & _positive_finite(eta2), R, jnp.nan)


def _fresnel_real_jvp(primals, tangents):
    t = _terms(*primals[:3], q_given=primals[3], own_jvp=True)
    dR_s, dR_p = _real_tangents(t, primals[0], tangents[:3])
    # the primal output through `_fresnel_real` itself (see `_sp_rt_real_jvp`)
    return _fresnel_real(*primals), 0.5 * (dR_s + dR_p)


_fresnel_real.defjvp(_fresnel_real_jvp, symbolic_zeros=True)


def _rt_two_loops(cos_i, eta1, eta2):
    """Unpolarized (R, T), real eta2, as two fused loops instead of about ten (R is `fresnel`'s).

    XLA on the CPU has no multi-output loop fusion: the quotients that both R and T need are
    otherwise each written to memory and read back (measured: `fresnel_rt` 12 ns/element against
    1.5 for `fresnel`, 11 fused loops). Here the transmittance loop recomputes everything from
    inputs passed through an optimization barrier, which XLA cannot identify with the reflectance
    loop's (so no common subexpression ties them together again). R and T then each carry their own
    roundings, and R + T - 1 is within a few ulps of 0 instead of exactly so.

    Both loops compute k_t^2 from the same expression, and the TIR decision and the m consistent
    with it (see `_kt_squared`) come from that in each. Materializing k_t^2 once instead (see
    `materialize`) made it worse: each loop's m, contracted its own way, then disagreed with the
    shared k_t^2, and the amplification near the critical angle broke R + T = 1 by 5e-3 in the
    stress test (float32). (The barriers do not materialize anything: XLA's CPU pipeline removes
    them before fusion; what they do is keep the two loops' copies apart.)
    """
    q = jax.lax.optimization_barrier(_q_real(cos_i, eta1, eta2))
    _, _, T_s, T_p = _sp_rt_real(*_own_loop(cos_i, eta1, eta2, q))
    return _fresnel_real(cos_i, eta1, eta2, q), unpolarized(T_s, T_p)


def _sp_rt_real_jvp(primals, tangents):
    r"""Closed-form derivatives of R_s and R_p (and T = 1 - R) for a real index.

    Autodiff through the careful forms above costs 3.4x (forward mode) to 17x (reverse) the
    function; these cost about nothing on top of it, since they reuse its intermediates
    (measured: `python -m jaxoptics bench`, gradient rows). With k_i = eta1 c, k_t^2 = q =
    eta2^2 - eta1^2 + k_i^2, m = k_i^2 - eta1^2 = -eta1^2 sin^2, diff = eta2^2 - eta1^2, g = 1/k_t,
    D_s = k_i + k_t, D_p = eta2^2 k_i + eta1^2 k_t:

    $$dR_s = \frac{4 r_s g}{D_s^2}\left(\eta_1\,\mathrm{diff}\,dc + c\,\eta_2^2\,d\eta_1 - k_i \eta_2\,d\eta_2\right)$$

    $$dR_p = \frac{4 r_p g \eta_1}{D_p^2}\left(\eta_1^2 \eta_2^2\,\mathrm{diff}\,dc - \eta_2^2 k_i (k_t^2 + m)\,d\eta_1
    + \eta_1 \eta_2 k_i (2 k_t^2 - \eta_2^2)\,d\eta_2\right)$$

    (the cancelling combinations k_t - k_i^2/k_t and k_t^2 - m are replaced by diff/k_t and
    eta2^2 exactly). Conventions kept from the autodiff version: 0 under TIR, at the critical
    angle (k_t = 0: the double-where square root), where there is no interface, and for invalid
    elements; d|c|/dc = +1 at c = 0 (`_abs_cos`). The coefficients are selected to 0 *before*
    multiplying the tangents, so the transposed (reverse-mode) map has no 0 * inf either.
    """
    cos_i, eta1, eta2, q = primals
    t = _terms(cos_i, eta1, eta2, q_given=q, own_jvp=True)
    dR_s, dR_p = _real_tangents(t, cos_i, tangents[:3])
    # The primal output through `_sp_rt_real` itself, not from `t`: differentiating this rule
    # (second derivatives) then uses this rule again instead of autodiff through the unguarded
    # own-derivative terms (XLA merges the two evaluations).
    return _sp_rt_real(*primals), (dR_s, dR_p, -dR_s, -dR_p)


_sp_rt_real.defjvp(_sp_rt_real_jvp, symbolic_zeros=True)


def _real_tangents(t: _Terms, cos_i, tangents):
    """(dR_s, dR_p) from the tangents of (cos_i, eta1, eta2) (see `_sp_rt_real_jvp`).

    This rule is itself differentiated where second derivatives are taken (a fit's
    implicit-function gradient takes them), so it uses the divisors guarded as in `_terms`: the
    terms of `_terms(..., own_jvp=True)` leave them 0 at grazing incidence, and reverse mode
    through `1 / 0` gives 0 * inf = NaN even where the result is selected away."""
    den_s, den_p = jnp.where(t.ok, t.den_s, 1), jnp.where(t.ok, t.den_p, 1)
    t = t._replace(den_s=den_s, den_p=den_p, inv_s=1 / den_s, inv_p=1 / den_p)
    r_s, r_p = _r_amplitudes(t)
    live = t.ok & t.valid & ~t.tir & (t.kt > 0)
    e1, e2, c, ki, m, diff = t.e1, t.e2, t.c, t.ki, t.m, t.diff
    kt = jnp.where(live, t.kt, 1)
    S = 4 * r_s * t.inv_s * t.inv_s / kt
    P = 4 * r_p * e1 * t.inv_p * t.inv_p / kt
    e2sq = e2 * e2
    # selected to 0 before they meet the tangents (no 0 * inf in the transposed map)
    sel = lambda x: jnp.where(live, x, 0)
    coef_s = (sel(S * (e1 * diff)), sel(S * (c * e2sq)), sel(S * (-ki * e2)))
    coef_p = (sel(P * (e1 * e1 * e2sq * diff)), sel(P * (-e2sq * ki * (kt * kt + m))), sel(P * (e1 * e2 * ki * (2 * kt * kt - e2sq))))
    sign = jnp.where(cos_i < 0, -1, 1).astype(c.dtype)
    zero = jnp.zeros_like(c)

    def apply(coefs):
        acc = zero
        for k, (a, d) in enumerate(zip(coefs, tangents)):
            if type(d) is SymbolicZero:
                continue
            acc = acc + a * (sign * d if k == 0 else d)
        return acc

    return apply(coef_s), apply(coef_p)
