r"""Reflected and refracted directions; critical and Brewster angles.

Conventions
-----------
The seeds' (de Greve's) convention: `i` is the unit incident direction pointing **toward** the
surface, `n` a unit normal, `eta1` the index of the medium the ray comes from and `eta2` that of the
medium it enters. The kernels face the normal toward the incident side themselves
(`n_f = -sign(i . n) n`), so a geometric normal pointing either way gives the same result;
`cos_i = |i . n|`. Directions are `(..., 3)` arrays; indices broadcast against the leading axes.

Mitsuba 3 and pbrt-v4 use `wi` pointing *away* from the surface and a single relative index
`eta = n_t / n_i`: their `refract(wi, n, eta)` corresponds to `refract(-wi, n, n_i, n_t)` here.

`refract` normalizes `i` and `n` (only their directions matter; unit inputs pass through
unchanged): at a large index contrast an ulp of error in their length would otherwise be amplified
into a visibly non-unit `t`. `reflect` does not (it is linear in `i` and has no such amplification):
pass it a unit normal. `refract` and `interface` take `cos_i = (i . n) / (|i| |n|)` from
double-word arithmetic, rounded once (within half an ulp): near the critical angle the TIR decision
hinges on its last ulp, and a plain dot product of normalized vectors carries about two. An
element whose `i` or `n` is zero or not finite, or whose index is not finite and positive, gives
NaN in every output (and `tir = False`); nothing raises inside `jit`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from .._core import _validate as V
from .._core._numerics import _positive_finite, materialize, sqrt_where
from .._core._program import program
from .._core._result import Unpacks, result
from ._fresnel_terms import _kt_squared

if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike, Float

METHODS = ("degreve", "heckbert", "bec", "oliveira")


@result
class Refraction(Unpacks):
    """Result of `refract`; unpacks as `t, tir = refract(...)`.

    **Fields:**

    - `t`: unit transmitted direction `(..., 3)`; where `tir`, the reflected direction.
    - `tir`: boolean mask `(...)`, true where total internal reflection occurs.
    """

    t: jnp.ndarray
    tir: jnp.ndarray


def _dot(a, b):
    # Written out, not jnp.sum(a * b, axis=-1): XLA on the CPU emits a reduction over a minor axis
    # of length 3 as a separate, slow loop (measured: 108 ms against 12 ms for 10^7 float32
    # vectors), and it cuts the kernel's fusion in two.
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _vectors(i, n, *etas) -> tuple[jax.Array, jax.Array, tuple[int, ...]]:
    """Validate; return i, n broadcast to one shape (..., 3) and the batch shape (...)."""
    i = V.vector(i, "i")
    n = V.vector(n, "n")
    named = {"i": jnp.shape(i), "n": jnp.shape(n)}
    for k, e in etas:
        named[k] = jnp.shape(e) + (3,)  # indices broadcast against the leading (batch) axes
    shape = V.broadcast_shapes(**named)
    return jnp.broadcast_to(i, shape), jnp.broadcast_to(n, shape), shape[:-1]


# ---- the cosine of incidence in double-word arithmetic ----------------------------------------
# Near the critical angle the TIR decision and t hinge on cos_i to the last ulp, and the backward
# bound there is tight: moving a component of i along i hardly changes the angle, so 2-ulp moves of
# the inputs move cos_i by only about 1 ulp. A dot product of normalized vectors carries about 4
# roundings (2 ulps). So cos_i = (i . n) / sqrt((i . i)(n . n)) is evaluated with each quantity as
# an unevaluated sum hi + lo (Dekker, Ogita-Rump-Oishi "Dot2") and rounded once at the end.
#
# The error-free product splits each factor by masking its low significand bits, not by
# Veltkamp's (2^s + 1) x trick: XLA's CPU compiler contracts a*b + c into an FMA where it sees fit,
# which breaks Veltkamp's split, while every product of masked halves below is exact, so it gives
# the same bits with or without contraction. (float32: 12 + 12 significand bits, products exact;
# float64: 26 + 27 bits, only the last, u^2-sized, partial product is rounded.)

_MASKS = {4: (jnp.uint32, 0xFFFFF000), 8: (jnp.uint64, 0xFFFFFFFFF8000000)}


def _split(x):
    ut, mask = _MASKS[x.dtype.itemsize]
    hi = jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(x, ut) & ut(mask), x.dtype)
    return hi, x - hi


def _two_prod(a, b):
    """p + e == a * b (exactly in float32), with p = fl(a * b)."""
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _two_sum(a, b):
    """s + e == a + b exactly, s = fl(a + b) (Knuth; no multiplications, so contraction-proof)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _dot2(a, b):
    """a . b over the last axis (length 3) as hi + lo, accurate as if computed in twice the
    working precision (Ogita, Rump and Oishi 2005, Algorithm Dot2)."""
    p0, e0 = _two_prod(a[..., 0], b[..., 0])
    p1, e1 = _two_prod(a[..., 1], b[..., 1])
    p2, e2 = _two_prod(a[..., 2], b[..., 2])
    s, t1 = _two_sum(p0, p1)
    s, t2 = _two_sum(s, p2)
    return s, (e0 + e1 + e2) + (t1 + t2)


