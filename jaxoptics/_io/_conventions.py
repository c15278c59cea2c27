"""The conventions of measured ellipsometric data, as explicit options of `load_spectra`, and the
step every reader ends with: conventions applied, rows grouped into spectra, values checked with
the file's line numbers.

jaxoptics' measured quantities are in the instrument (Nebraska, Azzam and Bashara) convention:
`rho = r_p / r_s = tan(Psi) exp(i Delta)` with the index `N = n - ik`, so a bare dielectric below
Brewster's angle has `Delta = 180` degrees. The options say how a file differs:

- `delta_convention`: what the file's Delta is, written in that Delta: `"delta"` (the same; every
  ellipsometer vendor's export and pyElli), `"-delta"` (the opposite handedness:
  `rho = tan(Psi) exp(-i Delta)` with `N = n - ik`), `"180-delta"` (tmm's `ellips` and
  `jaxoptics.ellipsometry`: `delta = arg(-r_p / r_s)` with `n + ik`), `"delta+180"` (the other sign
  of `r_p` in the same time convention).
- `delta_range`: `None` (Delta is a full phase, in any range: residuals are wrapped),
  `"-180..180"` or `"0..360"` (the same, and every value is checked to lie in that range), or
  `"0..180"`: the instrument measured only `cos Delta` (a rotating analyzer without compensator),
  and Delta above 180 was folded to `360 - Delta`. Such data are read as `N = cos 2Psi` and
  `C = sin 2Psi cos Delta`, which do not depend on the fold, and the fit uses those (it never
  folds the model).
- `mueller_s3_sign`: the sign `s` of `M34 = s sin 2Psi sin Delta` (and `M43 = -s sin 2Psi sin
  Delta`) in a normalized Mueller matrix: `+1` for the Woollam FAQ's and Sentech's matrices, `-1`
  for pyElli 0.23's.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._spectra import _RANGES, _WHY, KINDS, Spectra, _out_of_range

DELTA_CONVENTIONS = ("delta", "-delta", "180-delta", "delta+180")
DELTA_RANGES = (None, "-180..180", "0..360", "0..180")
_RANGE_BOUNDS = {"-180..180": (-180.0, 180.0), "0..360": (0.0, 360.0), "0..180": (0.0, 180.0)}
# what a Delta stated to lie in a range may exceed it by: the rounding of a printed value
_RANGE_SLACK_DEG = 1e-3


class Conventions(NamedTuple):
    """The conventions of one file (see the module docstring); checked by `conventions`."""

    delta_convention: str = "delta"
    delta_range: str | None = None
    mueller_s3_sign: int = 1


def conventions(delta_convention="delta", delta_range=None, mueller_s3_sign=1) -> Conventions:
    """`Conventions` from `load_spectra`'s keyword arguments, with an error naming a bad value."""
    if delta_convention not in DELTA_CONVENTIONS:
        raise ValueError(f"delta_convention={delta_convention!r}: must be one of {DELTA_CONVENTIONS}")
    if delta_range not in DELTA_RANGES:
        raise ValueError(f"delta_range={delta_range!r}: must be one of {DELTA_RANGES}")
    if mueller_s3_sign not in (1, -1):
        raise ValueError(f"mueller_s3_sign={mueller_s3_sign!r}: must be +1 (M34 = +sin 2Psi sin Delta, Woollam, Sentech) "
                         "or -1 (M34 = -sin 2Psi sin Delta, pyElli 0.23)")
    return Conventions(delta_convention, delta_range, int(mueller_s3_sign))


def delta_to_instrument(delta_file, convention):
    """The instrument's Delta (degrees) from a file's Delta written in `convention`."""
    d = np.asarray(delta_file, np.float64)
    return {"delta": d, "-delta": -d, "180-delta": 180.0 - d, "delta+180": d - 180.0}[convention]


def delta_from_instrument(delta, convention):
    """A file's Delta in `convention` from the instrument's Delta (degrees): the inverse of
    `delta_to_instrument` (the writers of the tests use it)."""
    d = np.asarray(delta, np.float64)
    return {"delta": d, "-delta": -d, "180-delta": 180.0 - d, "delta+180": d + 180.0}[convention]


