"""Reading reflectance measurements from CSV, with errors that name the file, line and value."""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

REQUIRED = ("angle_deg", "R")
OPTIONAL = ("polarization", "wavelength_um", "sigma")
_POL_ALIASES = {"s": "s", "te": "s", "p": "p", "tm": "p", "u": "unpolarized", "unpolarized": "unpolarized",
                "unpol": "unpolarized", "n": "unpolarized"}
_NEAR_MISSES = {"angle": "angle_deg", "theta": "angle_deg", "angle_rad": "angle_deg (in degrees)",
                "theta_deg": "angle_deg", "r": "R", "reflectance": "R", "lambda_um": "wavelength_um",
                "wavelength": "wavelength_um (in micrometres)", "wavelength_nm": "wavelength_um (in micrometres)",
                "pol": "polarization", "err": "sigma", "error": "sigma", "std": "sigma"}


class Curve(NamedTuple):
    """One reflectance curve: a single polarization and wavelength, sorted by angle.

    **Fields:**

    - `theta`: angles of incidence in radians, `(m,)`, ascending.
    - `R`: reflectance, `(m,)`.
    - `sigma`: standard deviation of each `R`, `(m,)`, or `None` when the file has no sigma column.
    - `polarization`: `"s"`, `"p"` or `"unpolarized"`.
    - `wavelength_um`: vacuum wavelength in micrometres, or `None` when the file has no wavelength.
    - `lines`: the CSV line number of each point, `(m,)`, for error messages.
    """

    theta: np.ndarray  # radians
    R: np.ndarray
    sigma: np.ndarray | None
    polarization: str
    wavelength_um: float | None
    lines: np.ndarray  # the CSV line of each point, for messages


class ReflectanceData(NamedTuple):
    """The rows of a reflectance CSV file, in file order (see `load_reflectance`).

    **Fields:** `path`; `angle_deg` (degrees), `R`, and the optional columns `sigma`,
    `polarization` (strings) and `wavelength_um` (micrometres), each `(rows,)` or `None` when
    absent; `lines`, the CSV line number of each row; `ignored_columns`, header names that were
    not used.

    **Properties and methods:** `theta` (radians); `curves()` splits the rows into `Curve`s, one
    per (wavelength, polarization), each sorted by angle.
    """

    path: str
    angle_deg: np.ndarray
    R: np.ndarray
    sigma: np.ndarray | None
    polarization: np.ndarray | None
    wavelength_um: np.ndarray | None
    lines: np.ndarray
    ignored_columns: tuple

    @property
    def theta(self):
        """Angles in radians."""
        return np.deg2rad(self.angle_deg)

    def curves(self, *, default_polarization="unpolarized") -> list[Curve]:
        """The data split into curves by (wavelength, polarization), each sorted by angle."""
        pol = self.polarization if self.polarization is not None else np.full(self.R.shape, default_polarization)
        lam = self.wavelength_um if self.wavelength_um is not None else np.full(self.R.shape, np.nan)
        out = []
        # (no wavelength is None, not NaN: NaN != NaN, so a set would keep one key per row)
        keys = sorted({(None if math.isnan(l) else float(l), str(p)) for l, p in zip(lam, pol)},
                      key=lambda k: (-1.0 if k[0] is None else k[0], k[1]))
        for l, p in keys:
            sel = (pol == p) & (np.isnan(lam) if l is None else (lam == l))
            order = np.argsort(self.angle_deg[sel], kind="stable")
            out.append(Curve(np.deg2rad(self.angle_deg[sel][order]), self.R[sel][order],
                             None if self.sigma is None else self.sigma[sel][order], p, l, self.lines[sel][order]))
        return out


def _fail(path, line, msg):
    raise ValueError(f"{path}, line {line}: {msg}")


def _header_names(path, line, text):
    """The column names of a CSV header line; a line that holds one name with semicolons or tabs in
    it (a file in another locale's or a spreadsheet's format) is refused, naming the separator."""
    names = [h.strip() for h in next(csv.reader([text]))]
    if len(names) == 1:
        for sep, what in ((";", "semicolons"), ("\t", "tabs")):
            if sep in names[0]:
                _fail(path, line, f"columns are separated by commas; this header, {text.strip()!r}, separates them by {what}")
    return names


