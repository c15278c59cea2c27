"""Scaling across devices with JAX's own sharding (no engine of our own).

Every kernel is elementwise over its batch axes, so an array sharded along the batch axis flows
through it (under `jit`, or eagerly) and comes out with the same sharding: XLA's partitioner does
the work, nothing is gathered. `fit_eta` likewise fits a sharded batch of curves where the curves
live (`fit_eta_sharded`, in `jaxoptics._fitting._index`, pads and shards one with these
helpers). The helpers here take care of the two chores: building a one-dimensional mesh over the
available devices, and padding a batch whose size is not a multiple of the device count (the
padding is removed again from the results).

Multi-host: call `jax.distributed.initialize()` on every process first; `jax.devices()` then
lists the devices of all hosts and the same code runs unchanged (each process passes the whole
logical batch, or builds a global array with `jax.make_array_from_process_local_data`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike

AXIS = "batch"
T = TypeVar("T")


def batch_mesh(*, devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-dimensional mesh named `"batch"` over `devices` (default: all of `jax.devices()`),
    for `shard_batch`, `sharded_map` and `fit_eta_sharded`. Multi-host: after
    `jax.distributed.initialize()`, `jax.devices()` spans the hosts."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), (AXIS,))


def batch_sharding(mesh: Mesh, ndim: int) -> NamedSharding:
    """Sharding of an array along its first axis over the mesh's batch axis (others replicated)."""
    return NamedSharding(mesh, P(AXIS, *([None] * (ndim - 1))))


def shard_batch(x: ArrayLike, *, mesh: Mesh | None = None) -> tuple[Array, int]:
    """Pad `x` along axis 0 to a multiple of the device count (repeating its last entry, so the
    padding is valid data) and place it sharded along that axis over `mesh` (default
    `batch_mesh()`).

    **Arguments:** `x`, an array of any dtype with a leading batch axis of length >= 1 (trailing
    axes are kept whole on every device).

    **Returns:** `(sharded, n)`: the padded array, sharded along axis 0, and `n` the original
    length. A scalar or an empty batch raises a `ValueError`."""
    mesh = batch_mesh() if mesh is None else mesh
    x = jnp.asarray(x)
    if x.ndim == 0 or x.shape[0] == 0:
        raise ValueError(f"shard_batch needs an array with a non-empty leading batch axis, got shape {x.shape}")
    n = x.shape[0]
    k = mesh.devices.size
    pad = (-n) % k
    if pad:
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)], axis=0)
    return jax.device_put(x, batch_sharding(mesh, x.ndim)), n


def from_blocks(blocks: dict[int, Array], length: int, mesh: Mesh, axis: str) -> Array:
    """One array of `length` rows sharded along its first axis over `mesh`'s `axis` (its other
    axes whole), from blocks of consecutive rows keyed by their first row, each computed on a
    device of the mesh: every device holds the block of its rows (moved only where the device
    holds a replica along another mesh axis). Only this process's devices take part."""
    first = next(iter(blocks.values()))
    shape = (length,) + first.shape[1:]
    target = NamedSharding(mesh, P(axis, *([None] * (len(shape) - 1))))
    parts = [jax.device_put(blocks[(index[0].start if index else None) or 0], device)
             for device, index in target.addressable_devices_indices_map(shape).items()]
    return jax.make_array_from_single_device_arrays(shape, target, parts)


def _trim(out, n, total, keep_padding):
    if total == n or keep_padding:
        return out
    return jax.tree_util.tree_map(lambda y: y[:n] if jnp.ndim(y) and y.shape[0] == total else y, out)


def sharded_map(fn: Callable[..., T], *arrays: ArrayLike, mesh: Mesh | None = None, broadcast: Sequence[ArrayLike] = (),
                keep_padding: bool = False) -> T:
    """Apply an elementwise-over-axis-0 function to arrays sharded along their first axis.

    **Arguments:** `fn(*arrays, *broadcast)`; `arrays` share their first (batch) axis, of any
    length; `broadcast` are passed to every shard whole (replicated), e.g. shared angles.

    **Returns:** `fn`'s outputs (any pytree), sharded along the batch axis. A length that is not a
    multiple of the device count is padded (with copies of the last entry) for the computation;
    with `keep_padding=False` (default) the padding is removed from the outputs, which JAX cannot
    shard unevenly, so those come back replicated; `keep_padding=True` keeps them sharded and
    padded (the first `n` rows are the results).
    """
    mesh = batch_mesh() if mesh is None else mesh
    placed = [shard_batch(a, mesh=mesh) for a in arrays]
    n = placed[0][1]
    if any(m != n for _, m in placed):
        raise ValueError(f"arrays must share their first axis, got lengths {[m for _, m in placed]}")
    out = jax.jit(fn)(*[a for a, _ in placed], *broadcast)
    return _trim(out, n, placed[0][0].shape[0], keep_padding)
