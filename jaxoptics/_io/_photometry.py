"""Readers of spectrophotometers' exports: reflectance and transmittance against wavelength, as
delimited text (two or more columns) or JCAMP-DX. Whether values are fractions or percent is read
from the file (a `%` in a column name or in JCAMP's `##YUNITS`), or from values above 1.5 (stated
in `meta["scale"]`), or given as `scale=`; a file that says nothing and whose values could be
either is refused rather than guessed. The angle of incidence and, where the column names do not
say, the quantity (`R`, `T`, `R_s`, ...) are given by the user.
"""

from __future__ import annotations

import re

import numpy as np

from ._conventions import finish
from ._vendors import fail, number, read_lines

_PHOTO = ("R", "R_s", "R_p", "T", "T_s", "T_p")
_WL_UNITS = {"nm": 1.0, "nanometers": 1.0, "um": 1e3, "µm": 1e3, "micrometers": 1e3, "microns": 1e3, "a": 0.1,
             "angstroms": 0.1}
_DECIMAL_COMMA = re.compile(r"^[-+]?\d*,?\d+(?:[eE][-+]?\d+)?$")
# values above this cannot be fractions (noise on a reflectance near 1 stays well below it)
_PERCENT_ABOVE = 1.5


def _quantity(name):
    """The quantity (`R`, `T`, `R_s`, ...) a column name means, and whether it says percent; None
    when the name is not one."""
    s = name.strip().lower()
    percent = "%" in s
    s = re.sub(r"[\s_\-\[\]\(\)%]|percent|fraction", "", s)
    for q, words in (("R_s", ("rs", "reflectances", "rte")), ("R_p", ("rp", "reflectancep", "rtm")),
                     ("T_s", ("ts", "transmittances", "tte")), ("T_p", ("tp", "transmittancep", "ttm")),
                     ("R", ("r", "reflectance", "refl", "reflection")), ("T", ("t", "transmittance", "trans", "transmission"))):
        if s in words:
            return q, percent
    return None


def _wavelength_unit(name):
    """The factor to nm of a wavelength column name (`wavelength_nm`, `Wavelength (um)`, `nm`,
    `lambda [A]`), or of a wavenumber column (`cm-1`, `1/cm`: returned as the string "1/cm");
    None when the name gives no unit."""
    s = name.strip().lower()
    if re.search(r"cm-1|cm\^-1|1/cm|wavenumber", s):
        return "1/cm"
    m = re.search(r"(?:^|[\s_\(\[])(nm|nanometers|um|µm|micrometers|microns|a|angstroms)(?:$|[\s\)\]])", s)
    return _WL_UNITS[m.group(1)] if m else None


def _scale(path, line, V, kinds, percent_named, scale, where):
    """Values as fractions; `meta["scale"]` says how the scale was decided."""
    if scale is not None:
        if scale not in ("fraction", "percent"):
            raise ValueError(f"scale={scale!r}: must be 'fraction' or 'percent'")
        how = f"{scale} (given)"
    elif percent_named:
        scale, how = "percent", f"percent ({where})"
    elif np.nanmax(V) > _PERCENT_ABOVE:
        scale, how = "percent", f"percent (values up to {np.nanmax(V):g}; fractions lie in [0, 1])"
    else:
        fail(path, line, f"cannot tell fractions from percent: the {', '.join(kinds)} values lie in [{np.nanmin(V):g}, "
                         f"{np.nanmax(V):g}] and the file does not say; pass scale='fraction' or scale='percent'")
    return (V / 100 if scale == "percent" else V), how


def _need_angle(path, angle_deg):
    if angle_deg is None:
        raise ValueError(f"{path}: the file does not give the angle of incidence; pass angle_deg= (for example 8 for a "
                         "spectrophotometer's near-normal reflectance accessory, 0 for transmittance at normal incidence)")
    return float(angle_deg)


