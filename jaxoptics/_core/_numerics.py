"""Numerical building blocks shared by the kernels, the stacks and the fits: values stored once
for every consumer (`materialize`, and its forms for complex values and tangents), the
unpolarized mean, square roots with finite gradients everywhere (the double-where rule), the
decaying branch of a complex root, and copies of values that XLA gives a fused loop of their own.

Each is written for XLA's CPU backend as it fuses and contracts, and says why in its docstring.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _abs2(z):
    return jnp.real(z) ** 2 + jnp.imag(z) ** 2


@jax.custom_jvp
def materialize(x):
    """`x`, computed once and stored, for every consumer to read (on XLA's CPU backend).

    XLA duplicates cheap elementwise work into each fused loop that consumes it, and contracts
    multiply-adds into FMAs independently in each copy, so a value near a decision threshold (k_t^2
    near the critical angle) can be computed twice and land on both sides of it: a mask returned
    as "transmitted" while the direction beside it was selected as "reflected". An optimization
    barrier does not prevent this (the CPU pipeline removes barriers before fusion: checked on the
    compiled HLO). A division with several consumers is materialized instead, so `x` is divided by
    a 1 the compiler cannot fold (2 only where `x` is NaN, which stays NaN): the same bits, one
    division per element.
    """
    return x / jnp.where(jnp.isnan(x), 2, 1).astype(x.dtype)


@materialize.defjvp
def _materialize_jvp(primals, tangents):
    # the divisor is 1 wherever x is a number: the tangent passes through unchanged (no division
    # in the forward-mode or the transposed reverse-mode program)
    (x,), (dx,) = primals, tangents
    return materialize(x), dx


@jax.custom_jvp
def materialize_both(x):
    """`x` computed once and stored like `materialize`, and its derivative too: in forward mode,
    the tangents of an expensive value with several consumers are then computed once (under
    `vmap` over tangent directions XLA otherwise fuses their whole computation into each
    consumer's loop).

    A complex `x` (and its tangent) is stored by one complex division by `1 + 0i` (`2 + 0i` where
    a part is NaN), not part by part as `materialize` does: two real divisions are two fused
    loops, and XLA's CPU backend computes the whole of `x` in each. The quotient is `x` except for
    the sign of a zero part (`(a + b e) / f` with `e = 0`: `-0 + 0 = +0`) and an infinite part,
    which makes the other part NaN, so it serves values whose consumers are indifferent to both
    (the stack's `rp_rs` in `model_quantities`, which takes delta's sign of zero into account)."""
    return _materialize_whole(x)


def _materialize_whole(x):
    if jnp.iscomplexobj(x):
        return _divide_by_one(x, x)
    return materialize(x)


def _divide_by_one(t, x):
    """`t / (1 + 0i)`, `2 + 0i` where a part of `x` is NaN (`materialize_both`)."""
    s = jnp.where(jnp.isnan(jnp.real(x)) | jnp.isnan(jnp.imag(x)), 2, 1).astype(jnp.real(x).dtype)
    return t / jax.lax.complex(s, jnp.zeros_like(s))


def _materialize_parts(x):
    if jnp.iscomplexobj(x):  # part by part: two real divisions instead of a complex one
        return jax.lax.complex(materialize(jnp.real(x)), materialize(jnp.imag(x)))
    return materialize(x)


@materialize_both.defjvp
def _materialize_both_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return _materialize_whole(x), materialize_tangent(dx, x)


def materialize_tangent(dx, x):
    """A tangent `dx` of `x`, stored once like `materialize_both`: divided by the primal's divisor
    (1 wherever `x` is a number), so it is linear in the tangent and reverse mode transposes it."""
    if jnp.iscomplexobj(dx):
        return _divide_by_one(dx, x)
    return dx / jnp.where(jnp.isnan(x), 2, 1).astype(dx.dtype)


@jax.custom_jvp
def unpolarized(a, b):
    """`(a + b) / 2`, the unpolarized value from the s and p ones, ending in a select.

    When a caller reduces the result (`jnp.sum(fresnel(...))`, a loss, a radiance estimate), XLA's
    CPU backend hands the reduction to a library fusion that also takes the elementwise add and
    multiply in front of it. The kernel's loop is then cut there: `R_s`, `R_p` and a broadcast of
    the constant 1/2 are each written to memory and read back, 7x the time of the kernel on its
    own (measured at 10^7 float32 elements; the benchmark's "consumed by jnp.sum" rows). A select
    is not taken into that fusion, so the whole kernel stays one loop feeding the reduction. The
    select changes nothing: where `a` is NaN both sides are NaN.
    """
    return jnp.where(jnp.isnan(a), a, 0.5 * (a + b))


@unpolarized.defjvp
def _unpolarized_jvp(primals, tangents):
    # (a + b) / 2 without the select: where `a` is NaN its derivative is not used. So the
    # derivative does not read the value of `a`, and a gradient whose cotangent does not depend on
    # the result (`grad(sum(R))`) needs no forward pass to find where `a` is NaN.
    (a, b), (da, db) = primals, tangents
    return unpolarized(a, b), 0.5 * (da + db)


def sqrt_where(x, mask):
    """`sqrt(x)` where `mask`, else 0, with finite gradients everywhere (the double-where rule).

    `sqrt` has an infinite derivative at 0, and a single `where` multiplies that by zero, which is
    NaN; so the square root's *input* is made harmless in the unselected lanes too. That input is
    `max(x, tiny)` (real) or `tiny` where `mask` is false (complex), not the customary 1: XLA may
    evaluate `mask` more than once, in fusions that contract multiply-adds into FMAs differently,
    and the two copies can then disagree where x is within rounding of 0. With 1 as the stand-in,
    such a lane would return sqrt(1) = 1 (seen: R = -3827 near the critical angle in a jitted
    float32 batch); with tiny it returns about 1e-19, which is as good as 0 there.
    """
    tiny = jnp.asarray(jnp.finfo(x.dtype).tiny, x.dtype)
    if jnp.iscomplexobj(x):
        safe = jnp.where(mask, x, tiny)
    else:
        safe = jnp.maximum(x, tiny)
    return jnp.where(mask, jnp.sqrt(safe), 0)


def decaying(kz):
    """The root with `Im >= 0` (the wave decays away from the interface). The principal root
    already has it when `Im(q) >= 0`; this also fixes a negative real `q` whose imaginary part is a
    signed zero."""
    return jnp.where(jnp.imag(kz) < 0, -kz, kz)


def decaying_sqrt(q):
    """`k_z = sqrt(q)` of a complex `q = k_z**2` on the decaying branch, with the double-where
    square root (the complex root is singular at 0, the critical angle of an index with k == 0:
    the derivative there is the finite one-sided value)."""
    return decaying(sqrt_where(q, q != 0))


def _positive_finite(x):
    return (x > 0) & (x < jnp.inf)


def _own_loop(*xs, order=0):
    """Copies of `xs` that XLA cannot identify with the originals, nor with copies made with another
    `order` (the operands pass an optimization barrier rotated by `order`, so two barriers are not
    merged): what is computed from them gets a fused loop of its own. XLA on the CPU has no
    multi-output loop fusion, so outputs sharing quotients are otherwise written to memory and read
    back, one loop per shared value."""
    k = order % len(xs)
    ys = jax.lax.optimization_barrier(xs[k:] + xs[:k])
    return ys[len(xs) - k:] + ys[:len(xs) - k]
