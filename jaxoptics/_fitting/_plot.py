"""Figures of fits: reflectance curves with the fitted index (`plot_fit`), a fitted dispersion law
with its error band and residuals (`plot_dispersion_fit`), layered-sample spectra with the fitted
model and the residuals (`plot_stack_fit`), and the fitted parameters over a map
(`plot_stack_map`). `python -m jaxoptics fit --plot` draws the first, `fit-stack --plot` the last
two. matplotlib is imported when a figure is drawn."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Sequence

    from jaxtyping import ArrayLike, Float
    from matplotlib.figure import Figure

    from .._films._sample import Sample
    from .._io._spectra import Spectra
    from ._dispersion_fit import DispersionFit
    from ._index_result import FitResult
    from ._stack_fit import StackFit


# the most curves `plot_fit` draws unless told which
MAX_CURVES = 10


def plot_fit(theta: Float[ArrayLike, " m"], R: Float[ArrayLike, "*batch m"], fit: FitResult, *, eta1: float = 1.0,
             polarization: str | Sequence[str] = "unpolarized", sigma: Float[ArrayLike, "*#batch #m"] | None = None,
             which: int | Sequence[int] | None = None, title: str | None = None) -> Figure:
    """A matplotlib figure of index fits (`fit`, the `FitResult` of `fit_eta` on these data): the
    measured reflectance against angle (dots, with `sigma` as error bars) and the reflectance of the
    fitted index over all angles (lines) above, the residuals `R_model - R` (the sign of
    `FitResult.residual_rms`) below. Where the data cannot tell the index from the other branch
    (`fit.eta_alt` finite), that branch's curve is drawn dashed; a fit that did not converge says
    so in its label.

    - `theta`, `R`, `eta1`, `polarization`, `sigma`: as given to `fit_eta` (`R` one curve `(m,)` or
      a batch `(..., m)` with the batch shape of `fit`).
    - `which`: positions of the curves to draw in the flattened batch; default all of them, or the
      first `MAX_CURVES` (10) of a larger batch, which the title then says.

    Returns the `Figure` (made with `pyplot`, so a notebook shows it); save it with `savefig`."""
    import matplotlib.pyplot as plt

    from ._index import _check_polarization

    theta = np.asarray(theta, np.float64)
    R = np.asarray(R, np.float64)
    if theta.ndim != 1 or R.ndim < 1 or R.shape[-1] != theta.size:
        raise ValueError(f"theta must be (m,) and R (..., m) with the same m; got theta {theta.shape}, R {R.shape}")
    batch = R.shape[:-1]
    eta = np.asarray(fit.eta)
    if eta.shape != batch:
        raise ValueError(f"the fit has batch shape {eta.shape}, R {batch}: plot a fit with the curves it was fitted to")
    n = int(np.prod(batch))
    pol = np.broadcast_to(np.asarray(_check_polarization(polarization, batch), dtype=object), batch).reshape(n)
    S = None if sigma is None else np.asarray(sigma, np.float64)
    if S is not None:
        try:
            S = np.broadcast_to(S, R.shape).reshape(n, -1)
        except ValueError:
            raise ValueError(f"sigma has shape {S.shape}, which does not broadcast to R's {R.shape}") from None
    if which is None:
        picked = list(range(min(n, MAX_CURVES)))
    else:
        picked = np.atleast_1d(np.asarray(which, dtype=object)).tolist()
        if not picked or any(not isinstance(k, (int, np.integer)) or isinstance(k, bool) or not 0 <= k < n for k in picked):
            raise ValueError(f"which must be positions of curves in 0..{n - 1}, got {which!r}")
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(7.5, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
    Rf = R.reshape(n, -1)
    fields = {f: np.asarray(getattr(fit, f)).reshape(n) for f in ("eta", "stderr", "eta_alt", "converged")}
    for c, k in enumerate(picked):
        at = f" [{k}]" if n > 1 else ""
        _draw_index_fit(ax, axr, theta, Rf[k], None if S is None else S[k], str(pol[k]), fields["eta"][k],
                        fields["stderr"][k], fields["eta_alt"][k], bool(fields["converged"][k]), eta1, f"C{c % 10}",
                        f"{pol[k]}{at}")
    shown = "" if which is not None or n <= MAX_CURVES else f" (curves 0-{MAX_CURVES - 1} of {n})"
    _finish_index_figure(ax, axr, f"{title or 'index fit'}{shown}")
    return fig


def plot_dispersion_fit(wavelength_um: Float[ArrayLike, " w"], theta: Float[ArrayLike, " m"], R: Float[ArrayLike, "w m"],
                        fit: DispersionFit, *, eta1: float = 1.0, polarization: str = "unpolarized",
                        title: str | None = None) -> Figure:
    """A matplotlib figure of a dispersion fit (`fit`, the `DispersionFit` of `fit_dispersion` on
    these data): the fitted law `n(lambda)` over the measured range with its band of two standard
    errors (`fit.index`), marked at the measured wavelengths, and the residuals `R_model - R` against
    angle, one colour per wavelength. The title names the law and says if the fit did not converge.

    - `wavelength_um`, `theta`, `R`, `eta1`, `polarization`: as given to `fit_dispersion`.

    Returns the `Figure` (made with `pyplot`, so a notebook shows it); save it with `savefig`."""
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    from ._index import _check_polarization

    lam = np.asarray(wavelength_um, np.float64)
    theta = np.asarray(theta, np.float64)
    R = np.asarray(R, np.float64)
    if lam.ndim != 1 or theta.ndim != 1 or R.shape != (lam.size, theta.size):
        raise ValueError(f"wavelength_um must be (w,), theta (m,) and R (w, m); got {lam.shape}, {theta.shape} and {R.shape}")
    _check_polarization(polarization, ())
    lo, hi = lam.min(), lam.max()
    grid = np.linspace(lo - 0.03 * (hi - lo), hi + 0.03 * (hi - lo), 300)
    n_all, se_all = (np.asarray(x) for x in fit.index(np.concatenate([grid, lam])))
    n_grid, se_grid, n_lam = n_all[: grid.size], se_all[: grid.size], n_all[grid.size :]
    fig, (ax, axr) = plt.subplots(1, 2, figsize=(11, 4.5))
    ax.fill_between(grid, n_grid - 2 * se_grid, n_grid + 2 * se_grid, color="C1", alpha=0.3, label="+- 2 standard errors")
    ax.plot(grid, n_grid, "C1", lw=1.2, label=f"{fit.model} law, {fit.terms} terms")
    ax.plot(lam, n_lam, "o", color="C1", ms=4, label="measured wavelengths")
    ax.set_xlabel("wavelength (um)")
    ax.set_ylabel("n")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    resid = _index_reflectance(float(eta1), str(polarization))(n_lam, theta) - R
    norm = Normalize(lo, hi if hi > lo else lo + 1)
    for k in np.argsort(lam):
        axr.plot(np.rad2deg(theta), resid[k], ".", ms=3, color=plt.get_cmap("viridis")(norm(lam[k])))
    fig.colorbar(ScalarMappable(norm, "viridis"), ax=axr, label="wavelength (um)")
    axr.axhline(0, color="k", lw=0.8)
    axr.set_xlabel("angle of incidence (degrees)")
    axr.set_ylabel("model - data")
    axr.grid(alpha=0.3)
    failed = "" if bool(np.asarray(fit.converged)) else " - the fit did NOT converge"
    fig.suptitle(f"{title or 'dispersion fit'}: {fit.model}, chi2/dof = {float(fit.chi2_reduced):.3g}{failed}", fontsize=10)
    fig.tight_layout()
    return fig


def _draw_index_fit(ax, axr, theta, R, sigma, polarization, eta, stderr, eta_alt, converged, eta1, color, name):
    """One curve of an index-fit figure: data and the fitted index's reflectance on `ax`, model -
    data on `axr`; the other branch dashed where `eta_alt` is finite."""
    fine = np.linspace(0.0, np.pi / 2, 400)
    model = _index_reflectance(float(eta1), polarization)
    deg = np.rad2deg(theta)
    absorbing = np.iscomplexobj(eta)
    if absorbing:
        e, se = complex(eta), complex(stderr)
        value = f"{e.real:.6g}{e.imag:+.6g}i (+- {se.real:.2g}, {se.imag:.2g}i)"
    else:
        value = f"{float(eta):.7g} +- {float(stderr):.2g}"
    if not converged:
        value += " (NOT converged)"
    ax.errorbar(deg, R, yerr=sigma, fmt="o", ms=3.5, color=color, label=f"data {name}")
    ax.plot(np.rad2deg(fine), model(eta, fine), "-", color=color, lw=1.2, label=f"fit {name}: eta = {value}")
    if not absorbing and np.isfinite(eta_alt):
        ax.plot(np.rad2deg(fine), model(eta_alt, fine), "--", color=color, lw=1,
                label=f"other branch: eta = {float(eta_alt):.7g} (fits almost as well)")
    axr.errorbar(deg, model(eta, theta) - R, yerr=sigma, fmt="o", ms=3, color=color)


def _finish_index_figure(ax, axr, title):
    axr.axhline(0, color="k", lw=0.8)
    ax.set_ylabel("reflectance R")
    axr.set_ylabel("model - data")
    axr.set_xlabel("angle of incidence (degrees)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    axr.grid(alpha=0.3)
    ax.figure.tight_layout()


@functools.lru_cache(maxsize=16)
def _index_reflectance(eta1, polarization):
    """`(eta, theta) -> R` for one index, compiled once per incident index and polarization (and
    per dtype of `eta`), as numbers."""
    import jax

    from ._index_model import synthetic_reflectance

    f = jax.jit(lambda eta, theta: synthetic_reflectance(None, eta, theta, eta1=eta1, polarization=polarization))
    return lambda eta, theta: np.asarray(f(eta, np.asarray(theta, np.float64)))


def _curves(sample, spectra, values, site=0, fine=8):
    """The curves of a fit of `sample` to one site of `spectra` with free parameters `values` (in
    the order of `sample.free_names()`): `(xlabel, panels)`, one panel `(kind, curves)` per
    measured quantity, each curve a tuple `(label, x_model, model, x_data, shown, residual,
    index)`, `index` the positions of its points among the spectra's points.

    A curve is one angle of incidence over wavelength, or one wavelength over angle for data with
    fewer distinct wavelengths than angles (angle scans). The model is evaluated (in one call for
    all curves) at the data's points and at `fine - 1` more points in each gap between them, so
    that a line through `(x_model, model)` follows the model between measurements. `residual` is
    model minus data at `x_data`. `delta_deg` is given in `[0, 360)`: `model` holds a NaN where
    the model wraps (a line drawn through it breaks there instead of crossing the axes), the
    residual is taken in `[-180, 180)` and `shown = model - residual` places each measurement on
    the model's branch. For other quantities `shown` is the data."""
    import jax.numpy as jnp

    wl, ang = np.asarray(spectra.wavelength_nm, float), np.asarray(spectra.angle_deg, float)
    V = np.asarray(spectra.values).reshape((-1,) + spectra.values.shape[-2:])[_site_index(spectra, site)]
    over_angle = np.unique(wl).size < np.unique(ang).size
    xs, keys = (ang, wl) if over_angle else (wl, ang)
    groups = []
    for key in np.unique(keys):
        m = np.flatnonzero(keys == key)
        m = m[np.argsort(xs[m], kind="stable")]
        u = np.unique(xs[m])
        between = np.linspace(u[0], u[-1], fine * (u.size - 1) + 1) if u.size > 1 else u
        groups.append((key, m, np.unique(np.concatenate([u, between]))))
    xf = np.concatenate([g[2] for g in groups])
    kf = np.concatenate([np.full(g[2].size, g[0]) for g in groups])
    try:
        quantities = _quantities(sample, tuple(spectra.kinds))
    except TypeError:  # a sample that cannot be a cache key
        quantities = _quantities.__wrapped__(sample, tuple(spectra.kinds))
    wl_f, ang_f = (kf, xf) if over_angle else (xf, kf)
    model = np.asarray(quantities(jnp.asarray(np.asarray(values, np.float64).reshape(-1)), jnp.asarray(wl_f),
                                  jnp.asarray(np.radians(ang_f))))
    panels = []
    for q, kind in enumerate(spectra.kinds):
        curves, start = [], 0
        for key, m, xg in groups:
            yg = model[q, start:start + xg.size]
            start += xg.size
            at = yg[np.searchsorted(xg, xs[m])]  # every measured x is a point of the group's grid
            resid = at - V[q][m]
            if kind == "delta_deg":
                resid = (resid + 180) % 360 - 180
                at, yg = at % 360, yg % 360
                cut = np.flatnonzero(np.abs(np.diff(yg)) > 180) + 1
                xg, yg = np.insert(xg, cut, np.nan), np.insert(yg, cut, np.nan)
            label = f"fit, {key:g} nm" if over_angle else f"fit, {key:g} deg"
            curves.append((label, xg, yg, xs[m], at - resid, resid, m))
        panels.append((kind, curves))
    return ("angle of incidence (deg)" if over_angle else "wavelength (nm)"), panels


