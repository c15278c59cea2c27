r"""The dispersion models of ellipsometry software beyond `_dispersion`'s: the Gaussian oscillator,
Cody-Lorentz, UV and IR poles, Sellmeier with an IR pole, a general oscillator sum (GenOsc) and
the Kramers-Kronig-consistent cubic B-spline.

Every model gives the dielectric function `eps = eps1 + i eps2` of the photon energy `E` (eV,
`E = 1.2398419843320026 / wavelength_um`) for the time dependence `exp(-i omega t)`: absorption
is `eps2 >= 0` and `k >= 0`, and an oscillator of positive strength raises `eps1` below its
energy and lowers it above. Each `eps1` is the Kramers-Kronig transform of its `eps2`::

    eps1(E) = eps_inf + (2 / pi) P int_0^inf xi eps2(xi) / (xi^2 - E^2) dxi

in closed form (Gaussian: Dawson's function; B-spline: logarithms; poles: lossless), or by a
fixed quadrature (Cody-Lorentz), as the test suite checks against the integral done numerically
at 30 digits.
"""

from __future__ import annotations

import dataclasses
import math
from fractions import Fraction
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._dispersion import Dispersion, DrudeLorentz, Free, TaucLorentz, _as_params, _energy, _from_eps, jax_complex

# FWHM = 2 sqrt(ln 2) s for exp(-((E - E0) / s)^2)
_FWHM_PER_S = 2 * math.sqrt(math.log(2))


class _FromEps(Dispersion):
    """A model defined by its dielectric function: `N = sqrt(eps)`, the principal root."""

    def nk(self, wavelength_um):
        return _from_eps(self.eps(wavelength_um))


@dataclasses.dataclass(frozen=True)
class Gaussian(_FromEps):
    r"""A Gaussian oscillator (energies in eV), the broadened absorption band of GenOsc:

    `eps2(E) = A [exp(-((E - E0) / s)^2) - exp(-((E + E0) / s)^2)]`, `s = Br / (2 sqrt(ln 2))`;
    `eps1(E) = eps_inf + (2 A / sqrt(pi)) [D((E + E0) / s) - D((E - E0) / s)]`,

    `D` Dawson's function (`jax.scipy.special.dawsn`): the Kramers-Kronig transform of `eps2` in
    closed form (the second Gaussian makes `eps2` odd in `E`, as the transform requires).

    Parameters: `A` (amplitude, the peak `eps2`), `E0` (centre, eV), `Br` (full width at half
    maximum, eV), `eps_inf`.

    References: H. Fujiwara and R. W. Collins (eds.), *Spectroscopic Ellipsometry for
    Photovoltaics*, vol. 1 (Springer, 2018), p. 137; the `Gaussian` oscillator of Woollam's GenOsc.
    """

    A: Any = 1.0
    E0: Any = 4.0
    Br: Any = 1.0
    eps_inf: Any = 1.0
    _params = ("A", "E0", "Br", "eps_inf")

    def eps(self, wavelength_um):
        from jax.scipy.special import dawsn

        E = _energy(wavelength_um)
        s = self.Br / _FWHM_PER_S
        lo, hi = (E - self.E0) / s, (E + self.E0) / s
        eps2 = self.A * (jnp.exp(-lo * lo) - jnp.exp(-hi * hi))
        eps1 = self.eps_inf + 2 * self.A / math.sqrt(math.pi) * (dawsn(hi) - dawsn(lo))
        return jax_complex(eps1, eps2)


