"""Refinement: the merit's residuals as a function of the slots' thicknesses, and a
Levenberg-Marquardt solve (optimistix) of many starts at once in one compiled program.

Bounds are kept by the change of variables the film fit uses (`x = lo + (hi - lo)(1 + sin u)/2`
between two bounds, `lo - 1 + sqrt(u^2 + 1)` above one), so the solver is unconstrained in `u`;
a slot that is not free keeps its thickness whatever `u` is (its column of the Jacobian is zero,
which the solver's damping handles).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._films._stack import stack
from .._runtime._options import compiler_options
from ._layers import Slots
from ._targets import Layout, quantities, residuals

# start values closer to a bound than this fraction of the range (of max(1, |lo|) above one
# bound) are moved inside: on a bound the change of variables has zero slope and the solver
# would never move the layer
_INSIDE = 1e-3


def box(u, lo, hi):
    """Thickness from the unconstrained variable (elementwise; `hi` may be inf)."""
    fin = jnp.isfinite(hi)
    h = jnp.where(fin, hi, lo + 1)
    return jnp.where(fin, lo + (h - lo) * (1 + jnp.sin(u)) / 2, lo - 1 + jnp.sqrt(u * u + 1))


def unbox(x, lo, hi):
    """The inverse of `box`, for starts (NumPy), moved inside the bounds first (`_INSIDE`)."""
    fin = np.isfinite(hi)
    h = np.where(fin, hi, lo + 1)
    width = np.where(fin & (h > lo), h - lo, 1.0)  # (a slot that is not free has lo == hi)
    eps = np.where(fin, _INSIDE * width, _INSIDE * np.maximum(1.0, np.abs(lo)))
    x = np.clip(x, lo + eps, np.where(fin, h - eps, np.inf))
    two = np.arcsin(np.clip(2 * (x - lo) / width - 1, -1, 1))
    one = np.sqrt(np.maximum((x - lo + 1) ** 2 - 1, 0))
    return np.where(fin, two, one)


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """What one `design` call evaluates: the materials (from `slots`), the targets' layout and
    arrays (as JAX arrays of `dtype`), and an optional set of relative and absolute thickness
    errors (`(draws, slots)` each) over which the merit is averaged (robust design)."""

    slots: Slots
    lay: Layout
    arrays: dict
    dtype: np.dtype
    errors: tuple | None = None

    def residuals(self, ids, d):
        """The merit's residuals of the design `(ids, d)` (any number of slots)."""
        return residuals(self.lay, self.values(ids, d), self.arrays)

    @functools.cached_property
    def _key(self):
        """What the traced programs depend on (not the slots' thicknesses or materials' order
        in use, which are arguments): equal problems share compiled programs."""
        arr = tuple((k, np.asarray(v).tobytes()) for k, v in sorted(self.arrays.items()))
        err = None if self.errors is None else tuple(np.asarray(e).tobytes() for e in self.errors)
        return (self.slots.materials, self.slots.ambient, self.slots.substrate, self.lay, arr, self.dtype, err)

    def __eq__(self, other):
        return isinstance(other, Problem) and self._key == other._key

    def __hash__(self):
        return hash(self._key)

    def values(self, ids, d):
        """Every target point's computed value (target order)."""
        n_table = self.slots.n_table
        return quantities(self.lay, lambda wl, cos_i: stack(n_table(wl)(ids), d, wl, cos_i), self.arrays)

    def objective(self, ids, d):
        """`residuals`, or with `errors`, the residuals of every perturbed design over
        `sqrt(draws)` (their sum of squares is the mean of `MF^2` over the draws)."""
        if self.errors is None:
            return self.residuals(ids, d)
        rel, ab = self.errors
        # (an absolute error does not make an unused, zero-thickness slot a layer)
        dd = jnp.where(d > 0, jnp.maximum(d[None] * (1 + rel) + ab, 0), 0)
        r = jax.vmap(lambda x: self.residuals(ids, x))(dd)
        return r.reshape(-1) / np.sqrt(rel.shape[0])


