"""Spectroscopic data of layered samples: ellipsometry (psi/delta; N, C, S; Mueller matrix) and
photometry (R, T), read from CSV with errors that name the file, line and column.

Conventions of the measured columns (what ellipsometers export for isotropic samples):

- `psi_deg`, `delta_deg`: the instrument's Psi and Delta in degrees, Azzam and Bashara's
  convention (`rho = r_p / r_s = tan(Psi) exp(i Delta)`, index `N = n - ik`; a bare dielectric
  below Brewster's angle has `Delta = 180`). Any range of Delta is accepted (`-180..180`,
  `0..360`): residuals are wrapped.
- `N`, `C`, `S`: `cos 2Psi`, `sin 2Psi cos Delta`, `sin 2Psi sin Delta`.
- `m11` ... `m44`: the Mueller matrix normalized by `m11`; for an isotropic sample it is
  `[[1, -N, 0, 0], [-N, 1, 0, 0], [0, 0, C, S], [0, 0, -S, C]]` (Fujiwara, *Spectroscopic
  Ellipsometry*, sec. 3.4), and the fit uses `N = -(m12 + m21)/2`, `C = (m33 + m44)/2`,
  `S = (m34 - m43)/2` (or the elements present).
- `R`, `T` (unpolarized), `R_s`, `R_p`, `T_s`, `T_p`: fractions (0 to 1), not percent.
"""

from __future__ import annotations

import csv
import os
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from jaxtyping import ArrayLike, Float

KINDS = ("psi_deg", "delta_deg", "N", "C", "S", "R", "R_s", "R_p", "T", "T_s", "T_p", "depolarization")
_MUELLER = tuple(f"m{i}{j}" for i in range(1, 5) for j in range(1, 5))
_NEAR = {"psi": "psi_deg", "delta": "delta_deg", "wavelength": "wavelength_nm or wavelength_um", "lambda": "wavelength_nm",
         "angle": "angle_deg", "theta": "angle_deg", "aoi": "angle_deg", "rs": "R_s", "rp": "R_p", "ts": "T_s", "tp": "T_p",
         "wavelength_a": "wavelength_nm", "energy_ev": "wavelength_nm (energies are not read; convert to nm)"}


# The range each measured quantity lies in. Measured values may stray outside it by noise, up to 5%
# of its width; beyond that they are refused as a mix-up of units or columns, with the reason.
_RANGES = {"psi_deg": (0.0, 90.0), **dict.fromkeys(("N", "C", "S"), (-1.0, 1.0)),
           **dict.fromkeys(("R", "R_s", "R_p", "T", "T_s", "T_p", "depolarization"), (0.0, 1.0)),
           **dict.fromkeys(_MUELLER, (-1.0, 1.0))}
_WHY = {"psi_deg": "Psi lies in [0, 90] degrees (Delta in the psi column?)",
        **dict.fromkeys(("N", "C", "S"), "N, C and S are cos 2Psi, sin 2Psi cos Delta and sin 2Psi sin Delta, in [-1, 1]"),
        **dict.fromkeys(("R", "R_s", "R_p", "T", "T_s", "T_p"),
                        "reflectance and transmittance are fractions in [0, 1] (percent? divide by 100)"),
        **dict.fromkeys(_MUELLER, "the elements of a Mueller matrix normalized by m11 lie in [-1, 1]"),
        "depolarization": "depolarization is a fraction in [0, 1] (a file's percent divided by 100)"}


def _out_of_range(kind, v):
    """The flat index of the first value of `kind` in `v` outside its range (with the noise margin of
    `_RANGES`), or None."""
    lo, hi = _RANGES.get(kind, (-np.inf, np.inf))
    slack = 0.05 * (hi - lo)
    bad = np.flatnonzero((np.ravel(v) < lo - slack) | (np.ravel(v) > hi + slack))
    return int(bad[0]) if bad.size else None


