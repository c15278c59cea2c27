"""Elementary functions for the layer recursion (`_layers`), written out so that XLA vectorizes them
and their derivatives stay exact: `sin(x)` and `cos(x) - 1` without cancellation, `(sin, cos)`
of a complex phase with a shared argument reduction, a vectorized `atan2` (Pade approximant on
a reduced range), the decaying complex square root, and the power series of `d s / d q` for
small phases."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

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