def make_problem(slots, lay, arrays, dtype, errors=None) -> Problem:
    arr = {k: jnp.asarray(v, dtype) for k, v in arrays.items()}
    return Problem(slots, lay, arr, np.dtype(dtype), errors)


# Programs whose work is at most this (starts x draws x target points x slots^2: the residuals
# times the Jacobian's columns times the layers each column passes through) are compiled with
# `QUICK_COMPILE`: compiling is then most of their time (a two-layer design over 16 wavelengths
# compiles in 2.5 s instead of 7-8 s and runs in 10 ms instead of 7 ms). Larger ones get XLA's
# defaults, whose code runs several times faster: 20 starts of a 24-layer design over 80 points
# refine in 5.6 s instead of 23.7 s (and compile in 5.7 s instead of 6.8 s).
QUICK_WORK = 1 << 16


def quick(problem: Problem, starts: int) -> bool:
    draws = 1 if problem.errors is None else problem.errors[0].shape[0]
    points = problem.lay.n_plain + problem.lay.n_dispersive
    return starts * draws * points * problem.slots.size**2 <= QUICK_WORK


@functools.cache
def jitted(fun, quick: bool, static: tuple):
    """`fun` jitted with the compiler options of `quick` (`jaxoptics._runtime._options`)."""
    return jax.jit(fun, static_argnames=static, compiler_options=compiler_options(quick))


def refine_program(problem: Problem, ids, U0, free, lo, hi, d_fixed, *, max_steps):
    """Levenberg-Marquardt from each row of `U0` (`(B, S)` unconstrained variables).

    **Returns:** `(d, mf2, steps)`: `(B, S)` thicknesses, `(B,)` merit squared, `(B,)` steps."""
    import optimistix as optx

    tol = 1e-10 if problem.dtype == np.float64 else 1e-5
    solver: optx.AbstractLeastSquaresSolver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    thick = lambda u: jnp.where(free, box(u, lo, hi), d_fixed)
    fn = lambda u, _: problem.objective(ids, thick(u))

    def one(u0):
        sol = optx.least_squares(fn, solver, u0, max_steps=max_steps, throw=False)
        r = fn(sol.value, None)
        return thick(sol.value), jnp.sum(r * r), sol.stats["num_steps"]

    return jax.vmap(one)(U0)


def merit2_program(problem: Problem, ids, D):
    """`MF^2` of each row of `D` (`(B, S)` thicknesses) with materials `ids`."""
    return jax.vmap(lambda d: jnp.sum(problem.objective(ids, d) ** 2))(D)


def merit2(problem: Problem, s: Slots) -> float:
    """`MF^2` of the design `s` as it is."""
    return float(run(merit2_program, problem, jnp.asarray(s.ids), jnp.asarray(s.d[None], problem.dtype))[0])


def values_program(problem: Problem, ids, d):
    return problem.values(ids, d)


def run(fun, problem: Problem, *args, starts: int = 1, **static):
    """`fun(problem, *args, **static)` as a compiled program (`quick` for small problems)."""
    return jitted(fun, quick(problem, starts), ("problem",) + tuple(static))(problem, *args, **static)


def refine(problem: Problem, s: Slots, D0, max_steps: int):
    """Refine the starts `D0` (`(B, S)` thicknesses of `s`'s slots; the slots that are not free
    keep theirs). **Returns:** `(D, mf2, steps)` as NumPy arrays."""
    dt = problem.dtype
    lo, hi = s.lo.astype(dt), s.hi.astype(dt)
    U0 = unbox(np.asarray(D0, dt), lo, hi)
    out = run(refine_program, problem, jnp.asarray(s.ids), jnp.asarray(U0, dt), jnp.asarray(s.free), jnp.asarray(lo),
               jnp.asarray(hi), jnp.asarray(s.d, dt), starts=U0.shape[0], max_steps=max_steps)
    return tuple(np.asarray(x) for x in out)