def _signed_cos_plain(i, n):
    return _dot(_normalize(i), _normalize(n))


@jax.custom_jvp
def _signed_cos(i, n):
    """(i . n) / (|i| |n|), within about half an ulp (one final rounding): the value from
    double-word arithmetic, the derivative from the plain formula (the same function; the
    derivative is not ill-conditioned). NaN-free derivative for zero vectors (as `refract`)."""
    dh, dl = _dot2(i, n)
    ih, il = _dot2(i, i)
    nh, nl = _dot2(n, n)
    # g = (i . i)(n . n) as gh + gl
    gh, ge = _two_prod(ih, nh)
    gl = ge + (ih * nl + il * nh)
    # 1/sqrt(g) as r0 (1 + h/2): r0 the working-precision rsqrt, h = 1 - g r0^2 its residual,
    # which is a few ulps, so one Newton step in this form leaves an O(u^2) error.
    r0 = _rsqrt_positive(gh)
    yh, yl = _two_prod(r0, r0)
    zh, zl = _two_prod(gh, yh)
    zl = zl + (gh * yl + gl * yh)
    h = (1 - zh) - zl  # 1 - zh is exact (Sterbenz: zh is within a few ulps of 1)
    rl = r0 * (0.5 * h)
    ph, pl = _two_prod(dh, r0)
    # Materialized: otherwise XLA recomputes these ~200 operations in each of refract's loops
    # that read the cosine (measured: 14 loops and 2.3x the time of the plain-cosine kernel; once:
    # 8 loops and about 10% over it).
    return materialize(ph + (pl + (dh * rl + dl * r0)))


@_signed_cos.defjvp
def _signed_cos_jvp(primals, tangents):
    _, dc = jax.jvp(_signed_cos_plain, primals, tangents)
    return _signed_cos(*primals), dc


def _cross(a, b):
    # Written out component by component, like `_dot` (jnp.cross slices and concatenates).
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


