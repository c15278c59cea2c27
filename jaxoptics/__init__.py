"""jaxoptics: differentiable, JIT-compilable optics of a smooth interface, in JAX.

Conventions (de Greve's): `i` points toward the surface, `eta1` is the medium the light comes
from, `eta2` the medium it enters (complex `n + ik`, `k >= 0`, where allowed); angles in radians;
vectors `(..., 3)`; dtype follows the inputs.

The fitting names (`fit_eta`, `FitResult`, `OneColumnLeastSquares`, `fit_dispersion`,
`DispersionFit`, `fit_stack`, `StackFit`) and the figures (`plot_fit`, `plot_dispersion_fit`,
`plot_stack_fit`, `plot_stack_map`) are imported on first use. optimistix, equinox and lineax
load when a fit traces a program (not when `fit_eta` or `fit_stack` loads its compiled program
from the cache); a program that only calls the kernels does not load them, and matplotlib loads
when a figure is drawn.
"""

import typing as _typing

from ._fresnel import FresnelAmplitudes as FresnelAmplitudes
from ._fresnel import fresnel as fresnel
from ._fresnel import fresnel_amplitudes as fresnel_amplitudes
from ._fresnel import fresnel_rt as fresnel_rt
from ._fresnel import fresnel_sp as fresnel_sp
from ._fresnel import schlick as schlick
from ._fresnel import schlick_tir as schlick_tir
from ._refract import Refraction as Refraction
from ._refract import brewster_angle as brewster_angle
from ._refract import critical_angle as critical_angle
from ._refract import reflect as reflect
from ._refract import refract as refract
from ._stack import Ellipsometry as Ellipsometry
from ._stack import StackResult as StackResult
from ._stack import ellipsometry as ellipsometry
from ._stack import stack as stack

from ._data import Curve as Curve
from ._data import ReflectanceData as ReflectanceData
from ._data import example_path as example_path
from ._data import load_reflectance as load_reflectance
from ._fit_model import synthetic_reflectance as synthetic_reflectance
from ._interface import Hit as Hit
from ._interface import Interaction as Interaction
from ._interface import InterfaceSpec as InterfaceSpec
from ._interface import SceneSpec as SceneSpec
from ._interface import interface as interface
from ._interface import scene_interface as scene_interface
from ._dispersion import Cauchy as Cauchy
from ._dispersion import Constant as Constant
from ._dispersion import Dispersion as Dispersion
from ._dispersion import Drude as Drude
from ._dispersion import DrudeLorentz as DrudeLorentz
from ._dispersion import Free as Free
from ._dispersion import Lorentz as Lorentz
from ._dispersion import Sellmeier as Sellmeier
from ._dispersion import Tabulated as Tabulated
from ._dispersion import TaucLorentz as TaucLorentz
from ._rii import RIIFormula as RIIFormula
from ._rii import builtin_materials as builtin_materials
from ._rii import load_rii_yaml as load_rii_yaml
from ._rii import material as material
from ._rii import rii_material as rii_material
from ._model_file import load_sample as load_sample
from ._sample import Layer as Layer
from ._sample import Sample as Sample
from ._spectra import KINDS as KINDS
from ._spectra import Spectra as Spectra
from ._spectra import load_spectra as load_spectra
from ._spectra import make_spectra as make_spectra
from ._spectra import save_spectra as save_spectra
from ._materials import MATERIALS as MATERIALS
from ._materials import Material as Material
from ._materials import cauchy as cauchy
from ._materials import material_index as material_index
from ._materials import sellmeier as sellmeier
from ._cache import enable_cache as enable_cache
from ._memory import keep_freed_memory as keep_freed_memory
from ._shard import batch_mesh as batch_mesh
from ._shard import fit_eta_sharded as fit_eta_sharded
from ._shard import shard_batch as shard_batch
from ._shard import sharded_map as sharded_map

__version__ = "0.1.0"

# imported on first use (see the module docstring); listed here for readers and type checkers
_LAZY = {
    "fit_eta": "._fit",
    "FitResult": "._fit_result",
    "OneColumnLeastSquares": "._fit_solver",
    "fit_dispersion": "._dispersion_fit",
    "DispersionFit": "._dispersion_fit",
    "fit_stack": "._stack_fit",
    "StackFit": "._stack_fit",
    "plot_fit": "._plot",
    "plot_dispersion_fit": "._plot",
    "plot_stack_fit": "._plot",
    "plot_stack_map": "._plot",
}
if _typing.TYPE_CHECKING:
    from ._fit import fit_eta as fit_eta
    from ._fit_result import FitResult as FitResult
    from ._fit_solver import OneColumnLeastSquares as OneColumnLeastSquares
    from ._dispersion_fit import DispersionFit as DispersionFit
    from ._dispersion_fit import fit_dispersion as fit_dispersion
    from ._stack_fit import StackFit as StackFit
    from ._stack_fit import fit_stack as fit_stack
    from ._plot import plot_dispersion_fit as plot_dispersion_fit
    from ._plot import plot_fit as plot_fit
    from ._plot import plot_stack_fit as plot_stack_fit
    from ._plot import plot_stack_map as plot_stack_map


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxoptics' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = sorted({n for n in globals() if not n.startswith("_")} | set(_LAZY))
