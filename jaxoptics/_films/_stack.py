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

How the stack is computed (the characteristic matrices, scaled so that nothing overflows, their
closed-form derivatives, the recursion over incoherent layers): see `jaxoptics._films._layers`.

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
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _validate as V
from .._core._numerics import _abs2, _materialize_parts, decaying_sqrt, sqrt_where, unpolarized
from .._core._program import program
from .._core._result import Unpacks, result
from ._elementary import _atan2
from ._layers import _group, _incoherent, _KzSq

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


# ---- the public kernels ------------------------------------------------------------------------


def _check_concrete(n, d, wavelength, cos_i):
    """Value checks on concrete inputs (skipped for traced ones, which get NaN instead)."""

    def concrete(x):
        return not isinstance(x, jax.core.Tracer)

    def first_bad(x, bad, what, name):
        if concrete(x):  # on the parts this process holds (an array may span several processes)
            V.first_bad(x, bad, lambda idx, v: f"{name}{idx} = {v!r}: {what}")

    first_bad(d, lambda x, _: ~(np.isfinite(x) & (x >= 0)), "thicknesses must be finite and >= 0", "d")
    first_bad(wavelength, lambda x, _: ~(np.isfinite(x) & (x > 0)), "wavelengths must be finite and > 0", "wavelength")
    first_bad(cos_i, lambda x, _: ~(np.isfinite(x) & (np.abs(x) <= 1 + 1e-6)), "cos_i must be finite and within [-1, 1]",
              "cos_i")
    first_bad(n, lambda x, _: ~(np.isfinite(x) & (np.real(x) > 0)) | V.is_gain(x),
              f"indices must be finite with real part > 0 and imaginary part k >= 0 (a k below 0 by at most "
              f"{V.K_ROUNDING:g} |n| is rounding, taken as 0)", "n")
    # (a part that does not hold the first medium, n sharded along the media, has nothing to check)
    first_bad(n, lambda x, start: (np.imag(x[..., :1]) != 0) & (start[-1] == 0),
              "the incident medium n[..., 0] must be real", "n")


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
    V.broadcast_shapes(n=jnp.shape(n)[:-1], d=jnp.shape(d)[:-1], wavelength=jnp.shape(wavelength), cos_i=jnp.shape(cos_i))
    return n, d, wavelength, cos_i, tuple(sorted(int(j) + 1 for j in inc))


def _padded(n, d, wavelength, cos_i):
    """The inputs in the computation's dtypes (`n` complex) with their batch ranks padded to the
    batch's (size-1 axes), sizes not: per-layer arrays of one point are broadcast inside the scan
    step, so no (layers x points) array is materialized for them. Also returns the batch shape."""
    batch = jnp.broadcast_shapes(jnp.shape(n)[:-1], jnp.shape(d)[:-1], jnp.shape(wavelength), jnp.shape(cos_i))
    dt = V.float_dtype(n, d, wavelength, cos_i)
    cdt = V.complex_dtype(dt)

    def pad(x, dtype, core):
        x = jnp.asarray(x, dtype)
        return x.reshape((1,) * (len(batch) + core - x.ndim) + x.shape)

    return pad(n, cdt, 1), pad(d, dt, 1), pad(wavelength, dt, 0), pad(cos_i, dt, 0), batch


def _valid(media, dd, wavelength, cos_i):
    """Elements with every input in the domain (`media`: `_Media`; `dd` layer axis first)."""
    good = lambda n: (jnp.real(n) > 0) & (jnp.real(n) < jnp.inf) & (jnp.imag(n) >= 0) & (jnp.imag(n) < jnp.inf)
    ends = good(media.first) & (jnp.imag(media.first) == 0) & good(media.last)
    shape = jnp.broadcast_shapes(ends.shape, media.inner.shape[1:])
    # one reduction over the media (its result stored once, for every output's NaN mask to read)
    ok = jnp.all(jnp.concatenate([jnp.broadcast_to(ends, shape)[None],
                                  jnp.broadcast_to(good(media.inner), media.inner.shape[:1] + shape)]), axis=0)
    ok &= jnp.all((dd >= 0) & (dd < jnp.inf), axis=0)
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
    inputs (`complex64` for float32, `complex128` for float64). Called eagerly, the kernel runs as
    one compiled program, compiled on the first call for each shape, dtype and `incoherent`
    layout; inside a caller's `jit`, `vmap` or derivative it is inlined into the caller's program.

    **Returns:** a `StackResult` (see there): `R_s, R_p, T_s, T_p`, `A_s, A_p` per inner layer,
    the complex amplitudes `r_s, r_p, t_s, t_p` (None with incoherent layers), and `rp_rs`.

    **Conventions:** those of the module (`jaxoptics._films._stack`): amplitude signs as
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
    n, d, wavelength, cos_i, inc = _prepare(n, d, wavelength, cos_i, incoherent)
    return _stack_program(n, d, wavelength, cos_i, inc=inc, block=_block_size())