def cs_to_instrument(C, S, convention):
    """`C = sin 2Psi cos Delta` and `S = sin 2Psi sin Delta` of the instrument from a file's, whose
    Delta is written in `convention` (`C` or `S` may be None)."""
    sc, ss = {"delta": (1, 1), "-delta": (1, -1), "180-delta": (-1, 1), "delta+180": (-1, -1)}[convention]
    return (None if C is None else sc * np.asarray(C, np.float64)), (None if S is None else ss * np.asarray(S, np.float64))


def folded_to_nc(psi_deg, delta_deg, sigma_psi=None, sigma_delta=None):
    """`N = cos 2Psi`, `C = sin 2Psi cos Delta` from Psi and a Delta folded into [0, 180] (both
    degrees), with their standard deviations propagated to first order when given (floored at
    1e-6, where both derivatives vanish)."""
    p, d = np.deg2rad(psi_deg), np.deg2rad(delta_deg)
    N, C = np.cos(2 * p), np.sin(2 * p) * np.cos(d)
    if sigma_psi is None:
        return N, C, None, None
    sp, sd = np.deg2rad(sigma_psi), np.deg2rad(sigma_delta)
    sN = np.abs(2 * np.sin(2 * p)) * sp
    sC = np.hypot(2 * np.cos(2 * p) * np.cos(d) * sp, np.sin(2 * p) * np.sin(d) * sd)
    return N, C, np.maximum(sN, 1e-6), np.maximum(sC, 1e-6)


def mueller_to_ncs(M: dict, sigma: dict | None, s3_sign: int):
    """`N`, `C`, `S` (and their standard deviations, where every element used has one) from the
    elements of a normalized Mueller matrix present in `M` (`"m12"`, ...), averaging the two
    elements of each: `N = -(m12 + m21)/2`, `C = (m33 + m44)/2`, `S = s (m34 - m43)/2`."""
    values, sigmas = {}, {}
    for q, parts in (("N", (("m12", -1), ("m21", -1))), ("C", (("m33", 1), ("m44", 1))),
                     ("S", (("m34", s3_sign), ("m43", -s3_sign)))):
        have = [(m, sign) for m, sign in parts if m in M]
        if not have:
            continue
        values[q] = np.sum([sign * np.asarray(M[m], np.float64) for m, sign in have], axis=0) / len(have)
        if sigma and all(m in sigma for m, _ in have):
            sigmas[q] = np.sqrt(np.sum([np.asarray(sigma[m], np.float64) ** 2 for m, _ in have], axis=0)) / len(have)
    return values, sigmas


def apply_delta_conventions(path, lines, values, sigmas, conv: Conventions, fail):
    """The instrument's quantities from a file's `psi_deg`, `delta_deg` (and `C`, `S`) under
    `conv`: Delta converted, its stated range checked (naming the line), folded data turned into
    `N`, `C`. Returns new `values`, `sigmas` dicts (kind -> per-row arrays)."""
    values, sigmas = dict(values), dict(sigmas)
    if "delta_deg" in values:
        d = values["delta_deg"]
        if conv.delta_range is not None:
            lo, hi = _RANGE_BOUNDS[conv.delta_range]
            bad = np.flatnonzero((d < lo - _RANGE_SLACK_DEG) | (d > hi + _RANGE_SLACK_DEG))
            if bad.size:
                fail(path, lines[bad[0]], f"Delta = {d[bad[0]]:g} lies outside delta_range={conv.delta_range!r}")
        if conv.delta_range == "0..180":
            sp, sd = (sigmas.pop("psi_deg", None), sigmas.pop("delta_deg", None))
            N, C, sN, sC = folded_to_nc(values.pop("psi_deg"), values.pop("delta_deg"), sp, sd)
            C, _ = cs_to_instrument(C, None, conv.delta_convention)
            values = {"N": N, "C": C, **values}
            if sN is not None:
                sigmas = {"N": sN, "C": sC, **sigmas}
        else:
            values["delta_deg"] = delta_to_instrument(d, conv.delta_convention)
    elif "C" in values or "S" in values:
        C, S = cs_to_instrument(values.get("C"), values.get("S"), conv.delta_convention)
        values.update({k: v for k, v in (("C", C), ("S", S)) if v is not None})
    return values, sigmas


