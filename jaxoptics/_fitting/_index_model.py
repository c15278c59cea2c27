"""The reflectance model the index fits use: R(theta; eta) for one polarization, with
derivatives in the index, and `synthetic_reflectance` to make test curves from it."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from .._core import _validate as V
from .._core._numerics import _own_loop
from .._interface._fresnel import fresnel, fresnel_sp

if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike, Float, Inexact, PRNGKeyArray

POLARIZATIONS = ("unpolarized", "s", "p")

# The weight of s-polarized light in the measured reflectance, per polarization: a batch of curves
# in different polarizations is fitted in one program with R = a R_s + (1 - a) R_p per curve.
S_WEIGHT = {"s": 1.0, "p": 0.0, "unpolarized": 0.5}


def _mix(polarization, s, p):
    """The quantity of one polarization from thunks `s()` and `p()` of its s and p parts:
    `polarization` is `"s"`, `"p"` or `"unpolarized"` (static: only what is needed is computed),
    or an array `a`, the weight of s-polarized light (broadcast against the parts): `a s + (1 - a) p`."""
    if isinstance(polarization, str):
        return {"s": s, "p": p, "unpolarized": lambda: 0.5 * (s() + p())}[polarization]()
    vs, vp = s(), p()
    a = polarization.astype(jnp.result_type(vs, vp))  # (complex parts: explicit, for strict dtype promotion)
    return a * vs + (1 - a) * vp


def _reflectance(cos_i, eta1, eta2, polarization):
    if isinstance(polarization, str) and polarization == "unpolarized":
        return fresnel(cos_i, eta1, eta2)
    R_s, R_p = fresnel_sp(cos_i, eta1, eta2)
    return _mix(polarization, lambda: R_s, lambda: R_p)


def _kt_squared_plain(ki, eta1, eta2):
    """k_t^2 = eta2^2 - eta1^2 sin^2 in the two forms of `fresnel` (see `_kt_squared`), by one select."""
    return jnp.where(eta1 > 2 * eta2, eta2 * eta2 + (ki - eta1) * (ki + eta1), (eta2 - eta1) * (eta2 + eta1) + ki * ki)


def _reflectance_d_eta2(cos_i, eta1, eta2, polarization):
    r"""`d R / d eta2` for a real `eta2`, written so that XLA compiles it to one fused loop.

    With k_i = eta1 |c|, k_t = sqrt(q), q = eta2^2 - eta1^2 + k_i^2, D_s = k_i + k_t and
    D_p = eta2^2 k_i + eta1^2 k_t (the same closed form as `fresnel`'s derivative rule):

    $$\frac{dR_s}{d\eta_2} = \frac{-4 k_i \eta_2 (k_i - k_t)}{k_t D_s^3}, \qquad
    \frac{dR_p}{d\eta_2} = \frac{4 \eta_1^2 \eta_2 k_i (2 q - \eta_2^2)(\eta_2^2 k_i - \eta_1^2 k_t)}{k_t D_p^3}$$

    and 0 under TIR and at the critical angle (q <= 0), as in `fresnel`. Only what a fit needs:
    no guards for invalid input (the fit's index is |y| and its data are checked), one select at
    the end. The kernel's own rule shares its quotients with the reflectance and selects on
    several masks; XLA on the CPU (no multi-output fusion) then wrote five arrays over all
    (curves x angles) per solver step for this one column.
    """
    ki = eta1 * jnp.abs(cos_i)
    e1sq, e2sq = eta1 * eta1, eta2 * eta2
    q = _kt_squared_plain(ki, eta1, eta2)
    kt = jnp.sqrt(jnp.maximum(q, jnp.finfo(q.dtype).tiny))

    def d_s():
        ds = ki + kt
        return -4 * ki * eta2 * (ki - kt) / (kt * ds * ds * ds)

    def d_p():
        dp = e2sq * ki + e1sq * kt
        return 4 * e1sq * eta2 * ki * (2 * q - e2sq) * (e2sq * ki - e1sq * kt) / (kt * dp * dp * dp)

    return jnp.where(q > 0, _mix(polarization, d_s, d_p), 0)


def _reflectance_plain(cos_i, eta1, eta2, polarization):
    """The reflectance for a real `eta2 > 0` as one expression XLA compiles to one fused loop: the
    fits' model (residuals, start ranking).

    `fresnel` is accurate to a few ulps relative to R everywhere; a fit needs R to an absolute
    accuracy far below any measurement noise, and pays for the kernel's guards and branches in
    every solver step. Here: the textbook amplitudes on k_t^2 formed as in `fresnel` (exact
    `eta2 - eta1`; for `eta1 > 2 eta2` the form that cancels only at the scale of eta2^2), one
    select at the end. Absolute error at most 1e-15 (tested against 50-digit mpmath), except
    within rounding of the critical angle, where both are ill-conditioned. On the fits' shapes the
    careful kernel split into four loops in the start and was 14% of a 10^4-curve fit in the
    solver (measured).
    """
    shape = jnp.broadcast_shapes(jnp.shape(cos_i), jnp.shape(eta1), jnp.shape(eta2))
    cos_i, eta1, eta2 = (jnp.broadcast_to(x, shape) for x in (cos_i, eta1, eta2))
    ki = eta1 * jnp.abs(cos_i)
    e1sq, e2sq = eta1 * eta1, eta2 * eta2
    kt = jnp.sqrt(jnp.maximum(_kt_squared_plain(ki, eta1, eta2), 0))  # 0 under TIR: R = 1
    rs = (ki - kt) / (ki + kt)
    rp = (e2sq * ki - e1sq * kt) / (e2sq * ki + e1sq * kt)
    R = _mix(polarization, lambda: rs * rs, lambda: rp * rp)
    # 0/0 only at exact grazing incidence with k_t = 0: no interface if eta1 == eta2 (R = 0), else
    # the grazing limit under TIR (R = 1). Written as `== 0` so that a NaN candidate (the TIR-onset
    # estimate of a curve without a plateau) keeps R = NaN and is never chosen: `> 0` made its R
    # 0, the best fit to an index-matched curve.
    return jnp.where(ki + kt == 0, jnp.where(eta1 == eta2, 0, 1), R)


def _amplitudes_complex(cos_i, eta1, eta2):
    """k_i, k_t, the denominators D_s and D_p, eta1^2 and eta2^2 for a complex `eta2 = n + ik`,
    `k >= 0`: what the complex fits' model and its derivative are written in (plain expressions,
    see `_reflectance_plain`)."""
    shape = jnp.broadcast_shapes(jnp.shape(cos_i), jnp.shape(eta1), jnp.shape(eta2))
    cos_i, eta1, eta2 = (jnp.broadcast_to(x, shape) for x in (cos_i, eta1, eta2))
    e1 = eta1.astype(eta2.dtype)  # explicit casts: also under jax_numpy_dtype_promotion="strict"
    ki = e1 * jnp.abs(cos_i).astype(eta2.dtype)
    e1sq, e2sq = e1 * e1, eta2 * eta2
    kt = jnp.sqrt((eta2 - e1) * (eta2 + e1) + ki * ki)  # principal root: Im >= 0 for k >= 0
    ds, dp = ki + kt, e2sq * ki + e1sq * kt
    return ki, kt, ds, dp, e1sq, e2sq


def _reflectance_complex_plain(cos_i, eta1, eta2, polarization):
    """The reflectance for a complex `eta2`, as `_reflectance_plain` for a real one (absolute error
    about 1e-14 against mpmath)."""
    ki, kt, ds, dp, e1sq, e2sq = _amplitudes_complex(cos_i, eta1, eta2)
    rs, rp = (ki - kt) / ds, (e2sq * ki - e1sq * kt) / dp
    a2 = lambda z: jnp.real(z) ** 2 + jnp.imag(z) ** 2
    R = _mix(polarization, lambda: a2(rs), lambda: a2(rp))
    return jnp.where(jnp.real(ds) == 0, jnp.where(eta1 == jnp.real(eta2), 0, 1), R)


def _reflectance_complex_grad(cos_i, eta1, eta2, polarization):
    """G with dR = Re(G d eta2): G = 2 conj(r) dr/deta2 for one polarization, the mean for both.
    dr_s/deta2 = -2 k_i eta2 / (k_t D_s^2), dr_p/deta2 = 2 eta1^2 eta2 k_i (2 k_t^2 - eta2^2) / (k_t D_p^2)."""
    ki, kt, ds, dp, e1sq, e2sq = _amplitudes_complex(cos_i, eta1, eta2)
    gs = lambda: 2 * jnp.conj((ki - kt) / ds) * (-2 * ki * eta2 / (kt * ds * ds))
    gp = lambda: 2 * jnp.conj((e2sq * ki - e1sq * kt) / dp) * (2 * e1sq * eta2 * ki * (2 * kt * kt - e2sq) / (kt * dp * dp))
    G = _mix(polarization, gs, gp)
    return jnp.where(jnp.abs(kt) > 0, G, 0)


def _reflectance_fit(cos_i, eta1, eta2, polarization):
    """The fits' model: `_reflectance_plain` for a real `eta2`, `_reflectance_complex_plain` for a
    complex one."""
    plain = _reflectance_complex_plain if jnp.iscomplexobj(eta2) else _reflectance_plain
    return plain(cos_i, eta1, eta2, polarization)


def _model(cos_i, eta1, eta2, polarization):
    """`_reflectance_fit`, whose derivative in `eta2` is in closed form and compiles to a loop of
    its own (`polarization`: a name, or the weights of s-polarized light, as in `_mix`).

    The solver linearizes the model at every step and needs the residuals and the Jacobian over all
    (curves x angles). Derived together, they share quotients, which XLA on the CPU writes to
    memory and reads back (the kernel's own derivative rule made five loops per step). Here the
    derivative comes from `_reflectance_d_eta2` (real `eta2`) or `_reflectance_complex_grad`
    (complex: `dR = Re(G d eta2)`), on inputs passed through an optimization barrier (`_own_loop`)
    so that no common subexpression ties it to the model's loop.
    """
    if isinstance(polarization, str):
        return _model_rule(cos_i, eta1, eta2, None, polarization)
    return _model_rule(cos_i, eta1, eta2, polarization, None)


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def _model_rule(cos_i, eta1, eta2, weight, name):
    return _reflectance_fit(cos_i, eta1, eta2, name if weight is None else weight)


@functools.partial(_model_rule.defjvp, symbolic_zeros=True)
def _model_jvp(name, primals, tangents):
    cos_i, eta1, eta2, weight = primals
    polarization = name if weight is None else weight
    out = _model_rule(cos_i, eta1, eta2, weight, name)
    dc, de1, de2, dw = tangents
    if any(type(t) not in (SymbolicZero, type(None)) for t in (dc, de1, dw)):
        raise NotImplementedError("the fits' model is differentiated in eta2 only (angles, eta1 and polarization are data)")
    if type(de2) is SymbolicZero:
        return out, jnp.zeros_like(out)
    copies = _own_loop(cos_i, eta1, eta2)
    if jnp.iscomplexobj(eta2):
        G = _reflectance_complex_grad(*copies, polarization)
        return out, jnp.real(G) * jnp.real(de2) - jnp.imag(G) * jnp.imag(de2)
    return out, _reflectance_d_eta2(*copies, polarization) * de2


def synthetic_reflectance(key: PRNGKeyArray | None, eta2: Inexact[ArrayLike, "*batch"], theta: Float[ArrayLike, " m"], *,
                          eta1: float = 1.0, polarization: str = "unpolarized",
                          noise: float = 0.0) -> Float[Array, "*batch m"]:
    r"""Reflectance curves `R(theta)` for index `eta2`, with optional Gaussian noise.

    **Arguments:**

    - `key`: a `jax.random` key (used only when `noise > 0`).
    - `eta2`: index of the reflecting medium, real or complex (`n + ik`), shape `(...)`.
    - `theta`: angles of incidence in radians, shape `(m,)`.
    - `eta1`: index of the incident medium (keyword).
    - `polarization`: `"unpolarized"`, `"s"` or `"p"`.
    - `noise`: standard deviation of additive Gaussian noise (not clipped to [0, 1], so the noise
      stays unbiased).

    **Returns:** `R` of shape `(..., m)`.
    """
    if polarization not in POLARIZATIONS:
        raise ValueError(f"polarization must be one of {POLARIZATIONS}, got {polarization!r}")
    theta = jnp.asarray(V.as_real(theta, "theta"))
    eta2 = jnp.asarray(eta2)
    R = _reflectance(jnp.cos(theta), eta1, eta2[..., None], polarization)
    if noise:
        if key is None:
            raise ValueError("noise > 0 needs a PRNG key: synthetic_reflectance(jax.random.PRNGKey(0), ...)")
        R = R + noise * jax.random.normal(key, R.shape, R.dtype)
    return R
