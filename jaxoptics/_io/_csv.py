"""jaxoptics' own CSV format of spectra (`format="csv"` of `load_spectra`)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from ._conventions import Conventions, apply_delta_conventions, mueller_to_ncs
from ._reflectance import _fail, _header_names
from ._spectra import _MUELLER, _NEAR, _RANGES, _WHY, KINDS, Spectra, _out_of_range


def read_csv(path: Path, conv: Conventions) -> Spectra:
    """Read spectroscopic data from jaxoptics' CSV format into `Spectra` (`format="csv"` of
    `load_spectra`).

    The first non-comment line is the header (lines starting with `#` are comments). Columns:

    - `wavelength_nm` or `wavelength_um` (one of them, required) and `angle_deg` (required);
    - measured quantities, any of `psi_deg, delta_deg, N, C, S, R, R_s, R_p, T, T_s, T_p`, or the
      normalized Mueller matrix `m11 ... m44` (converted to `N, C, S`, see the module docstring);
    - `sigma_<quantity>` (e.g. `sigma_psi_deg`), optional, for each measured quantity or none;
    - `site`, optional: a label of the map point; every site must list the same
      `(wavelength, angle)` points in the same order;
    - `x_mm`, `y_mm`, optional (both or neither, with `site`): the site's position on the sample,
      the same on every row of a site (`Spectra.site_xy`; `plot_stack_map` draws maps with them).

    Errors name the file, the line and the column: a cell that is not a number, a row with NaN
    (rejected, with its line), a row of the wrong length, an unknown column, a header separated
    by semicolons or tabs, angles outside `[0, 90)`, a value outside its quantity's range by more
    than noise (5% of the range: Psi in [0, 90] degrees, N, C, S and normalized Mueller elements
    in [-1, 1], R and T in [0, 1]), sites with different points, a site whose rows give
    different positions.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise ValueError(f"{path}: cannot read ({e.strerror})") from None
    lines = [(i, l) for i, l in enumerate(text.splitlines(), 1) if l.strip() and not l.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path}: no header line (the file is empty or all comments)")
    hline, header_text = lines[0]
    header = _header_names(path, hline, header_text)
    for j, h in enumerate(header, 1):
        ok = h in KINDS or h in _MUELLER or h in ("wavelength_nm", "wavelength_um", "angle_deg", "site", "x_mm", "y_mm") or (
            h.startswith("sigma_") and h[6:] in KINDS + _MUELLER)
        if not ok:
            hint = _NEAR.get(h.lower())
            hint = f" (did you mean {hint}?)" if hint else ""
            _fail(path, hline, f"column {j} {h!r} is not a known column{hint}; known: wavelength_nm | wavelength_um, angle_deg, site, x_mm, y_mm, "
                               f"{', '.join(KINDS)}, m11..m44, sigma_<quantity>")
    if len(set(header)) != len(header):
        _fail(path, hline, f"a column name appears twice in {header}")
    wl_cols = [h for h in header if h.startswith("wavelength_")]
    if len(wl_cols) != 1:
        _fail(path, hline, "give exactly one of the columns wavelength_nm, wavelength_um")
    if "angle_deg" not in header:
        _fail(path, hline, "missing column angle_deg (angle of incidence in degrees)")
    if ("x_mm" in header) != ("y_mm" in header):
        _fail(path, hline, "give both site position columns x_mm and y_mm, or neither")
    if "x_mm" in header and "site" not in header:
        _fail(path, hline, "x_mm and y_mm give the positions of sites: add a site column")
    measured = [h for h in header if h in KINDS or h in _MUELLER]
    if not measured:
        _fail(path, hline, f"no measured quantity; give one or more of {', '.join(KINDS)} or m11..m44")
    num = [h for h in header if h != "site"]
    cols: dict[str, list[float]] = {h: [] for h in num}
    site_col: list[str] = []
    line_no: list[int] = []
    for i, l in lines[1:]:
        cells = next(csv.reader([l]))
        if len(cells) != len(header):
            _fail(path, i, f"{len(cells)} cells, the header has {len(header)}")
        for j, (h, c) in enumerate(zip(header, cells), 1):
            c = c.strip()
            if h == "site":
                site_col.append(c)
                continue
            try:
                v = float(c)
            except ValueError:
                _fail(path, i, f"column {j} ({h}): {c!r} is not a number")
            if math.isnan(v):
                _fail(path, i, f"column {j} ({h}) is NaN; rows with missing values are rejected: remove the row or fill it")
            if math.isinf(v):
                _fail(path, i, f"column {j} ({h}) is infinite")
            cols[h].append(v)
        line_no.append(i)
    if not line_no:
        raise ValueError(f"{path}: no data rows after the header (line {hline})")
    A = {h: np.asarray(v, np.float64) for h, v in cols.items()}
    lines_arr = np.asarray(line_no)
    wl = A[wl_cols[0]] * (1000.0 if wl_cols[0] == "wavelength_um" else 1.0)
    for name, bad in (("wavelength", ~(wl > 0)), ("angle_deg", ~((A["angle_deg"] >= 0) & (A["angle_deg"] < 90)))):
        if bad.any():
            k = int(np.argmax(bad))
            col = wl_cols[0] if name == "wavelength" else "angle_deg"
            _fail(path, lines_arr[k], f"column {header.index(col) + 1} ({col}) = {A[col][k]}: must be "
                  + ("positive" if name == "wavelength" else "in [0, 90) degrees"))
    # quantities: the named ones, then N, C, S from a Mueller matrix
    values: dict[str, np.ndarray] = {}
    sigmas: dict[str, np.ndarray] = {}
    for kind in KINDS:
        if kind in A:
            values[kind] = A[kind]
            if "sigma_" + kind in A:
                sigmas[kind] = A["sigma_" + kind]
    mu = [m for m in _MUELLER if m in A]
    if mu:
        if "m11" in A and np.any(np.abs(A["m11"] - 1) > 1e-6):
            row = int(np.argmax(np.abs(A["m11"] - 1) > 1e-6))
            _fail(path, lines_arr[row], f"m11 = {A['m11'][row]}: the Mueller matrix must be normalized (m11 = 1)")
        mv, ms = mueller_to_ncs({m: A[m] for m in mu}, {m: A["sigma_" + m] for m in mu if "sigma_" + m in A}, conv.mueller_s3_sign)
        for q in mv:
            if q not in values:
                values[q] = mv[q]
                if q in ms:
                    sigmas[q] = ms[q]
        if not any(q in values for q in ("N", "C", "S")):
            _fail(path, hline, "Mueller columns given without any of m12, m21, m33, m44, m34, m43 (the isotropic elements)")
    for kind in header:
        stray = _out_of_range(kind, A[kind]) if kind in _RANGES else None
        if stray is not None:
            _fail(path, lines_arr[stray], f"column {header.index(kind) + 1} ({kind}) = {A[kind][stray]:g}: {_WHY[kind]}")
    if sigmas and set(sigmas) != set(values):
        missing = sorted(set(values) - set(sigmas))
        _fail(path, hline, f"sigma columns are given for some quantities but not for {missing}: give all or none")
    for kind, sg in sigmas.items():
        if np.any(sg <= 0):
            j = int(np.argmax(sg <= 0))
            _fail(path, lines_arr[j], f"sigma of {kind} = {sg[j]}: must be positive")
    values, sigmas = apply_delta_conventions(path, lines_arr, values, sigmas, conv, _fail)
    kinds = tuple(k for k in KINDS if k in values)
    V = np.stack([values[k] for k in kinds])  # (Q, rows)
    S = np.stack([sigmas[k] for k in kinds]) if sigmas else None
    a = A["angle_deg"]
    sites: tuple | None = None
    xy = None
    if site_col:
        labels = list(dict.fromkeys(site_col))
        idx = [np.flatnonzero(np.asarray(site_col) == lab) for lab in labels]
        P = len(idx[0])
        for lab, ix in zip(labels, idx):
            if len(ix) != P or not (np.array_equal(wl[ix], wl[idx[0]]) and np.array_equal(a[ix], a[idx[0]])):
                _fail(path, lines_arr[ix[0]], f"site {lab!r} does not list the same (wavelength, angle) points, in the same order, "
                      f"as site {labels[0]!r}")
        if "x_mm" in A:
            for lab, ix in zip(labels, idx):
                for c in ("x_mm", "y_mm"):
                    moved = np.flatnonzero(A[c][ix] != A[c][ix[0]])
                    if moved.size:
                        r = ix[moved[0]]
                        _fail(path, lines_arr[r], f"column {header.index(c) + 1} ({c}) = {A[c][r]}: site {lab!r} is at {c} = "
                              f"{A[c][ix[0]]} on line {lines_arr[ix[0]]}; a site has one position")
            xy = np.stack([[A["x_mm"][ix[0]], A["y_mm"][ix[0]]] for ix in idx])
        V = np.stack([V[:, ix] for ix in idx])
        S = None if S is None else np.stack([S[:, ix] for ix in idx])
        wl, a, sites = wl[idx[0]], a[idx[0]], tuple(labels)
    return Spectra(wl, a, kinds, V, S, sites, str(path), xy, {"format": "csv", "conventions": conv._asdict()})