def read_text(path, lines, *, angle_deg=None, quantity=None, scale=None, wavelength_unit=None):
    """Delimited text (commas, tabs, semicolons or spaces; a decimal comma with semicolons or
    tabs): optional comment lines (`#`, `;`, `//`), an optional header line naming the columns
    (a wavelength with its unit, then `R`, `T`, `R_s`, ..., `%R`, `Reflectance (%)`, ...), then
    rows `wavelength value [value ...]`. Without a header give `wavelength_unit=` ("nm", "um",
    "1/cm") and `quantity=` (one name, or one per value column)."""
    body = [(j + 1, l) for j, l in enumerate(lines) if l.strip() and not l.lstrip().startswith(("#", ";", "//"))]
    if not body:
        raise ValueError(f"{path}: no data rows (the file is empty or all comments)")

    def split(l):
        if "\t" in l:
            return [t.strip() for t in l.split("\t")]
        if ";" in l:
            return [t.strip() for t in l.split(";")]
        ws = l.split()
        if "," in l and not (len(ws) > 1 and all(_DECIMAL_COMMA.match(t) for t in ws)):
            return [t.strip() for t in l.split(",")]
        return ws

    first = split(body[0][1])
    try:
        [float(t.replace(",", ".")) for t in first]
        header = None
    except ValueError:
        header, body = (body[0][0], first), body[1:]
    rows, ln = [], []
    for j, l in body:
        tok = split(l)
        rows.append([number(path, j, t, f"column {c + 1}") for c, t in enumerate(tok)])
        ln.append(j)
        if len(tok) != len(rows[0]):
            fail(path, j, f"{len(tok)} columns, line {ln[0]} has {len(rows[0])}")
    if not rows:
        raise ValueError(f"{path}: no data rows after the header")
    A, ln = np.asarray(rows), np.asarray(ln)
    if A.shape[1] < 2:
        fail(path, ln[0], "one column; rows are: wavelength value [value ...]")
    nv = A.shape[1] - 1
    percent_named = False
    if header is not None:
        hline, names = header
        unit = _wavelength_unit(names[0]) if wavelength_unit is None else None
        if wavelength_unit is None and unit is None:
            fail(path, hline, f"column 1 ({names[0]!r}) does not give the wavelength's unit (nm, um, A, 1/cm); rename it "
                              "(e.g. wavelength_nm) or pass wavelength_unit=")
        found = [_quantity(n) for n in names[1:]]
        if quantity is None:
            for c, (n, f) in enumerate(zip(names[1:], found), 2):
                if f is None:
                    fail(path, hline, f"column {c} ({n!r}) is not a known quantity (R, T, R_s, R_p, T_s, T_p, Reflectance, "
                                      "%T, ...); rename it or pass quantity=")
            kinds = [f[0] for f in found]
            percent_named = all(f[1] for f in found)
            if any(f[1] for f in found) and not percent_named:
                fail(path, hline, "some columns say percent and some do not; give scale=")
    else:
        hline = ln[0]
        unit = None
        if wavelength_unit is None:
            fail(path, hline, "no header line: pass wavelength_unit= ('nm', 'um' or '1/cm') and quantity= (e.g. 'R')")
    if wavelength_unit is not None:
        if wavelength_unit not in ("nm", "um", "1/cm"):
            raise ValueError(f"wavelength_unit={wavelength_unit!r}: must be 'nm', 'um' or '1/cm'")
        unit = {"nm": 1.0, "um": 1e3, "1/cm": "1/cm"}[wavelength_unit]
    if quantity is not None:
        kinds = [quantity] * nv if isinstance(quantity, str) else list(quantity)
        if len(kinds) != nv or any(k not in _PHOTO for k in kinds):
            raise ValueError(f"quantity={quantity!r}: give one of {_PHOTO}, or one per value column ({nv})")
    elif header is None:
        fail(path, hline, "no header line: pass quantity= (e.g. 'R' or 'T_s')")
    if len(set(kinds)) != len(kinds):
        fail(path, hline, f"the columns name the same quantity twice: {kinds}")
    wl = 1e7 / A[:, 0] if unit == "1/cm" else A[:, 0] * unit
    V, how = _scale(path, hline, A[:, 1:], kinds, percent_named, scale, "the column names say %")
    values = {k: V[:, c] for c, k in enumerate(kinds)}
    angle = _need_angle(path, angle_deg)
    return finish(path, "text", wl, np.full(len(A), angle), values, {}, ln, meta={"scale": how}, fail=fail)