@program(static_argnames=("inc", "block"))
def _stack_program(n, d, wavelength, cos_i, *, inc, block):
    """`stack` after its checks, as one compiled program (as `jax.numpy`'s functions are): an
    eager call compiles it once per shape, dtype and layout instead of dispatching each of the
    kernel's hundreds of operations on its own, and inside a caller's `jit` it is inlined. `block`
    is `_block_size()`, passed in so that a program is keyed by the block size it was traced with."""
    n, d, wavelength, cos_i, batch = _padded(n, d, wavelength, cos_i)
    # the first and the last medium also apart (the kernel reads the inner layers of `n`): in
    # reverse mode each part's cotangent is then formed in a loop of its own and the three are
    # added once, outside the blocks (as one array, XLA builds the whole index's cotangent in one
    # fused loop over points and media, recomputing every medium's terms for each medium: 10x
    # the forward pass for one layer). `n` itself is not sliced: its blocks are a reshape, no copy.
    parts = ((n[..., 0], 0), (n, 1), (n[..., -1], 0), (d, 1), (wavelength, 0), (cos_i, 0))
    return _chunked(lambda *a: _stack(*a, inc), parts, batch, block)


# Points per block of `_chunked` on the CPU. The layer scan streams its carry (the tangential
# fields of both polarizations) and the per-layer terms through memory once per layer; over a
# block of this many points they stay in the CPU's caches. On a 10-layer stack (float64, 2-core
# EPYC, 10^6 points) blocks of 16k-64k points take half the time of one block of 10^6; below
# about 4k points per block the per-operation overhead of XLA's loops dominates.
_BLOCK = 32768
# On an accelerator (GPU, TPU): each step of the layer scan is at least one kernel launch of a few
# microseconds, whatever the block's size, so blocks are as large as memory comfortably allows
# (2^20 points: arrays of 16 MB in complex128).
_BLOCK_ACCELERATOR = 1 << 20


def _block_size():
    """Points per block for the default backend: `_BLOCK` on the CPU, `_BLOCK_ACCELERATOR` elsewhere."""
    return _BLOCK if jax.default_backend() == "cpu" else _BLOCK_ACCELERATOR


def _chunked(f, args, batch, block_size):
    """`f(*args)` over a large batch in blocks of at most `block_size` points (a `lax.map` over
    blocks), with each argument's core axes moved first.

    `args` are pairs `(x, core)`: `x` has the rank of `batch` followed by `core` (0 or 1) axes
    (the layer axis), with size-1 axes where it broadcasts. `f` takes arrays with the core axis
    first, then batch axes, and returns a pytree of arrays with the batch shape of its arguments
    plus trailing core axes. Arguments with one point are passed whole to every block; the others
    are broadcast to the batch, flattened and cut into `nb = ceil(N / block_size)` blocks of
    `ceil(N / nb)` points (the last padded by repeating the final point, fewer than `nb` points in
    all, whose results are dropped). An argument given per point is transposed once, block by
    block (`(nb, points, L)` to `(nb, L, points)`): each block's layer rows are then contiguous
    for the layer scan.

    Each block is rematerialized in the backward pass (`jax.checkpoint`): reverse mode then keeps
    one block's residuals at a time, in cache, instead of every layer's residuals for the whole
    batch, which the backward pass would stream through memory (measured: the gradient costs
    3x the forward pass this way, 7x without)."""
    N = math.prod(batch)
    nr = len(batch)
    first = lambda x, k: jnp.moveaxis(x, -1, 0) if k else x
    if N <= block_size:
        return f(*(first(x, k) for x, k in args))
    nb = -(-N // block_size)
    bs = -(-N // nb)
    # per argument: its blocks (nb, core..., bs), or None where it has one point (passed whole)
    blocks = []
    for x, k in args:
        core = x.shape[nr:]
        if math.prod(x.shape[:nr]) == 1:
            blocks.append(None)
        else:
            x = jnp.broadcast_to(x, batch + core).reshape((N,) + core)
            if nb * bs > N:
                x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (nb * bs - N,) + core)], axis=0)
            blocks.append(x.reshape((nb, bs) + core))
    mapped = [b for b in blocks if b is not None]

    def one_block(ys):
        it = iter(ys)
        return f(*(first(x.reshape((1,) + x.shape[nr:]) if b is None else next(it), k)
                   for (x, k), b in zip(args, blocks)))

    out = jax.lax.map(jax.checkpoint(one_block), mapped)
    unblock = lambda y: y.reshape((nb * bs,) + y.shape[2:])[:N].reshape(batch + y.shape[2:])
    return jax.tree.map(unblock, out)


