"""Dispersion models of a layer's complex index `N = n + ik` (`k >= 0`), with free parameters.

Each model is a frozen dataclass whose numeric fields are either numbers (fixed) or `Free`
(fitted, with bounds). `model.nk(wavelength_um)` evaluates the index with JAX (differentiable
with respect to the wavelength and to every parameter); `free_parameters(model)` lists the
`Free` fields and `substitute(model, values)` puts values (JAX arrays, tracers) in their place, so
a fit traces the model once with its free parameters as inputs.

Units: wavelengths in micrometres (the catalogues' unit); photon energies in electronvolts
(`E = 1.2398419843320026 / wavelength_um`) for the oscillator models (Tauc-Lorentz, Drude,
Lorentz), whose published forms are written in energy. Sign convention: `exp(-i omega t)`, so
absorption is `Im(eps) >= 0` and `k >= 0` (tmm, refractiveindex.info); `N = sqrt(eps)` is the
principal root.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _validate as V

# h c / e in eV um (CODATA 2018, exact)
HC_EV_UM = 1.2398419843320026


@dataclasses.dataclass(frozen=True)
class Free:
    """A fitted parameter: its starting `value` and `bounds` (`lower <= value <= upper`;
    infinite bounds allowed). A number in the same place is held fixed."""

    value: float
    lower: float = -math.inf
    upper: float = math.inf

    def __post_init__(self):
        for name in ("value", "lower", "upper"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise ValueError(f"Free.{name} must be a real number, got {v!r}")
        if math.isnan(self.value) or not math.isfinite(self.value):
            raise ValueError(f"Free.value must be finite, got {self.value}")
        if not self.lower < self.upper:
            raise ValueError(f"Free bounds must satisfy lower < upper, got ({self.lower}, {self.upper})")
        if not self.lower <= self.value <= self.upper:
            raise ValueError(f"Free start {self.value} lies outside its bounds ({self.lower}, {self.upper})")


class Dispersion:
    """Base of the dispersion models. Subclasses are frozen dataclasses; `_params` names the
    fields that hold parameters (numbers, `Free`, or tuples of them)."""

    _params: tuple[str, ...] = ()
    #: wavelength range (micrometres) where the model's data or coefficients are valid, or None
    range_um: tuple[float, float] | None = None

    def nk(self, wavelength_um):  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def _real(self) -> bool:
        """Whether `k` is zero at every wavelength for every value of the free parameters (the
        fit then differentiates the stack in the index's real part only: `_jacobian_plan`)."""
        return False

    def eps(self, wavelength_um):
        """The dielectric function `eps = N^2`."""
        N = self.nk(wavelength_um)
        return N * N


def _from_eps(eps):
    """`N = sqrt(eps)`, principal root: `Re N >= 0` and, for `Im eps >= 0`, `k >= 0`."""
    return jnp.sqrt(eps)


def _energy(wavelength_um):
    """The photon energy (eV) of a vacuum wavelength in micrometres."""
    return HC_EV_UM / jnp.asarray(wavelength_um)


def _fixed_zero(v):
    """Whether a parameter is held fixed at zero."""
    return isinstance(v, (int, float, np.integer, np.floating)) and v == 0


def _as_params(v):
    return tuple(v) if isinstance(v, (tuple, list)) else (v,)


@dataclasses.dataclass(frozen=True)
class Constant(Dispersion):
    """A constant index `n + ik` at every wavelength."""

    n: Any = 1.5
    k: Any = 0.0
    _params = ("n", "k")

    def _real(self):
        return _fixed_zero(self.k)

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        z = jnp.zeros_like(lam)
        return jax_complex(z + self.n, z + self.k)


def jax_complex(re, im):
    """`re + i im` in the complex dtype matching the real dtype of `re` (broadcast together)."""
    re = jnp.asarray(re)
    re, im = jnp.broadcast_arrays(re, jnp.asarray(im).astype(re.dtype))
    return jax.lax.complex(re, im)


@dataclasses.dataclass(frozen=True)
class Cauchy(Dispersion):
    r"""Cauchy's law with an Urbach absorption tail, the usual model of a transparent film:

    `n = A + B / lambda^2 + C / lambda^4` (lambda in micrometres, `B` in um^2, `C` in um^4),
    `k = k_amp * exp(k_exp * (E - E_band))` (E the photon energy in eV, `k_exp` in 1/eV).

    With `k_amp = 0` (the default) the film is transparent.
    Reference: Fujiwara, *Spectroscopic Ellipsometry* (2007), sec. 5.3.
    """

    A: Any = 1.45
    B: Any = 0.0
    C: Any = 0.0
    k_amp: Any = 0.0
    k_exp: Any = 1.5
    E_band: Any = 3.5
    _params = ("A", "B", "C", "k_amp", "k_exp", "E_band")

    def _real(self):
        return _fixed_zero(self.k_amp)

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        inv2 = 1 / (lam * lam)
        n = self.A + inv2 * (self.B + inv2 * self.C)
        k = self.k_amp * jnp.exp(self.k_exp * (_energy(lam) - self.E_band))
        return jax_complex(n, k)


@dataclasses.dataclass(frozen=True)
class Sellmeier(Dispersion):
    r"""Sellmeier's law `n^2 = eps_inf + sum_i B_i lambda^2 / (lambda^2 - C_i)` (lambda in
    micrometres, `C_i` in um^2); `B` and `C` are tuples of equal length. Transparent (`k = 0`)
    where `n^2 > 0`; where `n^2 < 0` (inside an absorption band, outside the law's range) the
    principal root gives `n = 0` and `k > 0`. Reference: W. Sellmeier (1871)."""

    B: Any = (1.0,)
    C: Any = (0.01,)
    eps_inf: Any = 1.0
    _params = ("B", "C", "eps_inf")

    def __post_init__(self):
        if len(_as_params(self.B)) != len(_as_params(self.C)):
            raise ValueError(f"Sellmeier: B and C must have equal lengths, got {self.B} and {self.C}")

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        l2 = lam * lam
        n2 = self.eps_inf + sum(b * l2 / (l2 - c) for b, c in zip(_as_params(self.B), _as_params(self.C)))
        return _from_eps(jax_complex(n2, 0.0))


@dataclasses.dataclass(frozen=True)
class TaucLorentz(Dispersion):
    r"""The Tauc-Lorentz model of an amorphous semiconductor or dielectric (Jellison and Modine),
    energies in eV:

    `eps2(E) = A E0 C (E - Eg)^2 / ((E^2 - E0^2)^2 + C^2 E^2) / E` for `E > Eg`, 0 below;
    `eps1(E) = eps_inf + (2/pi) P int_Eg^inf xi eps2(xi) / (xi^2 - E^2) dxi`, the Kramers-Kronig
    integral in closed form (Jellison and Modine's eq. with the erratum's corrections). The two
    logarithms of `|E - Eg|` are combined into `(E - Eg)^2 log|E - Eg|`, which is finite, with a
    finite derivative, at `E = Eg`.

    Parameters: `A` (amplitude, eV), `E0` (peak transition energy, eV), `C` (broadening, eV,
    `C < 2 E0`), `Eg` (optical gap, eV), `eps_inf`.

    References: G. E. Jellison Jr. and F. A. Modine, Appl. Phys. Lett. 69, 371 (1996);
    erratum Appl. Phys. Lett. 69, 2137 (1996).
    """

    A: Any = 100.0
    E0: Any = 4.0
    C: Any = 1.0
    Eg: Any = 2.0
    eps_inf: Any = 1.0
    _params = ("A", "E0", "C", "Eg", "eps_inf")

    def eps(self, wavelength_um):
        E = _energy(jnp.asarray(wavelength_um))
        A, E0, C, Eg = self.A, self.E0, self.C, self.Eg
        E2, E02, Eg2, C2 = E * E, E0 * E0, Eg * Eg, C * C
        above = E > Eg
        eps2 = jnp.where(above, A * E0 * C * (E - Eg) ** 2 / ((E2 - E02) ** 2 + C2 * E2) / E, 0)
        alpha = jnp.sqrt(4 * E02 - C2)
        gamma2 = E02 - C2 / 2
        zeta4 = (E2 - gamma2) ** 2 + alpha * alpha * C2 / 4
        a_ln = (Eg2 - E02) * E2 + Eg2 * C2 - E02 * (E02 + 3 * Eg2)
        a_atan = (E2 - E02) * (E02 + Eg2) + Eg2 * C2
        pi = jnp.pi
        t1 = A * C * a_ln / (2 * pi * zeta4 * alpha * E0) * jnp.log((E02 + Eg2 + alpha * Eg) / (E02 + Eg2 - alpha * Eg))
        t2 = -A * a_atan / (pi * zeta4 * E0) * (pi - jnp.arctan((2 * Eg + alpha) / C) + jnp.arctan((alpha - 2 * Eg) / C))
        t3 = 2 * A * E0 / (pi * zeta4 * alpha) * Eg * (E2 - gamma2) * (pi + 2 * jnp.arctan(2 * (gamma2 - Eg2) / (alpha * C)))
        x = E - Eg
        x_safe = jnp.where(x == 0, 1, x)  # x^2 log|x| -> 0 at x = 0; keep the log's input finite there
        x2log = jnp.where(x == 0, 0, x_safe * x_safe * jnp.log(jnp.abs(x_safe)))
        t45 = A * E0 * C / (pi * zeta4 * E) * ((E + Eg) ** 2 * jnp.log(E + Eg) - x2log) \
            - A * E0 * C * Eg / (pi * zeta4) * jnp.log((E02 - Eg2) ** 2 + Eg2 * C2)
        eps1 = self.eps_inf + t1 + t2 + t3 + t45
        return jax_complex(eps1, eps2)

    def nk(self, wavelength_um):
        return _from_eps(self.eps(wavelength_um))


@dataclasses.dataclass(frozen=True)
class DrudeLorentz(Dispersion):
    r"""Free-carrier (Drude) and bound (Lorentz) oscillators, energies in eV:

    `eps(E) = eps_inf - sum_j wp_j^2 / (E^2 + i g_j E) + sum_m f_m E_m^2 / (E_m^2 - E^2 - i G_m E)`

    `drude` is a tuple of `(wp, g)` pairs (plasma energy and damping, eV); `lorentz` a tuple of
    `(f, E_m, G_m)` triples (dimensionless strength, resonance and width in eV). With
    `exp(-i omega t)` every term has `Im(eps) >= 0` for positive dampings.
    `Drude(...)` and `Lorentz(...)` build the one-kind cases.
    Reference: Rakic et al., Appl. Opt. 37, 5271 (1998) (the Lorentz-Drude model of metals).
    """

    eps_inf: Any = 1.0
    drude: Any = ()
    lorentz: Any = ()
    _params = ("eps_inf", "drude", "lorentz")

    def __post_init__(self):
        if any(len(_as_params(t)) != 2 for t in self.drude):
            raise ValueError(f"DrudeLorentz: each drude term is (wp, gamma), got {self.drude}")
        if any(len(_as_params(t)) != 3 for t in self.lorentz):
            raise ValueError(f"DrudeLorentz: each lorentz term is (f, E0, gamma), got {self.lorentz}")

    def eps(self, wavelength_um):
        E = _energy(jnp.asarray(wavelength_um))
        cdt = V.complex_dtype(E.dtype)
        c = lambda x: jnp.asarray(x, E.dtype).astype(cdt)
        E = E.astype(cdt)
        out = c(self.eps_inf) + jnp.zeros_like(E)
        for wp, g in self.drude:
            out = out - c(wp) * c(wp) / (E * E + 1j * c(g) * E)
        for f, E0, G in self.lorentz:
            out = out + c(f) * c(E0) * c(E0) / (c(E0) * c(E0) - E * E - 1j * c(G) * E)
        return out

    def nk(self, wavelength_um):
        return _from_eps(self.eps(wavelength_um))


def Drude(wp: float | Free, gamma: float | Free, *, eps_inf: float | Free = 1.0) -> DrudeLorentz:
    """A Drude metal: `eps = eps_inf - wp^2 / (E^2 + i gamma E)` (eV)."""
    return DrudeLorentz(eps_inf=eps_inf, drude=((wp, gamma),))


def Lorentz(oscillators: Sequence[Sequence[float | Free]], *, eps_inf: float | Free = 1.0) -> DrudeLorentz:
    """A sum of Lorentz oscillators `((f, E0, gamma), ...)` (eV) over `eps_inf`."""
    return DrudeLorentz(eps_inf=eps_inf, lorentz=tuple(tuple(t) for t in oscillators))


def _interp_or_nan(x, xp, fp):
    y = jnp.interp(x, xp, fp)
    return jnp.where((x >= xp[0]) & (x <= xp[-1]), y, jnp.nan)


class _ByContent:
    """Equality and hash by `_key()` (the tables' bytes): two loads of the same material are
    equal, so a compiled fit is reused for them."""

    def __eq__(self, other):
        return type(other) is type(self) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())


