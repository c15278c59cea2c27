"""jaxoptics: differentiable, JIT-compilable optics of a smooth interface, in JAX.

Conventions (de Greve's): `i` points toward the surface, `eta1` is the medium the light comes
from, `eta2` the medium it enters (complex `n + ik`, `k >= 0`, where allowed); angles in radians;
vectors `(..., 3)`; dtype follows the inputs.

This file is the whole public API; the code lives in private subpackages, one per concern
(`_core`, `_runtime`, `_interface`, `_films`, `_render`, `_io`, `_fitting`, `_design`; the design page has
the map and the direction of imports between them).

The fitting names (`fit_eta`, `fit_eta_sharded`, `FitResult`, `OneColumnLeastSquares`,
`fit_dispersion`, `DispersionFit`, `fit_stack`, `StackFit`) and the figures (`plot_fit`,
`plot_dispersion_fit`, `plot_stack_fit`, `plot_stack_map`) and the coating-design names
(`Target`, `design`, `Design`, `merit`, `target_values`, `thickness_errors`, `ThicknessErrors`,
`ErrorAnalysis`, `load_design`, `plot_design`)
are imported on first use.
optimistix, equinox and lineax load when a fit traces a program (not when `fit_eta` or
`fit_stack` loads its compiled program from the cache); a program that only calls the kernels
does not load them, and matplotlib loads when a figure is drawn.
"""

import typing as _typing

# single-interface kernels
from ._interface._fresnel import FresnelAmplitudes as FresnelAmplitudes
from ._interface._fresnel import fresnel as fresnel
from ._interface._fresnel import fresnel_amplitudes as fresnel_amplitudes
from ._interface._fresnel import fresnel_rt as fresnel_rt
from ._interface._fresnel import fresnel_sp as fresnel_sp
from ._interface._fresnel import schlick as schlick
from ._interface._fresnel import schlick_tir as schlick_tir
from ._interface._refract import Refraction as Refraction
from ._interface._refract import brewster_angle as brewster_angle
from ._interface._refract import critical_angle as critical_angle
from ._interface._refract import reflect as reflect
from ._interface._refract import refract as refract

# thin films and materials
from ._films._stack import Ellipsometry as Ellipsometry
from ._films._stack import StackResult as StackResult
from ._films._stack import ellipsometry as ellipsometry
from ._films._stack import stack as stack
from ._films._dispersion import Cauchy as Cauchy
from ._films._dispersion import Constant as Constant
from ._films._dispersion import Dispersion as Dispersion
from ._films._dispersion import Drude as Drude
from ._films._dispersion import DrudeLorentz as DrudeLorentz
from ._films._dispersion import Free as Free
from ._films._dispersion import Lorentz as Lorentz
from ._films._dispersion import Sellmeier as Sellmeier
from ._films._dispersion import Tabulated as Tabulated
from ._films._dispersion import TaucLorentz as TaucLorentz
from ._films._instrument import Instrument as Instrument
from ._films._oscillators import BSpline as BSpline
from ._films._oscillators import CodyLorentz as CodyLorentz
from ._films._oscillators import GenOsc as GenOsc
from ._films._oscillators import Gaussian as Gaussian
from ._films._oscillators import Poles as Poles
from ._films._oscillators import SellmeierIR as SellmeierIR
from ._films._rii import RIIFormula as RIIFormula
from ._films._rii import builtin_materials as builtin_materials
from ._films._rii import load_rii_yaml as load_rii_yaml
from ._films._rii import material as material
from ._films._rii import rii_material as rii_material
from ._films._sample import Layer as Layer
from ._films._sample import Sample as Sample
from ._films._materials import MATERIALS as MATERIALS
from ._films._materials import Material as Material
from ._films._materials import cauchy as cauchy
from ._films._ema import EMA as EMA
from ._films._sample import roughness as roughness
from ._films._graded import Graded as Graded
from ._films._materials import material_index as material_index
from ._films._materials import sellmeier as sellmeier

# the fused kernels for renderers
from ._render._scene import Hit as Hit
from ._render._scene import Interaction as Interaction
from ._render._scene import InterfaceSpec as InterfaceSpec
from ._render._scene import SceneSpec as SceneSpec
from ._render._scene import interface as interface
from ._render._scene import scene_interface as scene_interface

