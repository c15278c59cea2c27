"""A layered sample: ambient, films, substrate; any thickness or dispersion parameter fixed or
`Free`. `Sample.quantities` evaluates what an ellipsometer or spectrophotometer measures, with
the `stack` kernel, as a function of the free parameters (for fitting) or of the fixed ones.

Units: wavelengths and thicknesses in nanometres (the materials' models take micrometres; the
conversion is internal); angles of incidence in degrees in data, radians in `quantities`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._core._numerics import materialize_both
from ._dispersion import Constant, Dispersion, Free, parameter_leaves, substitute
from ._elementary import _atan2
from ._ema import EMA
from ._graded import Graded
from ._instrument import Instrument
from ._stack import stack


def _as_dispersion(m, what):
    if isinstance(m, Dispersion):
        return m
    if isinstance(m, (Free,)):
        return Constant(n=m, k=0.0)
    if isinstance(m, bool) or not isinstance(m, (int, float, complex, np.number)):
        raise ValueError(f"{what}: a material is a Dispersion model (e.g. Cauchy, material('Si')) or a number, got {m!r}")
    m = complex(m)
    if m.imag < 0:
        raise ValueError(f"{what}: index {m} has k < 0; jaxoptics writes N = n + ik with k >= 0 for absorption")
    return Constant(n=m.real, k=m.imag)


@dataclasses.dataclass(frozen=True)
class Layer:
    """A film: its `material` (a `Dispersion` or a number `n` or `n + ik`), its `thickness_nm`
    (a number or `Free`; bounds below 0 are raised to 0), whether it is `incoherent` (thick:
    intensities add), and an optional `name` used in parameter names (default `layer1`, ...)."""

    material: Any
    thickness_nm: Any
    incoherent: bool = False
    name: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "material", _as_dispersion(self.material, f"layer {self.name or ''}".strip()))
        t = self.thickness_nm
        if isinstance(t, Free):
            if t.value < 0:
                raise ValueError(f"layer {self.name or ''}: thickness start {t.value} nm is negative")
            if t.lower < 0:
                object.__setattr__(self, "thickness_nm", Free(t.value, 0.0, t.upper))
        elif isinstance(t, bool) or not isinstance(t, (int, float, np.number)) or not t >= 0 or not math.isfinite(t):
            raise ValueError(f"layer {self.name or ''}: thickness_nm must be a finite number >= 0 or Free, got {t!r}")
        if self.incoherent and isinstance(self.material, Graded):
            raise ValueError(f"layer {self.name or ''}: a graded layer (its slices are thin films) cannot be incoherent")


def _starts(layers) -> np.ndarray:
    """Where each layer starts among the stack's inner layers (a graded layer is its slices there),
    and, last, their number."""
    return np.cumsum([0] + [layer.material.slices if isinstance(layer.material, Graded) else 1 for layer in layers])


def _incoherent(layers) -> tuple:
    """The incoherent layers' positions among the stack's inner layers."""
    starts = _starts(layers)
    return tuple(int(starts[i]) for i, layer in enumerate(layers) if layer.incoherent)


@dataclasses.dataclass(frozen=True)
class ParameterInfo:
    """One parameter of a `Sample`: its `name`, start `value`, `free` or not, and `bounds`."""

    name: str
    value: float
    free: bool
    lower: float
    upper: float
    is_thickness: bool


@dataclasses.dataclass(frozen=True)
class Sample:
    """A layered sample: light comes from `ambient` (real index, default air = 1), crosses
    `layers` in order (top first), and leaves into `substrate`; `instrument` (an `Instrument`, or
    None for an ideal measurement) adds the measurement's non-idealities (angle offset, bandwidth,
    thickness non-uniformity, back-side reflections, ...).

    `parameters()` lists every parameter (fixed and free) in a stable order, named like
    `oxide.thickness_nm`, `oxide.A`, `substrate.n`, `instrument.angle_offset_deg`; `free_names()`
    the free ones, which a fit returns in that order.
    """

    layers: tuple
    substrate: Any
    ambient: Any = 1.0
    instrument: Any = None

    def __post_init__(self):
        if self.instrument is not None and not isinstance(self.instrument, Instrument):
            raise ValueError(f"instrument must be an Instrument, got {type(self.instrument).__name__}")
        layers = tuple(self.layers)
        names = []
        for i, layer in enumerate(layers):
            if not isinstance(layer, Layer):
                raise ValueError(f"layers[{i}] must be a Layer, got {type(layer).__name__}")
            nm = layer.name or f"layer{i + 1}"
            if nm in names or nm in ("ambient", "substrate"):
                raise ValueError(f"layer name {nm!r} is used twice or is reserved")
            names.append(nm)
        object.__setattr__(self, "layers", layers)
        object.__setattr__(self, "substrate", _as_dispersion(self.substrate, "substrate"))
        amb = _as_dispersion(self.ambient, "ambient")
        if not isinstance(amb, Constant) or amb.k != 0:
            raise ValueError("ambient must be a real constant index (the medium the light comes from)")
        object.__setattr__(self, "ambient", amb)

    @property
    def layer_names(self):
        return [layer.name or f"layer{i + 1}" for i, layer in enumerate(self.layers)]

    def _slots(self):
        """`[(owner name, Dispersion)]` for ambient, layers, substrate."""
        return [("ambient", self.ambient)] + [(nm, layer.material) for nm, layer in zip(self.layer_names, self.layers)] \
            + [("substrate", self.substrate)]

    def parameters(self) -> list[ParameterInfo]:
        out = []
        for owner, model in self._slots():
            for pname, leaf in parameter_leaves(model):
                out.append(_info(f"{owner}.{pname}", leaf, False))
        for nm, layer in zip(self.layer_names, self.layers):
            out.append(_info(f"{nm}.thickness_nm", layer.thickness_nm, True))
        if self.instrument is not None:
            for pname in Instrument._params:
                out.append(_info(f"instrument.{pname}", getattr(self.instrument, pname), False))
        return out

    def free(self) -> list[ParameterInfo]:
        return [p for p in self.parameters() if p.free]

    def free_names(self) -> list[str]:
        return [p.name for p in self.free()]

    def with_values(self, values) -> _ResolvedSample:
        """This sample with its free parameters (in `free_names()` order) set to `values`
        (numbers or JAX arrays; used inside traced functions)."""
        it = iter(values)
        slots = self._slots()
        new_models = []
        for _, model in slots:
            k = sum(isinstance(leaf, Free) for _, leaf in parameter_leaves(model))
            new_models.append(substitute(model, [next(it) for _ in range(k)]) if k else model)
        layers = []
        for layer, model in zip(self.layers, new_models[1:-1]):
            t = layer.thickness_nm
            layers.append(_Resolved(model, t if not isinstance(t, Free) else None, layer.incoherent))
        thick = [next(it) if isinstance(layer.thickness_nm, Free) else None for layer in self.layers]
        layers = [lr._replace_t(t) for lr, t in zip(layers, thick)]
        instrument = self.instrument
        if instrument is not None:
            instrument = dataclasses.replace(instrument, **{
                f: next(it) for f in Instrument._params if isinstance(getattr(instrument, f), Free)})
        return _ResolvedSample(new_models[0], tuple(layers), new_models[-1], instrument)

    def fixed(self) -> _ResolvedSample:
        """This sample with every free parameter at its start value."""
        return self.with_values([p.value for p in self.free()])

    @property
    def incoherent(self) -> tuple:
        """The incoherent layers' positions among the stack's inner layers (a graded layer is
        its slices there)."""
        return _incoherent(self.layers)

    def _columns(self) -> list[int]:
        """Per slot (ambient, layers, substrate): its first column among the stack's media."""
        return [0] + [1 + int(c) for c in _starts(self.layers)]


