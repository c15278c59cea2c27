"""`load_spectra`: any supported measurement file into `Spectra`, its format detected from its
content or named."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from . import _nexus as nexus
from . import _photometry as photo
from . import _vendors as vend
from ._conventions import conventions
from ._csv import read_csv
from ._spectra import Spectra

FORMATS = ("csv", "woollam", "spectraray", "accurion", "horiba", "filmsense", "nexus", "text", "jcamp")


def _is_csv(lines):
    """jaxoptics' CSV: its header names the angle or Psi/Delta column as `save_spectra` writes
    them (the CSV reader then explains what else is wrong with the header)."""
    for l in lines:
        if l.strip() and not l.lstrip().startswith("#"):
            return any(name in l for name in ("angle_deg", "psi_deg", "delta_deg"))
    return False


def detect_format(path: str | os.PathLike) -> str:
    """The format of a measurement file, from its content (see `load_spectra`)."""
    if nexus.is_nexus(path):
        return "nexus"
    lines = vend.read_lines(Path(path))
    for name, test in (("csv", _is_csv), ("woollam", vend.is_woollam), ("spectraray", vend.is_spectraray),
                       ("accurion", vend.is_accurion), ("filmsense", vend.is_filmsense), ("horiba", vend.is_horiba),
                       ("jcamp", photo.is_jcamp)):
        if test(lines):
            return name
    return "text"


def load_spectra(path: str | os.PathLike, *, format: str | None = None, delta_convention: str = "delta",
                 delta_range: str | None = None, mueller_s3_sign: int = 1, angle_deg: float | None = None,
                 quantity: str | Sequence[str] | None = None, scale: str | None = None,
                 wavelength_unit: str | None = None) -> Spectra:
    """Read a measurement file into `Spectra`: ellipsometry (Psi/Delta; N, C, S; Mueller matrix)
    or photometry (R, T), for one spot, a map or a time series.

    **Arguments:**

    - `path`: the file.
    - `format`: one of `"csv"` (jaxoptics' CSV, written by `save_spectra`), `"woollam"` (WVASE and
      CompleteEASE `.dat`), `"spectraray"` (Sentech SpectraRay ASCII, Psi/Delta or Mueller matrix),
      `"accurion"` (nanofilm EP3/EP4 `.ds.dat`), `"horiba"` (DeltaPsi2 `.spe`), `"filmsense"`
      (Film Sense FS-1/FS-8), `"nexus"` (NeXus/HDF5 `NXellipsometry`), `"text"`
      (spectrophotometer R/T columns), `"jcamp"` (JCAMP-DX);
      `None` detects it from the content (`detect_format`). `docs/data-files.md` describes each
      layout.
    - `delta_convention`, `delta_range`, `mueller_s3_sign`: how the file's Delta and Mueller
      elements relate to the instrument convention jaxoptics fits in (see `docs/conventions.md`;
      the defaults are every vendor's): `delta_convention` one of `"delta"`, `"-delta"`,
      `"180-delta"`, `"delta+180"`; `delta_range` `None` (any range), `"-180..180"`, `"0..360"`
      (checked) or `"0..180"` (folded by the instrument: read as `N`, `C`); `mueller_s3_sign` `+1`
      (`M34 = +sin 2Psi sin Delta`, Woollam, Sentech) or `-1` (pyElli 0.23).
    - `angle_deg`, `quantity`, `scale`, `wavelength_unit`: for photometric files, what the file
      does not say: the angle of incidence in degrees, the quantity of each value column (`"R"`,
      `"T"`, `"R_s"`, `"R_p"`, `"T_s"`, `"T_p"`), `"fraction"` or `"percent"`, and the unit of the
      first column (`"nm"`, `"um"`, `"1/cm"`).

    **Returns:** `Spectra`; leading axes of `values` are the sites of a map or the times of a
    kinetic series (`sites` labels them; `meta["times"]` holds the times). `meta` holds the format,
    the header's fields, the conventions used and per-point extras (`depolarization_percent`,
    `uR`, `degree_of_polarization`, the whole `mueller` matrix).

    **Errors:** a malformed file raises `ValueError` naming the file, the line and what was
    expected; values outside their range by more than noise (Psi in [0, 90], N, C, S in [-1, 1],
    R, T in [0, 1]) are refused with the line.
    """
    path = Path(path)
    conv = conventions(delta_convention, delta_range, mueller_s3_sign)
    if format is None:
        format = detect_format(path)
    if format not in FORMATS:
        raise ValueError(f"format={format!r}: must be one of {FORMATS} or None (detected from the content)")
    photometric = dict(angle_deg=angle_deg, quantity=quantity, scale=scale)
    if format not in ("text", "jcamp"):
        given = [k for k, v in dict(photometric, wavelength_unit=wavelength_unit).items() if v is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: only for photometric files (format 'text' or 'jcamp'); this file is {format!r}")
    if format == "csv":
        return read_csv(path, conv)
    if format == "jcamp":
        return photo.read_jcamp(path, **photometric)
    if format == "nexus":
        if not nexus.is_nexus(path):
            raise ValueError(f"{path}: not an HDF5 file (detected: {detect_format(path)})")
        return nexus.read_nexus(path, conv)
    lines = vend.read_lines(path)
    if not any(l.strip() for l in lines):
        raise ValueError(f"{path}: the file is empty")
    if format == "text":
        return photo.read_text(path, lines, wavelength_unit=wavelength_unit, **photometric)
    check = getattr(vend, f"is_{format}")
    if not check(lines):
        raise ValueError(f"{path}: not a {format} file (detected: {detect_format(path)}); see docs/data-files.md for its layout")
    return getattr(vend, f"read_{format}")(path, lines, conv)
