"""Design targets and the merit function.

A `Target` asks for one quantity of the coating (reflectance, transmittance, absorptance, the
phase of an amplitude, group delay, group-delay dispersion, ellipsometric psi or delta) at a set
of wavelengths, at one or more angles of incidence and a polarization, with a tolerance and a
weight; `kind="="` asks for the value, `"<="` and `">="` for a bound, which counts only where it
is violated.

The merit is OptiLayer's: the root mean square of the tolerance-scaled deviations over all
target points, each weighted by its target's weight,

    MF^2 = sum_j w_j ((S_j - T_j) / tol_j)^2 / sum_j w_j,

where for a one-sided target the deviation is 0 on the allowed side. A design that meets every
target to within its tolerance has `MF <= 1`. Phases and delta deviate by the difference of the
angles wrapped into `(-180, 180]` degrees.

Conventions: time dependence `exp(-i omega t)` and amplitudes as `jaxoptics.stack` (tmm's), so
the phase of `r` grows with the optical path: group delay `GD = d(arg r)/d(omega)` in
femtoseconds and `GDD = d(GD)/d(omega)` in fs^2 are the physical delay and its dispersion (the
same numbers in the `exp(+i omega t)` convention, whose phases have the opposite sign), both by
automatic differentiation along the angular frequency, material dispersion included. `psi` and
`delta` are the instrument's `Psi` and `Delta` (degrees, `rho = r_p / r_s = tan(Psi) exp(i Delta)`
with `N = n - ik`), as `Spectra` and `fit_stack` use them.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._films._sample import model_quantities

# speed of light in nm per fs
C_NM_FS = 299.792458

COLOR = tuple(f"{side}_{c}" for side in "RT" for c in ("x", "y", "L*", "a*", "b*"))
QUANTITIES = ("R", "T", "A", "phase_r", "phase_t", "GD_r", "GD_t", "GDD_r", "GDD_t", "psi", "delta") + COLOR
# a tolerance per quantity where none is given: 1 % in R, T, A; 1 degree in angles; 1 fs; 10 fs^2;
# 0.005 in chromaticity; 1 in L*, a*, b*
DEFAULT_TOLERANCE = {"R": 0.01, "T": 0.01, "A": 0.01, "phase_r": 1.0, "phase_t": 1.0, "GD_r": 1.0, "GD_t": 1.0,
                     "GDD_r": 10.0, "GDD_t": 10.0, "psi": 1.0, "delta": 1.0,
                     **{q: 0.005 if q[2:] in ("x", "y") else 1.0 for q in COLOR}}
OBSERVER = "CIE 1931 2 Degree Standard Observer"
_ANGULAR = ("phase_r", "phase_t", "delta")
_DISPERSIVE = ("GD_r", "GD_t", "GDD_r", "GDD_t")
_NO_POLARIZATION = ("psi", "delta")


def _vector(x, what):
    a = np.asarray(x, dtype=float)
    if a.ndim > 1:
        raise ValueError(f"Target {what}: a number or a one-dimensional sequence, got shape {a.shape}")
    return a.reshape(-1)


@dataclasses.dataclass(frozen=True, eq=False)
class Target:
    """What a design should do: `quantity` (one of `QUANTITIES`: `"R"`, `"T"`, `"A"` = 1 - R - T,
    `"phase_r"`, `"phase_t"` in degrees, `"GD_r"`, `"GD_t"` in fs, `"GDD_r"`, `"GDD_t"` in fs^2,
    `"psi"`, `"delta"` in degrees) at `wavelength_nm` (a number or a sequence), equal to `value`
    (`kind="="`), at most (`"<="`) or at least (`">="`) it, within `tolerance` (default
    `DEFAULT_TOLERANCE[quantity]`), with `weight`.

    `value`, `tolerance` and `angle_deg` (the angle of incidence in the ambient, default 0) are
    numbers or sequences as long as `wavelength_nm`. `polarization` is `"s"`, `"p"` or `"avg"`
    (the mean of the two: for R, T and A the unpolarized value; for GD and GDD the mean delay);
    a phase needs `"s"` or `"p"`; psi and delta ignore it.

    Colour (`"R_x"`, `"R_y"`, `"R_L*"`, `"R_a*"`, `"R_b*"` of the reflected light, `"T_..."` of
    the transmitted): `wavelength_nm` is the grid the colour is integrated over (evenly spaced,
    for example `np.arange(380, 781, 5)`), `value` one number; chromaticity `x, y` (CIE 1931) or
    CIELAB `L*, a*, b*` of the reflectance or transmittance spectrum under `illuminant` (a name
    colour-science knows: `"D65"`, `"A"`, `"D50"`, ...), CIE 1931 2-degree observer, the tables
    from colour-science (the `colour` extra: `pip install colour-science`), summed as CIE 15's
    integration (`colour.sd_to_XYZ(..., method="Integration")`)."""

    quantity: str
    wavelength_nm: Any
    value: Any
    angle_deg: Any = 0.0
    polarization: str = "avg"
    tolerance: Any = None
    weight: float = 1.0
    kind: str = "="
    illuminant: str = "D65"
    # (wavelength_nm, value, angle_deg, tolerance) as float arrays of one length (for a colour:
    # value and tolerance of length 1), set on creation
    _points: tuple = dataclasses.field(init=False, repr=False, default=())

    def __post_init__(self):
        if self.quantity not in QUANTITIES:
            raise ValueError(f"Target quantity {self.quantity!r} is not one of {', '.join(QUANTITIES)}")
        if self.kind not in ("=", "<=", ">="):
            raise ValueError(f"Target kind {self.kind!r}: '=', '<=' or '>='")
        if self.polarization not in ("s", "p", "avg"):
            raise ValueError(f"Target polarization {self.polarization!r}: 's', 'p' or 'avg'")
        if self.quantity in ("phase_r", "phase_t") and self.polarization == "avg":
            raise ValueError(f"Target {self.quantity}: a phase needs polarization 's' or 'p'")
        wl = _vector(self.wavelength_nm, "wavelength_nm")
        if wl.size == 0 or not np.all(np.isfinite(wl) & (wl > 0)):
            raise ValueError(f"Target {self.quantity}: wavelengths must be finite and > 0, got {wl}")
        tol = DEFAULT_TOLERANCE[self.quantity] if self.tolerance is None else self.tolerance
        color = self.quantity in COLOR
        if color:
            step = np.diff(wl)
            if wl.size < 3 or not np.allclose(step, step[0], rtol=1e-9, atol=0) or step[0] <= 0:
                raise ValueError(f"Target {self.quantity}: a colour is integrated over evenly spaced, increasing "
                                 f"wavelengths (at least 3), got {wl}")
        cols = {}
        for name, v in (("value", self.value), ("angle_deg", self.angle_deg), ("tolerance", tol)):
            a = _vector(v, name)
            if color and a.size != 1:
                raise ValueError(f"Target {self.quantity}: a colour target's {name} is one number, got {a.size}")
            if a.size not in (1, wl.size):
                raise ValueError(f"Target {self.quantity}: {name} has {a.size} values for {wl.size} wavelengths")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Target {self.quantity}: {name} must be finite, got {a}")
            cols[name] = a.copy() if color and name != "angle_deg" else np.broadcast_to(a, wl.shape).copy()
        if np.any(cols["tolerance"] <= 0):
            raise ValueError(f"Target {self.quantity}: tolerance must be > 0, got {cols['tolerance']}")
        if np.any((cols["angle_deg"] < 0) | (cols["angle_deg"] >= 90)):
            raise ValueError(f"Target {self.quantity}: angle_deg must lie in [0, 90), got {cols['angle_deg']}")
        w = self.weight
        if isinstance(w, bool) or not isinstance(w, (int, float, np.number)) or not (math.isfinite(w) and w > 0):
            raise ValueError(f"Target {self.quantity}: weight must be a number > 0, got {w!r}")
        object.__setattr__(self, "_points", (wl, cols["value"], cols["angle_deg"], cols["tolerance"]))

    @property
    def points(self) -> int:
        """The number of target values: one per wavelength, one for a colour."""
        return self._points[1].size


@dataclasses.dataclass(frozen=True)
class Layout:
    """The targets' points concatenated, in two groups: `plain` (evaluated from the stack) and
    `dispersive` (GD and GDD, evaluated with two derivatives along the frequency). Static: the
    quantity, polarization and kind of each target and where its points lie in its group."""

    entries: tuple  # (quantity, polarization, kind, dispersive, start, stop) per target (its wavelengths in its group)
    n_plain: int
    n_dispersive: int


def layout(targets) -> tuple[Layout, dict]:
    """The static `Layout` of `targets` and their arrays: `wl_plain`, `angle_plain`,
    `wl_disp`, `angle_disp` (nm, degrees) and, over all points in target order, `value`,
    `tolerance`, `sqrt_w` (the square root of each point's share of the total weight); for the
    i-th target, a colour, `color{i}`: the `(4, n)` weights of X, Y, Z and the white's (X, Y, Z)
    in its first three columns' sums (see `_color_weights`)."""
    targets = list(targets)
    if not targets:
        raise ValueError("design needs at least one Target")
    for i, t in enumerate(targets):
        if not isinstance(t, Target):
            raise ValueError(f"targets[{i}] must be a jaxoptics.Target, got {type(t).__name__}")
    entries: list = []
    groups: dict[bool, list] = {False: [], True: []}
    counts = {False: 0, True: 0}
    for t in targets:
        disp = t.quantity in _DISPERSIVE
        wl, _, ang, _ = t._points
        entries.append((t.quantity, t.polarization, t.kind, disp, counts[disp], counts[disp] + wl.size))
        counts[disp] += wl.size
        groups[disp].append((wl, ang))
    cat = lambda parts, i: np.concatenate([p[i] for p in parts]) if parts else np.zeros(0)
    colors = {f"color{i}": _color_weights(t._points[0], t.illuminant) for i, t in enumerate(targets) if t.quantity in COLOR}
    total_w = sum(t.weight * t.points for t in targets)
    arrays = {
        "wl_plain": cat(groups[False], 0), "angle_plain": cat(groups[False], 1),
        "wl_disp": cat(groups[True], 0), "angle_disp": cat(groups[True], 1),
        "value": np.concatenate([t._points[1] for t in targets]),
        "tolerance": np.concatenate([t._points[3] for t in targets]),
        "sqrt_w": np.concatenate([np.full(t.points, math.sqrt(t.weight / total_w)) for t in targets]),
        **colors,
    }
    return Layout(tuple(entries), counts[False], counts[True]), arrays


def _count(entry) -> int:
    """The number of values a target's entry gives: one per wavelength, one for a colour."""
    return 1 if entry[0] in COLOR else entry[5] - entry[4]


def spans(lay: Layout) -> list[tuple[int, int]]:
    """Where each target's values lie among all values (target order)."""
    out, k = [], 0
    for e in lay.entries:
        out.append((k, k + _count(e)))
        k += _count(e)
    return out


def _color_weights(wl, illuminant):
    """`(4, n)`: rows 0-2 the weights `k S(l) xbar(l) dl` (and ybar, zbar) that give X, Y, Z from
    a spectrum at `wl` (CIE 15 integration, `k` making Y = 100 for a perfect reflector); row 3
    holds the white point (Xn, Yn, Zn) in its first three entries."""
    try:
        with np.printoptions():  # colour-science sets NumPy's legacy printing on import: the user's options stay
            import colour
    except ImportError:
        raise ValueError("colour targets need colour-science (pip install colour-science, or jaxoptics[colour])") from None
    if illuminant not in colour.SDS_ILLUMINANTS:
        raise ValueError(f"unknown illuminant {illuminant!r}; colour-science knows {', '.join(list(colour.SDS_ILLUMINANTS)[:12])}, ...")
    cmfs = colour.MSDS_CMFS[OBSERVER]
    ill = colour.SDS_ILLUMINANTS[illuminant]
    lo, hi = max(cmfs.wavelengths[0], ill.wavelengths[0]), min(cmfs.wavelengths[-1], ill.wavelengths[-1])
    if wl[0] < lo or wl[-1] > hi:
        raise ValueError(f"a colour under {illuminant} is integrated within {lo:g}-{hi:g} nm, got {wl[0]:g}-{wl[-1]:g} nm")
    bar = np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, i]) for i in range(3)])
    S = np.interp(wl, ill.wavelengths, ill.values)
    dl = wl[1] - wl[0]
    W = bar * S * dl
    W = W * (100 / np.sum(W[1]))
    white = np.zeros(wl.size)
    white[:3] = W.sum(axis=1)
    return np.concatenate([W, white[None]])


