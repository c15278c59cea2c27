r"""The layer recursion of `stack` (`_films._stack`, whose docstring states the conventions):
the characteristic matrices of the layers applied to the outgoing wave, with closed-form
derivatives, and the recursion over incoherent layers.

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
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._core._numerics import _abs2, _materialize_parts, decaying_sqrt, materialize_tangent
from .._interface._fresnel_terms import _kt_squared
from ._elementary import _DS_SERIES_MAX, _decaying_root, _ds_dq_series, _sincos


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
        # (an associative scan: XLA's CPU backend computes `cumsum` as a windowed reduction, m^2 adds)
        prefix = jnp.concatenate([jnp.zeros_like(im_phase[:1]), jax.lax.associative_scan(jnp.add, im_phase[:-1], axis=0)],
                                 axis=0)
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
        # stored once (a division by 1): in the transposed (reverse-mode) step its cotangent, a sum
        # over the four entries' terms, then feeds the cotangents of the layer's index and of the
        # incidence (carried) from memory instead of being recomputed in each of their loops
        dq = materialize_tangent(dnsq + dm, q)
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


def _incoherent(bounds, ki, nn, dd, k0, kz_sq):
    """Coherent groups between the incoherent layers `bounds[1:-1]` (indices among all media),
    summed in intensity. Arrays have the media (dd: inner layers) on the leading axis."""
    # k_z^2 stored once before its root (`materialize`): the root's mask and its input then read
    # the same bits where the layer is at its own critical angle (k_z^2 within rounding of 0)
    kz = {j: decaying_sqrt(_materialize_parts(kz_sq(nn[j]))) for j in bounds[1:]}
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
    return Rs, Rp, Ts, Tp, As, Ap, X[0]
