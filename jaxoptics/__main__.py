"""Command line: `python -m jaxoptics <command>`.

Commands:
  demo    print R_s, R_p, R and T across angles for air -> glass and glass -> air, with the
          critical and Brewster angles (a quick check that the install works).
  fit     fit the refractive index to reflectance-versus-angle data in a CSV file
          (`fit --example` uses the bundled N-BK7 measurement); with `--dispersion`, also one
          Sellmeier or Cauchy law over all its wavelengths.
  fit-stack  fit a layered sample (film thicknesses, n, k, dispersion) to spectroscopic data
          (psi/delta, N/C/S, Mueller, R, T) with a TOML model (`fit-stack --example`: SiO2 on Si).
  design  design a coating's layer thicknesses to meet targets (R, T, A, phase, GD, GDD,
          psi/delta) from a TOML file, by refinement and needle synthesis (`design --example`:
          a broadband anti-reflection coating on N-BK7).
  bench   measure speed (and error) side by side on this machine; --quick for a short run.
  stress  numerical stress test of every kernel (10^6 inputs per dtype; values, gradients,
          invariants) against high-precision references.
"""

from __future__ import annotations

import argparse
import atexit
import os
import sys
from pathlib import Path


def _use_compilation_cache(args) -> None:
    """`jaxoptics.enable_cache()` for this process (JAX's persistent compilation cache and the
    fits' traced programs, in `$JAXOPTICS_CACHE_DIR` or `~/.cache/jaxoptics/xla`), unless the
    command was given `--no-cache` or `JAXOPTICS_CACHE_DIR=off`."""
    if getattr(args, "no_cache", False):
        return
    from ._runtime._cache import enable_cache

    enable_cache()


def _demo(args) -> int:
    import jax
    import numpy as np

    _use_compilation_cache(args)

    jax.config.update("jax_enable_x64", True)
    import jaxoptics as jo

    pairs = [(1.0, args.eta), (args.eta, 1.0)]
    angles = np.array([0, 10, 20, 30, 40, 41.8, 45, 50, 56.3, 60, 70, 80, 85, 89, 90], dtype=np.float64)
    for e1, e2 in pairs:
        th_c = float(jo.critical_angle(e1, e2))
        th_b = float(jo.brewster_angle(e1, e2))
        crit = f"{np.rad2deg(th_c):.4f} deg" if e1 > e2 else "none (entering the denser medium)"
        print(f"\neta1 = {e1:g} -> eta2 = {e2:g}:  Brewster {np.rad2deg(th_b):.4f} deg,  critical {crit}")
        c = np.cos(np.deg2rad(angles))
        R_s, R_p = jo.fresnel_sp(c, e1, e2)
        R, T = jo.fresnel_rt(c, e1, e2)
        i = np.stack([np.sin(np.deg2rad(angles)), 0 * angles, -c], -1)
        t, tir = jo.refract(i, np.array([0.0, 0.0, 1.0]), e1, e2)
        theta_t = np.rad2deg(np.arctan2(np.hypot(t[:, 0], t[:, 1]), -np.asarray(t[:, 2])))
        print(f"{'theta_i':>8} {'R_s':>10} {'R_p':>10} {'R':>10} {'T':>10} {'theta_t':>9}  TIR")
        for k, a in enumerate(angles):
            tt = "   --" if bool(tir[k]) else f"{theta_t[k]:9.4f}"
            print(f"{a:8.2f} {float(R_s[k]):10.6f} {float(R_p[k]):10.6f} {float(R[k]):10.6f} {float(T[k]):10.6f} {tt:>9}  {'yes' if bool(tir[k]) else ''}")
    return 0


