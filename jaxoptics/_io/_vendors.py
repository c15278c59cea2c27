"""Readers of ellipsometers' text exports: J.A. Woollam (WVASE, CompleteEASE), Sentech
SpectraRay, Accurion nanofilm EP3/EP4, Horiba DeltaPsi2 and Film Sense. Each returns `Spectra` in
the instrument's convention (`_conventions`), with errors that name the file, the line and what
was expected. The layouts are those of the vendors' public example exports; `docs/data-files.md`
describes each.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ._conventions import Conventions, apply_delta_conventions, finish, mueller_to_ncs
from ._reflectance import _fail as fail


def read_lines(path: Path) -> list[str]:
    """The file's lines: UTF-8 (with or without a byte-order mark), else Windows-1252 (exports
    that write the micro sign or a degree sign in the local code page); any line ending."""
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise ValueError(f"{path}: cannot read ({e.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("cp1252", errors="replace")
    return text.splitlines()


def number(path, line, token, what):
    """A float from a token (a decimal comma accepted), or an error naming the line and column."""
    try:
        return float(token.replace(",", ".") if "," in token and "." not in token else token)
    except ValueError:
        fail(path, line, f"{what}: {token!r} is not a number")


# ---------------------------------------------------------------------------------------------
# J.A. Woollam WVASE and CompleteEASE .dat

_UNITS_NM = {"nm": lambda x: x, "angstroms": lambda x: x / 10, "angstrom": lambda x: x / 10, "a": lambda x: x / 10,
             "ev": lambda x: 1239.8419843320026 / x, "1/cm": lambda x: 1e7 / x, "cm-1": lambda x: 1e7 / x,
             "um": lambda x: 1000 * x, "µm": lambda x: 1000 * x, "microns": lambda x: 1000 * x}


def is_woollam(lines):
    return any(l.lstrip().startswith("VASEmethod[") for l in lines[:3])


def _vase_method(text):
    """The `VASEmethod[...]` header as a dict (`key=value` items; bare words map to True)."""
    inside = text.strip()[len("VASEmethod["):].rstrip("]")
    out = {}
    for item in inside.split(","):
        k, _, v = item.partition("=")
        if k.strip():
            out[k.strip()] = v.strip() if _ else True
    return out


def read_woollam(path, lines, conv: Conventions):
    """WVASE and CompleteEASE `.dat` exports (see `docs/data-files.md`): a title line, the
    `VASEmethod[...]` line, optional `Original[...]` and `Dynamic` lines, the units line (`nm`,
    `Angstroms`, `eV`, `1/cm`, `um`, optionally followed by `TRIG`), then rows `wavelength AOI Psi
    Delta [sigma_Psi sigma_Delta]` (plain or prefixed `E`; `tanPsi cosDelta` for `TRIG`; a time
    column last in `Dynamic` files), and `dPolE` (depolarization, %) and `uR` rows, either in
    blocks or interleaved (with AOI written 0)."""
    k = next(i for i, l in enumerate(lines[:3]) if l.lstrip().startswith("VASEmethod["))
    meta = {"title": lines[0].strip() if k > 0 else "", "VASEmethod": _vase_method(lines[k])}
    dynamic, trig, to_nm = False, False, None
    i = k + 1
    while i < len(lines) and to_nm is None:
        tok = lines[i].split()
        if not tok:
            i += 1
            continue
        if tok[0].startswith("Original["):
            meta["original"] = lines[i].strip()
        elif tok[0].lower() == "dynamic":
            dynamic = True
        elif tok[0].lower() in _UNITS_NM:
            to_nm = _UNITS_NM[tok[0].lower()]
            meta["units"] = tok[0]
            trig = len(tok) > 1 and tok[1].upper() == "TRIG"
            if len(tok) > 1 and not trig:
                fail(path, i + 1, f"the units line {lines[i].strip()!r}: after the unit only TRIG is known")
        else:
            fail(path, i + 1, f"expected the units line ({', '.join(sorted(_UNITS_NM))}, optionally with TRIG) after "
                              f"the VASEmethod line, got {lines[i].strip()!r}")
        i += 1
    if to_nm is None:
        raise ValueError(f"{path}: no units line (nm, Angstroms, eV, 1/cm) after the VASEmethod line")
    rows, extras = [], []  # (line, [numbers]); (line, prefix, [numbers])
    for j in range(i, len(lines)):
        tok = lines[j].split()
        if not tok:
            continue
        head = tok[0]
        if head == "E" or head[0].isdigit() or head[0] in "+-.":
            vals = tok[1:] if head == "E" else tok
            nums = [number(path, j + 1, t, f"column {c + 1}") for c, t in enumerate(vals)]
            time = None
            if dynamic:
                if len(nums) not in (5, 7):
                    fail(path, j + 1, f"{len(nums)} numbers; a Dynamic row is: wavelength AOI Psi Delta [sigma_Psi sigma_Delta] time")
                time, nums = nums[-1], nums[:-1]
            elif len(nums) not in (4, 6):
                fail(path, j + 1, f"{len(nums)} numbers; a data row is: wavelength AOI Psi Delta [sigma_Psi sigma_Delta]"
                                  + (" (tanPsi cosDelta for TRIG)" if trig else ""))
            rows.append((j + 1, nums, time))
        elif head.lower() in ("dpole", "ur"):
            nums = [number(path, j + 1, t, f"column {c + 2}") for c, t in enumerate(tok[1:])]
            if len(nums) not in (3, 4):
                fail(path, j + 1, f"a {head} row is: {head} wavelength AOI value [sigma], got {len(nums)} numbers")
            extras.append((j + 1, head.lower(), nums))
        else:
            fail(path, j + 1, f"unknown row {head!r}: known rows are numbers (wavelength AOI Psi Delta ...), E, dPolE and uR")
    if not rows:
        raise ValueError(f"{path}: no data rows after the units line")
    if len({len(r[1]) for r in rows}) > 1:
        ln = next(r[0] for r in rows if len(r[1]) != len(rows[0][1]))
        fail(path, ln, f"{len(next(r[1] for r in rows if r[0] == ln))} numbers, line {rows[0][0]} has {len(rows[0][1])}: "
                       "give sigma on every row or on none")
    line_no = np.asarray([r[0] for r in rows])
    A = np.asarray([r[1] for r in rows], np.float64)
    wl, aoi = to_nm(A[:, 0]), A[:, 1]
    if trig:
        t, cd = A[:, 2], A[:, 3]
        bad = np.flatnonzero((t < 0) | (np.abs(cd) > 1 + 1e-6))
        if bad.size:
            fail(path, line_no[bad[0]], f"tanPsi = {t[bad[0]]:g}, cosDelta = {cd[bad[0]]:g}: TRIG rows hold tanPsi >= 0 and cosDelta in [-1, 1]")
        u = 1 + t * t
        values = {"N": (1 - t * t) / u, "C": 2 * t / u * cd}
        sigmas = {}
        if A.shape[1] == 6:
            st, sc = A[:, 4], A[:, 5]
            sigmas = {"N": np.maximum(4 * t / u**2 * st, 1e-6),
                      "C": np.maximum(np.hypot(2 * (1 - t * t) / u**2 * cd * st, 2 * t / u * sc), 1e-6)}
        # cos Delta alone: the fold does not matter, the handedness does not either
        values, sigmas = apply_delta_conventions(path, line_no, values, sigmas, conv._replace(delta_range=None), fail)
        meta["trig"] = True
    else:
        values = {"psi_deg": A[:, 2], "delta_deg": A[:, 3]}
        sigmas = {"psi_deg": A[:, 4], "delta_deg": A[:, 5]} if A.shape[1] == 6 else {}
        values, sigmas = apply_delta_conventions(path, line_no, values, sigmas, conv, fail)
    extra: dict[str, np.ndarray] = {}
    if extras:
        key = {(round(float(w), 4), round(float(a), 4)): r for r, (w, a) in enumerate(zip(A[:, 0], A[:, 1]))}
        last = {}  # the latest data row of each wavelength, for rows with AOI written 0
        order = sorted([(r[0], "row", n) for n, r in enumerate(rows)] + [(e[0], "extra", n) for n, e in enumerate(extras)])
        for ln, what, n in order:
            if what == "row":
                last[round(float(A[n, 0]), 4)] = n
                continue
            _, kind, nums = extras[n]
            w, a = round(nums[0], 4), round(nums[1], 4)
            r = key.get((w, a)) if a != 0 else last.get(w)
            if r is None:
                fail(path, ln, f"this {kind} row (wavelength {nums[0]:g}, AOI {nums[1]:g}) matches no data row")
            name = "depolarization_percent" if kind == "dpole" else "uR"
            extra.setdefault(name, np.full(len(rows), np.nan))[r] = nums[2] if np.isfinite(nums[2]) else np.nan
            if kind == "dpole" and len(nums) == 4:
                extra.setdefault("depolarization_sigma_percent", np.full(len(rows), np.nan))[r] = nums[3]
    group = np.asarray([r[2] for r in rows]) if dynamic else None
    meta["conventions"] = conv._asdict()
    return finish(path, "woollam", wl, aoi, values, sigmas, line_no, group=group, group_name="time", meta=meta, extra=extra,
                  fail=fail)


# ---------------------------------------------------------------------------------------------
# Sentech SpectraRay ASCII

def is_spectraray(lines):
    return bool(lines) and lines[0].lstrip().startswith(";") and lines[0].lstrip(" ;").upper().startswith("WAVELENGTH")


def read_spectraray(path, lines, conv: Conventions):
    """SpectraRay ASCII exports: the first line `; WAVELENGTH` then, per column, its angle of
    incidence; Psi/Delta files name each angle twice (`a1 a1 a2 a2 ...`, rows `wavelength Psi1
    Delta1 Psi2 Delta2 ...`), normalized Mueller-matrix files sixteen times (rows `wavelength M11
    M12 ... M44`, row-major). A decimal comma is accepted."""
    angles = [number(path, 1, t, f"angle {c + 1} of the header") for c, t in enumerate(lines[0].lstrip(" ;").split()[1:])]
    if not angles:
        fail(path, 1, "the header names no angle of incidence after WAVELENGTH")
    mueller = len(angles) % 16 == 0 and all(len(set(angles[g:g + 16])) == 1 for g in range(0, len(angles), 16))
    width = 16 if mueller else 2
    if not mueller and (len(angles) % 2 or any(angles[g] != angles[g + 1] for g in range(0, len(angles), 2))):
        fail(path, 1, "a SpectraRay header names each angle twice (Psi and Delta columns) or sixteen times (a Mueller "
                      f"matrix); got {angles}")
    G = len(angles) // width
    data, line_no = [], []
    for j in range(1, len(lines)):
        tok = lines[j].split()
        if not tok or tok[0].startswith(";"):
            continue
        if len(tok) != 1 + len(angles):
            fail(path, j + 1, f"{len(tok)} columns, the header names {1 + len(angles)} (wavelength and one per angle entry)")
        data.append([number(path, j + 1, t, f"column {c + 1}") for c, t in enumerate(tok)])
        line_no.append(j + 1)
    if not data:
        raise ValueError(f"{path}: no data rows after the header")
    A = np.asarray(data)
    ln = np.tile(np.asarray(line_no), G)  # the points run angle-major: all wavelengths of the first angle, ...
    wl = np.tile(A[:, 0], G)
    aoi = np.repeat([angles[g * width] for g in range(G)], len(data))
    cols = [np.concatenate([A[:, 1 + g * width + e] for g in range(G)]) for e in range(width)]
    meta: dict[str, object] = {"conventions": conv._asdict()}
    if mueller:
        M = {f"m{r + 1}{c + 1}": cols[4 * r + c] for r in range(4) for c in range(4)}
        bad = np.flatnonzero(np.abs(M["m11"] - 1) > 1e-4)
        if bad.size:
            fail(path, ln[bad[0]], f"M11 = {M['m11'][bad[0]]:g}: the Mueller matrix must be normalized (M11 = 1)")
        values, _ = mueller_to_ncs(M, None, conv.mueller_s3_sign)
        meta["mueller"] = np.stack([np.stack([M[f"m{r + 1}{c + 1}"] for c in range(4)]) for r in range(4)])  # (4, 4, P)
        values, sigmas = apply_delta_conventions(path, ln, values, {}, conv, fail)
    else:
        values, sigmas = apply_delta_conventions(path, ln, {"psi_deg": cols[0], "delta_deg": cols[1]}, {}, conv, fail)
    return finish(path, "spectraray", wl, aoi, values, sigmas, ln, meta=meta, fail=fail)


# ---------------------------------------------------------------------------------------------
# Accurion nanofilm EP3/EP4 .ds.dat

def _is_accurion_wvase(lines):
    return len(lines) > 2 and [t for t in lines[1].split() if t] == ["nm", "Psi", "Delta"]


def is_accurion(lines):
    if _is_accurion_wvase(lines):
        return True
    if len(lines) < 2 or not lines[0].startswith("#") or not lines[1].startswith("#"):
        return False
    names = {c.strip().lstrip("#") for c in lines[0].split("\t")}
    return {"Lambda", "AOI", "Delta", "Psi"} <= names


# positions further apart than this (mm) are different sites of a map (the stage moves by about
# 0.01 mm between the angles of one site)
_SITE_STEP_MM = 0.2


def read_accurion(path, lines, conv: Conventions):
    """Accurion `.ds.dat` exports, tab-separated with a column-name row and a units row (both
    starting with `#`): the nulling layout (`Lambda, Bandwidth, AOI, Delta, Psi, Zone, ...,
    X_pos, Y_pos`; the zones of one point are averaged, Delta on the circle) and the imaging
    layout (`ROIidx, AOI, Lambda, ..., Delta, Psi`; each region of interest is a site of a map).
    A nulling file whose stage moved by more than 0.2 mm is a map: one site per position."""
    if _is_accurion_wvase(lines):
        return _read_accurion_wvase(path, lines, conv)
    names = [c.strip().lstrip("#") for c in lines[0].split("\t")]
    units = [c.strip().lstrip("#") for c in lines[1].split("\t")]
    col = {n: c for c, n in enumerate(names)}
    rows, line_no = [], []
    for j in range(2, len(lines)):
        tok = lines[j].split("\t")
        if not lines[j].strip() or lines[j].startswith("#"):
            continue
        if len(tok) != len(names):
            fail(path, j + 1, f"{len(tok)} columns, the header names {len(names)}")
        rows.append([number(path, j + 1, tok[col[n]], f"column {col[n] + 1} ({n})") for n in names])
        line_no.append(j + 1)
    if not rows:
        raise ValueError(f"{path}: no data rows after the header and units rows")
    A, ln = np.asarray(rows), np.asarray(line_no)
    if units[col["Lambda"]] not in ("nm", ""):
        fail(path, 2, f"the unit of Lambda is {units[col['Lambda']]!r}; nm expected")
    site = np.zeros(len(A), int)
    xy = None
    if "ROIidx" in col and len(set(A[:, col["ROIidx"]])) > 1:
        site = A[:, col["ROIidx"]].astype(int)
        layout = "imaging"
        if "ROI_x" in col and "ROI_y" in col:  # the region's place on the image, in micrometres (mm if the units say so)
            to_mm = 1.0 if units[col["ROI_x"]] == "mm" else 1e-3
            xy = {s: to_mm * A[site == s][:, [col["ROI_x"], col["ROI_y"]]].mean(axis=0) for s in np.unique(site)}
    elif "X_pos" in col and "Y_pos" in col:
        layout = "nulling"
        P = A[:, [col["X_pos"], col["Y_pos"]]]
        refs: list = []  # the first position of each site, in file order
        for r, pos in enumerate(P):
            near = [k for k, q in enumerate(refs) if np.hypot(*(pos - q)) <= _SITE_STEP_MM]
            if not near:
                refs.append(pos)
            site[r] = near[0] if near else len(refs) - 1
        xy = {s: P[site == s].mean(axis=0) for s in np.unique(site)}
    else:
        layout = "imaging" if "ROIidx" in col else "nulling"
    # one point per (site, wavelength, angle). Nulling files write zones 1-4, their average as
    # zone 0 (NaN where a zone did not null) and their range (max - min) as zone 5: a point is the
    # mean of the zones 1-4 that nulled (zone 0 where the file has no others), zone 5 goes to
    # meta; rows of the imaging layout are points.
    zone = A[:, col["Zone"]].astype(int) if "Zone" in col else np.ones(len(A), int)
    four = (zone >= 1) & (zone <= 4)
    use = four if four.any() else zone == 0
    spread = zone == 5
    key = np.stack([site, np.round(A[:, col["Lambda"]], 6), np.round(A[:, col["AOI"]], 6)], axis=1)
    ok = use & np.isfinite(A[:, col["Psi"]]) & np.isfinite(A[:, col["Delta"]])
    _, first, inv, counts = np.unique(key[use], axis=0, return_index=True, return_inverse=True, return_counts=True)
    order = np.argsort(first)  # points in file order
    inv = np.argsort(order)[inv.reshape(-1)]
    n = len(first)
    w = ok[use].astype(float)
    nvalid = np.bincount(inv, w, n)
    rows_use = np.flatnonzero(use)
    if np.any(nvalid == 0):
        p = int(np.flatnonzero(nvalid == 0)[0])
        fail(path, ln[rows_use[first[order][p]]], "Psi or Delta is NaN (the point did not null) in every zone of this point")
    Psi, D = np.nan_to_num(A[use, col["Psi"]]), np.deg2rad(np.nan_to_num(A[use, col["Delta"]]))
    psi = np.bincount(inv, w * Psi, n) / nvalid
    # Delta: the arithmetic mean of the zones, each taken within 180 degrees of their circular
    # mean (so zones on both sides of 0/360 average to a value between them)
    ref = np.arctan2(np.bincount(inv, w * np.sin(D), n), np.bincount(inv, w * np.cos(D), n))
    near = ref[inv] + (D - ref[inv] + np.pi) % (2 * np.pi) - np.pi
    delta = np.rad2deg(np.bincount(inv, w * near, n) / nvalid)
    # the circular mean keeps the file's range: a file without negative Delta stays in [0, 360)
    delta = np.where((delta < 0) & (np.nanmin(A[use, col["Delta"]]) >= 0), delta + 360, delta)
    first = rows_use[first]
    rows0 = first[order]
    values, sigmas = apply_delta_conventions(path, ln[rows0], {"psi_deg": psi, "delta_deg": delta}, {}, conv, fail)
    meta = {"layout": layout, "conventions": conv._asdict()}
    if "Zone" in col:
        meta["zones"] = "mean of the zones 1-4 that nulled" if four.any() else "zone 0 (the instrument's average)"
    extra = {}
    if spread.any():
        sk = {tuple(k): r for r, k in zip(np.flatnonzero(spread), key[spread])}
        for q in ("Psi", "Delta"):
            extra[f"zone_range_{q.lower()}_deg"] = np.asarray([A[sk[tuple(k)], col[q]] if tuple(k) in sk else np.nan
                                                               for k in key[rows0]])
    many = len(np.unique(site)) > 1
    return finish(path, "accurion", A[rows0, col["Lambda"]], A[rows0, col["AOI"]], values, sigmas, ln[rows0],
                  group=site[rows0] if many else None, group_xy=xy if many else None, meta=meta, extra=extra, fail=fail)


def _read_accurion_wvase(path, lines, conv):
    """The EP3/EP4 software's "WVASE format" export: a title line, the line `nm  Psi  Delta`, then
    rows `wavelength AOI Psi Delta`."""
    rows, ln = [], []
    for j in range(2, len(lines)):
        tok = lines[j].split()
        if not tok:
            continue
        if len(tok) != 4:
            fail(path, j + 1, f"{len(tok)} columns; a row is: wavelength AOI Psi Delta")
        rows.append([number(path, j + 1, t, name) for t, name in zip(tok, ("wavelength", "AOI", "Psi", "Delta"))])
        ln.append(j + 1)
    if not rows:
        raise ValueError(f"{path}: no data rows")
    A, ln = np.asarray(rows), np.asarray(ln)
    values, sigmas = apply_delta_conventions(path, ln, {"psi_deg": A[:, 2], "delta_deg": A[:, 3]}, {}, conv, fail)
    meta = {"layout": "wvase-format export", "title": lines[0].strip(), "conventions": conv._asdict()}
    return finish(path, "accurion", A[:, 0], A[:, 1], values, sigmas, ln, meta=meta, fail=fail)


# ---------------------------------------------------------------------------------------------
# Horiba DeltaPsi2 .spe

def is_horiba(lines):
    heads = {l.strip().rstrip(":").upper() for l in lines if l.startswith("#")}
    return "# DATA" in heads and any(h.startswith("# INCIDENCE ANGLE") for h in heads)


def read_horiba(path, lines, conv: Conventions):
    """DeltaPsi2 `.spe` exports: sections that start with a `# LABEL:` line and end at a blank
    line; `# INCIDENCE ANGLE:` holds the angle, `# DATA:` a space-separated table whose header
    names the columns `nm`, `Psi` and `Delta` (others are ignored)."""
    sections: dict[str, list] = {}
    cur = None
    for j, l in enumerate(lines):
        if l.startswith("#"):
            cur = l.lstrip("# ").strip().rstrip(":").upper()
            sections[cur] = []
        elif not l.strip():
            cur = None
        elif cur is not None:
            sections[cur].append((j + 1, l))
    angle_lines = sections.get("INCIDENCE ANGLE") or []
    m = re.search(r"[-+]?\d+(?:[.,]\d*)?", angle_lines[0][1]) if angle_lines else None
    if m is None:
        raise ValueError(f"{path}: the '# INCIDENCE ANGLE:' section holds no angle")
    angle = number(path, angle_lines[0][0], m.group(0), "the angle of incidence")
    data = sections.get("DATA") or []
    if len(data) < 2:
        raise ValueError(f"{path}: the '# DATA:' section has no header and rows")
    hline, header = data[0]
    names = header.split()
    for need in ("nm", "Psi", "Delta"):
        if need not in names:
            fail(path, hline, f"the data header {names} has no column {need!r}")
    c = {n: names.index(n) for n in ("nm", "Psi", "Delta")}
    rows, ln = [], []
    for j, l in data[1:]:
        tok = l.split()
        if len(tok) != len(names):
            fail(path, j, f"{len(tok)} columns, the data header names {len(names)}")
        rows.append([number(path, j, tok[c[n]], n) for n in ("nm", "Psi", "Delta")])
        ln.append(j)
    A, lines_no = np.asarray(rows), np.asarray(ln)
    values, sigmas = apply_delta_conventions(path, lines_no, {"psi_deg": A[:, 1], "delta_deg": A[:, 2]}, {}, conv, fail)
    meta: dict[str, object] = {k.lower(): " ".join(x for _, x in v) for k, v in sections.items() if k != "DATA"}
    meta["conventions"] = conv._asdict()
    return finish(path, "horiba", A[:, 0], np.full(len(A), angle), values, sigmas, lines_no, meta=meta, fail=fail)


# ---------------------------------------------------------------------------------------------
# Film Sense FS-1 / FS-8

def is_filmsense(lines):
    return bool(lines) and lines[0].strip() in ("Film_Sense_Data", "Film_Sense_Dyn_Data")


def read_filmsense(path, lines, conv: Conventions):
    """Film Sense exports. `Film_Sense_Data`: a line `n_wavelengths n_datasets AOI ...` (the
    angle written negative: its magnitude is used), one line per LED starting with its
    wavelength, then one line `N C S P Intensity` per LED. `Film_Sense_Dyn_Data`: the same header
    and LED lines, a column-name line, then per time a row `time` and `N C S P Intensity` for each
    LED (a time series: a leading axis). `N`, `C`, `S` are fitted as they are; `P` (the degree of
    polarization) is kept in `meta`."""
    dynamic = lines[0].strip() == "Film_Sense_Dyn_Data"
    tok = lines[1].split() if len(lines) > 1 else []
    if len(tok) < 3:
        fail(path, 2, "expected 'n_wavelengths n_datasets AOI ...'")
    nw, nd = int(number(path, 2, tok[0], "n_wavelengths")), int(number(path, 2, tok[1], "n_datasets"))
    aoi = abs(number(path, 2, tok[2], "AOI"))
    if len(lines) < 2 + nw:
        fail(path, len(lines), f"the header announces {nw} wavelengths; the file ends before their lines")
    wl = np.asarray([number(path, 3 + w, lines[2 + w].split()[0], "the LED's wavelength") for w in range(nw)])
    rows, ln, group = [], [], []
    if not dynamic:
        for w in range(nw * nd):
            j = 2 + nw + w
            if j >= len(lines):
                fail(path, j, f"the header announces {nd} data set(s) of {nw} lines; the file ends here")
            t = lines[j].split()
            if len(t) < 4:
                fail(path, j + 1, f"expected 'N C S P [Intensity]', got {lines[j].strip()!r}")
            rows.append([number(path, j + 1, x, name) for x, name in zip(t[:4], "NCSP")])
            ln.append(j + 1)
            group.append(w // nw)
    else:
        start = 2 + nw + 1  # the column-name line
        for d in range(nd):
            j = start + d
            if j >= len(lines):
                fail(path, j, f"the header announces {nd} times; the file ends here")
            t = lines[j].split()
            if len(t) < 1 + 5 * nw:
                fail(path, j + 1, f"{len(t)} columns; a row is the time and N C S P Intensity for each of {nw} LEDs")
            time = number(path, j + 1, t[0], "time")
            for w in range(nw):
                rows.append([number(path, j + 1, t[1 + 5 * w + q], name) for q, name in enumerate("NCSP")])
                ln.append(j + 1)
                group.append(time)
    A, lines_no = np.asarray(rows), np.asarray(ln)
    values, sigmas = apply_delta_conventions(path, lines_no, {"N": A[:, 0], "C": A[:, 1], "S": A[:, 2]}, {}, conv, fail)
    many = len(set(group)) > 1
    meta = {"nominal_aoi_written": float(tok[2]), "conventions": conv._asdict()}
    return finish(path, "filmsense", np.tile(wl, len(A) // nw), np.full(len(A), aoi), values, sigmas, lines_no,
                  group=np.asarray(group) if many else None, group_name="time" if dynamic else "dataset", meta=meta,
                  extra={"degree_of_polarization": A[:, 3]}, fail=fail)