@dataclasses.dataclass(frozen=True)
class Poles(_FromEps):
    r"""Lossless poles outside the measured range (energies in eV), the `Permanent Poles` of
    ellipsometry software:

    `eps(E) = eps_inf + uv_amp / (uv_energy^2 - E^2) - ir_amp / E^2`.

    The UV pole is a Lorentz oscillator without damping at `uv_energy` (strength `f E0^2 =
    uv_amp`, eV^2); the IR pole one at zero energy (a Drude term without damping, `ir_amp = wp^2`,
    eV^2). Positive amplitudes are oscillators of positive strength: the UV pole raises `eps1`
    below its energy, the IR pole lowers it. (Some open implementations write `+ A_ir / E^2`;
    here the sign is that of the physical limit, tested against Lorentz and Drude terms of
    vanishing damping.) `eps2 = 0`: where `eps1 < 0` the principal root gives `n = 0`, `k > 0`.
    """

    uv_amp: Any = 0.0
    uv_energy: Any = 11.0
    ir_amp: Any = 0.0
    eps_inf: Any = 1.0
    _params = ("uv_amp", "uv_energy", "ir_amp", "eps_inf")

    def eps(self, wavelength_um):
        E = _energy(wavelength_um)
        E2 = E * E
        return jax_complex(self.eps_inf + self.uv_amp / (self.uv_energy * self.uv_energy - E2) - self.ir_amp / E2, 0.0)


@dataclasses.dataclass(frozen=True)
class SellmeierIR(Dispersion):
    r"""Sellmeier's law with an infrared pole, in the form of Woollam's CompleteEASE (wavelengths in
    micrometres):

    `n^2 = eps_inf + A lambda^2 / (lambda^2 - En^2) - P lambda^2`

    `A` the strength of a UV resonance at wavelength `En` (um), `P` (um^-2) that of an infrared
    pole at zero energy. It is `Poles(uv_amp=A (hc/En)^2, uv_energy=hc/En, ir_amp=P (hc)^2)` written
    in wavelength. Transparent where `n^2 > 0`.

    Reference: J. A. Woollam Co., CompleteEASE Data Analysis Manual (2011), sec. 9 (Sellmeier).
    """

    eps_inf: Any = 1.0
    A: Any = 1.0
    En: Any = 0.1
    P: Any = 0.0
    _params = ("eps_inf", "A", "En", "P")

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        l2 = lam * lam
        return _from_eps(jax_complex(self.eps_inf + self.A * l2 / (l2 - self.En * self.En) - self.P * l2, 0.0))


# ---- Cody-Lorentz: eps1 by a fixed quadrature of the Kramers-Kronig integral -------------------

# Gauss-Legendre nodes and weights on (-1, 1), per segment between the breakpoints of the integrand
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(32)


def _kk_eps1(eps2, E, breaks):
    """`(2 / pi) P int_0^inf xi eps2(xi) / (xi^2 - E^2) dxi` for the energies `E`, with `eps2` a
    function continuous on `(0, inf)`, smooth between the `breaks` (scalars or arrays broadcastable
    to `E`: its kinks and the scales of its features).

    The principal value is taken by subtracting `E eps2(E)` from the numerator (`P int_0^inf
    dxi / (xi^2 - E^2) = 0`), which leaves an integrand that is smooth at `xi = E`; `E` is also a
    breakpoint, so no node lies on it. Each interval between sorted breakpoints gets 32
    Gauss-Legendre nodes, and `(T, inf)` (with `T` twice the largest breakpoint) the same nodes
    in `T / xi`."""
    shape, dtype = jnp.shape(E), jnp.result_type(E)
    e = jnp.reshape(E, (-1,))
    cols = [jnp.zeros_like(e), e] + [jnp.reshape(jnp.broadcast_to(jnp.abs(jnp.asarray(x, dtype)), shape), (-1,))
                                     for x in breaks]
    b = jnp.sort(jnp.stack(cols, axis=-1), axis=-1)  # (n, K + 1)
    T = 2 * b[:, -1]
    b = jnp.concatenate([b, T[:, None]], axis=-1)
    lo, hi = b[:, :-1], b[:, 1:]
    x = jnp.asarray(_GL_NODES, dtype)[None, None, :]
    w = jnp.asarray(_GL_WEIGHTS, dtype)[None, None, :]
    # x eps2(x) at E and its slope there: the integrand's limit at xi = E, where a node lies only
    # in an interval of zero width (a breakpoint at E): no weight, but its end's derivative has one
    f_E, df_E = jax.jvp(lambda x: x * eps2(x), (e,), (jnp.ones_like(e),))

    def g(xi):
        ee = e[:, None, None]
        at_E = xi == ee
        xs = jnp.where(at_E, ee + 1, xi)
        return jnp.where(at_E, (df_E / (2 * e))[:, None, None],
                         (xs * eps2(xs) - f_E[:, None, None]) / ((xs - ee) * (xs + ee)))

    half = ((hi - lo) / 2)[:, :, None]
    xi = ((lo + hi) / 2)[:, :, None] + half * x
    inner = jnp.sum(g(xi) * w * half, axis=(1, 2))
    t = (x + 1) / 2  # (0, 1): xi = T / t
    Tb = T[:, None, None]
    tail = jnp.sum(g(Tb / t) * (Tb / 2) / (t * t) * w, axis=(1, 2))
    return jnp.reshape(2 / math.pi * (inner + tail), shape)