@dataclasses.dataclass(frozen=True, eq=False)
class Tabulated(_ByContent, Dispersion):
    """Measured `n` and `k` against wavelength, interpolated linearly in wavelength inside jit.

    `n_table` and `k_table` are `(wavelengths_um, values)` pairs of 1-D NumPy arrays (the two may
    have different wavelength grids; `k_table=None` is a transparent material). Outside the
    tabulated range the index is NaN: tabulated data are not extrapolated (`fit_stack` checks the
    range before it starts). `name` and `reference` describe the source.
    """

    n_table: Any = None
    k_table: Any = None
    name: str = ""
    reference: str = ""

    def __post_init__(self):
        for label, tab in (("n", self.n_table), ("k", self.k_table)):
            if tab is None:
                if label == "n":
                    raise ValueError("Tabulated needs an n table")
                continue
            w, v = (np.asarray(a, np.float64) for a in tab)
            if w.ndim != 1 or w.shape != v.shape or w.size < 2:
                raise ValueError(f"Tabulated {self.name!r}: the {label} table needs two 1-D arrays of equal length >= 2")
            if np.any(np.diff(w) <= 0):
                raise ValueError(f"Tabulated {self.name!r}: the {label} table's wavelengths must increase strictly")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"Tabulated {self.name!r}: the {label} table has non-finite values")
            object.__setattr__(self, f"{label}_table", (w, v))

    def _key(self):
        tabs = tuple(None if t is None else (t[0].tobytes(), t[1].tobytes()) for t in (self.n_table, self.k_table))
        return (self.name, tabs)

    @property
    def range_um(self):
        lo, hi = self.n_table[0][0], self.n_table[0][-1]
        if self.k_table is not None:
            lo, hi = max(lo, self.k_table[0][0]), min(hi, self.k_table[0][-1])
        return (float(lo), float(hi))

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        dt = lam.dtype
        n = _interp_or_nan(lam, jnp.asarray(self.n_table[0], dt), jnp.asarray(self.n_table[1], dt))
        k = (jnp.zeros_like(n) if self.k_table is None
             else _interp_or_nan(lam, jnp.asarray(self.k_table[0], dt), jnp.asarray(self.k_table[1], dt)))
        return jax_complex(n, k)


