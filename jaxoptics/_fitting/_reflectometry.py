"""Film thickness from reflectance as reflectometers measure it: relative reflectance against a
reference of known reflectance made absolute (`absolute_reflectance`), and the Fourier-transform
estimate of a thick film's optical thickness (`fft_thickness`) that `fit_stack(...,
global_start="fft")` searches around.

A film of index `n` and thickness `d` on a substrate reflects with fringes periodic in the
wavenumber `sigma = 1/lambda`, `R ~ a + b cos(4 pi n_eff d sigma)` with `n_eff = sqrt(n^2 -
sin^2 theta)`: the spectrum of `R(sigma)` peaks at the optical path `2 n_eff d`. Its resolution is
`1 / (sigma_max - sigma_min)`, and a dispersive film's peak sits at its group index rather
than its index; so converted, the estimate is good to a fraction of a fringe for films of many
fringes (micrometres), where a grid search from zero would need thousands of points, and says
nothing for films thinner than one fringe (there the grid search is cheap).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from .._films._dispersion import Dispersion
from .._films._rii import material as _material
from .._films._sample import Sample
from .._io._spectra import Spectra, make_spectra

if TYPE_CHECKING:
    from jaxtyping import ArrayLike, Float

_PHOTOMETRIC = ("R", "R_s", "R_p", "T", "T_s", "T_p")


def absolute_reflectance(wavelength_nm: Float[ArrayLike, " P"], relative: Float[ArrayLike, "*sites P"],
                         reference: Sample | Dispersion | str | complex, *, angle_deg: float = 0.0,
                         sigma: Float[ArrayLike, "*sites P"] | None = None, kind: str = "R",
                         sites: tuple | None = None) -> Spectra:
    """Absolute reflectance from reflectance measured relative to a reference sample.

    A reflectometer measures the sample's signal over the reference's (both less the dark
    signal): `relative = R_sample / R_reference`. With the reference's reflectance known (bare
    silicon, a mirror, a calibrated standard), `R_sample = relative * R_reference`.

    **Arguments:**

    - `wavelength_nm`: `(P,)` wavelengths in nm.
    - `relative`: `(..., P)` the measured ratios (leading axes: sites of a map).
    - `reference`: the reference: a `Sample` (e.g. silicon with its native oxide), a material
      (a `Dispersion` or a built-in name such as `"Si"`: a bare substrate), or a constant index.
    - `angle_deg`: the angle of incidence (both measurements).
    - `sigma`: optional standard deviations of `relative` (scaled the same way).
    - `kind`: the quantity measured: `"R"` (unpolarized), `"R_s"` or `"R_p"`.
    - `sites`: labels of a map's sites.

    **Returns:** `Spectra` of `kind`, with `meta["reference_R"]` the reference's reflectance.
    """
    import jax.numpy as jnp

    if kind not in ("R", "R_s", "R_p"):
        raise ValueError(f"kind={kind!r}: must be 'R', 'R_s' or 'R_p'")
    if not isinstance(reference, Sample):
        reference = Sample((), _material(reference) if isinstance(reference, str) else reference)
    wl = np.asarray(wavelength_nm, np.float64).reshape(-1)
    rel = np.asarray(relative, np.float64)
    if rel.shape[-1] != wl.size:
        raise ValueError(f"relative has {rel.shape[-1]} points along its last axis, wavelength_nm has {wl.size}")
    if not np.all(np.isfinite(rel)) or np.any(rel < 0):
        i = int(np.argmax(~np.isfinite(rel.reshape(-1)) | (rel.reshape(-1) < 0)))
        raise ValueError(f"relative[{np.unravel_index(i, rel.shape)}] = {rel.reshape(-1)[i]}: ratios are finite and >= 0")
    R_ref = np.asarray(reference.fixed().quantities((kind,), jnp.asarray(wl), jnp.full(wl.shape, math.radians(angle_deg))))[0]
    values = {kind: rel * R_ref}
    sig = None if sigma is None else {kind: np.broadcast_to(np.asarray(sigma, np.float64), rel.shape) * R_ref}
    sp = make_spectra(wl, angle_deg, values, sigma=sig, sites=sites)
    return sp._replace(meta={"reference_R": R_ref, "relative": rel})


class ThicknessEstimate(NamedTuple):
    """`fft_thickness`'s result: `thickness_nm` `(...)` per site, `resolution_nm` (the spectrum's
    resolution in thickness, `1 / (2 n_eff (sigma_max - sigma_min))`), `n_eff` (the index that
    converts the optical path to thickness: the group index at normal incidence), `layer` (the
    film's name)."""

    thickness_nm: np.ndarray
    resolution_nm: float
    n_eff: float
    layer: str


def fft_thickness(sample: Sample, spectra: Spectra) -> ThicknessEstimate:
    """The thickness of `sample`'s one free-thickness film from the Fourier transform of its
    photometric spectra (see the module docstring), for every site of a map.

    The optical path is converted to thickness with the film's group index (its material's at
    the `Free` starts, at the middle of the wavenumber range, with the angle's correction); the
    angle is the spectra's (the most frequent one if several). The spectrum used is
    the first of `R, R_s, R_p, T, T_s, T_p` present, resampled uniformly in wavenumber,
    mean-subtracted and Hann-windowed; the peak beyond two fringes over the range is refined by a
    parabola through its three samples.

    Raises `ValueError` when the sample has not exactly one free thickness or the spectra hold no
    reflectance or transmittance.
    """
    import jax.numpy as jnp

    free = [f for f in sample.free() if f.is_thickness]
    if len(free) != 1:
        raise ValueError(f"the Fourier-transform start takes one free thickness; the sample has {len(free)}")
    layer = free[0].name.rsplit(".", 1)[0]
    kinds = [k for k in _PHOTOMETRIC if k in spectra.kinds]
    if not kinds:
        raise ValueError(f"the Fourier-transform start needs reflectance or transmittance data; these spectra hold {spectra.kinds}")
    q = spectra.kinds.index(kinds[0])
    ang = np.asarray(spectra.angle_deg)
    vals, counts = np.unique(ang, return_counts=True)
    a0 = vals[np.argmax(counts)]
    sel = np.flatnonzero(ang == a0)
    wl = np.asarray(spectra.wavelength_nm)[sel]
    order = np.argsort(1 / wl)
    s = (1 / wl)[order]
    if np.unique(s).size < 8:
        raise ValueError("the Fourier-transform start needs at least 8 wavelengths")
    li = sample.layer_names.index(layer)
    mid = 2 / (s[0] + s[-1])  # the wavelength at the middle of the wavenumber range
    h = 1e-3 * mid
    n_m, n_0, n_p = np.real(np.asarray(sample.fixed().layers[li].material.nk(jnp.asarray([mid - h, mid, mid + h]) / 1000)))
    # the fringes' phase is 4 pi sigma d sqrt(n^2 - sin^2 theta): its rate in sigma sets the peak,
    # (n^2 - sin^2 theta - lambda n dn/dlambda) / sqrt(n^2 - sin^2 theta), the group index at
    # normal incidence (a dispersive film's peak lies a few percent beyond 2 n d)
    s2 = math.sin(math.radians(a0)) ** 2
    root = math.sqrt(max(float(n_0) ** 2 - s2, 1e-12))
    n_eff = (float(n_0) ** 2 - s2 - mid * float(n_0) * float(n_p - n_m) / (2 * h)) / root
    Y = np.asarray(spectra.values)[..., q, :][..., sel][..., order].reshape(-1, sel.size)
    M = 1 << int(math.ceil(math.log2(4 * sel.size)))
    grid = np.linspace(s[0], s[-1], M)
    span = s[-1] - s[0]
    L = 16 * M
    freqs = np.fft.rfftfreq(L, d=grid[1] - grid[0])  # optical path difference, nm
    keep = freqs > 2 / span
    d = []
    for y in Y:
        u = np.interp(grid, s, y)
        u = (u - u.mean()) * np.hanning(M)
        F = np.abs(np.fft.rfft(u, L))
        F[~keep] = 0
        k = int(np.argmax(F))
        if 0 < k < F.size - 1 and F[k - 1] > 0 and F[k + 1] > 0:  # a parabola through the peak's samples
            a, b, c = F[k - 1], F[k], F[k + 1]
            k = k + 0.5 * (a - c) / (a - 2 * b + c)
        d.append(k * (freqs[1] - freqs[0]) / (2 * n_eff))
    batch = np.asarray(spectra.values).shape[:-2]
    return ThicknessEstimate(np.asarray(d).reshape(batch), 1 / (2 * n_eff * span), n_eff, layer)


def fft_window(sample: Sample, spectra: Spectra):
    """The thickness window `fit_stack(..., global_start="fft")` searches: `(index of the free
    thickness, low, high)` around every site's `fft_thickness`, wide by three resolutions and by
    the film's dispersion over the data (which shifts the peak), within the `Free` bounds."""
    import jax.numpy as jnp

    est = fft_thickness(sample, spectra)
    free = sample.free()
    i = next(j for j, f in enumerate(free) if f.is_thickness)
    li = sample.layer_names.index(est.layer)
    N = np.real(np.asarray(sample.fixed().layers[li].material.nk(jnp.asarray(np.asarray(spectra.wavelength_nm) / 1000))))
    spread = float(np.ptp(N) / max(float(np.mean(N)), 1e-12))
    d = np.asarray(est.thickness_nm).reshape(-1)
    w = 3 * est.resolution_nm + float(d.max()) * spread
    lo, hi = max(free[i].lower, float(d.min()) - w), min(free[i].upper, float(d.max()) + w)
    if not lo < hi:
        lo, hi = free[i].lower, min(free[i].upper, free[i].lower + 2 * w)
    return (i, float(lo), float(hi))