def load_reflectance(path: str | os.PathLike, *, r_tolerance: float = 0.05) -> ReflectanceData:
    r"""Read reflectance measurements from a CSV file.

    The first line that is not blank and not a `#` comment is the header. Columns (any order):
    `angle_deg` (angle of incidence, degrees, in [0, 90]) and `R` (reflectance) are required;
    `polarization` (`s`, `p` or `unpolarized`; `TE`/`TM` accepted), `wavelength_um` (micrometres)
    and `sigma` (standard deviation of `R`, positive) are optional. Other columns are ignored and
    listed in `ignored_columns`.

    **Arguments:** `path`; `r_tolerance`: how far outside [0, 1] a measured `R` may lie (noise)
    before it is refused (default 0.05).

    **Returns:** a `ReflectanceData`; `.curves()` splits it by wavelength and polarization.

    **Errors:** a `ValueError` naming the file, the line, the column and the value for: an empty
    file, a missing required column, a header separated by semicolons or tabs rather than commas,
    a row with the wrong number of fields, a value that is not a number, NaN or infinity, an
    angle outside [0, 90], `R` outside [-tol, 1 + tol], a `sigma` that is not positive, a
    wavelength that is not positive, an unknown polarization.
    """
    path = str(path)
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{path}: no such file")
    text = p.read_text(encoding="utf-8-sig").splitlines()
    rows = [(k + 1, line) for k, line in enumerate(text) if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise ValueError(f"{path}: the file is empty (no header, no data)")
    header_line, header = rows[0]
    names = _header_names(path, header_line, header)
    lookup = {n.lower(): k for k, n in enumerate(names)}
    cols = {}
    for want in REQUIRED + OPTIONAL:
        if want.lower() in lookup:
            cols[want] = lookup[want.lower()]
    for want in REQUIRED:
        if want not in cols:
            hint = [f"{n!r} (did you mean {_NEAR_MISSES[n.lower()]}?)" for n in names if n.lower() in _NEAR_MISSES]
            raise ValueError(
                f"{path}, line {header_line}: missing required column {want!r}; the header has {names}"
                + (f"; {', '.join(hint)}" if hint else "")
            )
    ignored = tuple(n for k, n in enumerate(names) if k not in cols.values())
    if len(rows) < 2:
        raise ValueError(f"{path}: a header but no data rows")
    data: dict[str, list] = {k: [] for k in cols}
    lines: list[int] = []
    for line_no, line in rows[1:]:
        fields = next(csv.reader([line]))
        if len(fields) != len(names):
            _fail(path, line_no, f"{len(fields)} fields, but the header (line {header_line}) has {len(names)}: {line.strip()!r}")
        for name, k in cols.items():
            raw = fields[k].strip()
            where = f"column {k + 1} ({name})"
            if name == "polarization":
                pol = _POL_ALIASES.get(raw.lower())
                if pol is None:
                    _fail(path, line_no, f"{where}: unknown polarization {raw!r} (use s, p or unpolarized)")
                data[name].append(pol)
                continue
            try:
                v = float(raw)
            except ValueError:
                _fail(path, line_no, f"{where}: {raw!r} is not a number")
            if not math.isfinite(v):
                _fail(path, line_no, f"{where}: {raw!r} is not finite")
            if name == "angle_deg" and not 0 <= v <= 90:
                _fail(path, line_no, f"{where}: angle {v} deg is outside [0, 90]")
            if name == "R" and not -r_tolerance <= v <= 1 + r_tolerance:
                _fail(path, line_no, f"{where}: reflectance {v} is outside [0, 1] by more than {r_tolerance}")
            if name in ("sigma", "wavelength_um") and not v > 0:
                _fail(path, line_no, f"{where}: {v} must be positive")
            data[name].append(v)
        lines.append(line_no)
    arr = lambda n, dt=np.float64: None if n not in data else np.asarray(data[n], dtype=dt)
    return ReflectanceData(path, np.asarray(data["angle_deg"], np.float64), np.asarray(data["R"], np.float64), arr("sigma"), arr("polarization", object),
                           arr("wavelength_um"), np.asarray(lines), ignored)


def example_path() -> Path:
    """Path of the bundled example measurement: reflectance of N-BK7 glass against angle, s and p
    polarization, with the columns of `load_reflectance` (its comment lines give the source).
    `python -m jaxoptics fit --example` fits it."""
    return Path(__file__).parents[1] / "data" / "example_bk7.csv"