def _fit(args) -> int:
    import jax
    import numpy as np

    _use_compilation_cache(args)

    jax.config.update("jax_enable_x64", True)
    import jaxoptics as jo

    if args.example == bool(args.file):
        print("fit: give either a CSV file or --example", file=sys.stderr)
        return 2
    if args.terms is not None and not args.dispersion:
        print("fit: --terms goes with --dispersion", file=sys.stderr)
        return 2
    path = jo.example_path() if args.example else args.file
    try:
        data = jo.load_reflectance(path)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    curves = data.curves(default_polarization=args.polarization or "unpolarized")
    if args.polarization and data.polarization is not None:
        curves = [c for c in curves if c.polarization == args.polarization]
        if not curves:
            print(f"error: {path} has no rows with polarization {args.polarization!r}", file=sys.stderr)
            return 2
    print(f"jaxoptics fit: {path}")
    print(f"{data.R.size} points in {len(curves)} curve(s); incident medium eta1 = {args.eta1:g}; "
          f"{'absorbing (n + ik)' if args.absorbing else 'real index'}; "
          f"errors {'from the sigma column' if data.sigma is not None else 'scaled by the residual scatter'}")
    head = f"{'wavelength_um':>13} {'pol':>11} {'points':>6} {'eta':>24} {'stderr':>22} {'converged':>9} {'rms resid':>10} {'chi2/dof':>9} {'steps':>5}"
    print(head)
    from jaxoptics._fitting._index import check_curves

    for c in curves:  # each curve's data checked on its own, so that an error names its lines
        try:
            check_curves(c.theta, c.R, c.sigma, n_params=2 if args.absorbing else 1)
        except ValueError as e:
            print(f"error: {path}, curve at lines {c.lines[0]}-{c.lines[-1]}: {e}", file=sys.stderr)
            return 2
    if args.dispersion and (why := _law_refused(curves, args)):
        print(f"error: {path}: --dispersion {why}", file=sys.stderr)
        return 2
    # Curves on the same angles (any polarization and wavelength) are fitted together: one
    # compiled program and one call per group.
    groups: dict = {}
    for c in curves:
        groups.setdefault((c.theta.tobytes(), c.sigma is None), []).append(c)
    fitted = {}
    for group in groups.values():
        r = jo.fit_eta(group[0].theta, np.stack([c.R for c in group]), eta1=args.eta1,
                       polarization=tuple(c.polarization for c in group),
                       sigma=None if group[0].sigma is None else np.stack([c.sigma for c in group]),
                       absorbing=args.absorbing)
        for k, c in enumerate(group):
            fitted[id(c)] = jax.tree_util.tree_map(lambda x, k=k: np.asarray(x)[k], r)
    fits = []
    for c in curves:
        r = fitted[id(c)]
        fits.append((c, r))
        lam = "-" if c.wavelength_um is None else f"{c.wavelength_um:g}"
        eta = complex(r.eta) if args.absorbing else float(r.eta)
        se = complex(r.stderr) if args.absorbing else float(r.stderr)
        eta_s = f"{eta.real:.6f}{eta.imag:+.6f}i" if args.absorbing else f"{eta:.7f}"
        se_s = f"{se.real:.2g}, {se.imag:.2g}i" if args.absorbing else f"{se:.2g}"
        print(f"{lam:>13} {c.polarization:>11} {c.R.size:>6} {eta_s:>24} {se_s:>22} {('yes' if bool(r.converged) else 'NO'):>9} "
              f"{float(r.residual_rms):>10.3g} {float(r.chi2_reduced):>9.3g} {int(r.num_steps):>5}")
        if not args.absorbing and np.isfinite(float(r.eta_alt)):
            print(f"{'':>13} {'':>11} {'':>6} note: eta = {float(r.eta_alt):.7f} (the other side of eta1 = {args.eta1:g}) "
                  "fits these data almost as well (Delta chi2 < 9); stderr includes it")
    if not args.absorbing:
        by_lam: dict = {}
        for c, r in fits:
            by_lam.setdefault(c.wavelength_um, []).append(r)
        for lam, rs in by_lam.items():
            if len(rs) > 1:
                wts = np.array([1 / float(r.stderr) ** 2 for r in rs])
                est = np.sum(wts * np.array([float(r.eta) for r in rs])) / np.sum(wts)
                where = "" if lam is None else f" at {lam:g} um"
                print(f"combined{where}: eta = {est:.7f} +- {1 / np.sqrt(np.sum(wts)):.2g} "
                      f"(inverse-variance mean of {len(rs)} curves)")
    if any(not bool(r.converged) for _, r in fits):
        print("warning: some fits did not converge (see the converged column)", file=sys.stderr)
    if args.dispersion:
        return _fit_law(curves, args, str(path))
    if args.plot:
        _plot_fits(fits, args, str(path))
        print(f"plot saved to {args.plot}")
    return 0