class Spectra(NamedTuple):
    """Measured spectra on one grid of `(wavelength, angle)` points, for one sample or a map.

    **Fields:**

    - `wavelength_nm`, `angle_deg`: `(P,)`, the points (vacuum wavelength in nm, angle of
      incidence in degrees).
    - `kinds`: the measured quantities, a tuple of names from `KINDS`.
    - `values`: `(..., Q, P)` with `Q = len(kinds)`; leading axes are map points (sites).
    - `sigma`: `(..., Q, P)` standard deviations, or `None` when the data give none.
    - `sites`: the site labels of a map, in the order of the leading axis, or `None`.
    - `path`: the file read, or `None`.
    - `site_xy`: `(n_sites, 2)`, the position of each site on the sample in mm (`x_mm`, `y_mm`
      columns), or `None`.
    - `meta`: what the file says beside the fitted quantities, or `None`: its `format`, header
      fields, the conventions it was read with, and per-point arrays such as
      `depolarization_percent` (laid out like one quantity of `values`, NaN where not measured).
    """

    wavelength_nm: np.ndarray
    angle_deg: np.ndarray
    kinds: tuple
    values: np.ndarray
    sigma: np.ndarray | None = None
    sites: tuple | None = None
    path: str | None = None
    site_xy: np.ndarray | None = None
    meta: dict | None = None

    @property
    def batch_shape(self):
        return self.values.shape[:-2]

    def with_depolarization(self, sigma: float | None = None) -> Spectra:
        """These spectra with the file's depolarization (`meta["depolarization_percent"]`, the
        `dPolE` rows of a Woollam file) added as the measured quantity `"depolarization"` (a
        fraction: `1 - sqrt(N^2 + C^2 + S^2)`), to be fitted with the rest. Its sigma: the file's
        (`depolarization_sigma_percent`), else `sigma` (a fraction) where the spectra carry sigmas.
        Raises where the file has no depolarization or lacks it at some point (naming the point)."""
        meta = self.meta or {}
        if "depolarization_percent" not in meta:
            raise ValueError(f"{self.path or 'these spectra'}: no depolarization in the file (meta['depolarization_percent'])")
        d = np.asarray(meta["depolarization_percent"], np.float64) / 100
        missing = np.flatnonzero(~np.isfinite(d.reshape(-1)))
        if missing.size:
            i = int(missing[0]) % d.shape[-1]
            raise ValueError(f"{self.path or 'these spectra'}: no depolarization at {self.wavelength_nm[i]:g} nm, "
                             f"{self.angle_deg[i]:g} deg ({missing.size} points lack it)")
        values = {k: self.values[..., q, :] for q, k in enumerate(self.kinds)} | {"depolarization": d}
        sig = None
        if self.sigma is not None:
            s_file = meta.get("depolarization_sigma_percent")
            if s_file is not None and np.all(np.isfinite(s_file)):
                s_d = np.asarray(s_file, np.float64) / 100
            elif sigma is not None:
                s_d = np.broadcast_to(np.float64(sigma), d.shape)
            else:
                raise ValueError("the spectra carry sigmas and the file gives none for the depolarization: pass sigma=")
            sig = {k: self.sigma[..., q, :] for q, k in enumerate(self.kinds)} | {"depolarization": s_d}
        out = make_spectra(self.wavelength_nm, self.angle_deg, values, sigma=sig, sites=self.sites, site_xy=self.site_xy)
        return out._replace(path=self.path, meta=self.meta)