# ---- free parameters: listing and substitution ------------------------------------------------


def _walk(value, path):
    """Yield `(path, leaf)` for the numeric leaves of a parameter field (numbers, `Free`, tuples,
    and the parameters of a model held in it: an effective medium's constituents)."""
    if value is None:  # an optional field left out (a graded layer's `bottom` or `profile`)
        return
    if isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            yield from _walk(v, path + (i,))
    elif isinstance(value, Dispersion):
        for field in value._params:
            yield from _walk(getattr(value, field), path + (field,))
    else:
        yield path, value


def parameter_leaves(model: Dispersion):
    """`[(name, leaf)]` for every parameter of `model`, named like `B`, `lorentz[0][1]` or
    `host.A` (a parameter of a constituent model)."""
    out = []
    for field in model._params:
        for path, leaf in _walk(getattr(model, field), ()):
            out.append((field + "".join(f".{i}" if isinstance(i, str) else f"[{i}]" for i in path), leaf))
    return out


def _replace(value, it):
    if isinstance(value, (tuple, list)):
        return tuple(_replace(v, it) for v in value)
    if isinstance(value, Dispersion):
        return dataclasses.replace(value, **{f: _replace(getattr(value, f), it) for f in value._params})
    return next(it) if isinstance(value, Free) else value


def substitute(model: Dispersion, values) -> Dispersion:
    """`model` with its `Free` leaves replaced, in `parameter_leaves` order, by `values`."""
    it = iter(values)
    changes = {f: _replace(getattr(model, f), it) for f in model._params}
    return dataclasses.replace(model, **changes)  # type: ignore[type-var]  # every model is a dataclass