@dataclasses.dataclass(frozen=True)
class CodyLorentz(_FromEps):
    r"""The Cody-Lorentz model of amorphous semiconductors (Ferlauto et al.), energies in eV:

    `eps2(E) = G(E) L(E)` for `E > Et`, `(E1 / E) exp((E - Et) / Eu)` for `0 < E <= Et` (an Urbach
    tail), with the band-edge function `G(E) = (E - Eg)^2 / ((E - Eg)^2 + Ep^2)`, the Lorentz
    oscillator `L(E) = A E0 C E / ((E^2 - E0^2)^2 + C^2 E^2)`, and `E1 = Et G(Et) L(Et)` (so `eps2`
    is continuous at `Et`). `Et = 0` leaves out the tail. `eps1 = eps_inf + ` the Kramers-Kronig
    integral of `eps2`, by Gauss-Legendre quadrature between the breakpoints `Eg`, `Et`, `Eg + Ep`,
    `E0 - C`, `E0`, `E0 + C` and `E` (32 nodes each, relative error below 1e-10 for the usual
    parameters; tested against the integral at 30 digits).

    Parameters: `A` (amplitude, eV), `E0` (peak, eV), `C` (broadening, eV), `Eg` (gap, eV), `Ep`
    (the band edge's width, eV), `Et` (start of the band-to-band transitions, eV), `Eu` (Urbach
    energy, eV), `eps_inf`.

    Reference: A. S. Ferlauto et al., J. Appl. Phys. 92, 2424 (2002).
    """

    A: Any = 50.0
    E0: Any = 3.6
    C: Any = 2.5
    Eg: Any = 1.6
    Ep: Any = 1.0
    Et: Any = 1.7
    Eu: Any = 0.05
    eps_inf: Any = 1.0
    _params = ("A", "E0", "C", "Eg", "Ep", "Et", "Eu", "eps_inf")

    def eps2(self, E):
        """`eps2` at the photon energies `E` (eV)."""
        A, E0, C, Eg, Ep, Et, Eu = self.A, self.E0, self.C, self.Eg, self.Ep, self.Et, self.Eu

        def GL(x):
            u = (x - Eg) ** 2
            return u / (u + Ep * Ep) * A * E0 * C * x / ((x * x - E0 * E0) ** 2 + C * C * x * x)

        above = E > Et
        x_tail = jnp.where(above | (E <= 0), jnp.ones_like(E), E)  # no overflow or 1/0 off its branch
        tail = Et * GL(Et) / x_tail * jnp.exp((jnp.minimum(x_tail, Et) - Et) / Eu)
        return jnp.where(above, GL(jnp.where(above, E, Et + 1.0)), jnp.where(E > 0, tail, 0))

    def eps(self, wavelength_um):
        E = _energy(wavelength_um)
        breaks = (self.Eg, self.Et, self.Eg + self.Ep, self.E0 - self.C, self.E0, self.E0 + self.C)
        eps1 = self.eps_inf + _kk_eps1(self.eps2, E, breaks)
        return jax_complex(eps1, self.eps2(E))


# ---- the Kramers-Kronig-consistent B-spline ----------------------------------------------------