def _lab_f(t):
    d = 6 / 29
    return jnp.where(t > d**3, jnp.cbrt(jnp.maximum(t, d**3)), t / (3 * d * d) + 4 / 29)


def _color(quantity, spectrum, W):
    """A colour quantity (`COLOR`) of `spectrum` with `_color_weights` `W`."""
    X, Y, Z = (jnp.sum(W[i] * spectrum) for i in range(3))
    c = quantity[2:]
    if c in ("x", "y"):
        return (X if c == "x" else Y) / (X + Y + Z)
    fx, fy, fz = _lab_f(X / W[3, 0]), _lab_f(Y / W[3, 1]), _lab_f(Z / W[3, 2])
    return {"L*": 116 * fy - 16, "a*": 500 * (fx - fy), "b*": 200 * (fy - fz)}[c]


def _pick(pol, s, p):
    return s if pol == "s" else p if pol == "p" else (s + p) / 2


def _phase_deg(z):
    return jnp.degrees(jnp.angle(z))


def quantities(lay: Layout, stack_fn, arrays) -> jax.Array:
    """Every target point's computed value, in target order. `stack_fn(wavelength_nm, cos_i)`
    returns the `StackResult` of the design at those points (a function of the wavelength, so
    that GD and GDD differentiate it along the frequency)."""
    dt = arrays["wl_plain"].dtype if lay.n_plain else arrays["wl_disp"].dtype
    plain = disp = None
    if lay.n_plain:
        plain = stack_fn(arrays["wl_plain"], jnp.cos(jnp.radians(arrays["angle_plain"])))
    if lay.n_dispersive:
        wl, cos_i = arrays["wl_disp"], jnp.cos(jnp.radians(arrays["angle_disp"]))

        def amplitudes(omega):  # omega in rad/fs
            res = stack_fn(2 * jnp.pi * C_NM_FS / omega, cos_i)
            return jnp.stack([res.r_s, res.r_p, res.t_s, res.t_p])

        omega = 2 * jnp.pi * C_NM_FS / wl
        one = jnp.ones_like(omega)
        first = lambda w: jax.jvp(amplitudes, (w,), (one,))
        (a, a1), (_, a2) = jax.jvp(first, (omega,), (one,))
        q1 = a1 / a
        gd = jnp.imag(q1)  # d arg(a) / d omega
        gdd = jnp.imag(a2 / a - q1 * q1)  # its derivative
        disp = (gd, gdd)
    out = []
    for i, (quantity, pol, _, is_disp, start, stop) in enumerate(lay.entries):
        if is_disp:
            gd, gdd = disp  # type: ignore[misc]
            v = gd if quantity.startswith("GD_") else gdd
            k = 0 if quantity.endswith("_r") else 2
            out.append(_pick(pol, v[k, start:stop], v[k + 1, start:stop]))
            continue
        res = jax.tree.map(lambda x: x[start:stop], plain)
        if quantity in COLOR:
            spec = _pick(pol, res.R_s, res.R_p) if quantity[0] == "R" else _pick(pol, res.T_s, res.T_p)
            out.append(_color(quantity, spec, arrays[f"color{i}"])[None])
            continue
        if quantity == "R":
            v = _pick(pol, res.R_s, res.R_p)
        elif quantity == "T":
            v = _pick(pol, res.T_s, res.T_p)
        elif quantity == "A":
            v = 1 - _pick(pol, res.R_s + res.T_s, res.R_p + res.T_p)
        elif quantity == "phase_r":
            v = _phase_deg(res.r_s if pol == "s" else res.r_p)
        elif quantity == "phase_t":
            v = _phase_deg(res.t_s if pol == "s" else res.t_p)
        else:
            v = model_quantities(res, ("psi_deg" if quantity == "psi" else "delta_deg",))[..., 0, :]
        out.append(v)
    return jnp.concatenate(out).astype(dt)


def residuals(lay: Layout, computed, arrays):
    """The tolerance-scaled, weighted deviations whose sum of squares is `MF^2` (module docstring)."""
    dev = computed - arrays["value"]
    out, k = [], 0
    for e in lay.entries:
        quantity, kind = e[0], e[2]
        d = dev[k:k + _count(e)]
        k += _count(e)
        if quantity in _ANGULAR:
            d = d - 360 * jnp.round(d / 360)
        if kind == "<=":
            d = jnp.maximum(d, 0)
        elif kind == ">=":
            d = jnp.minimum(d, 0)
        out.append(d)
    return jnp.concatenate(out) / arrays["tolerance"] * arrays["sqrt_w"]

