"""A fused interface kernel specialized to the scene, and its material-level form.

At a ray hit a renderer needs some of: the reflected and transmitted directions, the TIR mask,
reflectance and transmittance. `interface` computes them in one pass sharing `cos_i`, `k_t` and
the rest, and a static, hashable `InterfaceSpec` says what the scene needs. Outputs that are not
asked for are not computed (they are `None`, and the traced program never contains them), and the
options select cheaper formulas where the scene allows (Schlick, no TIR, no input checks).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _validate as V
from .._core._numerics import _own_loop, _positive_finite, materialize, unpolarized
from .._core._program import program
from .._core._result import Unpacks, result
from .._films._stack import stack
from .._interface._fresnel import _schlick_from_r0
from .._interface._fresnel_terms import _kt_squared, _powers, _terms, _valid_index
from .._interface._refract import (
    METHODS,
    _cross,
    _dot,
    _normalize,
    _refracted,
    _signed_cos,
    _valid_vectors,
    _vectors,
)

if TYPE_CHECKING:
    from jaxtyping import ArrayLike, Float, Inexact, Int

OUTPUTS = ("r", "t", "tir", "R", "T", "R_s", "R_p")
FRESNEL_MODELS = ("exact", "schlick", "schlick_tir")


class InterfaceSpec(NamedTuple):
    """What a scene needs at an interface (static and hashable: it selects the compiled program).

    **Fields:**

    - `outputs`: names among `"r"` (reflected direction), `"t"` (transmitted direction), `"tir"`,
      `"R"`, `"T"` (unpolarized), `"R_s"`, `"R_p"`. Default: `("r", "t", "tir", "R", "T")`.
    - `fresnel`: `"exact"`, `"schlick"` or `"schlick_tir"`.
    - `method`: the refraction formulation of `refract`.
    - `complex_index`: `eta2` may be complex (a conductor); then there is no transmitted direction.
    - `tir_possible`: `False` promises `eta1 <= eta2` everywhere (every ray enters a denser
      medium): the TIR selects are left out.
    - `check_inputs`: `False` leaves out the NaN-for-invalid-input masks (the caller guarantees
      unit-length non-zero vectors, finite inputs and positive indices), and the cosine of
      incidence is the plain dot product (not the double-word one of `refract`).
    """

    outputs: tuple = ("r", "t", "tir", "R", "T")
    fresnel: str = "exact"
    method: str = "degreve"
    complex_index: bool = False
    tir_possible: bool = True
    check_inputs: bool = True

    def validate(self):
        bad = [o for o in self.outputs if o not in OUTPUTS]
        if bad:
            raise ValueError(f"unknown outputs {bad}; choose among {OUTPUTS}")
        if self.fresnel not in FRESNEL_MODELS:
            raise ValueError(f"fresnel must be one of {FRESNEL_MODELS}, got {self.fresnel!r}")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.complex_index and ("t" in self.outputs or self.fresnel != "exact"):
            raise ValueError("a complex index (conductor) has no transmitted direction and uses the exact Fresnel model")
        if self.fresnel != "exact" and {"R_s", "R_p"} & set(self.outputs):
            raise ValueError("R_s and R_p need fresnel='exact'")
        return self


@result
class Interaction(Unpacks):
    """Outputs of `interface`; fields not asked for in the spec are `None`.

    **Fields:** `r`, `t`: unit reflected and transmitted directions `(..., 3)` (`t` is the
    reflected direction where `tir`); `tir`: boolean `(...)`; `R`, `T`: unpolarized reflectance
    and transmittance `(...)`; `R_s`, `R_p`: reflectance per polarization `(...)`. Dtype of the
    inputs; NaN (and `tir = False`) for out-of-domain elements.
    """

    r: jax.Array | None = None
    t: jax.Array | None = None
    tir: jax.Array | None = None
    R: jax.Array | None = None
    T: jax.Array | None = None
    R_s: jax.Array | None = None
    R_p: jax.Array | None = None


DEFAULT_SPEC = InterfaceSpec()


@program(static_argnames=("spec",))
def interface(i: Float[ArrayLike, "*batch 3"], n: Float[ArrayLike, "*#batch 3"], eta1: Float[ArrayLike, "*#batch"],
              eta2: Inexact[ArrayLike, "*#batch"], *, spec: InterfaceSpec = DEFAULT_SPEC) -> Interaction:
    r"""Everything a renderer needs at a hit, in one pass, specialized by `spec`.

    **Arguments:** `i` (toward the surface), `n` (either orientation), `(..., 3)`; `eta1`, `eta2`
    indices broadcasting against the leading axes (`eta2` complex with `complex_index=True`);
    `spec` an `InterfaceSpec`.

    **Returns:** an `Interaction`. Values equal those of `reflect`, `refract`, `fresnel_rt`,
    `fresnel_sp`, `schlick` and `schlick_tir` (same formulas, shared intermediates; `refract`'s
    conventions: `t` is the reflected direction under TIR).

    **Edge cases:** as the separate kernels (NaN for invalid elements when `check_inputs`).
    With `tir_possible=False` and `eta1 > eta2` somewhere the results there are unspecified.
    """
    spec = spec.validate()
    want = set(spec.outputs)
    eta1 = V.as_index(eta1, "eta1", allow_complex=False)
    eta2 = V.as_index(eta2, "eta2", allow_complex=spec.complex_index)
    dt = V.float_dtype(i, n, eta1, eta2)
    i, n, batch = _vectors(i, n, ("eta1", eta1), ("eta2", eta2))
    i, n = i.astype(dt), n.astype(dt)
    e1 = jnp.broadcast_to(jnp.asarray(eta1, dt), batch)
    e2 = jnp.asarray(eta2, V.complex_dtype(dt) if spec.complex_index else dt)
    e2 = jnp.broadcast_to(e2, batch)

    if spec.check_inputs:
        valid = _valid_vectors(i, n) & _positive_finite(e1)
        valid &= _valid_index(e2) if spec.complex_index else _positive_finite(e2)
        d = _signed_cos(i, n)  # to about half an ulp, as in `refract`
        i, n = _normalize(i), _normalize(n)
    else:
        d = materialize(_dot(i, n))  # once, so that every loop sees the same cosine
    flip = d > 0
    nf = materialize(jnp.where(flip[..., None], -n, n))  # stored once, as in `refract` (see there)
    c = jnp.where(flip, d, -d)
    if spec.check_inputs:
        c = jnp.where(c > 1, 1, c)
    out = {}
    if "r" in want or ("t" in want and spec.tir_possible):
        out["r"] = i + 2 * c[..., None] * nf

    need_terms = bool(want & {"t", "tir"}) or (spec.fresnel != "schlick" and bool(want & {"R", "T", "R_s", "R_p"}))
    cr = s2 = None
    if ("t" in want or "tir" in want) and spec.method == "degreve" and spec.tir_possible:
        cr = _cross(i, n)
        s2 = materialize(_dot(cr, cr))
    # R and T both wanted (exact, real index): T in a loop of its own on inputs behind an
    # optimization barrier (which keeps XLA from identifying them with R's). XLA on the CPU has no
    # multi-output loop fusion, and R and T sharing every quotient made about ten loops (see
    # `fresnel_rt`).
    split_rt = (spec.fresnel == "exact" and not spec.complex_index and "T" in want
                and bool(want & {"R", "R_s", "R_p"}))
    q = None
    if need_terms and not spec.complex_index and (split_rt or (spec.tir_possible and want & {"t", "tir"})):
        # k_t^2 computed once and stored, when several outputs must agree on its sign: the mask,
        # the direction selected on it, R and T (left to itself XLA recomputes it in each loop,
        # contracting multiply-adds differently, and near the critical angle the copies can
        # disagree). Its inputs c and sin^2 are materialized above for the same reason.
        q = materialize(_kt_squared(e1 * c, e1, e2, s2)[0])
    tm = _terms(c, e1, e2, s2, q_given=q) if need_terms else None
    tir = tm.tir if (tm is not None and spec.tir_possible) else None

    if "t" in want:
        assert tm is not None  # need_terms holds when t is wanted
        col = lambda x: x[..., None]
        t = _refracted(spec.method, i, n, nf, col(c), col(tm.ki), col(tm.kt), col(tm.diff), cr, col(e1), col(e2), 1.0)
        if spec.tir_possible:
            t = jnp.where(_req(tir)[..., None], out["r"], t)
        out["t"] = t
    if "tir" in want:
        out["tir"] = tir if tir is not None else jnp.zeros(batch, bool)

    if want & {"R", "T", "R_s", "R_p"}:
        if spec.fresnel == "exact":
            no_tir = lambda x: x if spec.tir_possible else x._replace(tir=jnp.zeros_like(x.ok))
            if split_rt:
                # R and T each in a loop of its own, apart from the direction loop too: within one
                # loop with `t`, R came out of a differently contracted k_i and broke R + T = 1 by
                # 200 eps near the critical angle.
                def powers_in_own_loop(order):
                    c_, e1_, e2_, s2_, q_ = _own_loop(c, e1, e2, s2, q, order=order)
                    return _powers(no_tir(_terms(c_, e1_, e2_, s2_, q_given=q_)), e1_, e2_)

                (R_s, R_p, _, _), (_, _, T_s, T_p) = powers_in_own_loop(4), powers_in_own_loop(0)
            else:
                R_s, R_p, T_s, T_p = _powers(no_tir(tm), e1, e2)
            out.update(R=unpolarized(R_s, R_p), T=unpolarized(T_s, T_p), R_s=R_s, R_p=R_p)
        else:
            a = (e1 - e2) / (e1 + e2)
            r0 = a * a
            if spec.fresnel == "schlick_tir":
                assert tm is not None  # need_terms holds for schlick_tir
                cos_t = tm.kt / e2
                cu = jnp.where(e1 > e2, cos_t, c)
                R = _schlick_from_r0(cu, r0)
                if spec.tir_possible:
                    R = jnp.where(_req(tir), 1, R)
            else:
                R = _schlick_from_r0(c, r0)
            out.update(R=R, T=1 - R)
    if spec.check_inputs:
        for k, v in out.items():
            if k == "tir":
                out[k] = v & valid
            else:
                out[k] = jnp.where(valid[..., None] if v.ndim > valid.ndim else valid, v, jnp.nan)
    return Interaction(**{k: v for k, v in out.items() if k in want})


# ---- the material-level form -----------------------------------------------------------------

MATERIAL_KINDS = ("mirror", "dielectric", "conductor", "thin_dielectric", "coated_dielectric", "coated_conductor")
COATED_KINDS = ("coated_dielectric", "coated_conductor")


class SceneSpec(NamedTuple):
    """The kinds of material a scene contains (static). The compiled kernel has branches for these
    kinds only.

    **Fields:**

    - `kinds`: a tuple among `"mirror"` (R = 1), `"dielectric"` (exact Fresnel, refraction with
      TIR), `"conductor"` (complex index, R from the exact formulas, no transmission),
      `"thin_dielectric"` (a thin sheet: incoherent sum of the multiple internal reflections,
      `R' = 2R / (1 + R)`, transmitted ray continues undeviated), `"coated_dielectric"` and
      `"coated_conductor"` (the same with a thin film on the surface: `R` and `T` are those of the
      coherent three-medium stack `eta1 | film | eta2` from `stack`, per wavelength: thin-film
      interference, the colours of soap films and oil slicks; directions as without the film,
      since a film with parallel faces does not change them).
    - `wavelengths`: static tuple of vacuum wavelengths, in the unit of the film thickness. When
      given, `R` and `T` of every kind have a trailing spectral axis of this length (an
      uncoated kind repeats its value: indices are taken as non-dispersive); the coated kinds
      need it. For an RGB renderer, three wavelengths standing for its primaries (for example
      `(630.0, 532.0, 465.0)` nm) give a per-channel reflectance; integrating a finer spectrum
      against colour-matching functions gives the colour itself (notebook 06).
    - `fresnel` and `method` as in `InterfaceSpec` for the dielectric branch; `check_inputs`.
    """

    kinds: tuple = ("dielectric",)
    fresnel: str = "exact"
    method: str = "degreve"
    check_inputs: bool = True
    wavelengths: tuple = ()


@result
class Hit(Unpacks):
    """Per-hit result of `scene_interface`: reflected and transmitted directions, the energy
    fractions R (reflected) and T (transmitted; 0 for mirrors and conductors) and the TIR mask.
    With `SceneSpec.wavelengths`, `R` and `T` have a trailing spectral axis; under a coating
    `R + T < 1` where the film absorbs."""

    r: jax.Array
    t: jax.Array
    R: jax.Array
    T: jax.Array
    tir: jax.Array


def scene_interface(i: Float[ArrayLike, "*batch 3"], n: Float[ArrayLike, "*#batch 3"], kind: Int[ArrayLike, "*#batch"],
                    eta1: Float[ArrayLike, "*#batch"], eta2: Inexact[ArrayLike, "*#batch"], *,
                    scene: SceneSpec = SceneSpec(), film_eta: Inexact[ArrayLike, "*#batch"] | None = None,
                    film_d: Float[ArrayLike, "*#batch"] | None = None) -> Hit:
    r"""The interface at each hit of a scene with several kinds of material.

    **Arguments:** `i`, `n` `(..., 3)`; `kind` `(...)` integer index into `scene.kinds` per hit;
    `eta1` real `(...)`; `eta2` `(...)` (complex for conductors, its real part used for
    dielectrics); `scene` a `SceneSpec`. With coated kinds: `film_eta` `(...)` the film's index
    (real or complex `n + ik`) and `film_d` `(...)` its thickness (same unit as
    `scene.wavelengths`), per hit; for a per-material film, index a table by `kind`
    (`film_eta=table[kind]`).

    **Returns:** a `Hit`. Each present kind is evaluated and selected by `kind`; kinds not in the
    scene are not compiled at all. Hits whose `kind` is out of range get NaN.

    **Edge cases:** a coated dielectric under TIR at its substrate has `T = 0` and `R = 1` minus
    what the film absorbs; gradients with respect to the film's index and thickness are those of
    `stack` (finite everywhere).
    """
    kinds = tuple(scene.kinds)
    unknown = [k for k in kinds if k not in MATERIAL_KINDS]
    if unknown or not kinds:
        raise ValueError(f"scene kinds must be a non-empty tuple among {MATERIAL_KINDS}, got {kinds}")
    wls = tuple(float(w) for w in scene.wavelengths)
    coated = [k for k in kinds if k in COATED_KINDS]
    if coated and not wls:
        raise ValueError(f"the coated kinds {coated} need SceneSpec.wavelengths (the wavelengths to evaluate)")
    if coated and (film_eta is None or film_d is None):
        raise ValueError(f"the coated kinds {coated} need film_eta and film_d (the film's index and thickness per hit)")
    if not coated and (film_eta is not None or film_d is not None):
        raise ValueError("film_eta and film_d were given but the scene has no coated kind "
                         f"{COATED_KINDS}: add one to SceneSpec.kinds")
    if any(not (w > 0 and w < float("inf")) for w in wls):
        raise ValueError(f"SceneSpec.wavelengths must be finite and > 0, got {scene.wavelengths}")
    if coated:
        for name, arr, bad, what in (("film_d", film_d, lambda v: ~(np.isfinite(v) & (v >= 0)), "finite and >= 0"),
                                   ("film_eta", film_eta, lambda v: ~((np.real(v) > 0) & (np.imag(v) >= 0)),
                                    "real part > 0 and k >= 0")):
            assert arr is not None  # (coated kinds have both: checked above)
            if not isinstance(arr, jax.core.Tracer):  # on the parts this process holds
                V.first_bad(np.atleast_1d(arr) if np.ndim(arr) == 0 else arr, lambda v, _: bad(v),
                            lambda idx, v: f"{name}{idx} = {v!r}: must be {what}")
    if isinstance(kind, (int, list, tuple)):  # (an int stays an int: see `program`)
        kind = np.asarray(kind)
    scene = scene._replace(kinds=kinds, wavelengths=wls)  # hashable: it keys the program
    return _scene_program(i, n, kind, eta1, eta2, scene=scene, film_eta=film_eta, film_d=film_d)


@program(static_argnames=("scene",))
def _scene_program(i, n, kind, eta1, eta2, *, scene, film_eta, film_d):
    """`scene_interface` after its value checks, as one program (see `program`)."""
    kinds, wls = scene.kinds, scene.wavelengths
    kind_arr = jnp.asarray(kind)
    if not jnp.issubdtype(kind_arr.dtype, jnp.integer):
        raise ValueError(f"kind must be an integer array (an index into scene.kinds), got dtype {kind_arr.dtype}")
    dt = V.float_dtype(i, n, eta1, eta2)
    e2c = jnp.asarray(eta2)
    e2r = jnp.real(e2c).astype(dt) if jnp.iscomplexobj(e2c) else e2c.astype(dt)
    results: list[Hit] = []
    for k in kinds:
        if k == "mirror":
            r = _req(interface(i, n, eta1, e2r, spec=InterfaceSpec(outputs=("r",), check_inputs=scene.check_inputs)).r)
            one = jnp.ones(r.shape[:-1], dt)
            results.append(Hit(r, r, one, jnp.zeros_like(one), jnp.zeros(one.shape, bool)))
        elif k == "conductor":
            e2k = e2c if jnp.iscomplexobj(e2c) else e2c.astype(V.complex_dtype(dt))
            x = interface(i, n, eta1, e2k, spec=InterfaceSpec(outputs=("r", "R"), complex_index=True,
                                                              check_inputs=scene.check_inputs))
            results.append(Hit(_req(x.r), _req(x.r), _req(x.R), jnp.zeros_like(_req(x.R)), jnp.zeros(_req(x.R).shape, bool)))
        elif k == "dielectric":
            x = interface(i, n, eta1, e2r, spec=InterfaceSpec(("r", "t", "tir", "R", "T"), scene.fresnel, scene.method,
                                                              check_inputs=scene.check_inputs))
            results.append(Hit(_req(x.r), _req(x.t), _req(x.R), _req(x.T), _req(x.tir)))
        elif k == "thin_dielectric":  # thin sheet: both faces, light bouncing inside adds incoherently
            x = interface(i, n, eta1, e2r, spec=InterfaceSpec(("r", "R"), scene.fresnel, scene.method,
                                                              tir_possible=False, check_inputs=scene.check_inputs))
            Rt = 2 * _req(x.R) / (1 + _req(x.R))
            results.append(Hit(_req(x.r), jnp.broadcast_to(i, _req(x.r).shape).astype(dt), Rt, 1 - Rt, jnp.zeros(Rt.shape, bool)))
        elif k == "coated_dielectric":
            x = interface(i, n, eta1, e2r, spec=InterfaceSpec(("r", "t", "tir"), scene.fresnel, scene.method,
                                                              check_inputs=scene.check_inputs))
            R, T = _film(i, n, eta1, e2r, film_eta, film_d, wls, dt)
            results.append(Hit(_req(x.r), _req(x.t), R, T, _req(x.tir)))
        else:  # coated conductor
            e2k = e2c if jnp.iscomplexobj(e2c) else e2c.astype(V.complex_dtype(dt))
            r = _req(interface(i, n, eta1, e2r, spec=InterfaceSpec(outputs=("r",), check_inputs=scene.check_inputs)).r)
            R, _ = _film(i, n, eta1, e2k, film_eta, film_d, wls, dt)
            results.append(Hit(r, r, R, jnp.zeros_like(R), jnp.zeros(r.shape[:-1], bool)))
    if wls:  # every kind spectral: uncoated ones repeat their (non-dispersive) value
        rep = lambda x: jnp.broadcast_to(x[..., None], x.shape + (len(wls),))
        results = [h if k in COATED_KINDS else dataclasses.replace(h, R=rep(h.R), T=rep(h.T)) for k, h in zip(kinds, results)]
    if len(results) == 1:
        out = results[0]
        inside = kind_arr == 0
    else:
        idx = jnp.clip(kind_arr, 0, len(kinds) - 1)
        out = jax.tree_util.tree_map(lambda *xs: _select(idx, xs), *results)
        inside = (kind_arr >= 0) & (kind_arr < len(kinds))
    nan = lambda v: jnp.where(inside[..., None] if v.ndim > inside.ndim else inside, v, jnp.nan)
    return Hit(nan(out.r), nan(out.t), nan(out.R), nan(out.T), out.tir & inside)


def _req(v: jax.Array | None) -> jax.Array:
    """An output `interface` was asked for (so not None)."""
    assert v is not None
    return v


def _film(i, n, eta1, eta2, film_eta, film_d, wls, dt):
    """(R, T), shape (..., W): unpolarized, of the stack eta1 | film | eta2 at the hit's angle."""
    d = _signed_cos(jnp.asarray(i, dt), jnp.asarray(n, dt))  # as `interface`: to about half an ulp
    c = jnp.minimum(jnp.where(d < 0, -d, d), 1)
    cdt = V.complex_dtype(dt)
    batch = c.shape
    e1 = jnp.broadcast_to(jnp.asarray(eta1, dt), batch).astype(cdt)
    ef = jnp.broadcast_to(jnp.asarray(film_eta).astype(cdt), batch)
    e2 = jnp.broadcast_to(jnp.asarray(eta2).astype(cdt), batch)
    nstack = jnp.stack([e1, ef, e2], -1)[..., None, :]  # (..., 1, 3): one stack per hit
    thick = jnp.broadcast_to(jnp.asarray(film_d, dt), batch)[..., None, None]
    res = stack(nstack, thick, jnp.asarray(wls, dt), c[..., None])
    return res.R, res.T


def _select(idx, xs):
    stacked = jnp.stack(xs, axis=0)
    ix = idx.reshape((1,) + idx.shape + (1,) * (stacked.ndim - 1 - idx.ndim))
    ix = jnp.broadcast_to(ix, (1,) + stacked.shape[1:])
    return jnp.take_along_axis(stacked, ix, axis=0)[0]