def _info(name, leaf, is_t):
    if isinstance(leaf, Free):
        return ParameterInfo(name, float(leaf.value), True, float(leaf.lower), float(leaf.upper), is_t)
    v = leaf if not isinstance(leaf, complex) else leaf.real
    return ParameterInfo(name, float(v), False, -math.inf, math.inf, is_t)


@dataclasses.dataclass(frozen=True)
class _Resolved:
    material: Dispersion
    thickness_nm: Any
    incoherent: bool

    def _replace_t(self, t):
        return self if t is None else dataclasses.replace(self, thickness_nm=t)


@dataclasses.dataclass(frozen=True)
class _ResolvedSample:
    ambient: Dispersion
    layers: tuple
    substrate: Dispersion
    instrument: Instrument | None = None

    def indices(self, wavelength_nm):
        """`(..., L)` complex indices of all media at `wavelength_nm`."""
        lam_um = wavelength_nm / 1000
        # `(..., media)` per slot: a graded layer is its slices
        one = lambda m: jnp.asarray(m.nk(lam_um))[..., None]
        Ns = [one(self.ambient)] + [m.nk_slices(lam_um) if isinstance(m, Graded) else one(m) for m in (layer.material for layer in self.layers)] \
            + [one(self.substrate)]
        cdt = jnp.result_type(*Ns)
        Ns = [jnp.broadcast_to(N.astype(cdt), jnp.shape(lam_um) + N.shape[-1:]) for N in Ns]
        return jnp.concatenate(Ns, axis=-1)

    def stack_inputs(self, wavelength_nm):
        """`(n, d)` for `stack`: `(..., L)` indices (the ambient's real part) and `(L-2,)` thicknesses."""
        wl = jnp.asarray(wavelength_nm)
        n = self.indices(wl)
        n = n.at[..., 0].set(jnp.real(n[..., 0]).astype(n.dtype))
        # a graded layer's slices share its thickness equally (t / 1 is t, exactly)
        k = np.diff(_starts(self.layers))
        parts = [jnp.broadcast_to(jnp.asarray(layer.thickness_nm, wl.dtype) / int(kj), (int(kj),)) for layer, kj in zip(self.layers, k)]
        d = jnp.concatenate(parts) if parts else jnp.zeros((0,), wl.dtype)
        return n, d

    @property
    def incoherent(self) -> tuple:
        return _incoherent(self.layers)

    def stack(self, wavelength_nm, angle_rad):
        wl = jnp.asarray(wavelength_nm)
        n, d = self.stack_inputs(wl)
        return stack(n, d, wl, jnp.cos(jnp.asarray(angle_rad, wl.dtype)), incoherent=self.incoherent)

    def quantities(self, kinds, wavelength_nm, angle_rad, *, flat=False):
        """The measured quantities `kinds` (names from `jaxoptics.KINDS`) at each point, stacked
        along a new second-to-last axis: `(..., Q, P)` for points of shape `(..., P)` (with
        `flat=True`, `(..., Q * P)`, quantity after quantity). With an `Instrument`, its effects
        are applied (intensities averaged over its conditions)."""
        if self.instrument is not None:
            return model_quantities(self.instrument.averaged(self, wavelength_nm, angle_rad), kinds, flat)
        return model_quantities(self.stack(wavelength_nm, angle_rad), kinds, flat)


