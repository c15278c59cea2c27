r"""Thin-film stacks: coherent and incoherent multilayers and ellipsometry.

Conventions
-----------
* A stack of ``L`` media: ``n[..., 0]`` is the (real) medium the light comes from, ``n[..., -1]``
  the medium it leaves into (real or absorbing), ``n[..., 1:-1]`` the inner layers, of thickness
  ``d[..., :]`` in the same unit as the vacuum ``wavelength``. Indices are ``n + ik`` with
  ``k >= 0`` absorbing, time dependence ``exp(-i omega t)``, as in `fresnel` and tmm. A ``k``
  below zero by at most ``1e-12 |n|`` (rounding, as interpolated tables give near ``k = 0``) is
  taken as ``k = 0``; further below, it is gain, which the kernel refuses.
* ``cos_i`` is the cosine of the angle of incidence in medium 0 (its sign is ignored).
* Amplitudes use the sign convention of `fresnel_amplitudes` (Hecht's, the one tmm uses):
  ``r_p = -r_s`` at normal incidence; ``t_s``, ``t_p`` are ratios of the transmitted to the
  incident electric field amplitude (for p, of the whole in-plane field, not its tangential part).
  With ``L = 2`` the stack is one interface and equals `fresnel_amplitudes` / `fresnel_sp`.
* Powers are fractions of the incident power: ``R = |r|**2``; ``T`` the power crossing into the last
  medium (``Re(k_z)`` normalization, as tmm's ``T``); ``A[..., j]`` the power absorbed in inner
  layer ``j``. ``R + T + sum(A) = 1`` for each polarization, to rounding.
* Ellipsometry: ``psi = atan(|r_p / r_s|)``, ``delta = arg(-r_p / r_s)`` in ``(-pi, pi]`` (tmm's
  ``ellips``). Instruments (``N = n - ik``, ``rho = r_p / r_s``) report ``Psi = psi`` and
  ``Delta = pi - delta``; see `ellipsometry`.

Formulation, and why
--------------------
Each inner layer ``j`` has ``q_j = k_{z,j}**2 = n_j**2 - n_0**2 sin**2`` (formed as in `fresnel`,
without ``1 - cos**2``) and phase thickness ``delta_j = a_j k_{z,j}``, ``a_j = 2 pi d_j / lambda``.
The tangential fields ``(E, H)`` on the two faces of a layer are related by its characteristic
matrix (s: admittance ``k_z``; p: ``n**2 / k_z``)::

    s: [[cos d, -i s],  [-i q s,       cos d]]        s = sin(delta) / k_z
    p: [[cos d, -i q s / n**2], [-i n**2 s, cos d]]

and the stack is the product of these applied to the field of the outgoing wave, ``(1, k_z)``
(s) or ``(k_z, n**2)`` (p), in the last medium. Three properties decide the formulation:

1. **No overflow.** ``cos(delta)`` and ``sin(delta)`` grow like ``exp(Im delta)`` in an absorbing
   or evanescent layer (plain transfer matrices overflow for ``d k / lambda`` beyond about 100 in
   float64, 10 in float32). Each layer's matrix is therefore multiplied by
   ``g = |exp(i delta)| = exp(-Im delta)``, ``<= 1`` on the decaying branch ``Im k_z >= 0``; its
   entries become ``(cos x (1 + e) - i sin x (1 - e)) / 2`` and the like (``delta = x + i y``,
   ``e = exp(-2 y)``, `_layer_cs`), all bounded, and ``e`` underflows harmlessly to 0.
   Reflection amplitudes are ratios and do not see the factors; transmission and the flux at each
   interface are multiplied back by the products of ``g`` in front of them, which are <= 1.
   The factor is real so that a lossless layer's matrix stays real: with lossless layers and an
   evanescent wave in the last medium (total internal reflection) the fields then keep their
   phases exactly, every flux is an exact 0 and ``R = 1`` to a few ulps. (A complex factor such as
   ``exp(i delta)`` lets rounding mix the phases. Near grazing incidence the stack is a cavity of
   high finesse between the first interface and the last, whose resonances amplify that mixing:
   with ``exp(i delta)``, float32 ``R`` of such a stack is off by up to 4%, with absorption in
   lossless layers.)
2. **No removable singularities.** The Abeles/Rouard recursion on interface coefficients
   ``r_{j,j+1}`` divides by ``k_{z,j} + k_{z,j+1}`` and gives 0/0 (NaN) when an inner layer is at
   its own critical angle (``k_{z,j} = 0``, so ``r = +-1`` on both of its faces). The matrix
   entries above are even in ``k_z``, hence entire functions of ``q``: nothing is singular there.
3. **Exact, finite derivatives.** Because the entries are entire in ``q``, their derivatives are
   given in closed form (``d cos / dq = -a s / 2``, ``d s / dq = (a cos - s) / (2 q)``, which
   cancels for small ``delta``; there ``s a**2 R(delta**2)`` with ``R = (delta cot(delta) - 1) /
   (2 delta**2)`` by its power series), never through ``dk_z / dq = 1 / (2 k_z)``. The scale factor
   ``g`` is given a zero derivative: every output is invariant under rescaling a layer's matrix
   when the same factor multiplies the flux normalization, so the derivatives computed this way
   are the exact ones.

The layer recursion has its own `jax.custom_jvp` (`_fields`): a scan over the layers that also
records the field entering each layer and its ``c``, ``s``, then a second scan that carries the
tangent fields, linear in the tangents, with the closed forms above. Forward mode runs both; reverse
mode transposes only the second, which reads the recorded values instead of recomputing the layers'
exponentials and argument reductions. The magnetic field is carried as ``-i H``, which makes the
matrices free of the factor ``i`` (fewer complex multiplications in both scans). The recording scan
has a rule of its own too (`_fields_recorded`: the tangents of the recorded fields and entries come
from the second scan), so second derivatives use the same closed forms: they are exact where a
layer's ``k_z`` is 0 as well (tested against mpmath).

The only genuine branch point is that of the last medium (its critical angle, where ``k_z`` of the
outgoing wave is 0): there the derivative with respect to the angle or the indices is infinite
(as for one interface); the kernel returns the finite one-sided value of `fresnel`'s convention
(the ``k_z`` of the last medium is given a zero derivative at that point only).

Large batches are cut into blocks of 32768 points, evaluated one after the other inside the
compiled program (`lax.map`): the per-layer loop then works on arrays that stay in the CPU's
caches, which halves the time per point on 10^6 points (see `_chunked`).

Incoherent layers
-----------------
An incoherent layer (thick: phases average out, intensities add) is treated as tmm's ``inc_tmm``
does (S. Byrnes, arXiv:1603.02720): the coherent groups between incoherent layers have forward
and backward R, T and absorption; an incoherent layer passes intensity with
``P = exp(-2 a Im k_z)`` per pass. The multiple reflections are summed by a backward recursion of
the effective reflectance ``Gamma = R_f + T_f T_b P**2 Gamma' / (1 - R_b P**2 Gamma')``, which
contains only decaying factors (tmm's intensity transfer matrices divide by ``P`` and clamp it at
1e-30). For ellipsometry the same recursion carries the incoherent sum of ``r_p conj(r_s)`` over
all paths (field products of the same path only; paths do not interfere).

Out-of-domain values
--------------------
Nothing raises inside ``jit``: an element with a negative or non-finite thickness or wavelength,
a non-finite ``cos_i``, an index with real part <= 0 or imaginary part < 0, or an absorbing
incident medium gives NaN in every output. Concrete (non-traced) inputs are checked before
tracing and raise a ``ValueError`` naming the argument and the first bad value.

References: M. Born, E. Wolf, *Principles of Optics*, sec. 1.6; H. A. Macleod, *Thin-Film Optical
Filters*, ch. 2; S. J. Byrnes, *Multilayer optical calculations*, arXiv:1603.02720 (tmm);
R. M. A. Azzam, N. M. Bashara, *Ellipsometry and Polarized Light*.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _validate as V
from ._fresnel import _abs2, _kt_squared, _materialize_parts, decaying_sqrt, sqrt_where, unpolarized
from ._result import Unpacks, result

if TYPE_CHECKING:
    from jaxtyping import ArrayLike, Float, Inexact


@result
class StackResult(Unpacks):
    """Result of `stack` (arrays of the batch shape ``(...)`` unless stated).

    **Fields:**

    - `R_s`, `R_p`, `T_s`, `T_p`: real reflectance and transmittance per polarization.
    - `A_s`, `A_p`: real, shape ``(..., L-2)``: the fraction absorbed in each inner layer.
    - `r_s`, `r_p`, `t_s`, `t_p`: complex amplitudes (see the module conventions); `None` when
      the stack has incoherent layers (amplitudes have no meaning there).
    - `rp_rs`: complex ``r_p * conj(r_s)``, summed incoherently over paths where layers are
      incoherent; `ellipsometry` is computed from it. ``|rp_rs| / sqrt(R_p R_s)`` is 1 for a
      coherent stack and less than 1 (depolarization) with incoherent layers.

    **Properties:** `R`, `T` (unpolarized), `A` (unpolarized, ``(..., L-2)``).
    """

    R_s: jax.Array
    R_p: jax.Array
    T_s: jax.Array
    T_p: jax.Array
    A_s: jax.Array
    A_p: jax.Array
    r_s: jax.Array | None
    r_p: jax.Array | None
    t_s: jax.Array | None
    t_p: jax.Array | None
    rp_rs: jax.Array

    @property
    def R(self):
        """Unpolarized reflectance ``(R_s + R_p) / 2``."""
        return unpolarized(self.R_s, self.R_p)

    @property
    def T(self):
        """Unpolarized transmittance ``(T_s + T_p) / 2``."""
        return unpolarized(self.T_s, self.T_p)

    @property
    def A(self):
        """Unpolarized absorption per inner layer ``(A_s + A_p) / 2``, shape ``(..., L-2)``."""
        return unpolarized(self.A_s, self.A_p)


@result
class Ellipsometry(Unpacks):
    """Ellipsometric angles in radians, arrays of the batch shape: `psi` in `[0, pi/2]`, `delta`
    in `(-pi, pi]` (tmm's `ellips` convention; instruments report `Psi = psi`,
    `Delta = pi - delta`: see `ellipsometry`). NaN for out-of-domain elements."""

    psi: jax.Array
    delta: jax.Array


# ---- the layer's matrix entries, entire in q ---------------------------------------------------

# |a^2 q| below this: d s/dq = s a^2 R(a^2 q) with R by its power series (8 terms: truncation
# below 1e-17 relative, the series converging for |a^2 q| < pi^2); above it the closed form
# (a c - s) / (2 q) cancels by at most 3 / |a^2 q| = 48 ulps
_DS_SERIES_MAX = 1 / 16
_DS_SERIES_TERMS = 8


def _bernoulli_even(m):
    """B_0, B_2, ..., B_2m as exact fractions (Akiyama-Tanigawa)."""
    from fractions import Fraction

    out, a = [], []
    for n in range(2 * m + 1):
        a.append(Fraction(1, n + 1))
        for j in range(n, 0, -1):
            a[j - 1] = j * (a[j - 1] - a[j])
        if n % 2 == 0:
            out.append(a[0])
    return out


# R(x) = (delta cot(delta) - 1) / (2 delta^2), x = delta^2: the coefficients of x^(n-1), n >= 1,
# from delta cot(delta) = sum_n (-1)^n 2^(2n) B_2n delta^(2n) / (2n)!
_R_COEFFS = tuple(float((-1) ** n * 2 ** (2 * n) * b / (2 * math.factorial(2 * n)))
                  for n, b in enumerate(_bernoulli_even(_DS_SERIES_TERMS)) if n >= 1)


def _sin_cosm1(x):
    """(sin x, cos x - 1) for |x| <= pi/4 by their Taylor series (truncation below 1e-19 relative
    in float64 with 8 and 9 terms, 1e-9 in float32 with 4 and 5)."""
    x2 = x * x
    f64 = x.dtype == jnp.float64
    ns, nc = (8, 9) if f64 else (4, 5)
    ps = jnp.zeros_like(x)
    for k in range(ns, 0, -1):  # sum_{k>=1} (-1)^k x^(2k) / (2k+1)!
        ps = ps * x2 + (-1) ** k / math.factorial(2 * k + 1)
    pc = jnp.zeros_like(x)
    for k in range(nc, 0, -1):  # sum_{k>=1} (-1)^k x^(2k-2) / (2k)!
        pc = pc * x2 + (-1) ** k / math.factorial(2 * k)
    return x + x * x2 * ps, x2 * pc


# pi/2 = sum of the parts (all but the last with trailing zero bits, so that their products with
# an integer k are exact): fdlibm's pio2_1, pio2_2, pio2_3 (33 + 33 + 53 bits) and its tail, and
# Cephes' sinf DP1..DP3 doubled (8 + 11 + 21 bits, the last rounded to float32) and the tail
_PIO2_SPLIT_F64 = (1.57079632673412561417e+00, 6.07710050630396597660e-11, 2.02226624871116645580e-21,
                   8.47842766036889956997e-32)
_PIO2_SPLIT_F32 = (1.5703125, 4.837512969970703125e-4, 7.549789415861596e-8, 5.390302953474238e-15)


def _sincos(y):
    """(sin y, cos y) for real y of any size, with one argument reduction, vectorized.

    XLA's float64 sine and cosine on the CPU cost about 7 ns per element (exp: 0.5 ns; measured at
    10^6 elements) and reduce the argument once each. Here `k = round(y / (pi/2))` and
    `r = y - k pi/2` with pi/2 split in four parts whose leading ones have trailing zero bits (Cody
    and Waite; fdlibm's and Cephes' constants), so the products with `k` are exact for
    `|k| < 2**20` (float64) or `2**13` (float32) and `r` is accurate to an ulp even where it is tiny
    (y near a multiple of pi/2); sin and cos of `r` come from one polynomial each, rotated by
    `k mod 4`. The layer entries formed from them are within 4 ulps of mpmath (tested); beyond
    `|y| = 1.6e6` (float64) or `1.3e4` (float32) the reduction adds an error of order ulp(y), as
    large as the rounding of `y` itself.
    """
    k = jnp.round(y * (2 / math.pi))
    split = _PIO2_SPLIT_F64 if y.dtype == jnp.float64 else _PIO2_SPLIT_F32
    r = y
    for part in split:
        r = r - k * part
    sn, cm1 = _sin_cosm1(r)
    m = k - 4 * jnp.floor(0.25 * k)  # k mod 4, in 0..3
    cs = 1 + cm1
    sin_y = jnp.where(m == 0, sn, jnp.where(m == 1, cs, jnp.where(m == 2, -sn, -cs)))
    cos_y = jnp.where(m == 0, cs, jnp.where(m == 1, -sn, jnp.where(m == 2, -cs, sn)))
    return sin_y, cos_y


def _pade(c, L, M):
    """The [L/M] Pade approximant of the power series `sum c[k] w^k`: numerator and denominator
    coefficients (constant term first, the denominator's equal to 1) as exact fractions, from the
    linear system `sum_j q_j c_(L+i-j) = 0`, `i = 1..M`, solved by Gaussian elimination."""
    from fractions import Fraction

    c = [Fraction(x) for x in c]
    at = lambda k: c[k] if k >= 0 else Fraction(0)
    A = [[at(L + i - j) for j in range(1, M + 1)] + [-at(L + i)] for i in range(1, M + 1)]
    for col in range(M):
        piv = next(r for r in range(col, M) if A[r][col] != 0)
        A[col], A[piv] = A[piv], A[col]
        for r in range(M):
            if r != col and A[r][col] != 0:
                f = A[r][col] / A[col][col]
                A[r] = [a - f * b for a, b in zip(A[r], A[col])]
    q = [Fraction(1)] + [A[i][M] / A[i][i] for i in range(M)]
    p = [sum(q[j] * at(k - j) for j in range(min(k, M) + 1)) for k in range(L + 1)]
    return p, q


def _atan_pade(L, M):
    """atan(z) = z (1 + w g(w) / Q(w)), w = z^2, from the [L/M] Pade approximant P/Q of
    f(w) = atan(sqrt(w)) / sqrt(w) = sum_k (-1)^k w^k / (2k + 1): `(g, Q)` coefficients (constant
    first), g(w) = (P(w) - Q(w)) / w formed exactly, so that the small correction is not the
    difference of two rounded numbers near 1."""
    from fractions import Fraction

    P, Q = _pade([Fraction((-1) ** k, 2 * k + 1) for k in range(L + M + 1)], L, M)
    n = max(L, M)
    P, Q = P + [Fraction(0)] * (n + 1 - len(P)), Q + [Fraction(0)] * (n + 1 - len(Q))
    return tuple(float(P[k] - Q[k]) for k in range(1, n + 1)), tuple(float(x) for x in Q[: M + 1])


# atan(z) for |z| <= tan(pi/8) from the Pade approximant of atan(sqrt(w)) / sqrt(w): [5/6] in
# float64 (relative error below 2.3e-17 on the range) and [2/3] in float32 (below 5.9e-9), as
# checked with mpmath when these degrees were chosen
_ATAN_PADE = {"float64": _atan_pade(5, 6), "float32": _atan_pade(2, 3)}
_TAN_PI_8 = math.sqrt(2) - 1


def _pio4_split(bits):
    """pi/4 as `hi + lo`, `hi` on a grid of `2**-bits` (so `k hi` is exact for k <= 4 in a float
    with more than `bits + 2` mantissa bits) and `lo` the rest, from pi to 40 digits."""
    from fractions import Fraction

    pio4 = Fraction("3.141592653589793238462643383279502884197") / 4
    hi = Fraction(round(pio4 * 2**bits), 2**bits)
    return float(hi), float(pio4 - hi)


_PIO4_SPLIT = {"float64": _pio4_split(50), "float32": _pio4_split(21)}


@jax.custom_jvp
def _atan2(y, x):
    """`arctan2(y, x)` for real `y`, `x` (same dtype), vectorized: within 2 ulps of mpmath (tested).

    XLA's CPU backend computes `atan2` by a scalar library call per element, which costs a third
    of the ellipsometric quantities' time. Here `t = min(|x|, |y|) / max(|x|, |y|)` in `[0, 1]`,
    reduced to `|z| <= tan(pi/8)` by `atan(t) = pi/4 + atan((t - 1) / (t + 1))` (with `z` formed
    from `x` and `y` directly: `(min - max) / (min + max)`), `atan(z)` from a
    Pade approximant (`_ATAN_PADE`), then the octant restored in one addition, `k pi/4 +- a` with
    pi/4 in two parts (`pi/2 - a` where `|y| > |x|`, `pi - a` where `x` is negative or -0), and
    the sign of `y`. `(0, 0)` gives 0 (or pi for
    `x = -0`) as `arctan2` does; non-finite inputs give NaN. Its derivative is
    `(x dy - y dx) / (x^2 + y^2)` (0 at the origin)."""
    name = "float64" if y.dtype == jnp.float64 else "float32"
    g, q = _ATAN_PADE[name]
    hi_4, lo_4 = _PIO4_SPLIT[name]
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi, lo = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    t = jnp.where(hi > 0, lo / jnp.where(hi > 0, hi, 1), 0)
    big = t > _TAN_PI_8
    z = jnp.where(big, (lo - hi) / jnp.where(big, lo + hi, 1), t)  # (t - 1) / (t + 1) without t's rounding
    w = z * z
    num, den = jnp.full_like(w, g[-1]), jnp.full_like(w, q[-1])
    for c in g[-2::-1]:
        num = num * w + c
    for c in q[-2::-1]:
        den = den * w + c
    a = z + z * w * (num / den)
    # the octant: |atan2| = k pi/4 + sign a, added once, with pi/4 in two parts (k hi is exact)
    k = jnp.where(big, 1, 0)
    sign = jnp.where(ay > ax, -1, 1)
    k = jnp.where(ay > ax, 2 - k, k)
    sign = jnp.where(jnp.signbit(x), -sign, sign)
    k = jnp.where(jnp.signbit(x), 4 - k, k).astype(y.dtype)
    a = (k * hi_4 + sign * a) + k * lo_4
    out = jnp.where(jnp.signbit(y), -a, a)
    return jnp.where(jnp.isfinite(x) & jnp.isfinite(y), out, jnp.nan)


@_atan2.defjvp
def _atan2_jvp(primals, tangents):
    y, x = primals
    dy, dx = tangents
    r2 = x * x + y * y
    return _atan2(y, x), jnp.where(r2 > 0, (x * dy - y * dx) / jnp.where(r2 > 0, r2, 1), 0)


def _decaying_root(q):
    """sqrt(q) with Im >= 0, written out (Kahan's form: no cancellation; 4x cheaper than XLA's
    complex sqrt on the CPU). Not differentiable at q = 0: used where no derivative is taken."""
    x, y = jnp.real(q), jnp.imag(q)
    t = jnp.sqrt(0.5 * (jnp.abs(x) + jnp.hypot(x, y)))
    h = jnp.where(t > 0, 0.5 * y / jnp.where(t > 0, t, 1), 0)  # y / (2t)
    re = jnp.where(x >= 0, jnp.where(y < 0, -t, t), h)
    im = jnp.where(x >= 0, jnp.abs(h), t)
    return jax.lax.complex(re, im)


def _ds_dq_series(x):
    """R(x) = (delta cot(delta) - 1) / (2 delta^2) with x = delta^2, by its series: d s/dq = s a^2 R.

    (With g held constant, s = g a sin(delta)/delta and d s/dq = g a^3 (delta cos(delta) -
    sin(delta)) / (2 delta^3); their ratio is a^2 R. So the derivative needs neither g nor a
    division where the closed form cancels.)"""
    acc = jnp.zeros_like(x)
    for coef in reversed(_R_COEFFS):
        acc = acc * x + coef
    return acc


# ---- one coherent group ------------------------------------------------------------------------


class _Group(NamedTuple):
    """One polarization's results for a coherent group lit from its first medium."""

    r: jax.Array
    t: jax.Array
    R: jax.Array
    T: jax.Array
    entering: jax.Array  # power crossing the first interface (1 - R for a real incident medium)
    A: jax.Array  # absorbed in each inner layer, layer axis first: (m, ...)


def _group(kz0, n0, kze, ne, nn, dd, k0, kz_sq, *, real_incident: bool):
    """Coherent group: incident medium (kz0, n0), exit medium (kze, ne), inner layers of index
    `nn` and thickness `dd` stacked on a leading layer axis, front to back, and the vacuum wave
    number k0 = 2 pi / lambda; `kz_sq(n)` gives a medium's k_z^2 (formed as in `fresnel`, from
    medium 0 of the stack). `nn`, `dd`, `k0` broadcastable to the batch shape, which they need not
    have: a layer's phase thickness a = k0 d is formed inside the scan step, so no (layers x
    points) array is materialized. Returns (s, p) `_Group`s.

    The fields are carried from the back to the front by a `lax.scan` over the layers (XLA
    duplicates the two-component recurrence into each consumer when it is unrolled: compile time
    and work then grow much faster than the number of layers)."""
    m = nn.shape[0]
    one = jnp.ones_like(kze)
    v_s, v_p = (one, kze), (kze, jnp.broadcast_to(ne * ne, kze.shape))
    if m:
        (w0s, w0p, fs, fp), (S_all, im_phase) = _fields(nn, dd, k0, kz_sq.ki, kz_sq.n0, (v_s, v_p))
        # the product of the scale factors, and |the product in front of interface k|^2 from the
        # prefix sums of the attenuations (not as total minus suffix: with 1e5 nepers in a thick
        # absorber behind, that difference loses everything in float32)
        G = jnp.exp(-jnp.imag(S_all))  # (for the amplitudes t only: dropped from the program without them)
        X_last = jnp.exp(-2 * jnp.imag(S_all))  # G^2
        prefix = jnp.concatenate([jnp.zeros_like(im_phase[:1]), jnp.cumsum(im_phase[:-1], axis=0)], axis=0)
        X = jnp.exp(-2 * prefix)
    else:
        w0s, w0p = v_s, v_p
        fs = fp = jnp.zeros((0,) + jnp.shape(kze), jnp.real(kze).dtype)
        G = X_last = jnp.ones(jnp.shape(kze), jnp.real(kze).dtype)
        X = fs
    out = []
    n0sq = n0 * n0
    for pol, (B, C), flux_hat in (("s", w0s, fs), ("p", w0p, fp)):
        if pol == "s":
            D = kz0 * B + C
            r = (kz0 * B - C)
            tnum = 2 * kz0
        else:
            D = n0sq * B + kz0 * C
            r = (kz0 * C - n0sq * B)
            tnum = 2 * n0 * ne * kz0
        nu, f = _flux_norm(pol, kz0, n0sq, real_incident)
        # D = 0 only at grazing incidence on a stack with no interface at all (every medium of the
        # incident medium's index): r = 0, t = 1, as `fresnel` there. The divisor is replaced too, so
        # no NaN leaks into gradients.
        ok = _abs2(D) > 0
        D = jnp.where(ok, D, 1)
        # 1/D and 1/|D|^2 through D scaled by a power of 2 (the same bits): near grazing incidence
        # on such a stack |D| is small, and the derivative of 1/|D|^2, taken as 1/|D|^4, would
        # underflow to 0 in float32 where |D| < 1e-10 (a NaN gradient)
        sc = _pow2_scale(D)
        Dh = D * sc.astype(D.dtype)
        inv_D = _materialize_parts(jnp.conj(Dh) * (sc / _abs2(Dh)).astype(D.dtype))
        r = jnp.where(ok, _over(r, D, inv_D), 0)
        t = jnp.where(ok, _over(_rmul(G, tnum), D, inv_D), 1)
        # flux through each interface, times the scale factors in front of it (module docs):
        # interfaces 0..m-1 from the scan, the first and the last also directly
        scale = nu * (sc * f * sc) / _abs2(Dh)  # the powers of 2 first: no intermediate overflow
        last = jnp.where(ok, _flux(*(v_s if pol == "s" else v_p)) * scale * X_last, 1)
        entering = jnp.where(ok, _flux(B, C) * scale, 1)
        inner = jnp.where(ok[None], flux_hat * scale[None] * X, 1)
        A = inner - jnp.concatenate([inner[1:], last[None]], axis=0)
        out.append(_Group(r, t, _abs2(r), last, entering, A))
    return out[0], out[1]


@jax.custom_jvp
def _over(x, D, inv_D):
    """`x / D` as `x * inv_D`, with `inv_D = 1 / D` computed once by the caller (shared by its
    quotients), and the derivative `(dx - (x / D) dD) / D`: the tangent of `1 / D` on its own, of
    order `dD / D^2`, is never formed. Near grazing incidence on a stack with no interface (D of
    order cos_i, dD of order 1 / cos_i in the imaginary parts of the indices) it overflows float32,
    and times `x = 0` (r there) gives NaN in forward mode."""
    return x * inv_D


@_over.defjvp
def _over_jvp(primals, tangents):
    x, D, inv_D = primals
    dx, dD, _ = tangents  # inv_D's own tangent is the dD term
    q = _over(x, D, inv_D)
    return q, _over(dx - q * dD, D, inv_D)


def _pow2_scale(D):
    """2**-e for the exponent e of the larger part of the complex D (so |D| 2**-e is between 1/2
    and 1.5), held constant for autodiff; limited to the dtype's normal range."""
    m = jnp.maximum(jnp.abs(jnp.real(D)), jnp.abs(jnp.imag(D)))
    lim = jnp.finfo(m.dtype).maxexp - 3
    e = jnp.clip(jnp.frexp(m)[1], -lim, lim)
    return jax.lax.stop_gradient(jnp.ldexp(jnp.ones_like(m), -e))


class _KzSq(NamedTuple):
    """k_z^2 of a medium, formed as in `fresnel` from the incident medium's (ki, n0)."""

    ki: jax.Array
    n0: jax.Array

    def __call__(self, nj):
        return _kt_squared(self.ki, self.n0, nj)[0]


def _rot(z):
    """-i z, without a complex multiplication."""
    return jax.lax.complex(jnp.imag(z), -jnp.real(z))


def _unrot(z):
    """i z, without a complex multiplication."""
    return jax.lax.complex(-jnp.imag(z), jnp.real(z))


def _rmul(x, z):
    """x z for real x and complex z, as two real multiplications."""
    return jax.lax.complex(x * jnp.real(z), x * jnp.imag(z))


def _ds_dq(c, s, q, a):
    """d s / d q (with g held constant) from c, s, q and the real a: module docstring, point 3."""
    a2 = a * a
    x = _rmul(a2, q)
    small = _abs2(x) < _DS_SERIES_MAX**2
    q_safe = jnp.where(small, 1, q)
    inv_2q = _rmul(0.5 / _abs2(q_safe), jnp.conj(q_safe))  # 1 / (2q), one real division
    return jnp.where(small, _rmul(a2, s) * _ds_dq_series(jnp.where(small, x, 0)), (_rmul(a, c) - s) * inv_2q)


def _apply(c, s, qs, rs, ns, w):
    """A layer's matrices applied to the fields w = (E_s, -i H_s, E_p, -i H_p): qs = q s,
    rs = (q / n^2) s, ns = n^2 s."""
    E1, T1, E2, T2 = w
    return c * E1 + s * T1, c * T1 - qs * E1, c * E2 + rs * T2, c * T2 - ns * E2


@jax.custom_jvp
def _fields(nn, dd, k0, ki, n0, v):
    """Fields at the front of the stack from the outgoing wave `v` in the exit medium, carried
    through the inner layers (index `nn`, thickness `dd`, layer axis first) by a `lax.scan` from
    back to front. Returns ((w0s, w0p, fluxes_s, fluxes_p), (sum of phases, Im phase per layer)):
    the second pair carries no derivative (the scale factors, module docstring point 3).

    Inside, the magnetic field is carried as ``H~ = -i H``: the characteristic matrices are then
    ``[[c, s], [-q s, c]]`` (s) and ``[[c, (q / n^2) s], [-n^2 s, c]]`` (p), with no factor i."""
    out, _ = _fields_scan(nn, dd, k0, ki, n0, v, False)
    return out


def _fields_scan(nn, dd, k0, ki, n0, v, residuals):
    """The primal scan of `_fields`: its outputs, and with `residuals` also, per layer, the field
    entering it from behind and its entries c, s (for the tangent scan of `_fields_jvp`)."""
    (Es, Hs), (Ep, Hp) = v

    def step(carry, lay):
        (Es, Ts, Ep, Tp), S = carry
        nj, dj = lay
        nsq = nj * nj
        # k_z^2 once and stored (`materialize`): XLA otherwise recomputes it in each fused loop
        # that reads it, contracting multiply-adds differently, and where it is near 0 (the layer
        # at its critical angle) the copies fall on both sides of 0 and the root's branch
        # differs between loops (tested: R = 0.22 instead of 1 in jitted float32)
        q = _materialize_parts(_kt_squared(ki, n0, nj)[0])
        a = k0 * dj
        kz = _decaying_root(q)
        phase = _rmul(a, kz)
        c, s = _layer_cs(phase, a)
        w2 = _apply(c, s, q * s, (q * (1 / nsq)) * s, nsq * s, (Es, Ts, Ep, Tp))
        fl = lambda E, T: jnp.imag(E * jnp.conj(T))
        ys = (fl(w2[0], w2[1]), fl(w2[2], w2[3]), jnp.imag(phase))
        if residuals:  # for the tangent scan: the field entering the layer from behind, c and s
            ys = ys + (((Es, Ts, Ep, Tp), c, s),)
        return (w2, S + phase), ys

    init = ((Es, _rot(Hs), Ep, _rot(Hp)), jnp.zeros(jnp.shape(Es), Es.dtype))
    (w0, S_all), ys = jax.lax.scan(step, init, (nn, dd), reverse=True)
    out = (((w0[0], _unrot(w0[1])), (w0[2], _unrot(w0[3])), ys[0], ys[1]), (S_all, ys[2]))
    return out, (ys[3] if residuals else None)


@jax.custom_jvp
def _fields_recorded(nn, dd, k0, ki, n0, v):
    """`_fields_scan` with its residuals: the outputs of `_fields` and, per layer, the field entering
    it from behind and its entries c, s.

    `_fields_jvp` takes its primal values from here, so that where the rule is itself
    differentiated (second derivatives) this function's own rule is used instead of autodiff
    through the scan: JAX applies a custom rule at the next order only to a function the rule
    calls. Autodiff would go through dk_z/dq = 1/(2 k_z) and through the scale factors g, whose
    derivatives are infinite where a layer's k_z is 0 (an inner layer at its own critical angle,
    or every layer of the incident medium's index at grazing incidence), and the Hessian would be
    NaN there, although no output depends on g."""
    return _fields_scan(nn, dd, k0, ki, n0, v, True)


def _tangents(primals, tangents, phases, residuals, *, recorded: bool):
    """A scan of the tangent fields from back to front, linear in the tangents: d(M w) = M dw + dM w,
    with dM from dq, da and d(n^2) through the closed-form entry derivatives (module docstring,
    point 3), g held constant. Returns the tangents of `_fields`' outputs and, with `recorded`, of
    the residuals too (per layer: the tangent field entering it from behind, dc, ds)."""
    nn, dd, k0, ki, n0, _ = primals
    dnn, ddd, dk0, dki, dn0, dv = tangents
    W_in, C, Sv = residuals
    (dEs, dHs), (dEp, dHp) = dv
    # the part of dq common to all layers: q = n^2 - n0^2 + ki^2 (either form of `_kt_squared`)
    dm = 2 * (ki * dki - n0 * dn0)

    def tstep(dw, lay):
        nj, dj, dnj, ddj, w, c, s = lay
        E1, T1, E2, T2 = w
        dE1, dT1, dE2, dT2 = dw
        a = k0 * dj
        da = (k0 * ddj + dj * dk0).astype(c.dtype)
        nsq = nj * nj
        inv = 1 / nsq
        q = _kt_squared(ki, n0, nj)[0]
        gam = _ds_dq(c, s, q, a)
        dnsq = 2 * nj * dnj
        dq = dnsq + dm
        qs = q * s
        dc = -_rmul(0.5 * a, s) * dq - qs * da
        ds = gam * dq + c * da
        dqs = dq * s + q * ds
        rho = q * inv
        drs = (dq - rho * dnsq) * inv * s + rho * ds
        dns = dnsq * s + nsq * ds
        dw2 = (c * dE1 + s * dT1 + dc * E1 + ds * T1,
               c * dT1 - qs * dE1 + dc * T1 - dqs * E1,
               c * dE2 + rho * s * dT2 + dc * E2 + drs * T2,
               c * dT2 - nsq * s * dE2 + dc * T2 - dns * E2)
        w2 = _apply(c, s, qs, rho * s, nsq * s, w)
        dfl = lambda E, T, dE, dT: jnp.imag(dE * jnp.conj(T) + E * jnp.conj(dT))
        ys = (dfl(w2[0], w2[1], dw2[0], dw2[1]), dfl(w2[2], w2[3], dw2[2], dw2[3]))
        if recorded:
            ys = ys + ((dw, dc, ds),)
        return dw2, ys

    dv_rot = (dEs, _rot(dHs), dEp, _rot(dHp))
    dw0, ys = jax.lax.scan(jax.checkpoint(tstep), dv_rot, (nn, dd, dnn, ddd, W_in, C, Sv), reverse=True)
    zeros = jax.tree.map(jnp.zeros_like, phases)  # (sum of phases, Im phase): no derivative
    d_out = (((dw0[0], _unrot(dw0[1])), (dw0[2], _unrot(dw0[3])), ys[0], ys[1]), zeros)
    return (d_out, ys[2]) if recorded else d_out


@_fields_recorded.defjvp
def _fields_recorded_jvp(primals, tangents):
    out, residuals = _fields_recorded(*primals)
    d_out, d_residuals = _tangents(primals, tangents, out[1], residuals, recorded=True)
    return (out, residuals), (d_out, d_residuals)


@_fields.defjvp
def _fields_jvp(primals, tangents):
    """The primal scan, recording (`_fields_recorded`); then the tangent scan (`_tangents`).
    Reverse mode transposes only the second."""
    out, residuals = _fields_recorded(*primals)
    return out, _tangents(primals, tangents, out[1], residuals, recorded=False)


def _layer_cs(delta, a):
    """c = g cos(delta), s = g sin(delta) / k_z with g = |exp(i delta)| = exp(-Im delta),
    delta = a k_z (a real, Im delta >= 0).

    With ``delta = x + i y``: ``g cos(delta) = cos x (1 + e) / 2 - i sin x (1 - e) / 2`` and
    ``g sin(delta) = sin x (1 + e) / 2 + i cos x (1 - e) / 2``, ``e = exp(-2 y)``, ``1 - e`` as
    ``-expm1(-2 y)``: every part to a few ulps, and no part cancels. For a real ``delta`` (a
    lossless layer, propagating) or an imaginary one (lossless, evanescent) the imaginary parts of
    ``c``, ``s / a`` and ``delta`` are exact zeros, so a lossless stack's matrices are real and
    conserve the flux exactly (module docstring, point 1)."""
    x, y = jnp.real(delta), jnp.imag(delta)
    # stored once for the four products of the step that read c and s (XLA would otherwise
    # recompute the argument reduction and the polynomials in each of their fused loops); c and s
    # themselves are a few multiplications from them, cheaper to recompute than to store
    sn, cs = _sincos(x)
    om = -jnp.expm1(-2 * y)  # 1 - e
    sn, cs, om = (_materialize_parts(v) for v in (sn, cs, om))
    op = 2 - om  # 1 + e, to half an ulp
    c = jax.lax.complex(0.5 * cs * op, -0.5 * sn * om)
    g_sin = jax.lax.complex(0.5 * sn * op, 0.5 * cs * om)
    # s = a g sin(delta) / delta, one real division; a (the limit) for |delta| < 2**-60 (where
    # sin(delta) / delta and g are 1 to rounding in float64, and |delta|^2 and the product below
    # stay far above float32's smallest normal number)
    d2 = _abs2(delta)
    big = d2 >= 2.0**-120
    ratio = g_sin * jnp.conj(delta) * (1 / jnp.where(big, d2, 1)).astype(delta.dtype)
    return c, _rmul(a, jnp.where(big, ratio, 1))


def _flux_norm(pol, kz0, n0sq, real_incident):
    """`(nu, f)`: 4 / (incident flux per |D|^2) is `nu * f`, with `f` a power of 2 held constant for
    autodiff; the flux Re(E H*) at an interface times it over |D|^2 is the fraction of the incident
    power crossing it."""
    if real_incident:  # kz0, n0 real: 4 kz0 (s) or 4 n0^2 kz0 (p), 0 at grazing incidence
        return 4 * jnp.real(kz0) * (1 if pol == "s" else jnp.real(n0sq)), 1
    # an incoherent absorbing layer lighting the group: tmm's Re(n cos) normalization. Where the
    # wave in that layer is evanescent it carries no power toward the group: the fluxes are 0 (and
    # no light reaches such a layer either: its forward T is 0 too).
    # The quotient is of order |kz0| and is formed from kz0 scaled by a power of 2 to order one
    # (the same bits): its derivative, taken as num / den^2, times the large cotangent it receives
    # near grazing incidence (where it multiplies 1 / |D|^2) would overflow in float32 (an infinite
    # gradient for |kz0| below about 1e-14).
    sk = _pow2_scale(kz0)
    k = kz0 * sk.astype(kz0.dtype)
    if pol == "s":
        num, den = 4 * _abs2(k), jnp.real(k)
    else:
        num, den = 4 * _abs2(n0sq) * _abs2(k), jnp.real(k * jnp.conj(n0sq))
    pos = den > 0
    return jnp.where(pos, num / jnp.where(pos, den, 1), 0), 1 / sk


def _flux(E, H):
    return jnp.real(E * jnp.conj(H))


# ---- the public kernels ------------------------------------------------------------------------


def _check_concrete(n, d, wavelength, cos_i):
    """Value checks on concrete inputs (skipped for traced ones, which get NaN instead)."""

    def concrete(x):
        return not isinstance(x, jax.core.Tracer)

    def first_bad(x, bad, what, name):
        if concrete(x):
            xs = np.asarray(x)
            b = np.asarray(bad(xs))
            if b.any():
                idx = tuple(int(i) for i in np.argwhere(b)[0])
                raise ValueError(f"{name}{list(idx)} = {xs[idx].item()!r}: {what}")

    first_bad(d, lambda x: ~(np.isfinite(x) & (x >= 0)), "thicknesses must be finite and >= 0", "d")
    first_bad(wavelength, lambda x: ~(np.isfinite(x) & (x > 0)), "wavelengths must be finite and > 0", "wavelength")
    first_bad(cos_i, lambda x: ~(np.isfinite(x) & (np.abs(x) <= 1 + 1e-6)), "cos_i must be finite and within [-1, 1]",
              "cos_i")
    first_bad(n, lambda x: ~(np.isfinite(x) & (np.real(x) > 0)) | V.is_gain(x),
              f"indices must be finite with real part > 0 and imaginary part k >= 0 (a k below 0 by at most "
              f"{V.K_ROUNDING:g} |n| is rounding, taken as 0)", "n")
    first_bad(n, lambda x: np.imag(x[..., :1]) != 0, "the incident medium n[..., 0] must be real", "n")


def _prepare(n, d, wavelength, cos_i, incoherent):
    n = V.as_index(n, "n", allow_complex=True)
    if jnp.ndim(n) == 0 or jnp.shape(n)[-1] < 2:
        raise ValueError(f"n must have shape (..., L) with L >= 2 media, got shape {jnp.shape(n)}")
    L = jnp.shape(n)[-1]
    d = V.as_real(d, "d")
    if jnp.ndim(d) == 0 or jnp.shape(d)[-1] != L - 2:
        raise ValueError(f"d must have shape (..., L-2) = (..., {L - 2}) for the {L - 2} inner layers of n "
                         f"(shape {jnp.shape(n)}), got shape {jnp.shape(d)}")
    wavelength = V.as_real(wavelength, "wavelength")
    cos_i = V.as_real(cos_i, "cos_i")
    inc = tuple(incoherent)
    for j in inc:
        if not isinstance(j, (int, np.integer)) or isinstance(j, bool) or not 0 <= j < L - 2:
            raise ValueError(f"incoherent must hold positions among the {L - 2} inner layers (0 to {L - 3}), got {j!r}")
    if len(set(inc)) != len(inc):
        raise ValueError(f"incoherent has a repeated position: {inc}")
    _check_concrete(n, d, wavelength, cos_i)
    batch = V.broadcast_shapes(n=jnp.shape(n)[:-1], d=jnp.shape(d)[:-1], wavelength=jnp.shape(wavelength),
                               cos_i=jnp.shape(cos_i))
    dt = V.float_dtype(n, d, wavelength, cos_i)
    cdt = V.complex_dtype(dt)
    # ranks padded to the batch's (size-1 axes), sizes not: the per-layer arrays are broadcast
    # inside the scan step, so no (layers x points) array is materialized
    def pad(x, dtype, core):
        x = jnp.asarray(x, dtype)
        return x.reshape((1,) * (len(batch) + core - x.ndim) + x.shape)

    n, d = V.without_rounding_k(pad(n, cdt, 1)), pad(d, dt, 1)
    wavelength, cos_i = pad(wavelength, dt, 0), pad(cos_i, dt, 0)
    return n, d, wavelength, cos_i, tuple(sorted(int(j) + 1 for j in inc)), dt, batch


def _valid(n, d, wavelength, cos_i):
    nr, ni = jnp.real(n), jnp.imag(n)
    ok = jnp.all((nr > 0) & (nr < jnp.inf) & (ni >= 0) & (ni < jnp.inf), axis=-1) & (ni[..., 0] == 0)
    ok &= jnp.all((d >= 0) & (d < jnp.inf), axis=-1)
    ok &= (wavelength > 0) & (wavelength < jnp.inf) & (jnp.abs(cos_i) < jnp.inf)
    return ok


def stack(n: Inexact[ArrayLike, "*#batch L"], d: Float[ArrayLike, "*#batch L-2"], wavelength: Float[ArrayLike, "*#batch"],
          cos_i: Float[ArrayLike, "*#batch"], *, incoherent: tuple[int, ...] = ()) -> StackResult:
    r"""Reflection, transmission and absorption of a multilayer stack, both polarizations.

    **Arguments:**

    - `n`: indices of the `L >= 2` media, shape `(..., L)`, real or complex `n + ik` (`k >= 0`);
      `n[..., 0]` (incident) must be real; `n[..., -1]` is the medium the light leaves into.
    - `d`: thicknesses of the inner layers, shape `(..., L-2)`, `>= 0`, same unit as `wavelength`.
    - `wavelength`: vacuum wavelength, shape `(...)`.
    - `cos_i`: cosine of the angle of incidence in medium 0, shape `(...)`; the sign is ignored.
    - `incoherent`: static tuple of inner-layer positions (0-based among the `L-2` inner layers)
      that are incoherent: thick layers where intensities add and phases do not (tmm's `'i'`).

    Leading axes of all four broadcast together; the computation runs in the floating dtype of the
    inputs (`complex64` for float32, `complex128` for float64).

    **Returns:** a `StackResult` (see there): `R_s, R_p, T_s, T_p`, `A_s, A_p` per inner layer,
    the complex amplitudes `r_s, r_p, t_s, t_p` (None with incoherent layers), and `rp_rs`.

    **Conventions:** those of the module (`jaxoptics._stack`): amplitude signs as
    `fresnel_amplitudes` and tmm, `exp(-i omega t)`, decaying branch `Im(n cos) >= 0`.

    **Edge cases:** total internal reflection in any layer (frustrated TIR: evanescent layers
    tunnel), grazing incidence (`R = 1`, `r = -1`), layers of zero thickness (equal to the stack
    without them, coherent ones), index-matched layers, and thick absorbing layers (`d k / lambda`
    up to `1e6` and beyond: transmission underflows to 0, no overflow) are all finite.
    NaN for out-of-domain elements (see the module docstring); concrete bad input raises
    `ValueError` before tracing.

    **Accuracy:** agrees with tmm's `coh_tmm`, `inc_tmm`, `absorp_in_each_layer` and
    `inc_absorp_in_each_layer` to 1e-10 or better in float64 (tested on random stacks of 1 to 30
    layers); with `L = 2` it equals `fresnel_amplitudes` to rounding.

    Reference: Born & Wolf, sec. 1.6; Byrnes, arXiv:1603.02720.
    """
    n, d, wavelength, cos_i, inc, _, batch = _prepare(n, d, wavelength, cos_i, incoherent)
    return _chunked(lambda n_, d_, w_, c_: _stack(n_, d_, w_, c_, inc), (n, d, wavelength, cos_i), batch)


# Points per block of `_chunked`. The layer scan streams its carry (the tangential fields of both
# polarizations) and the per-layer terms through memory once per layer; over a block of this many
# points they stay in the CPU's caches. On a 10-layer stack (float64, 2-core EPYC, 10^6 points)
# blocks of 16k-64k points take half the time of one block of 10^6; below about 4k points per
# block the per-operation overhead of XLA's loops dominates.
_BLOCK = 32768


def _chunked(f, args, batch):
    """`f(*args)` over a large batch in blocks of `_BLOCK` points (a `lax.map` over blocks).

    `args` have the rank of `batch` plus trailing core axes, with size-1 axes where they
    broadcast. `f` takes such arguments and returns a pytree of arrays with the batch shape of its
    arguments plus trailing core axes. Arguments with one point are passed whole to every block;
    the others are broadcast to the batch, flattened and cut into blocks (the last padded by
    repeating the final point, whose results are dropped).

    Each block is rematerialized in the backward pass (`jax.checkpoint`): reverse mode then keeps
    one block's residuals at a time, in cache, instead of every layer's residuals for the whole
    batch, which the backward pass would stream through memory (measured: the gradient costs
    3x the forward pass this way, 7x without)."""
    N = math.prod(batch)
    if N <= _BLOCK:
        return f(*args)
    nb = -(-N // _BLOCK)
    nr = len(batch)
    # per argument: its blocks (nb, _BLOCK, ...), or None where it has one point and is passed whole
    blocks = []
    for x in args:
        core = x.shape[nr:]
        if math.prod(x.shape[:nr]) == 1:
            blocks.append(None)
        else:
            x = jnp.broadcast_to(x, batch + core).reshape((N,) + core)
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (nb * _BLOCK - N,) + core)], axis=0)
            blocks.append(x.reshape((nb, _BLOCK) + core))
    mapped = [b for b in blocks if b is not None]

    def block(xs):
        it = iter(xs)
        return f(*(x.reshape((1,) + x.shape[nr:]) if b is None else next(it) for x, b in zip(args, blocks)))

    out = jax.lax.map(jax.checkpoint(block), mapped)
    unblock = lambda y: y.reshape((nb * _BLOCK,) + y.shape[2:])[:N].reshape(batch + y.shape[2:])
    return jax.tree.map(unblock, out)