def plot_stack_fit(sample: Sample, spectra: Spectra, fit: StackFit, *, site: int | str = 0, residuals: str = "difference",
                   fine: int = 8, title: str | None = None) -> Figure:
    """A matplotlib figure of the fit `fit` (a `StackFit` of `sample` to `spectra`) at one site:
    for each measured quantity, the data (dots) and the model (lines, drawn between the measured
    points too, with delta's line broken where it wraps) above, the residuals below; the fitted
    values in the title (which says so if the fit did not converge).

    - `site`: the map point, by position or by label (`spectra.sites`); ignored for one spectrum.
    - `residuals`: `"difference"` (model - data, in the quantity's unit) or `"normalized"`
      (model - data over sigma; needs `spectra.sigma`).
    - `fine`: the model's points per gap between measured points (at least 1).

    Returns the `Figure` (made with `pyplot`, so a notebook shows it); save it with `savefig`."""
    import matplotlib.pyplot as plt

    if residuals not in ("difference", "normalized"):
        raise ValueError(f"residuals must be 'difference' or 'normalized', got {residuals!r}")
    if residuals == "normalized" and spectra.sigma is None:
        raise ValueError("residuals='normalized' needs the spectra's sigma; these spectra have none")
    if not isinstance(fine, (int, np.integer)) or isinstance(fine, bool) or fine < 1:
        raise ValueError(f"fine must be a whole number of points per gap, at least 1, got {fine!r}")
    _check_fit(spectra, fit)
    k = _site_index(spectra, site)
    x = np.asarray(fit.values).reshape(-1, len(fit.names))[k]
    xlabel, panels = _curves(sample, spectra, x, k, fine)
    # the residuals' scale: sigma, or 1 for differences
    S = np.ones(spectra.values.shape[-2:]) if residuals == "difference" else np.asarray(spectra.sigma).reshape(
        (-1,) + spectra.values.shape[-2:])[k]
    Q = len(panels)
    fig, axes = plt.subplots(2, Q, figsize=(5 * Q, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]}, squeeze=False)
    for q, (kind, curves) in enumerate(panels):
        for label, xf, yf, xd, shown, resid, m in curves:
            line, = axes[0, q].plot(xf, yf, lw=1.2, label=label)
            axes[0, q].plot(xd, shown, ".", ms=2.5, color=line.get_color())
            axes[1, q].plot(xd, resid / S[q][m], ".", ms=2.5, color=line.get_color())
        axes[0, q].set_ylabel(kind)
        axes[1, q].set_ylabel("(model - data) / sigma" if residuals == "normalized" else "model - data")
        axes[1, q].set_xlabel(xlabel)
        axes[1, q].axhline(0, color="k", lw=0.5)
    axes[0, 0].legend(fontsize=8)
    params = ", ".join(f"{n} = {v:.5g}" for n, v in zip(fit.names, x))
    n_sites = np.asarray(fit.values).size // len(fit.names)
    where = f" (site {spectra.sites[k] if spectra.sites else k} of {n_sites})" if spectra.batch_shape else ""
    failed = "" if np.asarray(fit.converged).reshape(-1)[k] else " - the fit did NOT converge"
    fig.suptitle(f"{title or _name(spectra) or 'layered-sample fit'}{where}{failed}\n{params}", fontsize=9)
    fig.tight_layout()
    return fig