class _Media:
    """The indices of a stack's media, layer axis first, from the first medium, the inner layers and
    the last medium held apart: `media[j]` is medium `j`, `media[i:j]` inner layers only."""

    def __init__(self, first, inner, last):
        self.first, self.inner, self.last = first, inner, last
        self.L = inner.shape[0] + 2

    def __getitem__(self, j):
        if isinstance(j, slice):
            start, stop, step = j.indices(self.L)
            if step != 1 or start < 1 or stop > self.L - 1:
                raise IndexError(f"only inner layers slice: {j}")
            return self.inner[start - 1:stop - 1]
        j = j % self.L
        return self.first if j == 0 else self.last if j == self.L - 1 else self.inner[j - 1]


def _stack(n_first, nn, n_last, dd, wavelength, cos_i, inc):
    """The kernel on `_padded`'s arrays: the first and the last medium, and `nn` (every medium,
    of which the inner layers are read) and `dd` with the layer axis first, not broadcast to the
    batch (the scan step does that). A `k` within rounding below 0 is set to 0 here, block by
    block, and the media are then stored once (for the scan and the validity check to read
    contiguous rows; on the whole batch, XLA fuses the clean-up into the transpose of a per-point
    `n` and then transposes twice)."""
    clean = V.without_rounding_k
    media = _Media(*(_materialize_parts(clean(x)) for x in (n_first, nn[1:-1], n_last)))
    batch = jnp.broadcast_shapes(n_first.shape, nn.shape[1:], n_last.shape, dd.shape[1:], wavelength.shape, cos_i.shape)
    cdt = nn.dtype
    valid = _valid(media, dd, wavelength, cos_i)
    c = jnp.where(cos_i < 0, -cos_i, cos_i)  # |cos_i|, derivative +1 at 0 (as in fresnel)
    n0 = jnp.real(media.first)
    ki = jnp.broadcast_to((n0 * c).astype(cdt), batch)
    n0c = n0.astype(cdt)
    k0 = 2 * jnp.pi / wavelength
    kz_sq = _KzSq(ki, n0c)  # k_z^2 formed as in `fresnel`
    kz_exit = _materialize_parts(decaying_sqrt(kz_sq(media.last)))
    if not inc:
        s, p = _group(ki, n0c, kz_exit, media.last, media.inner, dd, k0, kz_sq, real_incident=True)
        return _finish(valid, s.R, p.R, s.T, p.T, s.A, p.A, (s.r, p.r, s.t, p.t), p.r * jnp.conj(s.r))
    Rs, Rp, Ts, Tp, As, Ap, rp_rs = _incoherent((0,) + inc + (media.L - 1,), ki, media, dd, k0, kz_sq)
    return _finish(valid, Rs, Rp, Ts, Tp, As, Ap, None, rp_rs)


def _finish(valid, Rs, Rp, Ts, Tp, As, Ap, amps, rp_rs):
    """The outputs, NaN where an input is out of the domain. `As`, `Ap`: the absorption per inner
    layer, layer axis first (an array, or a list of the layers' arrays); masked as one array and
    moved to the last axis in one transpose (layer by layer, XLA's CPU backend writes each
    layer's masked copy, then stacks them: two passes over every layer's values)."""
    nan = lambda x: jnp.where(valid, x, jnp.nan)  # (and broadcast to the batch shape)

    def per_layer(A):
        if not len(A):
            return jnp.zeros(Rs.shape + (0,), Rs.dtype)
        A = jnp.stack(jnp.broadcast_arrays(*A)) if isinstance(A, list) else A
        return jnp.moveaxis(jnp.where(valid[None], A, jnp.nan), 0, -1)

    A_s, A_p = per_layer(As), per_layer(Ap)
    amps = tuple(nan(x) for x in amps) if amps is not None else (None,) * 4
    return StackResult(nan(Rs), nan(Rp), nan(Ts), nan(Tp), A_s, A_p, *amps, nan(rp_rs))


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
    n, d, wavelength, cos_i, inc = _prepare(n, d, wavelength, cos_i, incoherent)
    return _ellipsometry_program(n, d, wavelength, cos_i, inc=inc, block=_block_size())


@program(static_argnames=("inc", "block"))
def _ellipsometry_program(n, d, wavelength, cos_i, *, inc, block):
    """`ellipsometry` after its checks, one compiled program (see `_stack_program`)."""
    res = _stack_program(n, d, wavelength, cos_i, inc=inc, block=block)
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