def _law_refused(curves, args) -> str | None:
    """Why `fit --dispersion` cannot fit one law to these curves (one polarization, two or more
    wavelengths, all on the same angles), or None."""
    import numpy as np

    from ._fitting._dispersion_fit import _SELLMEIER_POLES, DEFAULT_TERMS

    if args.absorbing:
        return "fits a real index law; leave out --absorbing"
    terms = DEFAULT_TERMS if args.terms is None else args.terms
    if args.dispersion == "sellmeier" and terms not in _SELLMEIER_POLES or terms < 1:
        return f"{args.dispersion}: --terms {terms} is not available (Sellmeier: 1-3 terms; Cauchy: 1 or more coefficients)"
    if any(c.wavelength_um is None for c in curves):
        return "needs a wavelength_um column"
    pols = sorted({c.polarization for c in curves})
    if len(pols) > 1:
        return f"fits curves of one polarization, these have {', '.join(pols)}: choose one with --polarization"
    if len({c.wavelength_um for c in curves}) < 2:
        return f"needs curves at two or more wavelengths, these are all at {curves[0].wavelength_um:g} um"
    first = curves[0]
    n_par = terms * (2 if args.dispersion == "sellmeier" else 1)
    if len(curves) * first.theta.size <= n_par:
        return f"{len(curves) * first.theta.size} points cannot determine {n_par} coefficients"
    for c in curves[1:]:
        if not np.array_equal(c.theta, first.theta):
            what = "other angles than" if c.theta.size == first.theta.size else f"{c.theta.size} angles, against {first.theta.size} at"
            return (f"needs every wavelength measured at the same angles: {c.wavelength_um:g} um (lines "
                    f"{c.lines.min()}-{c.lines.max()}) has {what} {first.wavelength_um:g} um "
                    f"(lines {first.lines.min()}-{first.lines.max()})")
    return None


def _fit_law(curves, args, path) -> int:
    """`fit --dispersion`: one law fitted to all the curves (checked by `_law_refused`), its
    coefficients and the index at each wavelength."""
    import numpy as np

    import jaxoptics as jo

    curves = sorted(curves, key=lambda c: c.wavelength_um)
    first, pol = curves[0], curves[0].polarization
    lam = np.array([c.wavelength_um for c in curves])
    R = np.stack([c.R for c in curves])
    sigma = None if first.sigma is None else np.stack([c.sigma for c in curves])
    law = jo.fit_dispersion(lam, first.theta, R, model=args.dispersion, terms=args.terms, eta1=args.eta1,
                            polarization=pol, sigma=sigma)
    coef, se = np.asarray(law.coefficients), np.asarray(law.stderr)
    k = law.terms
    names = ([f"B_{i + 1}" for i in range(k)] + [f"C_{i + 1} (um^2)" for i in range(k)] if law.model == "sellmeier"
             else [(chr(65 + i) if i < 26 else f"a_{i}") + ("" if i == 0 else f" (um^{2 * i})") for i in range(k)])
    print(f"\n{law.model} law, {k} {'terms' if law.model == 'sellmeier' else 'coefficients'}, fitted to all {R.size} points: "
          f"converged {'yes' if bool(law.converged) else 'NO'}, chi2/dof {float(law.chi2_reduced):.3g}, "
          f"rms resid {float(law.residual_rms):.3g}, {int(law.num_steps)} steps, condition number {float(law.condition_number):.3g}")
    for name, v, e in zip(names, coef, se):
        print(f"  {name:<14} {v:>14.7g} +- {e:.3g}")
    n, n_se = (np.asarray(x) for x in law.index(lam))
    print(f"{'wavelength_um':>13} {'n (law)':>12} {'stderr':>9}")
    for l, v, e in zip(lam, n, n_se):
        print(f"{l:>13g} {v:>12.7f} {e:>9.2g}")
    if not bool(law.converged):
        print("warning: the dispersion fit did not converge", file=sys.stderr)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        fig = jo.plot_dispersion_fit(lam, first.theta, R, law, eta1=args.eta1, polarization=pol, title=Path(path).name)
        fig.savefig(args.plot, dpi=120)
        print(f"plot saved to {args.plot}")
    return 0