def _stack(n, d, wavelength, cos_i, inc):
    batch = jnp.broadcast_shapes(n.shape[:-1], d.shape[:-1], wavelength.shape, cos_i.shape)
    L = n.shape[-1]
    cdt = n.dtype
    valid = _valid(n, d, wavelength, cos_i)
    c = jnp.where(cos_i < 0, -cos_i, cos_i)  # |cos_i|, derivative +1 at 0 (as in fresnel)
    n0 = jnp.real(n[..., 0])
    ki = jnp.broadcast_to((n0 * c).astype(cdt), batch)
    n0c = n0.astype(cdt)
    # per medium, layer axis first (not broadcast to the batch: the scan step does that)
    first = lambda x: jnp.moveaxis(x, -1, 0)
    nn = first(n)
    dd = first(d)  # inner layers only: dd[j - 1]
    k0 = 2 * jnp.pi / wavelength
    kz_sq = _KzSq(ki, n0c)  # k_z^2 formed as in `fresnel`
    kz_exit = _materialize_parts(decaying_sqrt(kz_sq(nn[L - 1])))
    if not inc:
        s, p = _group(ki, n0c, kz_exit, nn[L - 1], nn[1:L - 1], dd, k0, kz_sq, real_incident=True)
        return _finish(valid, s.R, p.R, s.T, p.T, list(s.A), list(p.A), (s.r, p.r, s.t, p.t), p.r * jnp.conj(s.r))
    return _incoherent(valid, (0,) + inc + (L - 1,), ki, nn, dd, k0, kz_sq)