def read_jcamp(path, *, angle_deg=None, quantity=None, scale=None):
    """JCAMP-DX spectra (`##XYDATA` in any of the standard's compressions, read with the `jcamp`
    package): `##XUNITS` NANOMETERS, MICROMETERS or 1/CM; `##YUNITS` REFLECTANCE or
    TRANSMITTANCE (fractions) or %R, %T, PERCENT ... (percent). Absorbance is refused."""
    try:
        import jcamp
    except ImportError:
        raise ImportError("reading JCAMP-DX needs the jcamp package: pip install 'jaxoptics[instruments]'") from None
    try:
        d = jcamp.readfile(str(path))
    except Exception as e:  # the package raises many kinds on a malformed file
        raise ValueError(f"{path}: not a readable JCAMP-DX file ({type(e).__name__}: {e})") from None
    if "x" not in d or "y" not in d or len(d["x"]) == 0:
        raise ValueError(f"{path}: no ##XYDATA (or ##XYPOINTS) block")
    xu, yu = str(d.get("xunits", "")).strip().upper(), str(d.get("yunits", "")).strip().upper()
    lines = read_lines(path)
    yline = next((j + 1 for j, l in enumerate(lines) if l.upper().startswith("##YUNITS")), 1)
    xline = next((j + 1 for j, l in enumerate(lines) if l.upper().startswith("##XUNITS")), 1)
    if xu in ("NANOMETERS", "NM"):
        wl = np.asarray(d["x"], np.float64)
    elif xu in ("MICROMETERS", "UM", "MICRONS"):
        wl = 1e3 * np.asarray(d["x"], np.float64)
    elif xu in ("1/CM", "CM-1", "CM^-1"):
        wl = 1e7 / np.asarray(d["x"], np.float64)
    else:
        fail(path, xline, f"##XUNITS={xu or '(missing)'}: NANOMETERS, MICROMETERS or 1/CM expected")
    pct = "%" in yu or "PERCENT" in yu
    guess = "R" if "REFL" in yu or yu in ("%R", "R") else "T" if "TRANS" in yu or yu in ("%T", "T") else None
    if "ABSORB" in yu:
        fail(path, yline, f"##YUNITS={yu}: absorbance is not a reflectance or transmittance; convert it (T = 10^-A)")
    kind = quantity or guess
    if kind is None:
        fail(path, yline, f"##YUNITS={yu or '(missing)'} does not say reflectance or transmittance; pass quantity=")
    if kind not in _PHOTO:
        raise ValueError(f"quantity={kind!r}: must be one of {_PHOTO}")
    Y = np.asarray(d["y"], np.float64)
    V, how = _scale(path, yline, Y, [kind], pct, scale, f"##YUNITS={yu}")
    ln = np.full(len(Y), yline)  # points of compressed data have no line of their own
    meta = {"scale": how, "title": d.get("title", ""), "jcamp": {k: v for k, v in d.items() if k not in ("x", "y")}}
    return finish(path, "jcamp", wl, np.full(len(Y), _need_angle(path, angle_deg)), {kind: V}, {}, ln, meta=meta, fail=fail)


def is_jcamp(lines):
    return any(l.lstrip().startswith("##TITLE") or l.lstrip().startswith("##JCAMP") for l in lines[:5])