def _fit_stack(args) -> int:
    import jax
    import numpy as np

    _use_compilation_cache(args)
    jax.config.update("jax_enable_x64", True)
    import jaxoptics as jo

    from ._fitting._joint import is_joint_file

    if args.model and not args.data and not args.example and is_joint_file(args.model):
        return _fit_joint(args)
    if args.example == bool(args.data):
        print("fit-stack: give a data file and --model, or --example, or a joint fit's --model listing [[dataset]]s",
              file=sys.stderr)
        return 2
    data_dir = Path(jo.__file__).parent / "data"
    data_path = data_dir / "example_sio2_si.csv" if args.example else Path(args.data)
    model_path = Path(args.model) if args.model else (data_dir / "example_sio2_si.toml" if args.example else None)
    if model_path is None:
        print("fit-stack: --model MODEL.toml is required (see `python -m jaxoptics fit-stack --help`)", file=sys.stderr)
        return 2
    try:
        spectra = jo.load_spectra(data_path, format=args.format, delta_convention=args.delta_convention,
                                  delta_range=args.delta_range, mueller_s3_sign=args.mueller_s3_sign, angle_deg=args.angle_deg,
                                  quantity=args.quantity, scale=args.scale, wavelength_unit=args.wavelength_unit)
        sample = jo.load_sample(model_path)
        fmt = (spectra.meta or {}).get("format", "csv")
        print(f"jaxoptics fit-stack: {data_path} ({fmt}) with model {model_path}")
        nsites = int(np.prod(spectra.batch_shape)) if spectra.batch_shape else 1
        print(f"{spectra.wavelength_nm.size} points ({spectra.wavelength_nm.min():g}-{spectra.wavelength_nm.max():g} nm, "
              f"angles {', '.join(f'{a:g}' for a in np.unique(spectra.angle_deg))} deg) x {', '.join(spectra.kinds)}"
              f"{f'; {nsites} sites' if spectra.batch_shape else ''}; "
              f"errors {'from the sigma columns' if spectra.sigma is not None else 'scaled by the residual scatter'}")
        fit = jo.fit_stack(sample, spectra, starts=args.starts, progress=nsites > 256)
    except (ValueError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stats = jo.fit_statistics(sample, spectra, fit)
    if not spectra.batch_shape:
        print(fit.table(statistics=stats))
        i = range(len(fit.names))
        corr = np.asarray(fit.correlation)
        strong = [(fit.names[a], fit.names[b], corr[a, b]) for a in i for b in i if a < b and abs(corr[a, b]) > 0.9]
        for a, b, c in strong:
            print(f"note: {a} and {b} are correlated ({c:+.3f}): the data determine a combination of them better than either")
    else:
        vals = np.asarray(fit.values).reshape(nsites, -1)
        sds = np.asarray(fit.stderr).reshape(nsites, -1)
        conv = np.asarray(fit.converged).reshape(nsites)
        print(f"{'parameter':<24} {'mean':>14} {'std over sites':>15} {'median stderr':>14}")
        for k, n in enumerate(fit.names):
            print(f"{n:<24} {vals[:, k].mean():>14.6g} {vals[:, k].std():>15.3g} {np.median(sds[:, k]):>14.3g}")
        med = lambda a: f"{np.nanmedian(a):.4g}" if np.isfinite(a).any() else "n/a"
        print(f"converged at {int(conv.sum())} of {nsites} sites; median MSE {med(stats.mse)} (WVASE), "
              f"{med(stats.mse_ncs)} (CompleteEASE N,C,S)")
        if args.out:
            labels = spectra.sites or tuple(str(k) for k in range(nsites))
            with open(args.out, "w", encoding="utf-8") as f:
                xy = None if spectra.site_xy is None else np.asarray(spectra.site_xy).reshape(nsites, 2)
                where = ["x_mm", "y_mm"] if xy is not None else []
                f.write(",".join(["site"] + where + [x for n in fit.names for x in (n, f"stderr_{n}", f"ci90_{n}")]
                                 + ["chi2_reduced", "mse", "mse_ncs", "converged"]) + "\n")
                chi = np.asarray(fit.chi2_reduced).reshape(nsites)
                ci = np.asarray(stats.ci90).reshape(nsites, -1)
                mse, mse_ncs = (np.asarray(a).reshape(nsites) for a in (stats.mse, stats.mse_ncs))
                for s in range(nsites):
                    cells = [labels[s]] + ([repr(float(c)) for c in xy[s]] if xy is not None else [])
                    cells += [repr(float(x)) for k in range(len(fit.names)) for x in (vals[s, k], sds[s, k], ci[s, k])]
                    f.write(",".join(cells + [repr(float(v)) for v in (chi[s], mse[s], mse_ncs[s])] + [str(bool(conv[s]))]) + "\n")
            print(f"per-site results written to {args.out}")
    poor = not bool(np.all(np.asarray(fit.converged))) or float(np.max(np.asarray(fit.chi2_reduced))) > 4
    if not bool(np.all(np.asarray(fit.converged))):
        print("warning: some fits did not converge", file=sys.stderr)
    unbounded = [f.name for f in sample.free() if f.is_thickness and not np.isfinite(f.upper)]
    if poor and unbounded:
        print(f"note: {', '.join(unbounded)} {'has' if len(unbounded) == 1 else 'have'} no upper bound, so no search over "
              "fringes was made: a fit started a fringe away ends in a wrong minimum; give the thickness a max in the model file",
              file=sys.stderr)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from ._fitting._plot import plot_stack_fit

        fig = plot_stack_fit(sample, spectra, fit, title=f"fit-stack: {data_path.name}")
        fig.savefig(args.plot, dpi=120)
        plt.close(fig)
        print(f"plot saved to {args.plot}" + (f" (site {spectra.sites[0] if spectra.sites else 0})" if spectra.batch_shape else ""))
        if spectra.batch_shape:
            from ._fitting._plot import plot_stack_map

            out = Path(args.plot)
            out = out.with_name(out.stem + "_map" + (out.suffix or ".png"))
            fig = plot_stack_map(spectra, fit)
            fig.savefig(out, dpi=120)
            plt.close(fig)
            print(f"maps of the fitted parameters saved to {out}")
    return 0


def _fit_joint(args) -> int:
    """`fit-stack --model joint.toml`: the data sets the file lists, fitted together."""
    import numpy as np

    import jaxoptics as jo

    from ._fitting._joint import load_joint

    try:
        datasets, shared = load_joint(args.model)
        print(f"jaxoptics fit-stack: joint fit of {len(datasets)} data sets from {args.model}")
        for k, d in enumerate(datasets):
            sp = d.spectra
            print(f"  {d.name or f'data{k + 1}'}: {sp.path} ({(sp.meta or {}).get('format', 'csv')}), {sp.wavelength_nm.size} "
                  f"points x {', '.join(sp.kinds)}, weight {d.weight:g}")
        fit = jo.fit_joint(datasets, shared=shared)
    except (ValueError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if fit.values.ndim == 1:
        print(fit.table())
    else:
        vals = np.asarray(fit.values).reshape(-1, len(fit.names))
        print(f"{'parameter':<32} {'mean':>14} {'std over sites':>15}")
        for k, n in enumerate(fit.names):
            print(f"{n:<32} {vals[:, k].mean():>14.6g} {vals[:, k].std():>15.3g}")
        print(f"converged at {int(np.sum(fit.converged))} of {vals.shape[0]} sites")
    if not bool(np.all(np.asarray(fit.converged))):
        print("warning: some fits did not converge", file=sys.stderr)
    return 0


def _plot_fits(fits, args, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ._fitting._plot import _draw_index_fit, _finish_index_figure

    fig, (ax, axr) = plt.subplots(2, 1, figsize=(7.5, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
    for k, (c, r) in enumerate(fits):
        lam = "" if c.wavelength_um is None else f", {c.wavelength_um:g} um"
        _draw_index_fit(ax, axr, c.theta, c.R, c.sigma, c.polarization, r.eta, r.stderr, r.eta_alt, bool(r.converged),
                        args.eta1, f"C{k % 10}", f"({c.polarization}{lam})")
    _finish_index_figure(ax, axr, f"index fit: {Path(title).name}")
    fig.savefig(args.plot, dpi=120)


def _design(args) -> int:
    import jax
    import numpy as np

    _use_compilation_cache(args)
    jax.config.update("jax_enable_x64", True)
    import jaxoptics as jo

    from ._design._file import DesignFile, write_sample

    if args.example == bool(args.file):
        print("design: give a design file or --example", file=sys.stderr)
        return 2
    path = Path(jo.__file__).parent / "data" / "example_ar_design.toml" if args.example else Path(args.file)
    try:
        src = DesignFile(path)
        opts = dict(src.options)
        print(f"jaxoptics design: {path}: {len(src.sample.layers)} start layers, {len(src.targets)} targets "
              f"({sum(t.points for t in src.targets)} points), merit {jo.merit(src.sample, src.targets):.4g}"
              + (f"; needle synthesis with {len(opts.get('materials', []))} materials" if opts.get("needle") else ""))
        d = jo.design(src.sample, src.targets, progress=True, **opts)
    except (ValueError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(d.table())
    ea = jo.thickness_errors(d, src.targets)
    print(f"under 1 % thickness errors (100 draws): expected merit {ea.expected_merit:.4g}, "
          f"yield (merit <= 1) {100 * ea.yield_fraction:.0f} %; most sensitive layer: "
          f"{d.names[int(np.argmax(ea.sensitivity))] if d.layers else '-'}")
    if args.out:
        write_sample(args.out, d, src)
        print(f"designed sample written to {args.out}")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig = jo.plot_design(d, src.targets, title=src.doc.get("title"))
        fig.savefig(args.plot, dpi=120)
        plt.close(fig)
        print(f"plot saved to {args.plot}")
    return 0


def _tools_missing() -> str | None:
    """The name of a tool dependency that is not installed, or None."""
    import importlib.util

    for mod in ("mpmath", "tqdm", "scipy", "tmm"):
        if importlib.util.find_spec(mod) is None:
            return mod
    return None


def _need_tools(command) -> int | None:
    missing = _tools_missing()
    if missing:
        print(f"{command}: needs the measuring tools' dependencies ({missing} is not installed): "
              "pip install 'jaxoptics[tools]'", file=sys.stderr)
        return 2
    return None


def _bench(args) -> int:
    if (rc := _need_tools("bench")) is not None:
        return rc
    from .tools.bench import run

    run(quick=args.quick, sections=tuple(args.sections.split(",")), out_dir=args.out, mitsuba=not args.no_mitsuba)
    return 0


def _stress(args) -> int:
    if (rc := _need_tools("stress")) is not None:
        return rc
    from .tools.stress import run

    run(n=args.n, out_dir=args.out, mp_samples=args.mp_samples, mitsuba=not args.no_mitsuba)
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jaxoptics", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="Fresnel table for air/glass in both directions")
    p.add_argument("--eta", type=float, default=1.5, help="index of the glass (default 1.5)")
    p.add_argument("--no-cache", action="store_true", help="do not use the compilation cache (see `fit --help`)")
    p.set_defaults(func=_demo)
    p = sub.add_parser("fit", help="fit the index to reflectance-vs-angle data in a CSV file")
    p.add_argument("file", nargs="?", help="CSV with columns angle_deg, R [, polarization, wavelength_um, sigma]")
    p.add_argument("--example", action="store_true", help="use the bundled N-BK7 example measurement")
    p.add_argument("--polarization", choices=["s", "p", "unpolarized"],
                   help="polarization of files without a polarization column; with one, fit only these rows")
    p.add_argument("--eta1", type=float, default=1.0, help="index of the incident medium (default 1.0)")
    p.add_argument("--absorbing", action="store_true", help="fit a complex index n + ik")
    p.add_argument("--dispersion", choices=["sellmeier", "cauchy"],
                   help="also fit this law n(wavelength) to all curves at once (one polarization, every "
                        "wavelength on the same angles)")
    p.add_argument("--terms", type=int, help="Sellmeier terms or Cauchy coefficients (default 3; 2 for noisy "
                                             "Sellmeier data over the visible)")
    p.add_argument("--plot", metavar="OUT.png", help="save data, fit and residuals as a figure (with --dispersion: "
                                                     "the law with its error band and the residuals)")
    p.add_argument("--no-cache", action="store_true",
                   help="do not keep compiled programs between runs (by default they are kept in "
                        "$JAXOPTICS_CACHE_DIR or ~/.cache/jaxoptics/xla; JAXOPTICS_CACHE_DIR=off turns it off)")
    p.set_defaults(func=_fit)
    p = sub.add_parser("fit-stack", help="fit a layered sample to spectroscopic data (psi/delta, N/C/S, Mueller, R, T)")
    p.add_argument("data", nargs="?", help="the measurement: jaxoptics' CSV (wavelength_nm|wavelength_um, angle_deg and "
                   "measured columns psi_deg, delta_deg, N, C, S, m11..m44, R, R_s, R_p, T, T_s, T_p; sigma_<column>; site "
                   "for maps) or an instrument's export (Woollam .dat, SpectraRay, Accurion, Horiba, Film Sense, R/T text, "
                   "JCAMP-DX: docs/data-files), detected from its content")
    p.add_argument("--model", metavar="MODEL.toml", help="the sample: layers, materials, free parameters (format: docs/layered-fits); "
                                                         "or, without a data file, a joint fit listing [[dataset]]s (data, model, weight) "
                                                         "and shared parameters")
    p.add_argument("--example", action="store_true", help="the bundled example: psi/delta of a thermal SiO2 film on Si")
    p.add_argument("--starts", type=int, default=1, help="grid points refined per spectrum (default 1)")
    p.add_argument("--plot", metavar="OUT.png", help="save the measured and fitted spectra with residuals (a map's first site), "
                                                     "and for a map the fitted parameters over it as OUT_map.png")
    p.add_argument("--out", metavar="RESULTS.csv", help="per-site values and errors of a map")
    p.add_argument("--format", help="the data file's format, instead of detecting it: csv, woollam, spectraray, accurion, "
                                    "horiba, filmsense, text, jcamp")
    p.add_argument("--delta-convention", default="delta", help="the file's Delta in terms of the instrument's: delta "
                   "(default, every vendor), -delta, 180-delta (tmm's ellips), delta+180")
    p.add_argument("--delta-range", help="-180..180 or 0..360 (checked), or 0..180: Delta folded by a rotating analyzer "
                                         "without compensator (fitted as N and C)")
    p.add_argument("--mueller-s3-sign", type=int, default=1, help="+1: M34 = +sin 2Psi sin Delta (default; Woollam, Sentech); "
                                                                 "-1: M34 = -sin 2Psi sin Delta (pyElli 0.23)")
    p.add_argument("--angle-deg", type=float, help="angle of incidence of a photometric file (text, JCAMP-DX)")
    p.add_argument("--quantity", help="what a photometric file's value column is when it does not say: R, T, R_s, R_p, T_s, T_p")
    p.add_argument("--scale", choices=("fraction", "percent"), help="a photometric file's scale when it does not say")
    p.add_argument("--wavelength-unit", choices=("nm", "um", "1/cm"), help="a headerless photometric file's wavelength unit")
    p.add_argument("--no-cache", action="store_true", help="do not use the compilation cache (see `fit --help`)")
    p.set_defaults(func=_fit_stack)

    p = sub.add_parser("design", help="design a coating to meet targets, from a TOML file (refinement, needle synthesis)")
    p.add_argument("file", nargs="?", help="the design: a sample file (docs/layered-fits) with [[target]] tables and "
                                           "[design] options (docs/coatings)")
    p.add_argument("--example", action="store_true", help="the bundled example: a broadband AR coating on N-BK7")
    p.add_argument("--plot", metavar="OUT.png", help="save the designed spectra against the targets, the index profile "
                                                     "and the merit's history")
    p.add_argument("--out", metavar="DESIGN.toml", help="write the designed sample as a sample file (fit-stack --model reads it)")
    p.add_argument("--no-cache", action="store_true", help="do not use the compilation cache (see `fit --help`)")
    p.set_defaults(func=_design)

    p = sub.add_parser("bench", help="speed and error, side by side with peers, on this machine")
    p.add_argument("--quick", action="store_true", help="a reduced run (about a minute)")
    p.add_argument("--out", default="bench_out", help="directory for bench.md, bench.json and the charts")
    p.add_argument("--sections", default="kernels,fit,stack,stackfit,design,devices,latency",
                   help="comma-separated: kernels, fit, stack, stackfit, design, devices, latency")
    p.add_argument("--no-mitsuba", action="store_true", help="skip Mitsuba 3 even if installed")
    p.set_defaults(func=_bench)
    p = sub.add_parser("stress", help="numerical stress test of every kernel")
    p.add_argument("--n", type=int, default=1_000_000, help="inputs per dtype (default 10^6)")
    p.add_argument("--mp-samples", type=int, default=2000, help="float64 inputs checked against mpmath per kernel")
    p.add_argument("--no-mitsuba", action="store_true", help="skip the side-by-side run of Mitsuba 3")
    p.add_argument("--out", default="stress_out", help="directory for stress.md and stress.json")
    p.set_defaults(func=_stress)
    args = parser.parse_args(argv)
    return args.func(args)


def _exit_now(code: int) -> None:
    """End the command's process without the interpreter's teardown.

    A process that has imported jax spends about 0.2 s after its last statement freeing its
    modules and jaxlib's objects (`python -c "import jax"`: 0.20 s from the last statement to the
    end of the process; `fit --example`: 0.24 s, about a sixth of a warm run; 2-core EPYC). None of
    it is output: every file a command writes is closed when `main` returns. What the normal exit
    does that matters is done here: the exit handlers run (JAX's wait for pending effects such as
    host callbacks, the finalizers of temporary files, handlers a user registered), logging is
    flushed, and so are the standard streams, before `os._exit`.
    """
    atexit._run_exitfuncs()
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (`| head`) or a closed stream
            code = code or 1
    os._exit(code)


if __name__ == "__main__":
    _exit_now(main())
