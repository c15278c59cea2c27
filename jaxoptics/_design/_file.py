"""The TOML file of a design, read by `load_design` and `python -m jaxoptics design`, and the
designed sample written back as a sample file the fitter reads (`load_sample`).

A design file is a sample file (the format of `jaxoptics._io._model_file`: `ambient`,
`[[layer]]`, `[substrate]`; free thicknesses are designed) with the targets and the options:

```toml
[[target]]
quantity = "R"                                    # a Target quantity
wavelength_nm = { from = 420, to = 680, step = 10 }   # or a list, or a number
value = 0.0                                       # a number or a list as long as the wavelengths
tolerance = 0.005                                 # optional, as value
angle_deg = 0.0                                   # optional
polarization = "avg"                              # optional: s, p, avg
kind = "="                                        # optional: =, <=, >=
weight = 1.0                                      # optional

[design]                                          # optional: the keyword arguments of `design`
needle = true
materials = ["SiO2", "Si3N4"]                     # candidates, materials as in [[layer]]
min_thickness_nm = 10.0
max_layers = 20
```

`[design]` takes `starts`, `needle`, `materials`, `max_layers`, `min_thickness_nm`,
`max_thickness_nm`, `max_total_nm`, `max_rounds`, `max_steps`, `gradual`, `needles` and `seed`.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from .._films._sample import Sample
from .._io._model_file import material_of, read_toml, sample_from_doc, tables
from ._targets import Target

_TARGET_KEYS = ("quantity", "wavelength_nm", "value", "tolerance", "angle_deg", "polarization", "kind", "weight")
_OPTIONS = {"starts": int, "needle": bool, "materials": list, "max_layers": int, "min_thickness_nm": float,
            "max_thickness_nm": float, "max_total_nm": float, "max_rounds": int, "max_steps": int, "seed": int,
            "gradual": float, "needles": int}


def _wavelengths(v, where):
    if isinstance(v, dict):
        if set(v) != {"from", "to", "step"}:
            raise ValueError(f"{where}: a range is {{ from = ..., to = ..., step = ... }}, got keys {sorted(v)}")
        a, b, h = (float(v[k]) for k in ("from", "to", "step"))
        if not (h > 0 and b >= a):
            raise ValueError(f"{where}: the range needs from <= to and step > 0, got {v}")
        return a + h * np.arange(int(math.floor((b - a) / h + 1e-9)) + 1)
    return v


class DesignFile:
    """A parsed design file: `sample`, `targets`, `options` (keyword arguments of `design`), and
    the TOML values of its materials (to write the designed sample back)."""

    def __init__(self, path: str | Path):
        path = Path(path)
        doc = read_toml(path)
        self.path = path
        self.doc = doc
        self.sample: Sample = sample_from_doc(doc, path, ("target", "design"))
        raw = doc.get("target")
        if not isinstance(raw, list) or not raw:
            raise ValueError(f"{path}: no targets: give one or more [[target]] tables")
        self.targets = []
        for where, t in tables(raw, path, "target", _TARGET_KEYS):
            for key in ("quantity", "wavelength_nm", "value"):
                if key not in t:
                    raise ValueError(f"{where}: `{key}` is missing")
            kw = {k: v for k, v in t.items() if k not in ("quantity", "wavelength_nm", "value")}
            try:
                self.targets.append(Target(t["quantity"], _wavelengths(t["wavelength_nm"], f"{where}.wavelength_nm"),
                                           t["value"], **kw))
            except (TypeError, ValueError) as e:
                raise ValueError(f"{where}: {e}") from None
        opts = doc.get("design", {})
        if not isinstance(opts, dict):
            raise ValueError(f"{path}: [design] must be a table")
        self.options: dict = {}
        for key, value in opts.items():
            if key not in _OPTIONS:
                raise ValueError(f"{path}: design.{key} is not an option (known: {', '.join(_OPTIONS)})")
            want = _OPTIONS[key]
            ok = isinstance(value, want) and not (want is int and isinstance(value, bool)) or \
                (want is float and isinstance(value, int) and not isinstance(value, bool))
            if not ok:
                raise ValueError(f"{path}: design.{key} must be {want.__name__}, got {value!r}")
            self.options[key] = float(value) if want is float else value
        # each material with the TOML value it was read from: the layers' (read with the sample),
        # then the needle candidates'
        self._materials = [(layer.material, lay["material"]) for layer, lay in zip(self.sample.layers, doc.get("layer", []))]
        if "materials" in self.options:
            cands = [(material_of(v, f"design.materials[{i}]", path.parent), v) for i, v in enumerate(self.options["materials"])]
            self._materials += cands
            self.options["materials"] = [m for m, _ in cands]

    def spec_of(self, m):
        """The TOML value that described material `m`."""
        for x, v in self._materials:
            if x is m or x == m:
                return v
        raise ValueError(f"material {m!r} is not one of {self.path}'s")


def load_design(path: str | Path) -> tuple[Sample, list[Target], dict]:
    """Read a design file (format in this module's docstring): `(sample, targets, options)`,
    `options` the keyword arguments of `design` it gives. Errors name the file and the key."""
    f = DesignFile(path)
    return f.sample, f.targets, f.options


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return ("inf" if f > 0 else "-inf") if math.isinf(f) else "nan" if math.isnan(f) else repr(f)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        key = lambda k: k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_value(k)
        return "{ " + ", ".join(f"{key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise ValueError(f"cannot write {v!r} to TOML")


def write_sample(path: str | Path, design, source: DesignFile, title: str | None = None) -> None:
    """Write `design`'s sample as a sample file (`load_sample` reads it): every thickness fixed,
    materials as the design file gave them."""
    doc = source.doc
    lines = [f"# designed by jaxoptics: {design.layers} layers, merit {design.merit:.6g}"]
    if title or "title" in doc:
        lines.append(f"title = {_toml_value(title or doc['title'])}")
    lines.append(f"ambient = {_toml_value(float(doc.get('ambient', 1.0)))}")
    for j, (t, m) in enumerate(zip(design.values, design.materials)):
        lines += ["", "[[layer]]", f'name = "layer{j + 1}"', f"thickness_nm = {_toml_value(float(t))}",
                  f"material = {_toml_value(source.spec_of(m))}"]
    lines += ["", "[substrate]", f"material = {_toml_value(doc['substrate']['material'])}", ""]
    Path(path).write_text("\n".join(lines), encoding="utf-8")
