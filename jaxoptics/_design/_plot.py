"""The figure of a design: per target, the designed quantity over its wavelengths with the target
points and their tolerances; the index profile (real part at the shortest target wavelength
against depth); the merit's history."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ._targets import Target

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ._design import Design

_UNITS = {"R": "", "T": "", "A": "", "phase_r": " (deg)", "phase_t": " (deg)", "GD_r": " (fs)", "GD_t": " (fs)",
          "GDD_r": " (fs$^2$)", "GDD_t": " (fs$^2$)", "psi": " (deg)", "delta": " (deg)"}


def plot_design(design: Design, targets: Sequence[Target], *, title: str | None = None) -> Figure:
    """A matplotlib `Figure` of `design` (a `Design`) against `targets`: one panel per target
    (the designed curve over the target's wavelengths, 10 % wider where it is one wavelength;
    the target points, with their tolerances as a band, or as error bars for one point;
    one-sided targets as triangles), the index profile, and the merit per needle round (or, for
    a refinement alone, the merit each start reached)."""
    import matplotlib.pyplot as plt

    from ._design import target_values
    from ._targets import COLOR

    targets = list(targets)
    probes = []
    for t in targets:
        wl = t._points[0]
        if t.quantity in COLOR:  # the spectrum whose colour it is
            probes.append(Target(t.quantity[0], wl, 0.0, angle_deg=float(t._points[2][0]), polarization=t.polarization))
            continue
        lo, hi = float(wl.min()), float(wl.max())
        if hi - lo < 1e-9 * hi:
            lo, hi = 0.9 * lo, 1.1 * hi
        ang = t._points[2]
        probes.append(Target(t.quantity, np.linspace(lo, hi, 241), 0.0, angle_deg=float(np.mean(ang)),
                             polarization=t.polarization))
    curves = target_values(design, probes)
    colors = target_values(design, [t for t in targets if t.quantity in COLOR]) if any(t.quantity in COLOR for t in targets) else []
    colors_it = iter(colors)
    n = len(targets) + 2
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.4 * rows), squeeze=False)
    axes = axes.ravel()
    for ax, t, p, c in zip(axes, targets, probes, curves):
        wl, value, ang, tol = t._points
        ax.plot(p._points[0], c, lw=1.4, label="design")
        if t.quantity in COLOR:
            got = float(next(colors_it)[0])
            ax.set_title(f"{t.quantity} under {t.illuminant}: {got:.4g} (target {t.kind} {value[0]:g} +- {tol[0]:g})", fontsize=9)
            ax.set_xlabel("wavelength (nm)")
            ax.set_ylabel(t.quantity[0])
            continue
        marker = {"=": "o", "<=": "v", ">=": "^"}[t.kind]
        if wl.size > 1:  # one tolerance around the target, or beyond a bound (the scale of its violation)
            order = np.argsort(wl)
            w, v, e = wl[order], value[order], tol[order]
            lo = v - e if t.kind == "=" else v if t.kind == "<=" else v - e
            hi = v + e if t.kind == "=" else v + e if t.kind == "<=" else v
            ax.fill_between(w, lo, hi, color="C3", alpha=0.15, lw=0,
                            label="tolerance" if t.kind == "=" else "one tolerance beyond the bound")
            ax.plot(w, v, marker, ms=2.5, color="C3", label=f"target ({t.kind})")
        else:
            ax.errorbar(wl, value, yerr=tol, fmt=marker, ms=4, lw=0.8, color="C3", label=f"target ({t.kind})")
        pol = "" if t.quantity in ("psi", "delta") else f", {t.polarization}"
        ax.set_title(f"{t.quantity}{pol}, {np.mean(ang):g} deg", fontsize=9)
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel(t.quantity + _UNITS[t.quantity])
        ax.legend(fontsize=7)
    ax = axes[len(targets)]
    wl_min = min(float(t._points[0].min()) for t in targets)
    depth = np.concatenate([[0.0], np.cumsum(design.values)])
    n_re = [float(np.real(np.asarray(m.nk(wl_min / 1000)))) for m in design.materials]
    if design.layers:
        ax.stairs(n_re, depth, baseline=None, lw=1.4)
    ax.set_xlabel("depth from the top (nm)")
    ax.set_ylabel(f"n at {wl_min:g} nm")
    ax.set_title(f"{design.layers} layers, {depth[-1]:.0f} nm", fontsize=9)
    ax = axes[len(targets) + 1]
    if design.history.size > 1:
        ax.semilogy(np.arange(design.history.size), design.history, "o-", ms=3)
        ax.set_xlabel("refinement (0: the starts; then needle rounds)")
    else:  # one refinement: what each start reached
        ax.semilogy(np.arange(1, design.merits.size + 1), np.sort(design.merits), "o", ms=3)
        ax.set_xlabel("start (sorted by the merit it reached)")
    ax.set_ylabel("merit")
    ax.set_title(f"merit {design.merit:.4g}", fontsize=9)
    for ax in axes[n:]:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