# data files and model files
from ._io._reflectance import Curve as Curve
from ._io._reflectance import ReflectanceData as ReflectanceData
from ._io._reflectance import example_path as example_path
from ._io._reflectance import load_reflectance as load_reflectance
from ._io._spectra import KINDS as KINDS
from ._io._spectra import Spectra as Spectra
from ._io._load import load_spectra as load_spectra
from ._io._spectra import make_spectra as make_spectra
from ._io._spectra import save_spectra as save_spectra
from ._io._model_file import load_sample as load_sample
from ._io._nk_file import load_nk as load_nk

# the fits' model of a reflectance curve (the rest of the fitting names: `_LAZY`)
from ._fitting._index_model import synthetic_reflectance as synthetic_reflectance

# compilation, caching and devices
from ._runtime._cache import enable_cache as enable_cache
from ._runtime._memory import keep_freed_memory as keep_freed_memory
from ._runtime._shard import batch_mesh as batch_mesh
from ._runtime._shard import shard_batch as shard_batch
from ._runtime._shard import sharded_map as sharded_map

__version__ = "0.1.0"

# imported on first use (see the module docstring); listed here for readers and type checkers
_LAZY = {
    "fit_eta": "._fitting._index",
    "fit_eta_sharded": "._fitting._index",
    "FitResult": "._fitting._index_result",
    "OneColumnLeastSquares": "._fitting._index_solver",
    "fit_dispersion": "._fitting._dispersion_fit",
    "DispersionFit": "._fitting._dispersion_fit",
    "fit_stack": "._fitting._stack_fit",
    "StackFit": "._fitting._stack_fit",
    "fit_joint": "._fitting._joint",
    "Dataset": "._fitting._joint",
    "fit_statistics": "._fitting._statistics",
    "fit_nk": "._fitting._nk",
    "NKFit": "._fitting._nk",
    "absolute_reflectance": "._fitting._reflectometry",
    "fft_thickness": "._fitting._reflectometry",
    "ThicknessEstimate": "._fitting._reflectometry",
    "FitStatistics": "._fitting._statistics",
    "plot_fit": "._fitting._plot",
    "plot_dispersion_fit": "._fitting._plot",
    "plot_stack_fit": "._fitting._plot",
    "plot_stack_map": "._fitting._plot",
    "Target": "._design._targets",
    "design": "._design._design",
    "Design": "._design._design",
    "merit": "._design._design",
    "thickness_errors": "._design._design",
    "target_values": "._design._design",
    "load_design": "._design._file",
    "plot_design": "._design._plot",
    "ThicknessErrors": "._design._errors",
    "ErrorAnalysis": "._design._errors",
}
if _typing.TYPE_CHECKING:
    from ._fitting._index import fit_eta as fit_eta
    from ._fitting._index import fit_eta_sharded as fit_eta_sharded
    from ._fitting._index_result import FitResult as FitResult
    from ._fitting._index_solver import OneColumnLeastSquares as OneColumnLeastSquares
    from ._fitting._dispersion_fit import DispersionFit as DispersionFit
    from ._fitting._dispersion_fit import fit_dispersion as fit_dispersion
    from ._fitting._stack_fit import StackFit as StackFit
    from ._fitting._stack_fit import fit_stack as fit_stack
    from ._fitting._joint import Dataset as Dataset
    from ._fitting._nk import NKFit as NKFit
    from ._fitting._nk import fit_nk as fit_nk
    from ._fitting._joint import fit_joint as fit_joint
    from ._fitting._reflectometry import ThicknessEstimate as ThicknessEstimate
    from ._fitting._reflectometry import absolute_reflectance as absolute_reflectance
    from ._fitting._reflectometry import fft_thickness as fft_thickness
    from ._fitting._statistics import FitStatistics as FitStatistics
    from ._fitting._statistics import fit_statistics as fit_statistics
    from ._fitting._plot import plot_dispersion_fit as plot_dispersion_fit
    from ._fitting._plot import plot_fit as plot_fit
    from ._fitting._plot import plot_stack_fit as plot_stack_fit
    from ._fitting._plot import plot_stack_map as plot_stack_map
    from ._design._targets import Target as Target
    from ._design._design import Design as Design
    from ._design._design import design as design
    from ._design._design import merit as merit
    from ._design._design import target_values as target_values
    from ._design._file import load_design as load_design
    from ._design._plot import plot_design as plot_design
    from ._design._design import thickness_errors as thickness_errors
    from ._design._errors import ErrorAnalysis as ErrorAnalysis
    from ._design._errors import ThicknessErrors as ThicknessErrors


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
