"""Checks made once, at trace time, on what the user passes in.

Everything here looks only at static information (shapes and dtypes), so it runs while JAX
traces a program and raises a plain ``ValueError`` before any computation is compiled. Values
cannot be checked inside ``jit``; the kernels document what out-of-domain values produce instead.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _dtype_of(x):
    return jnp.result_type(x)


def as_real(x, name: str):
    """Return ``x`` as a JAX array with a floating dtype; integer or bool arrays raise.

    Python ``int``/``float`` scalars are accepted (they are weakly typed and take the dtype of the
    other arguments), so ``eta1=1`` works. Integer *arrays* are refused: silently computing in a
    default float dtype would hide a units or dtype mistake.
    """
    x = check_real(x, name)
    return x if isinstance(x, (int, float)) else jnp.asarray(x)


def check_real(x, name: str):
    """The checks of `as_real`, without conversion: ``x`` as given (lists as NumPy arrays)."""
    if isinstance(x, bool) or (hasattr(x, "dtype") and np.dtype(x.dtype) == np.bool_):
        raise ValueError(f"{name} must be a floating-point array or Python number, got a boolean")
    if isinstance(x, (int, float)):
        return x
    if not hasattr(x, "dtype"):  # lists, tuples: look at what NumPy makes of them
        x = np.asarray(x)
    if isinstance(x, complex) or (hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.complexfloating)):
        raise ValueError(f"{name} must be real, got a complex value (dtype {_dtype_of(x)})")
    dt = _dtype_of(x)
    if not jnp.issubdtype(dt, jnp.floating):
        raise ValueError(
            f"{name} must have a floating dtype (float32 or float64), got dtype {dt}; "
            f"convert it explicitly, e.g. {name}.astype(jnp.float32)"
        )
    return x


def as_index(x, name: str, *, allow_complex: bool):
    """A refractive index: real floating, or complex ``n + ik`` where allowed."""
    if isinstance(x, complex) or (hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.complexfloating)):
        if not allow_complex:
            raise ValueError(
                f"{name} must be real here, got a complex index (dtype {_dtype_of(x)}); "
                "complex indices are accepted for eta2 of fresnel, fresnel_sp, fresnel_rt, "
                "fresnel_amplitudes and schlick"
            )
        return x if isinstance(x, complex) else jnp.asarray(x)
    return as_real(x, name)


# An index `N = n + ik` whose `k` lies below zero by at most this fraction of `|N|` is taken as
# `k = 0`: that is rounding (interpolating a k table near zero gives k = -1e-39), not gain. Every
# kernel that takes a complex index (`stack`, the Fresnel kernels) and `fit_stack`'s check of its
# media use this one tolerance; a `k` further below zero is gain, which they refuse (concrete
# input) or give NaN for (traced).
K_ROUNDING = 1e-12


def is_gain(N):
    """Whether `N` (NumPy or JAX, real or complex) has `k < -K_ROUNDING |N|`: gain, not rounding."""
    xp = jnp if isinstance(N, jax.Array) else np
    return xp.imag(N) < -K_ROUNDING * xp.abs(N)


def without_rounding_k(N):
    """`N` with a `k` within rounding below zero (`K_ROUNDING`) set to 0; unchanged elsewhere,
    gain included (the kernels' validity mask then flags it). Real `N` is returned as it is."""
    if not jnp.iscomplexobj(N):
        return N
    k = jnp.imag(N)
    return jnp.where((k < 0) & ~is_gain(N), jax.lax.complex(jnp.real(N), jnp.zeros_like(k)), N)


def is_complex(*xs) -> bool:
    return any(
        isinstance(x, complex) or (hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.complexfloating))
        for x in xs
    )


def vector(x, name: str) -> jax.Array:
    """A direction: floating array of shape ``(..., 3)``."""
    x = as_real(x, name)
    shape = np.shape(x)
    if len(shape) == 0 or shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (a trailing axis of length 3), got shape {shape}")
    return jnp.asarray(x)


def broadcast_shapes(**named_shapes) -> tuple[int, ...]:
    """``jnp.broadcast_shapes`` (which also takes the symbolic dimensions of `jax.export`) with an
    error that names every argument and its shape."""
    try:
        return jnp.broadcast_shapes(*named_shapes.values())
    except ValueError:
        listing = ", ".join(f"{k} {tuple(v)}" for k, v in named_shapes.items())
        raise ValueError(f"shapes cannot be broadcast together: {listing}") from None


def float_dtype(*xs):
    """The floating dtype the computation runs in: that of the array inputs (the real part's dtype
    for complex ones). Python scalars are weakly typed and follow; with no arrays at all, JAX's
    default float dtype."""
    parts = []
    for x in xs:
        if isinstance(x, (int, float, complex)) or getattr(x, "weak_type", False):
            continue
        dt = np.dtype(jnp.result_type(x))
        parts.append(np.finfo(dt).dtype if np.issubdtype(dt, np.complexfloating) else dt)
    if not parts:
        return jnp.zeros(()).dtype
    return np.result_type(*parts)


def complex_dtype(float_dt):
    """complex64 for float32 (and narrower), complex128 for float64."""
    return np.dtype(np.complex128) if np.dtype(float_dt).itemsize >= 8 else np.dtype(np.complex64)


def local_parts(x) -> list[tuple[tuple[int, ...], np.ndarray]]:
    """The parts of a concrete array this process can read, each with the index of its first
    element in the whole array: `[((0, ...), x)]` for NumPy data and for a `jax.Array` whose
    devices are all this process's; for an array that spans the devices of several processes
    (`jax.distributed`) and is not replicated on all of them, its addressable shards, one per
    distinct block. Value checks run on
    these, so each process checks the data it holds and nothing is gathered across hosts."""
    if isinstance(x, jax.Array) and not (x.is_fully_addressable or x.is_fully_replicated):
        parts, seen = [], set()
        for shard in x.addressable_shards:
            start = tuple(s.indices(n)[0] for s, n in zip(shard.index, x.shape))
            if start not in seen:
                seen.add(start)
                parts.append((start, np.asarray(shard.data)))
        return parts
    a = np.asarray(x)
    return [((0,) * a.ndim, a)]


def first_bad(x, bad, message):
    """Raise `ValueError(message(index, value))` at the first element of `x` (a concrete array)
    where `bad(part, start)` is true, looked for in the parts this process holds (`local_parts`);
    `index` is the element's index in the whole array."""
    for start, part in local_parts(x):
        b = np.asarray(bad(part, start))
        if b.any():
            local = tuple(int(i) for i in np.argwhere(b)[0])
            raise ValueError(message([i + s for i, s in zip(local, start)], part[local].item()))