def _bspline_moments(count):
    """Even central moments `M_0, M_2, ...` of the cardinal cubic B-spline (unit knot spacing,
    integral 1): the moments of a sum of four uniform variables on (-1/2, 1/2), from the power
    series of `(sinh(t/2) / (t/2))^4` in exact fractions."""
    K = 2 * count
    one = [Fraction(1, math.factorial(2 * k + 1) * 4**k) if n == 2 * k else Fraction(0)
           for n in range(K) for k in [n // 2]]
    p = [Fraction(1)] + [Fraction(0)] * (K - 1)
    for _ in range(4):
        p = [sum(p[i] * one[n - i] for i in range(n + 1)) for n in range(K)]
    return np.asarray([float(p[2 * k] * math.factorial(2 * k)) for k in range(count)])


# `I(s) = -sum_k M_2k / s^(2k+1)` beyond |s| = 4, where each term is at most 4^-k of the first
_FAR, _FAR_TERMS = 4.0, 30
_MOMENTS = _bspline_moments(_FAR_TERMS)
_WEIGHTS = (1.0, -4.0, 6.0, -4.0, 1.0)


def _cubic_bspline(s):
    """The cardinal cubic B-spline at `s` (knots at -2 ... 2, peak 2/3 at 0, integral 1)."""
    a = jnp.abs(s)
    return jnp.where(a < 1, 2 / 3 - a * a + a * a * a / 2, jnp.where(a < 2, (2 - jnp.minimum(a, 2)) ** 3 / 6, 0))


def _cubic_bspline_hilbert(s):
    """`P int B(t) / (t - s) dt` for the cardinal cubic B-spline `B`: `(1/6) sum_m w_m b_m^3
    log|b_m|` with `b_m = m - 2 - s` and `w = (1, -4, 6, -4, 1)` (the fourth difference that
    builds `B` from truncated cubes; the polynomial parts of their transforms cancel), finite with
    finite first and second derivatives at the knots. Far from the support (`|s| > 4`), where
    the sum cancels to `-1/s`, the moment series is used instead."""
    far = jnp.abs(s) > _FAR
    s_near = jnp.where(far, 0.0, s)
    total = 0.0
    for m, w in enumerate(_WEIGHTS):
        b = m - 2 - s_near
        zero = b == 0
        b_safe = jnp.where(zero, 1.0, b)
        total = total + w * jnp.where(zero, 0.0, b_safe * b_safe * b_safe * jnp.log(jnp.abs(b_safe)))
    s_far = jnp.where(far, s, _FAR + 1)
    inv2 = 1 / (s_far * s_far)
    series = 0.0
    for Mk in _MOMENTS[::-1]:  # Horner in 1/s^2
        series = series * inv2 + float(Mk)
    return jnp.where(far, -series / s_far, total / 6)


@dataclasses.dataclass(frozen=True)
class BSpline(_FromEps):
    r"""The Kramers-Kronig-consistent B-spline dielectric function (Johs and Hale), energies in eV:

    `eps2(E) = sum_i c_i B((E - E_i) / h)`,
    `eps1(E) = eps_inf + (1/pi) sum_i c_i [H((E - E_i) / h) + H((-E - E_i) / h)]`,

    with `B` the cardinal cubic B-spline (nodes `E_i = start + i h`, `h = spacing`; `B(0) = 2/3`,
    and the basis functions sum to 1, so equal coefficients give a flat `eps2` of that value
    between the outer nodes) and `H(s) = P int B(t) / (t - s) dt`, in closed form `(1/6) sum_m w_m
    (m - 2 - s)^3 log|m - 2 - s|` (`w = 1, -4, 6, -4, 1`; `m = 0 ... 4`): the analytic
    Kramers-Kronig transform of each basis function, with `eps2` extended to negative energies as
    an odd function, as the transform assumes. Each basis function has support `[E_i - 2h, E_i +
    2h]`, which must lie at `E >= 0` (`start >= 2 spacing`). `eps2 >= 0` (absorption) needs
    non-negative coefficients, which the model does not impose.

    Parameters: `coefficients` (a tuple, each a number or `Free`), `start` (first node, eV),
    `spacing` (node spacing, eV), `eps_inf`. The spacing sets the resolution: 0.05-0.3 eV is
    usual.

    Reference: B. Johs and J. S. Hale, Phys. Status Solidi A 205, 715 (2008).
    """

    coefficients: Any = (0.0,)
    start: Any = 1.0
    spacing: Any = 0.25
    eps_inf: Any = 1.0
    _params = ("coefficients", "start", "spacing", "eps_inf")

    def __post_init__(self):
        c = _as_params(self.coefficients)
        if not c:
            raise ValueError("BSpline: give at least one coefficient")
        object.__setattr__(self, "coefficients", c)
        # (checked on numbers and `Free` starts; a fit substitutes traced values, checked before)
        start, h = (v.value if isinstance(v, Free) else v for v in (self.start, self.spacing))
        lower = self.spacing.lower if isinstance(self.spacing, Free) else h
        if isinstance(h, (int, float)) and not (h > 0 and lower > 0):
            raise ValueError(f"BSpline: spacing must be > 0 (a Free spacing's lower bound too), got {self.spacing!r}")
        if isinstance(h, (int, float)) and isinstance(start, (int, float)) and start < 2 * h:
            raise ValueError(f"BSpline: the first basis function must lie at E >= 0: start ({start}) >= 2 spacing ({2 * h})")

    def eps(self, wavelength_um):
        E = _energy(wavelength_um)
        h = self.spacing
        eps1 = jnp.zeros_like(E) + self.eps_inf
        eps2 = jnp.zeros_like(E)
        for i, c in enumerate(self.coefficients):
            Ei = self.start + i * h
            s = (E - Ei) / h
            eps2 = eps2 + c * _cubic_bspline(s)
            # P int_0^inf xi B(xi)/(xi^2 - E^2) * 2 = P int B [1/(xi - E) + 1/(xi + E)]
            eps1 = eps1 + c / math.pi * (_cubic_bspline_hilbert(s) + _cubic_bspline_hilbert((-E - Ei) / h))
        return jax_complex(eps1, eps2)


# ---- the general oscillator sum ---------------------------------------------------------------

#: the models a `GenOsc` sums (each contributes its `eps` less its own `eps_inf`)
OSCILLATORS: tuple[type, ...] = (Gaussian, TaucLorentz, CodyLorentz, DrudeLorentz, Poles, BSpline)


@dataclasses.dataclass(frozen=True)
class GenOsc(_FromEps):
    r"""A general oscillator sum, like Woollam's GenOsc: `eps(E) = eps_inf + sum_j (eps_j(E) -
    eps_inf_j)` over `oscillators`, each a `Gaussian`, `TaucLorentz`, `CodyLorentz`,
    `DrudeLorentz` (`Drude`, `Lorentz`), `Poles` or `BSpline` with its own parameters (fixed or
    `Free`, named `oscillators[j].A` in a fit); their own `eps_inf` does not count (it must not be
    `Free`). Every term is Kramers-Kronig consistent, and so is the sum.
    """

    eps_inf: Any = 1.0
    oscillators: Any = ()
    _params = ("eps_inf", "oscillators")

    def __post_init__(self):
        osc = tuple(self.oscillators)
        for j, o in enumerate(osc):
            if not isinstance(o, OSCILLATORS):
                raise ValueError(f"GenOsc: oscillators[{j}] is {type(o).__name__}; an oscillator is one of "
                                 f"{', '.join(sorted(k.__name__ for k in OSCILLATORS))}")
            if isinstance(o.eps_inf, Free):
                raise ValueError(f"GenOsc: oscillators[{j}].eps_inf is Free; only the sum's eps_inf counts")
        object.__setattr__(self, "oscillators", osc)

    def eps(self, wavelength_um):
        E = _energy(wavelength_um)
        out = jax_complex(jnp.zeros_like(E) + self.eps_inf, 0.0)
        for o in self.oscillators:
            out = out + (o.eps(wavelength_um) - o.eps_inf)
        return out