@jax.custom_jvp
def _cross_exact(a, b):
    """a x b with each component a_j b_k - a_k b_j from error-free products (`_two_prod`): within
    an ulp of the exact cross product, the same bits in every fused loop that computes it (with or
    without contraction). For nearly parallel vectors the plain form cancels (relative error up to
    eps / sin of their angle), and XLA recomputes it in each loop that reads it, so two readers
    could see copies that differ in their leading digits. Its derivative is the plain one's."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]

    def minus(u, v, w, z):
        p, e = _two_prod(u, v)
        q, f = _two_prod(w, z)
        return (p - q) + (e - f)

    return jnp.stack([minus(ay, bz, az, by), minus(az, bx, ax, bz), minus(ax, by, ay, bx)], axis=-1)


@_cross_exact.defjvp
def _cross_exact_jvp(primals, tangents):
    _, dc = jax.jvp(_cross, primals, tangents)
    return _cross_exact(*primals), dc


def _rsqrt_positive(x):
    ok = x > 0
    return jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, x, 1)), 1)


def _normalize(v) -> jax.Array:
    """v / |v| over the last axis; zero vectors stay zero, with a finite derivative (double where)."""
    return v * _rsqrt_positive(_dot(v, v))[..., None]


def _valid_vectors(i, n):
    ii = _dot(i, i)
    nn = _dot(n, n)
    return (ii > 0) & (nn > 0) & jnp.isfinite(ii + nn)


@program()
def reflect(i: Float[ArrayLike, "*batch 3"], n: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*batch 3"]:
    r"""Mirror direction `r = i - 2 (i . n) n`.

    **Arguments:**

    - `i`: unit incident direction toward the surface, `(..., 3)`.
    - `n`: unit normal, `(..., 3)`, either orientation (the formula is even in `n`).

    **Returns:** `r`, `(..., 3)`, pointing away from the surface on the incident side, in the dtype
    of the inputs.

    **Edge cases:** a zero or non-finite `i` or `n` gives NaN. Grazing incidence returns `i`.
    """
    i, n, _ = _vectors(i, n)
    d = _dot(i, n)[..., None]
    r = i - 2 * d * n
    return jnp.where(_valid_vectors(i, n)[..., None], r, jnp.nan)


@program(static_argnames=("method",))
def refract(i: Float[ArrayLike, "*batch 3"], n: Float[ArrayLike, "*#batch 3"], eta1: Float[ArrayLike, "*#batch"],
            eta2: Float[ArrayLike, "*#batch"], *, method: str = "degreve", oliveira_c: float = 1.0) -> Refraction:
    r"""Refracted direction by Snell's law, with the total-internal-reflection mask.

    **Arguments:**

    - `i`: unit incident direction toward the surface, `(..., 3)`.
    - `n`: unit normal `(..., 3)`, either orientation; the kernel faces it toward the incident side.
    - `eta1`, `eta2`: real indices of the incident and the entered medium, broadcastable with the
      leading axes of `i` and `n`.
    - `method`: the formulation (all return the same `tir` mask, computed exactly):

      * `"degreve"` (default): de Greve's vector form `t = r i + (r cos_i - cos_t) n_f` written
        without cancellation: `k_t**2 = (eta2 - eta1)(eta2 + eta1) + (eta1 cos_i)**2`, or
        `eta2**2 - eta1**2 |i x n|**2` when `eta1 > 2 eta2` (the sine from a cross product keeps
        the angle near normal incidence, where the critical angle lies for a large contrast), and
        `r cos_i - cos_t = (eta1**2 - eta2**2) / (eta2 (k_i + k_t))`. Backward stable everywhere;
        `t = i` when `eta1 == eta2`. One square root, two divisions, one cross product.
      * `"heckbert"`: the same algebra as written in Heckbert's method and the de Greve note,
        `cos_t = sqrt(1 - r**2 (1 - cos_i**2))`, `r = eta1 / eta2`. Loses accuracy at grazing
        incidence when `eta1` is close to `eta2` (the subtraction `r cos_i - cos_t` cancels) and
        near normal incidence when `eta1 >> eta2`. Kept as the textbook baseline.
      * `"bec"`: Bec's form (Real-Time Rendering, 2nd ed. eqs. 6.26-6.27):
        `w = r cos_i`, `k = sqrt(1 + (w - r)(w + r))`, `t = r i + (w - k) n_f`. Agrees with
        `"degreve"` to rounding error for `eta1 <= 2 eta2`; like `"heckbert"` it takes `cos_t` from
        `cos_i`, which loses the angle near the critical angle when `eta1 >> eta2`.
      * `"oliveira"`: Oliveira's cheap approximation (Real-Time Rendering, 2nd ed. eq. 6.28),
        `t = normalize(i - c n_f)` with the constant `c = oliveira_c`. No square root of the
        index term and independent of the indices (it does not follow Snell's law): the angular
        error is up to about 14 degrees for glass (`eta2 / eta1 = 1.5`, `c = 1`) and it does not
        reduce to `t = i` when `eta1 == eta2`. Meant only for entering a denser medium; the TIR
        mask is still exact.
    - `oliveira_c`: Oliveira's constant (default 1.0); used only by `method="oliveira"`.

    **Returns:** `Refraction(t, tir)`: `t` the unit transmitted direction in the dtype of the
    inputs; `tir` a boolean mask. Where `tir`, `t` is the reflected direction (all the light
    reflects): finite and unit, never NaN.

    **Edge cases:** `eta1 == eta2` gives `t = i` (except `"oliveira"`); at exactly the critical
    angle `tir` is false and `t` grazes the surface; zero or non-finite vectors and non-positive
    indices give NaN. Gradients are finite everywhere (double `where` at the square root and the
    0/0 divisions).

    Reference: B. de Greve, *Reflections and Refractions in Ray Tracing* (2006), eq. 22;
    P. Heckbert in A. Glassner (ed.), *An Introduction to Ray Tracing* (1989);
    X. Bec, *Faster Refraction Formula, and Transmission Color Filtering*, Ray Tracing News 10(1)
    (1997); M. Oliveira, *Interactive GPU-based refraction* (2000); Real-Time Rendering, 2nd ed.,
    section 6.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    eta1 = V.as_index(eta1, "eta1", allow_complex=False)
    eta2 = V.as_index(eta2, "eta2", allow_complex=False)
    dt = V.float_dtype(i, n, eta1, eta2)
    i, n, batch = _vectors(i, n, ("eta1", eta1), ("eta2", eta2))
    i, n = i.astype(dt), n.astype(dt)
    eta1 = jnp.broadcast_to(jnp.asarray(eta1, dt), batch)[..., None]
    eta2 = jnp.broadcast_to(jnp.asarray(eta2, dt), batch)[..., None]

    valid = _valid_vectors(i, n) & _positive_finite(eta1[..., 0]) & _positive_finite(eta2[..., 0])
    # Normalize: at a large index contrast, an error of an ulp in |i| is amplified by
    # (eta1/eta2)^2 in cos_t^2, so directions a few ulps off unit length would otherwise give a
    # visibly non-unit t. (rsqrt of exactly 1 is 1: unit inputs pass through unchanged.) The
    # double where keeps the gradient finite for zero vectors, which give NaN below anyway.
    d = _signed_cos(i, n)[..., None]  # to about half an ulp (see `_signed_cos`)
    i, n = _normalize(i), _normalize(n)
    # Face the normal toward the incident side: cos_i = -(i . n_f) = |i . n| >= 0, at most 1
    # (rounding can leave it an ulp above, which at a large index contrast would make cos_t > 1;
    # a where, not jnp.minimum, so that the derivative at exactly normal incidence is kept).
    flip = d > 0
    # n_f stored once (`materialize`): read as the select between -n and n, XLA's CPU backend may
    # compute what reads it once per branch and contract the multiply-adds into FMAs differently
    # in each, so t would depend on the normal's orientation by an ulp (whether it does depends on
    # the method and on the program the kernel is fused into; the stored n_f costs 5-20% of the
    # kernel's time in float32, less in float64)
    nf = materialize(jnp.where(flip, -n, n))
    c = jnp.where(flip, d, -d)
    c = jnp.where(c > 1, 1, c)
    reflected = i + 2 * c * nf

    ki = eta1 * c
    # sin^2 from the cross product: near normal incidence a cosine is within an ulp of 1 and has
    # lost the angle (c = 1 - theta^2/2), which matters when eta1 >> eta2 puts the critical angle
    # there (eta2/eta1 = 1e-3: theta_c = 1e-3 rad); |i x n|^2 keeps it to full relative accuracy.
    # (error-free products: s2 and i_tan below must agree, see `_cross_exact`)
    cr = _cross_exact(i, n)
    s2 = _dot(cr, cr)[..., None]
    q, diff, _ = _kt_squared(ki, eta1, eta2, sin_sq=s2)  # (eta2 cos_t)^2; < 0 under TIR
    # One materialized q: otherwise XLA recomputes q in several fused loops, contracting
    # multiply-adds into FMAs differently in each, and the returned mask could disagree with the
    # select below for q within rounding of 0 (a reflected t reported as transmitted: seen in the
    # stress test as a Snell residual of 0.25).
    q = materialize(q)
    tir = q < 0

    kt = sqrt_where(q, q > 0)  # double where (see sqrt_where): k_t = 0 under TIR
    t = _refracted(method, i, n, nf, c, ki, kt, diff, cr, eta1, eta2, oliveira_c)

    t = jnp.where(tir, reflected, t)
    t = jnp.where(valid[..., None], t, jnp.nan)
    return Refraction(t, tir[..., 0] & valid)


def _refracted(method, i, n, nf, c, ki, kt, diff, cr, eta1, eta2, oliveira_c):
    """The transmitted direction outside TIR, for each formulation (shared with `interface`).

    `c`, `ki`, `kt`, `diff`, `eta1`, `eta2` have shape (..., 1); `cr = i x n`, or None to skip the
    leaving-side form (when the caller promises eta1 <= eta2).
    """
    if method == "degreve":
        den = ki + kt
        ok = den > 0  # false only at grazing incidence with eta1 == eta2 (0/0): t = i there
        # r cos_i - cos_t = (eta1^2 - eta2^2) / (eta2 (k_i + k_t)): no cancellation, exactly 0 for
        # eta1 == eta2, where r = eta1 / eta2 is exactly 1, so t is (normalized) i bit for bit.
        coef = jnp.where(ok, -diff / (eta2 * jnp.where(ok, den, 1)), 0)
        t = (eta1 / eta2) * i + coef * nf
        if cr is None:
            return t
        # Leaving the denser medium, the normal component of that form, -r cos_i + coef = -cos_t,
        # cancels by a factor up to eta1/eta2 (about 1000 at normal incidence for 1000:1). So there
        # t = (eta1 i_tan - k_t n_f) / eta2 instead, with the tangential part of i from cross
        # products, i_tan = n x (i x n), whose normal component is zero to within eps * sin_i.
        i_tan = _cross(n, cr)
        return jnp.where(eta1 > eta2, (eta1 * i_tan - kt * nf) / eta2, t)
    if method in ("heckbert", "bec"):
        r = eta1 / eta2
        w = r * c
        k2 = 1 - r * r * (1 - c * c) if method == "heckbert" else 1 + (w - r) * (w + r)
        return r * i + (w - sqrt_where(k2, k2 > 0)) * nf  # double where (see sqrt_where)
    t = i - oliveira_c * nf  # oliveira
    tt = _dot(t, t)[..., None]
    return t / jnp.sqrt(jnp.maximum(tt, jnp.asarray(jnp.finfo(tt.dtype).tiny, tt.dtype)))  # tt > 0 unless i == c n_f


@program()
def critical_angle(eta1: Float[ArrayLike, "*batch"], eta2: Float[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    r"""Critical angle `asin(eta2 / eta1)` in radians, for light going from `eta1` into `eta2`.

    Computed as `atan2(eta2, sqrt((eta1 - eta2)(eta1 + eta2)))`, which is accurate even when the
    ratio is close to 1 (where `asin` of a rounded ratio is not).

    **Edge cases:** where no critical angle exists (`eta2 >= eta1`) the value is `pi / 2`, so that
    "TIR occurs exactly when `theta_i > critical_angle`" holds for all inputs; `eta1 == eta2` is
    `pi / 2` continuously. Non-positive or non-finite indices give NaN. Real indices only.
    """
    eta1 = V.as_index(eta1, "eta1", allow_complex=False)
    eta2 = V.as_index(eta2, "eta2", allow_complex=False)
    shape = V.broadcast_shapes(eta1=jnp.shape(eta1), eta2=jnp.shape(eta2))
    dt = V.float_dtype(eta1, eta2)
    eta1 = jnp.broadcast_to(jnp.asarray(eta1, dt), shape)
    eta2 = jnp.broadcast_to(jnp.asarray(eta2, dt), shape)
    diff = (eta1 - eta2) * (eta1 + eta2)
    pos = diff > 0
    # double where (see sqrt_where): sqrt'(0) is infinite at eta1 == eta2
    theta = jnp.where(pos, jnp.arctan2(eta2, sqrt_where(diff, pos)), jnp.pi / 2)
    valid = _positive_finite(eta1) & _positive_finite(eta2)
    return jnp.where(valid, theta, jnp.nan).astype(dt)


@program()
def brewster_angle(eta1: Float[ArrayLike, "*batch"], eta2: Float[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    r"""Brewster's angle `atan(eta2 / eta1)` in radians, where `R_p = 0`.

    Computed as `atan2(eta2, eta1)`. Exists for all positive real indices, for either direction
    of travel (for `eta1 > eta2` it lies below the critical angle).

    **Edge cases:** `pi / 4` when `eta1 == eta2` (where `R_p` is 0 at every angle anyway);
    non-positive or non-finite indices give NaN; complex indices (where there is only a
    pseudo-Brewster minimum) are refused with a `ValueError`.
    """
    eta1 = V.as_index(eta1, "eta1", allow_complex=False)
    eta2 = V.as_index(eta2, "eta2", allow_complex=False)
    shape = V.broadcast_shapes(eta1=jnp.shape(eta1), eta2=jnp.shape(eta2))
    dt = V.float_dtype(eta1, eta2)
    eta1 = jnp.broadcast_to(jnp.asarray(eta1, dt), shape)
    eta2 = jnp.broadcast_to(jnp.asarray(eta2, dt), shape)
    valid = _positive_finite(eta1) & _positive_finite(eta2)
    return jnp.where(valid, jnp.arctan2(eta2, eta1), jnp.nan).astype(dt)