def make_spectra(wavelength_nm: Float[ArrayLike, " P"], angle_deg: Float[ArrayLike, "#P"], values: dict, *, sigma: dict | None = None,
                 sites: tuple | None = None, site_xy: Float[ArrayLike, "n_sites 2"] | None = None) -> Spectra:
    """Build `Spectra` from arrays: `values` maps kind names (see `KINDS`) to arrays `(..., P)`,
    `sigma` (optional) maps the same names to standard deviations of the same shapes. For a map
    (leading axes), `sites` labels its sites and `site_xy` gives their positions in mm, both in
    the order of the flattened leading axes. Values are checked as `load_spectra` checks a file's
    (finite; each quantity in its range up to noise), naming the quantity and the point."""
    w = np.asarray(wavelength_nm, np.float64).reshape(-1)
    a = np.broadcast_to(np.asarray(angle_deg, np.float64), w.shape).copy()
    if not values:
        raise ValueError("values is empty: give at least one measured quantity")
    bad = [k for k in values if k not in KINDS]
    if bad:
        raise ValueError(f"unknown measured quantities {bad}; known: {', '.join(KINDS)}")
    kinds = tuple(values)
    V = np.stack([np.asarray(values[k], np.float64) for k in kinds], axis=-2)
    if V.shape[-1] != w.shape[0]:
        raise ValueError(f"values have {V.shape[-1]} points along their last axis, wavelength_nm has {w.shape[0]}")
    S = None
    if sigma is not None:
        if set(sigma) != set(kinds):
            raise ValueError(f"sigma must give the same quantities as values: {sorted(kinds)}, got {sorted(sigma)}")
        S = np.stack([np.broadcast_to(np.asarray(sigma[k], np.float64), V.shape[:-2] + V.shape[-1:]) for k in kinds], axis=-2)
    _check_values(w, a, kinds, V, S, None)
    n = int(np.prod(V.shape[:-2]))
    if (sites is not None or site_xy is not None) and V.ndim < 3:
        raise ValueError("sites and site_xy describe a map: give values with leading (site) axes")
    if sites is not None:
        sites = tuple(str(x) for x in sites)
        if len(sites) != n or len(set(sites)) != n:
            raise ValueError(f"sites must be {n} distinct labels (one per spectrum), got {len(sites)} ({len(set(sites))} distinct)")
    if site_xy is not None:
        site_xy = np.asarray(site_xy, np.float64)
        if site_xy.shape != (n, 2) or not np.all(np.isfinite(site_xy)):
            raise ValueError(f"site_xy must be finite positions of shape ({n}, 2), got shape {site_xy.shape}")
    return Spectra(w, a, kinds, V, S, sites, None, site_xy)


def _check_values(w, a, kinds, V, S, where):
    at = f"{where}: " if where else ""
    if not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"{at}wavelengths must be finite and positive")
    if not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a >= 90):
        raise ValueError(f"{at}angles of incidence must lie in [0, 90) degrees")
    if not np.all(np.isfinite(V)):
        i = np.argwhere(~np.isfinite(V))[0]
        raise ValueError(f"{at}non-finite value of {kinds[i[-2]]} at point {i[-1]}")
    for q, kind in enumerate(kinds):
        j = _out_of_range(kind, V[..., q, :])
        if j is not None:
            site, p = divmod(j, V.shape[-1])
            where_p = f"point {p}" + (f" of spectrum {site}" if V.ndim > 2 else "")
            raise ValueError(f"{at}{kind} = {V[..., q, :].reshape(-1)[j]:g} at {where_p}: {_WHY[kind]}")
    if S is not None and (not np.all(np.isfinite(S)) or np.any(S <= 0)):
        raise ValueError(f"{at}sigma must be finite and positive")


def save_spectra(path: str | os.PathLike, spectra: Spectra) -> None:
    """Write `Spectra` as CSV in the format `load_spectra` reads (a `site` column for maps, and
    `x_mm`, `y_mm` where the sites have positions)."""
    batch = spectra.values.shape[:-2]
    V = spectra.values.reshape((-1,) + spectra.values.shape[-2:])
    S = None if spectra.sigma is None else spectra.sigma.reshape(V.shape)
    labels = spectra.sites or (tuple(str(i) for i in range(V.shape[0])) if batch else (None,))
    cols = ["wavelength_nm", "angle_deg"] + list(spectra.kinds) + ([f"sigma_{k}" for k in spectra.kinds] if S is not None else [])
    xy = None if spectra.site_xy is None or not batch else np.asarray(spectra.site_xy, np.float64).reshape(-1, 2)
    with open(path, "w", encoding="utf-8", newline="") as f:
        w = csv.writer(f)
        w.writerow((["site"] if batch else []) + (["x_mm", "y_mm"] if xy is not None else []) + cols)
        for b, lab in enumerate(labels):
            where = [repr(float(c)) for c in xy[b]] if xy is not None else []
            for p in range(V.shape[-1]):
                row = [repr(float(spectra.wavelength_nm[p])), repr(float(spectra.angle_deg[p]))]
                row += [repr(float(x)) for x in V[b, :, p]]
                if S is not None:
                    row += [repr(float(x)) for x in S[b, :, p]]
                w.writerow(([lab] if batch else []) + where + row)
