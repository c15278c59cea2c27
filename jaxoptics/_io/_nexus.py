"""NeXus/HDF5 `NXellipsometry` files (read with `h5py`, the `instruments` extra).

Two layouts are read, told apart by where `data_type` is:

- the application definition's (`NXoptical_spectroscopy`): `entry/data_collection/data_type`,
  `measured_data[N_measurements, N_observables, N_spectrum]`, `data_error` (or
  `measured_data_errors`) of the same shape, the spectrum axis `wavelength_spectrum`;
- the older one: `entry/sample/data_type`, `entry/sample/measured_data` with leading axes of
  length 1 before `[N_aoi, N_observables, N_spectrum]`, the spectrum at
  `entry/instrument/spectrometer/wavelength`.

In both the angles of incidence are `entry/instrument/angle_of_incidence` (one per measurement).
The `units` attributes are honoured (spectrum in nm, Angstrom, um or eV; angles and Psi, Delta in
degrees or radians); a missing unit is taken as the definition's default (Angstrom for the
spectrum, degrees for angles) and stated in `meta["assumed_units"]`.
"""

from __future__ import annotations

import numpy as np

from ._conventions import Conventions, apply_delta_conventions, finish, mueller_to_ncs

_SPECTRUM: dict[str, float | str] = {"nm": 1.0, "nanometer": 1.0, "nanometers": 1.0, "angstrom": 0.1, "angstroms": 0.1, "a": 0.1, "å": 0.1,
             "um": 1e3, "µm": 1e3, "micrometer": 1e3, "micrometers": 1e3, "ev": "eV"}
_ANGLE = {"deg": 1.0, "degree": 1.0, "degrees": 1.0, "°": 1.0, "rad": 180 / np.pi, "radian": 180 / np.pi,
          "radians": 180 / np.pi}


