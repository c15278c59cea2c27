"""Instrument and sample non-idealities of a measurement, as part of the `Sample` model
(`Sample(..., instrument=Instrument(...))`): an angle-of-incidence offset, a wavelength shift, a
Gaussian spectral bandwidth and angular spread, a non-uniform film thickness across the spot, and
the incoherent reflections from the back of a transparent substrate.

Each effect that spreads the light over several conditions is an average of intensities, never of
Psi and Delta: the reflectances `R_s`, `R_p`, the cross term `X = r_p conj(r_s)` and the
transmittances are averaged over the conditions (quadrature nodes), and the measured quantities
are formed from the averages (`model_quantities`). So the model's light is partially
depolarized, `N^2 + C^2 + S^2 < 1`, as an ellipsometer sees it on such samples; `Psi` and `Delta`
are those an instrument reports from `N`, `C`, `S`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._dispersion import Free, _fixed_zero
from ._stack import stack

_FWHM_PER_SIGMA = 2 * math.sqrt(2 * math.log(2))


def _gauss_hermite(n):
    """Nodes `z` and weights `w` with `sum w f(z) = E[f(Z)]` for a standard normal `Z`."""
    x, w = np.polynomial.hermite_e.hermegauss(n)
    return x, w / w.sum()


def _gauss_legendre_uniform(n):
    """Nodes `u` in `(-1/2, 1/2)` and weights with `sum w f(u) = E[f(U)]`, `U` uniform there."""
    x, w = np.polynomial.legendre.leggauss(n)
    return x / 2, w / 2


class Averaged(NamedTuple):
    """The intensities of a `StackResult` averaged over a measurement's conditions (the fields
    `model_quantities` reads)."""

    R_s: Any
    R_p: Any
    T_s: Any
    T_p: Any
    rp_rs: Any


@dataclasses.dataclass(frozen=True)
class Instrument:
    """What a real measurement adds to the ideal sample; each number may be `Free` (fitted like the
    sample's parameters, named `instrument.angle_offset_deg`, ...).

    **Fields:**

    - `angle_offset_deg`: added to every data point's angle of incidence.
    - `wavelength_shift_nm`: the light's wavelength is the data's plus this.
    - `bandwidth_nm`: full width at half maximum of the Gaussian spectral band around each
      wavelength (the monochromator's or spectrometer's slit function).
    - `angle_spread_deg`: full width at half maximum of the Gaussian spread of angles of incidence
      (a focused or divergent beam).
    - `thickness_nonuniformity`: the films' thicknesses vary across the spot uniformly over this
      fraction of their value, full width (0.02: +-1%); every coherent film scales together (a
      wedge), as CompleteEASE's `% Thickness Non-uniformity` with the ideal profile.
    - `backside`: the fraction of the light reflected from the back of a transparent substrate
      that the detector collects (0 none, 1 all): the substrate is then an incoherent slab of
      `substrate_mm` millimetres with the ambient behind it, and `R = R_front + backside (R_slab -
      R_front)` (likewise the cross term); `T` is the slab's.
    - `substrate_mm`: the substrate's thickness for `backside` (matters where it absorbs).
    - `nodes`: quadrature nodes per averaged effect (Gauss-Hermite for the Gaussian band and
      spread, Gauss-Legendre for the thickness): 5 by default, exact for polynomials of degree 9
      in the offset; the effects that are on combine as a product grid. An effect held at 0 costs
      nothing.
    """

    angle_offset_deg: Any = 0.0
    wavelength_shift_nm: Any = 0.0
    bandwidth_nm: Any = 0.0
    angle_spread_deg: Any = 0.0
    thickness_nonuniformity: Any = 0.0
    backside: Any = 0.0
    substrate_mm: float = 1.0
    nodes: int = 5
    _params = ("angle_offset_deg", "wavelength_shift_nm", "bandwidth_nm", "angle_spread_deg", "thickness_nonuniformity",
               "backside")

    def __post_init__(self):
        if any(isinstance(getattr(self, name), jax.Array) for name in self._params):
            return  # values a fit substitutes (traced), checked as numbers before
        for name in self._params:
            v = getattr(self, name)
            if isinstance(v, Free):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not math.isfinite(v):
                raise ValueError(f"Instrument.{name} must be a finite number or Free, got {v!r}")
        for name in ("bandwidth_nm", "angle_spread_deg", "thickness_nonuniformity", "backside"):
            v = getattr(self, name)
            lo = v.lower if isinstance(v, Free) else v
            if lo < 0:
                raise ValueError(f"Instrument.{name} must be >= 0 (a Free one's lower bound too), got {v!r}")
        b = self.backside
        if (b.upper if isinstance(b, Free) else b) > 1:
            raise ValueError(f"Instrument.backside is a fraction in [0, 1], got {b!r}")
        if not (isinstance(self.nodes, int) and self.nodes >= 1):
            raise ValueError(f"Instrument.nodes must be an integer >= 1, got {self.nodes!r}")
        if not self.substrate_mm > 0:
            raise ValueError(f"Instrument.substrate_mm must be > 0, got {self.substrate_mm!r}")

    def _grid(self, dtype):
        """The averaging conditions: per node, `(wavelength offset, angle offset, thickness
        factor)` as functions of the (possibly traced) widths, and the nodes' weights; one node of
        weight 1 where nothing is averaged."""
        axes = []
        if not _fixed_zero(self.bandwidth_nm):
            z, w = _gauss_hermite(self.nodes)
            axes.append(("wl", z, w))
        if not _fixed_zero(self.angle_spread_deg):
            z, w = _gauss_hermite(self.nodes)
            axes.append(("ang", z, w))
        if not _fixed_zero(self.thickness_nonuniformity):
            z, w = _gauss_legendre_uniform(self.nodes)
            axes.append(("d", z, w))
        dwl, dang, fd, wts = [], [], [], []
        for combo in itertools.product(*[range(len(a[1])) for a in axes]):
            e = {"wl": 0.0, "ang": 0.0, "d": 0.0}
            wt = 1.0
            for (kind, z, w), i in zip(axes, combo):
                e[kind] = float(z[i])
                wt *= float(w[i])
            dwl.append(e["wl"])
            dang.append(e["ang"])
            fd.append(e["d"])
            wts.append(wt)
        bw = self.bandwidth_nm / _FWHM_PER_SIGMA
        sp = math.pi / 180 * self.angle_spread_deg / _FWHM_PER_SIGMA
        arr = lambda v: jnp.asarray(np.asarray(v), dtype)
        return arr(dwl) * bw, arr(dang) * sp, 1 + arr(fd) * self.thickness_nonuniformity, arr(wts)

    def averaged(self, sample, wavelength_nm, angle_rad) -> Averaged:
        """The intensities of the resolved `sample` (its free parameters substituted) at the data's
        points, with this instrument's effects."""
        wl = jnp.asarray(wavelength_nm)
        dt = wl.dtype
        ang = jnp.asarray(angle_rad, dt) + math.pi / 180 * self.angle_offset_deg
        wl = wl + self.wavelength_shift_nm
        dwl, dang, fd, wts = self._grid(dt)
        K = wts.shape[0]
        shape = jnp.broadcast_shapes(jnp.shape(wl), jnp.shape(ang))
        node = lambda a: jnp.reshape(a, (K,) + (1,) * len(shape))
        wl_k = jnp.broadcast_to(wl, shape)[None] + node(dwl)
        cos_k = jnp.cos(jnp.broadcast_to(ang, shape)[None] + node(dang))
        n, d = sample.stack_inputs(wl_k)
        inc = sample.incoherent
        lead = (1,) * (1 + len(shape))
        # coherent films scale together; incoherent layers keep their thickness
        coh = np.ones(d.shape[-1], bool)
        coh[list(inc)] = False
        scale = jnp.where(jnp.asarray(coh.reshape(lead + coh.shape)), jnp.reshape(fd, (K,) + lead[1:] + (1,)), 1)
        d_k = jnp.reshape(d, lead + d.shape) * scale
        res = stack(n, d_k, wl_k, cos_k, incoherent=inc)
        Rs, Rp, X, Ts, Tp = res.R_s, res.R_p, res.rp_rs, res.T_s, res.T_p
        if not _fixed_zero(self.backside):
            amb = n[..., :1]
            n_b = jnp.concatenate([n, amb.astype(n.dtype)], axis=-1)
            slab = jnp.broadcast_to(jnp.asarray(self.substrate_mm * 1e6, dt), d_k.shape[:-1] + (1,))
            d_b = jnp.concatenate([d_k, slab], axis=-1)
            rb = stack(n_b, d_b, wl_k, cos_k, incoherent=tuple(inc) + (d.shape[-1],))
            f = jnp.asarray(self.backside, dt)
            Rs, Rp = Rs + f * (rb.R_s - Rs), Rp + f * (rb.R_p - Rp)
            X = X + f.astype(X.dtype) * (rb.rp_rs - X)
            Ts, Tp = rb.T_s, rb.T_p
        w = node(wts)
        mean = lambda a: jnp.sum(w.astype(a.dtype) * a, axis=0)
        return Averaged(mean(Rs), mean(Rp), mean(Ts), mean(Tp), mean(X))
