"""Tabulated optical constants from other tools' files (`load_nk`): plain columns of wavelength
and `n, k` or `e1, e2`, and SpectraRay `.mat` tables, with the sign convention of the imaginary
part as an explicit option."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .._films._dispersion import Tabulated
from ._vendors import fail, number, read_lines

_X_UNITS = {"nm": ("nm", 1.0), "um": ("nm", 1e3), "µm": ("nm", 1e3), "a": ("nm", 0.1), "angstroms": ("nm", 0.1),
            "ev": ("eV", 1.0), "1/cm": ("1/cm", 1.0), "cm-1": ("1/cm", 1.0)}


def _to_um(x, unit):
    kind, f = unit
    if kind == "eV":
        return 1.2398419843320026 / x
    if kind == "1/cm":
        return 1e4 / x
    return x * f / 1000


def load_nk(path: str | os.PathLike, *, wavelength_unit: str | None = None, k_sign: str | None = None,
            name: str | None = None) -> Tabulated:
    """Read a table of optical constants into a `Tabulated` material.

    **Formats** (detected):

    - Text columns (commas, tabs, semicolons or spaces; `#` comments): a header naming the first
      column with its unit (`wavelength_nm`, `Wavelength (um)`, `eV`, `cm-1`) and the others `n`,
      `k` or `e1`, `e2` (also `eps1`, `eps2`); without a header, three columns `x n k` and
      `wavelength_unit=` ("nm", "um", "eV", "1/cm").
    - SpectraRay `.mat`: a `Units=<x unit>,<NK or E1E2>` line, then rows `x v1 v2` between
      `Begin of array` and `End of array`.

    **Sign of the imaginary part** (`k_sign`): jaxoptics' index is `n + ik` with `k >= 0`
    absorbing (`eps2 >= 0`). Tools of the other time convention write the index `n - ik`; most
    still tabulate `k >= 0`, and then nothing changes (`k_sign="+"`), but some write absorption
    as negative `k` or `eps2` (`k_sign="-"`: the values' sign is flipped). With `k_sign=None` a
    table whose imaginary parts are all `>= 0` is read as it is, one whose nonzero imaginary parts
    are all negative is refused with a message naming `k_sign="-"`, and mixed signs (gain) are
    refused naming the line.

    **Returns:** `Tabulated` (wavelengths in micrometres, increasing; outside the table the index
    is NaN, and `fit_stack` refuses data beyond it).
    """
    path = Path(path)
    if k_sign not in (None, "+", "-"):
        raise ValueError(f"k_sign={k_sign!r}: must be '+', '-' or None")
    lines = read_lines(path)
    rows: list = []
    ln: list = []
    cols: tuple = ()
    unit = None
    if wavelength_unit is not None:
        if wavelength_unit.lower() not in _X_UNITS:
            raise ValueError(f"wavelength_unit={wavelength_unit!r}: must be one of nm, um, eV, 1/cm")
        unit = _X_UNITS[wavelength_unit.lower()]
    units_line = next((j for j, l in enumerate(lines) if l.strip().lower().startswith("units=")), None)
    if units_line is not None:  # SpectraRay .mat
        x_unit, _, rep = lines[units_line].split("=", 1)[1].partition(",")
        if x_unit.strip().lower() not in _X_UNITS:
            fail(path, units_line + 1, f"unit {x_unit.strip()!r}: known nm, um, eV, 1/cm")
        unit = unit or _X_UNITS[x_unit.strip().lower()]
        cols = ("e1", "e2") if rep.strip().upper() == "E1E2" else ("n", "k") if rep.strip().upper() == "NK" else ()
        if not cols:
            fail(path, units_line + 1, f"representation {rep.strip()!r}: NK or E1E2 expected")
        start = next((j for j, l in enumerate(lines) if l.strip().lower() == "begin of array"), None)
        end = next((j for j, l in enumerate(lines) if l.strip().lower() == "end of array"), len(lines))
        if start is None:
            raise ValueError(f"{path}: no 'Begin of array' line")
        body = [(j + 1, lines[j]) for j in range(start + 1, end) if lines[j].strip()]
    else:
        body = [(j + 1, l) for j, l in enumerate(lines) if l.strip() and not l.lstrip().startswith("#")]
        if not body:
            raise ValueError(f"{path}: no data rows")
        first = re.split(r"[,;\t]|\s+", body[0][1].strip())
        try:
            [float(t) for t in first]
        except ValueError:
            hline, names = body[0][0], [t.strip().lower() for t in re.split(r"[,;\t]", body[0][1].strip())]
            if len(names) == 1:
                names = body[0][1].lower().split()
            body = body[1:]
            m = re.search(r"(nm|um|µm|angstroms|ev|1/cm|cm-1)", names[0])
            if unit is None:
                if m is None:
                    fail(path, hline, f"column 1 ({names[0]!r}) does not give its unit (nm, um, eV, 1/cm); pass wavelength_unit=")
                else:
                    unit = _X_UNITS[m.group(1)]
            alias = {"n": "n", "k": "k", "e1": "e1", "e2": "e2", "eps1": "e1", "eps2": "e2", "epsilon1": "e1", "epsilon2": "e2"}
            got = tuple(alias.get(n.strip(), "?") for n in names[1:])
            if got not in (("n", "k"), ("e1", "e2"), ("n",)):
                fail(path, hline, f"columns {names[1:]}: expected n, k or e1, e2 after the wavelength")
            cols = got
        else:
            if unit is None:
                fail(path, body[0][0], "no header line: pass wavelength_unit= ('nm', 'um', 'eV' or '1/cm')")
            cols = ("n", "k")[: len(first) - 1]
    for j, l in body:
        tok = [t for t in re.split(r"[,;\t]|\s+", l.strip()) if t]
        if len(tok) != 1 + len(cols):
            fail(path, j, f"{len(tok)} columns; rows are: wavelength {' '.join(cols)}")
        rows.append([number(path, j, t, f"column {c + 1}") for c, t in enumerate(tok)])
        ln.append(j)
    if len(rows) < 2:
        raise ValueError(f"{path}: fewer than two rows")
    A, ln_arr = np.asarray(rows), np.asarray(ln)
    lam = _to_um(A[:, 0], unit)
    if cols[0] == "e1":
        im = A[:, 2]
    else:
        im = A[:, 2] if len(cols) == 2 else np.zeros(len(A))
    if k_sign is None:
        neg, pos = im < 0, im > 0
        if neg.any() and not pos.any():
            fail(path, ln_arr[np.argmax(neg)], f"{cols[-1]} = {im[np.argmax(neg)]:g}: every nonzero {cols[-1]} is negative, as "
                                               "tools of the n - ik convention write absorption; pass k_sign='-' to read "
                                               "them as absorbing (or '+' if the material has gain)")
        if neg.any():
            fail(path, ln_arr[np.argmax(neg)], f"{cols[-1]} = {im[np.argmax(neg)]:g} while others are positive: a gain medium is "
                                               "not supported")
    elif k_sign == "-":
        im = -im
    if cols[0] == "e1":
        N = np.sqrt(A[:, 1] + 1j * im)  # the principal root: n > 0, k >= 0 for eps2 >= 0
        n, k = N.real, N.imag
    else:
        n, k = A[:, 1], im
    order = np.argsort(lam)
    lam, n, k = lam[order], n[order], k[order]
    if np.any(np.diff(lam) <= 0):
        raise ValueError(f"{path}: a wavelength appears twice")
    label = name or path.stem
    return Tabulated((lam, n), (lam, k) if np.any(k != 0) else None, name=label, reference=str(path))