def is_nexus(path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


def _text(ds):
    v = ds[()]
    return (v.decode("utf-8") if isinstance(v, bytes) else str(v)).strip()


def read_nexus(path, conv: Conventions):
    """`NXellipsometry` data (see the module docstring) into `Spectra`: Psi/Delta,
    tan(Psi)/cos(Delta) (read as N, C), N/C/S, a Mueller matrix (16 observables, row by row, read
    as N, C, S), reflectivity or transmittance (R or T)."""
    try:
        import h5py
    except ImportError:
        raise ImportError("reading NeXus files needs h5py: pip install 'jaxoptics[instruments]'") from None

    def fail(_path, where, msg):
        raise ValueError(f"{path}, {where}: {msg}")

    with h5py.File(path, "r") as h5:
        entry = next((k for k in h5 if isinstance(h5[k], h5py.Group)), None)
        if entry is None:
            raise ValueError(f"{path}: no NXentry group")
        E = h5[entry]
        if "data_collection/data_type" in E:
            base, spec_path, layout = "data_collection", "data_collection/wavelength_spectrum", "NXellipsometry"
        elif "sample/data_type" in E:
            base, spec_path, layout = "sample", "instrument/spectrometer/wavelength", "legacy"
        else:
            raise ValueError(f"{path}: no {entry}/data_collection/data_type (nor {entry}/sample/data_type): not NXellipsometry")
        data_type = _text(E[f"{base}/data_type"])
        for need in (f"{base}/measured_data", spec_path, "instrument/angle_of_incidence"):
            if need not in E:
                raise ValueError(f"{path}: {entry}/{need} is missing")
        M = np.asarray(E[f"{base}/measured_data"][()], np.float64)
        err_path = next((f"{base}/{n}" for n in ("data_error", "measured_data_errors") if f"{base}/{n}" in E), None)
        Se = None if err_path is None else np.asarray(E[err_path][()], np.float64)
        if layout == "legacy":
            if M.ndim < 3 or int(np.prod(M.shape[:-3])) != 1:
                fail(path, f"{entry}/sample/measured_data", f"shape {M.shape}: expected (1, ..., 1, N_aoi, N_observables, N_spectrum)")
            M = M.reshape(M.shape[-3:])
            Se = None if Se is None else Se.reshape(Se.shape[-3:])
        assumed = {}

        def unit(ds_path, table, default):
            u = E[ds_path].attrs.get("units")
            u = (u.decode() if isinstance(u, bytes) else str(u)).strip() if u is not None else None
            if u is None:
                assumed[ds_path] = default
                u = default
            if u.lower() not in table:
                fail(path, f"{entry}/{ds_path}", f"units {u!r}: known {sorted(set(table))}")
            return table[u.lower()]

        x = np.asarray(E[spec_path][()], np.float64).reshape(-1)
        fx = unit(spec_path, _SPECTRUM, "angstrom")
        wl = 1239.8419843320026 / x if fx == "eV" else x * float(fx)
        aoi = np.asarray(E["instrument/angle_of_incidence"][()], np.float64).reshape(-1)
        aoi = aoi * float(unit("instrument/angle_of_incidence", _ANGLE, "degree"))
        data_unit = E[f"{base}/measured_data"].attrs.get("units")
    if M.ndim != 3 or M.shape[2] != wl.size:
        fail(path, f"{entry}/{base}/measured_data", f"shape {M.shape}: expected (measurements, observables, {wl.size})")
    if M.shape[0] != aoi.size:
        fail(path, f"{entry}/{base}/measured_data", f"{M.shape[0]} measurements and {aoi.size} angles of incidence: one "
                                                    "angle per measurement is read")
    if Se is not None and Se.shape != M.shape:
        fail(path, f"{entry}/{err_path}", f"shape {Se.shape}, measured_data has {M.shape}")
    nm, no, ns = M.shape
    wl_rows, aoi_rows = np.tile(wl, nm), np.repeat(aoi, ns)
    rows = lambda a: a.reshape(-1)  # (measurements, spectrum) -> points, angle-major
    obs = lambda j: rows(M[:, j, :])
    errs = None if Se is None else [rows(Se[:, j, :]) for j in range(Se.shape[1])]
    where = np.arange(nm * ns)  # the "line" of a point: its flat index (measurement-major)
    key = data_type.lower().replace(" ", "")
    deg = 1.0
    if data_unit is not None and (data_unit.decode() if isinstance(data_unit, bytes) else str(data_unit)).lower().startswith("rad"):
        deg = 180 / np.pi
    meta: dict[str, object] = {"layout": layout, "data_type": data_type, "conventions": conv._asdict(),
                               "assumed_units": assumed}
    n_obs = {"psi/delta": 2, "tan(psi)/cos(delta)": 2, "n/c/s": 3, "muellermatrix": 16, "reflectivity": 1, "transmittance": 1}
    if key not in n_obs:
        fail(path, f"{entry}/{base}/data_type", f"{data_type!r}: known Psi/Delta, tan(Psi)/cos(Delta), N/C/S, Mueller matrix, "
                                                "reflectivity, transmittance")
    if no != n_obs[key]:
        fail(path, f"{entry}/{base}/measured_data", f"{no} observables; {data_type} has {n_obs[key]}")
    sig: dict = {}
    if key == "psi/delta":
        values = {"psi_deg": deg * obs(0), "delta_deg": deg * obs(1)}
        if errs is not None:
            sig = {"psi_deg": deg * errs[0], "delta_deg": deg * errs[1]}
    elif key == "tan(psi)/cos(delta)":
        t, cd = obs(0), obs(1)
        values = {"N": (1 - t * t) / (1 + t * t), "C": 2 * t / (1 + t * t) * cd}
        conv = conv._replace(delta_range=None)
    elif key == "n/c/s":
        values = {"N": obs(0), "C": obs(1), "S": obs(2)}
        if errs is not None:
            sig = {"N": errs[0], "C": errs[1], "S": errs[2]}
    elif key == "muellermatrix":
        Mm = {f"m{r + 1}{c + 1}": obs(4 * r + c) for r in range(4) for c in range(4)}
        values, sig = mueller_to_ncs(Mm, None if errs is None else {f"m{r + 1}{c + 1}": errs[4 * r + c]
                                                                    for r in range(4) for c in range(4)}, conv.mueller_s3_sign)
    else:
        values = {"R" if key == "reflectivity" else "T": obs(0)}
    located = lambda _p, i, msg: fail(path, f"measurement {i // ns}, spectrum point {i % ns}", msg)
    values, sig = apply_delta_conventions(path, where, values, sig, conv, located)
    return finish(path, "nexus", wl_rows, aoi_rows, values, sig, where, meta=meta, fail=located)
