"""Kernels that run as one compiled program when called eagerly.

A kernel written as `jax.numpy` operations runs, called eagerly, one operation at a time: JAX
dispatches (and on first sight of a shape compiles) each of its tens to hundreds of operations on
its own, so an eager `refract` of one ray took milliseconds. `program` wraps a public kernel in
`jax.jit(..., inline=True)`: an eager call compiles the whole kernel once per shape, dtype and
static argument and then runs it as one program (as `jax.numpy`'s own functions do); inside a
caller's `jit`, `vmap` or derivative it is inlined, so the caller's program is what it would be
without the wrapper. An eager call and a call inside the user's `jit` therefore run the same
compiled arithmetic (XLA fuses and contracts multiply-adds into FMAs the same way in both).

The kernels' argument checks (`_validate`) look only at shapes and dtypes, so they run the same
while the program is traced and raise the same `ValueError` before anything is compiled. Two kinds
of argument are converted before the call, so that they are checked as they were given rather
than as `jit` would convert them: a Python `int` (`eta1=1`, accepted and weakly typed like a
`float`) becomes a `float`, and a list or tuple becomes a NumPy array. Arguments named in
`static_argnames` (a method's name, a specification) key the program; a `NamedTuple`
specification's list fields are made tuples for that.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any, TypeVar

import jax
import numpy as np

F = TypeVar("F", bound=Callable[..., Any])


def _as_given(x: Any) -> Any:
    """`x` in the form the kernel's checks read it in: a Python `int` (not `bool`) as a `float`,
    a list or tuple as a NumPy array; anything else unchanged."""
    if isinstance(x, int) and not isinstance(x, bool):
        return float(x)
    if isinstance(x, (list, tuple)):
        return np.asarray(x)
    return x


def _hashable(x: Any) -> Any:
    """A static argument as a key of the program: a `NamedTuple` specification (`InterfaceSpec`)
    with its list fields as tuples (`outputs=["t", "R"]` is accepted as it always was)."""
    if isinstance(x, tuple) and hasattr(x, "_replace"):
        lists = {k: tuple(v) for k, v in zip(x._fields, x) if isinstance(v, list)}  # type: ignore[attr-defined]
        return x._replace(**lists) if lists else x
    return x


def program(*, static_argnames: tuple[str, ...] = ()) -> Callable[[F], F]:
    """Decorator: run the kernel as one compiled program when called eagerly and inline it when
    traced (see the module docstring)."""

    def wrap(fun: F) -> F:
        jitted = jax.jit(fun, static_argnames=static_argnames, inline=True)
        params = list(inspect.signature(fun).parameters)
        static = set(static_argnames)

        @functools.wraps(fun)
        def call(*args: Any, **kwargs: Any) -> Any:
            args = tuple(_hashable(a) if params[j] in static else _as_given(a) for j, a in enumerate(args))
            kwargs = {k: _hashable(v) if k in static else _as_given(v) for k, v in kwargs.items()}
            return jitted(*args, **kwargs)

        return call  # type: ignore[return-value]

    return wrap