@functools.lru_cache(maxsize=16)
def _quantities(sample, kinds):
    """`(x, wavelength_nm, angle_rad) -> quantities` of `sample` with free parameters `x`, compiled
    as one program (evaluated op by op, JAX would compile each of the model's operations for new
    shapes: several seconds on a first figure) and kept for the next figure of the same sample."""
    import jax

    return jax.jit(lambda x, w, a: sample.with_values(list(x)).quantities(kinds, w, a))


def _name(spectra):
    """The name of the file the spectra were read from, or None."""
    import os

    return os.path.basename(spectra.path) if spectra.path else None


def _check_fit(spectra, fit):
    """That `fit` holds one fit per spectrum of `spectra`."""
    n = int(np.prod(spectra.batch_shape))
    m = np.asarray(fit.values).size // max(len(fit.names), 1)
    if m != n:
        raise ValueError(f"the fit holds {m} fits, the spectra {n} spectra: plot a fit with the spectra it was fitted to")


def _site_index(spectra, site):
    """The position of `site` (a position or a label of `spectra.sites`) among the spectra's sites."""
    n = int(np.prod(spectra.batch_shape))
    if isinstance(site, str):
        if not spectra.sites or site not in spectra.sites:
            some = "" if not spectra.sites else f" (sites: {', '.join(spectra.sites[:5])}{', ...' if len(spectra.sites) > 5 else ''})"
            raise ValueError(f"site {site!r} is not a site of these spectra{some}")
        return spectra.sites.index(site)
    if not isinstance(site, (int, np.integer)) or not -n <= site < n:
        raise ValueError(f"site must be a position in 0..{n - 1} or a site label, got {site!r}")
    return int(site) % n