def _finish(valid, Rs, Rp, Ts, Tp, As, Ap, amps, rp_rs):
    nan = lambda x: jnp.where(valid, x, jnp.nan)  # (and broadcast to the batch shape)
    A_s = jnp.stack([nan(x) for x in As], axis=-1) if As else jnp.zeros(Rs.shape + (0,), Rs.dtype)
    A_p = jnp.stack([nan(x) for x in Ap], axis=-1) if Ap else jnp.zeros(Rs.shape + (0,), Rs.dtype)
    amps = tuple(nan(x) for x in amps) if amps is not None else (None,) * 4
    return StackResult(nan(Rs), nan(Rp), nan(Ts), nan(Tp), A_s, A_p, *amps, nan(rp_rs))


def _incoherent(valid, bounds, ki, nn, dd, k0, kz_sq):
    """Coherent groups between the incoherent layers `bounds[1:-1]` (indices among all media),
    summed in intensity. Arrays have the media (dd: inner layers) on the leading axis."""
    kz = {j: decaying_sqrt(kz_sq(nn[j])) for j in bounds[1:]}
    kz[0] = ki
    N = len(bounds)
    fwd, bwd = [], []
    for e in range(N - 1):
        i0, i1 = bounds[e], bounds[e + 1]
        fwd.append(_group(kz[i0], nn[i0], kz[i1], nn[i1], nn[i0 + 1:i1], dd[i0:i1 - 1], k0, kz_sq,
                          real_incident=(e == 0)))
        if e < N - 2:  # lit from behind, from inside incoherent layer i1
            fl = lambda x: jnp.flip(x, axis=0)
            bwd.append(_group(kz[i1], nn[i1], kz[i0], nn[i0], fl(nn[i0 + 1:i1]), fl(dd[i0:i1 - 1]), k0, kz_sq,
                              real_incident=False))
    # single-pass intensity transmission of each inner incoherent layer
    Ppass = [None] + [jnp.exp(-2 * (k0 * dd[bounds[e] - 1]) * jnp.imag(kz[bounds[e]])) for e in range(1, N - 1)]

    def reflect_sum(rho_f, tt, rho_b):
        """Gamma_e, backward: Gamma = rho_f + tt P^2 Gamma' / (1 - rho_b P^2 Gamma'). Returns the list
        of Gamma_e and of the denominators (1 for the last element)."""
        G = [None] * (N - 1)
        den = [None] * (N - 1)
        G[N - 2] = rho_f[N - 2]
        den[N - 2] = jnp.ones_like(rho_f[N - 2])
        for e in range(N - 3, -1, -1):
            x = (Ppass[e + 1] ** 2).astype(G[e + 1].dtype) * G[e + 1]
            dd = 1 - rho_b[e] * x
            ok = dd != 0
            dd = jnp.where(ok, dd, 1)
            den[e] = dd
            G[e] = rho_f[e] + jnp.where(ok, tt[e] * x / dd, 0)
        return G, den

    res = {}
    for k, pol in enumerate(("s", "p")):
        f = [x[k] for x in fwd]
        b = [x[k] for x in bwd]
        Gam, den = reflect_sum([g.R for g in f], [f[e].T * b[e].T for e in range(N - 2)] + [None],
                               [g.R for g in b] + [None])
        # forward pass: F[e] the forward intensity arriving at element e, B[e] the backward
        # intensity arriving at it from behind
        F = [jnp.ones_like(Gam[0])]
        B = []
        for e in range(N - 1):
            V1 = F[e] * f[e].T / den[e]
            if e < N - 2:
                P = Ppass[e + 1]
                B.append(V1 * P * P * Gam[e + 1])
                F.append(V1 * P)
            else:
                T = V1
        A = []
        for e in range(N - 1):
            m = f[e].A.shape[0]  # coherent layers of element e: lit from the front, and from behind
            A += [F[e] * f[e].A[j] + (B[e] * b[e].A[m - 1 - j] if e < N - 2 else 0) for j in range(m)]
            if e < N - 2:  # the incoherent layer behind element e: in through e, out through e + 1
                into = F[e] * f[e].T - B[e] * b[e].entering
                out_ = F[e + 1] * f[e + 1].entering - (B[e + 1] * b[e + 1].T if e + 1 < N - 2 else 0)
                A.append(into - out_)
        res[pol] = (Gam[0], T, A)
    # incoherent sum of r_p conj(r_s) over paths
    fs, fp = [x[0] for x in fwd], [x[1] for x in fwd]
    bs, bp = [x[0] for x in bwd], [x[1] for x in bwd]
    mix = lambda u, v: u * jnp.conj(v)
    X, _ = reflect_sum([mix(fp[e].r, fs[e].r) for e in range(N - 1)],
                       [mix(fp[e].t, fs[e].t) * mix(bp[e].t, bs[e].t) for e in range(N - 2)] + [None],
                       [mix(bp[e].r, bs[e].r) for e in range(N - 2)] + [None])
    (Rs, Ts, As), (Rp, Tp, Ap) = res["s"], res["p"]
    return _finish(valid, Rs, Rp, Ts, Tp, As, Ap, None, X[0])