def finish(path, fmt, wl, aoi, values, sigmas, lines, *, group=None, group_xy=None, group_name="site", meta=None,
           extra=None, fail) -> Spectra:
    """`Spectra` from per-row arrays: `values`, `sigmas` map kinds to `(rows,)` arrays in the
    instrument's convention, `lines` gives each row's line in the file. `group` (optional, `(rows,)`
    labels) splits the rows into the spectra of a map or a time series (a leading axis); every
    group must list the same `(wavelength, angle)` points in the same order. `group_xy` gives each
    group's position in mm. `extra` maps names to per-row arrays kept in `meta` with the same
    layout as the values (depolarization, ...). Values are checked as `make_spectra` checks them,
    naming the file's line."""
    lines = np.asarray(lines)
    if lines.size == 0:
        raise ValueError(f"{path}: no data rows")
    wl, aoi = np.asarray(wl, np.float64), np.asarray(aoi, np.float64)
    for name, arr, ok, why in (("wavelength", wl, wl > 0, "must be positive"),
                               ("angle of incidence", aoi, (aoi >= 0) & (aoi < 90), "must lie in [0, 90) degrees")):
        bad = np.flatnonzero(~(np.isfinite(arr) & ok))
        if bad.size:
            fail(path, lines[bad[0]], f"{name} = {arr[bad[0]]:g}: {why}")
    for kind, v in values.items():
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            fail(path, lines[bad[0]], f"{kind} = {v[bad[0]]}: not a finite number")
        j = _out_of_range(kind, v) if kind in _RANGES else None
        if j is not None:
            fail(path, lines[j], f"{kind} = {v[j]:g}: {_WHY[kind]}")
    for kind, s in sigmas.items():
        bad = np.flatnonzero(~(np.isfinite(s) & (s > 0)))
        if bad.size:
            fail(path, lines[bad[0]], f"the standard deviation of {kind} = {s[bad[0]]:g}: must be finite and positive")
    kinds = tuple(k for k in KINDS if k in values)
    V = np.stack([values[k] for k in kinds])
    S = np.stack([sigmas[k] for k in kinds]) if sigmas and set(sigmas) >= set(kinds) else None
    extra = {k: np.asarray(v, np.float64) for k, v in (extra or {}).items()}
    meta = {"format": fmt, **(meta or {})}
    sites = xy = None
    if group is not None:
        group = np.asarray(group)
        labels = list(dict.fromkeys(group.tolist()))
        idx = [np.flatnonzero(group == lab) for lab in labels]
        P = len(idx[0])
        for lab, ix in zip(labels, idx):
            if len(ix) != P or not (np.allclose(wl[ix], wl[idx[0]], rtol=0, atol=1e-6)
                                    and np.allclose(aoi[ix], aoi[idx[0]], rtol=0, atol=1e-6)):
                fail(path, lines[ix[0]], f"{group_name} {lab} does not list the same (wavelength, angle) points, in the same "
                                        f"order, as {group_name} {labels[0]} (line {lines[idx[0][0]]}): every {group_name} of a "
                                        "file must")
        V = np.stack([V[:, ix] for ix in idx])
        S = None if S is None else np.stack([S[:, ix] for ix in idx])
        extra = {k: np.stack([v[ix] for ix in idx]) for k, v in extra.items()}
        sites = tuple(str(x) for x in labels)
        if group_xy is not None:
            xy = np.asarray([group_xy[lab] for lab in labels], np.float64)
        wl, aoi = wl[idx[0]], aoi[idx[0]]
        meta[group_name + "s"] = np.asarray(labels)
    meta.update(extra)
    return Spectra(wl, aoi, kinds, V, S, sites, str(path), xy, meta)