def plot_stack_map(spectra: Spectra, fit: StackFit, *, names: tuple | list | None = None) -> Figure:
    """A matplotlib figure of a map fit (`fit_stack` on `spectra` with sites): for each free
    parameter (or those in `names`) its fitted value and its standard error over the map, and
    `chi2_reduced`; sites that did not converge are marked with a red x.

    With site positions (`spectra.site_xy`: the `x_mm`, `y_mm` columns) each panel is a map over
    the sample, colour interpolated linearly between the sites (over their Delaunay triangles;
    sites on one line are drawn as dots). Without them, each panel plots the quantity against the
    site's position in the file.

    Returns the `Figure` (made with `pyplot`, so a notebook shows it); save it with `savefig`."""
    import matplotlib.pyplot as plt

    if not spectra.batch_shape:
        raise ValueError("plot_stack_map draws maps: these spectra are one spectrum (no sites); see plot_stack_fit")
    names = list(fit.names) if names is None else list(names)
    unknown = [n for n in names if n not in fit.names]
    if unknown:
        raise ValueError(f"{unknown} are not free parameters of this fit; they are {', '.join(fit.names)}")
    _check_fit(spectra, fit)
    n = int(np.prod(spectra.batch_shape))
    vals = np.asarray(fit.values, np.float64).reshape(n, -1)
    sds = np.asarray(fit.stderr, np.float64).reshape(n, -1)
    panels = []
    for name in names:
        k = list(fit.names).index(name)
        panels += [(name, vals[:, k], "viridis"), (f"stderr of {name}", sds[:, k], "magma")]
    panels.append(("chi2_reduced", np.asarray(fit.chi2_reduced, np.float64).reshape(n), "cividis"))
    failed = ~np.asarray(fit.converged, bool).reshape(n)
    xy = None if spectra.site_xy is None else np.asarray(spectra.site_xy, np.float64).reshape(n, 2)
    tri = None
    if xy is not None and n >= 3:
        import matplotlib.tri as mtri

        try:
            tri = mtri.Triangulation(xy[:, 0], xy[:, 1])
        except (ValueError, RuntimeError):  # fewer than three distinct sites, or all on one line
            tri = None
    rows = (len(panels) + 1) // 2
    fig, axes = plt.subplots(rows, 2, figsize=(10, 3.8 * rows), squeeze=False)
    for ax, (title, z, cmap) in zip(axes.flat, panels):
        if xy is None:
            ax.plot(np.arange(n), z, ".", ms=3)
            ax.plot(np.flatnonzero(failed), z[failed], "x", color="red", ms=6)
            ax.set_xlabel("site (position in the file)")
        else:
            finite = np.isfinite(z)
            if tri is not None and finite.all():
                art = ax.tripcolor(tri, z, shading="gouraud", cmap=cmap)
            else:
                art = ax.scatter(xy[:, 0], xy[:, 1], c=np.where(finite, z, np.nan), cmap=cmap, s=12)
            fig.colorbar(art, ax=ax, shrink=0.85)
            ax.plot(xy[failed, 0], xy[failed, 1], "x", color="red", ms=6)
            ax.set_aspect("equal")
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
        ax.set_title(title, fontsize=10)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    note = f"; {int(failed.sum())} not converged (x)" if failed.any() else ""
    fig.suptitle(f"{_name(spectra) or 'map fit'}: {n} sites{note}", fontsize=9)
    fig.tight_layout()
    return fig