def ellipsometry(n: Inexact[ArrayLike, "*#batch L"], d: Float[ArrayLike, "*#batch L-2"],
                 wavelength: Float[ArrayLike, "*#batch"], cos_i: Float[ArrayLike, "*#batch"], *,
                 incoherent: tuple[int, ...] = ()) -> Ellipsometry:
    r"""Ellipsometric angles `(psi, delta)` of a stack, in radians.

    **Arguments:** as `stack`.

    **Returns:** an `Ellipsometry` named tuple `(psi, delta)`:
    `psi = atan(|r_p / r_s|)` in `[0, pi/2]` and `delta = arg(-r_p / r_s)` in `(-pi, pi]`, with
    `r_p`, `r_s` in the amplitude convention of `fresnel_amplitudes` (tmm's `ellips`).

    **Conventions:** `delta` is tmm's `ellips` Delta: with this amplitude convention (`r_p = -r_s`
    at normal incidence) and time dependence `exp(-i omega t)`, `delta = 0` at normal incidence on
    any sample and `delta = pi` for a bare dielectric beyond Brewster's angle. The ellipsometry
    literature (Azzam and Bashara's Nebraska convention, as in Fujiwara's textbook) writes the
    index `N = n - ik` (time dependence `exp(+i omega t)`) and `rho = tan(Psi) exp(i Delta) =
    r_p / r_s` with the same Fresnel formulas; there
    `Psi = psi` and `Delta = pi - delta` (mod `2 pi`; a bare dielectric has `Delta = 180`
    degrees below Brewster's angle). Tested against an independent transcription in that
    convention.

    With incoherent layers the reflected light is partially depolarized: `psi =
    atan(sqrt(R_p / R_s))` and `delta = arg(-<r_p conj(r_s)>)`, the incoherent path sum
    `StackResult.rp_rs` (what an ellipsometer fits from the Mueller matrix elements of an
    isotropic, depolarizing sample).

    **Edge cases:** where `r_p = 0` (Brewster's angle of a bare interface) `delta` is undefined and
    returned as 0 (gradient 0); `psi` has a kink there and its gradient is the one from `r_p -> 0`
    (0). NaN for out-of-domain elements, as `stack`.
    """
    res = stack(n, d, wavelength, cos_i, incoherent=incoherent)
    return _psi_delta(res.R_s, res.R_p, res.rp_rs)


def _psi_delta(R_s, R_p, X):
    abs_p = sqrt_where(R_p, R_p > 0)
    abs_s = sqrt_where(R_s, R_s > 0)
    both = (abs_p > 0) | (abs_s > 0)
    psi = _atan2(jnp.where(both, abs_p, 0), jnp.where(both, abs_s, 1))
    psi = jnp.where(jnp.isnan(R_s + R_p), jnp.nan, psi)
    y = -X
    nz = _abs2(y) > 0
    ys = jnp.where(nz, y, 1)
    delta = jnp.where(nz, _atan2(jnp.imag(ys), jnp.real(ys)), 0)
    delta = jnp.where(delta <= -jnp.pi, jnp.pi, delta)
    delta = jnp.where(jnp.isnan(jnp.real(X)), jnp.nan, delta)
    return Ellipsometry(psi, delta)