def model_quantities(res, kinds, flat_out=False):
    """Measured quantities from a `StackResult`, in the instrument conventions of `jaxoptics._io._spectra`.

    With `X = r_p conj(r_s)` (`StackResult.rp_rs`, the incoherent sum with incoherent layers), the
    instrument's `rho = r_p / r_s` is `tan(Psi) exp(i Delta)` with `N = n - ik`, which equals
    `conj(X) / |r_s|^2` here (`exp(-i omega t)`, `N = n + ik`, and this package's `r_p` sign):
    so `N = (R_s - R_p) / (R_s + R_p)`, `C = 2 Re(X) / (R_s + R_p)`, `S = -2 Im(X) / (R_s + R_p)`,
    `Psi = atan(sqrt(R_p / R_s))`, `Delta = atan2(S, C)` (degrees in `(-180, 180]`), and the
    depolarization `1 - sqrt(N^2 + C^2 + S^2)` (one minus the degree of polarization of the light
    reflected from a beam polarized at 45 degrees: 0 for a coherent model)."""
    # stored once (values and derivatives): every quantity reads them, and XLA would otherwise
    # recompute the stack's last steps in each quantity's loop
    Rs, Rp, X = materialize_both(res.R_s), materialize_both(res.R_p), materialize_both(res.rp_rs)
    tot = Rs + Rp
    out = {}

    def get(k):
        if k in out:
            return out[k]
        if k == "N":
            v = (Rs - Rp) / tot
        elif k == "C":
            v = 2 * jnp.real(X) / tot
        elif k == "S":
            v = -2 * jnp.imag(X) / tot
        elif k == "psi_deg":
            v = jnp.degrees(_atan2(jnp.sqrt(Rp), jnp.sqrt(Rs)))
        elif k == "delta_deg":
            # in (-180, 180]: -pi (atan2 of a zero S whose sign is negative, as in a lossless
            # stack, where X is real and its zero imaginary part carries either sign) is pi
            a = _atan2(get("S"), get("C"))
            v = jnp.degrees(jnp.where(a <= -jnp.pi, a + 2 * jnp.pi, a))
        elif k == "depolarization":  # 1 - sqrt(N^2 + C^2 + S^2)
            v = 1 - jnp.sqrt((Rs - Rp) ** 2 + 4 * (jnp.real(X) ** 2 + jnp.imag(X) ** 2)) / tot
        elif k == "R":
            v = 0.5 * tot
        elif k == "T":
            v = 0.5 * (res.T_s + res.T_p)
        else:
            v = getattr(res, k)
        out[k] = v
        return v

    # concatenated along the last axis and reshaped (a stack along axis -2 is laid out so that
    # XLA's CPU backend runs the whole stack kernel about 20x slower, measured under vmap)
    vals = [get(k) for k in kinds]
    shape = jnp.broadcast_shapes(*(v.shape for v in vals))
    flat = jnp.concatenate([jnp.broadcast_to(v, shape) for v in vals], axis=-1)
    return flat if flat_out else flat.reshape(shape[:-1] + (len(kinds), shape[-1]))


def roughness(material: Any, thickness_nm: Any, *, void_fraction: Any = 0.5, name: str = "roughness") -> Layer:
    """A surface roughness layer: a Bruggeman mixture of `material` (the film below it) with
    void, `void_fraction` of it void (0.5 by default, the usual model; a number or `Free`), of
    thickness `thickness_nm` (a number or `Free`). Put it above the film it roughens."""
    return Layer(EMA(material, 1.0, void_fraction, "bruggeman"), thickness_nm, name=name)
