"""Benchmark section `design`: refinement of a multilayer from many starts in one call against
scipy.optimize.least_squares over the same merit, one start at a time; and needle synthesis.

The problem: a 24-layer edge filter of two constant indices (2.1 and 1.46, alternating, on glass
1.52): R = 1 over 450-530 nm and R = 0 over 600-750 nm, unpolarized, at 0 and 30 degrees, 150
wavelengths per angle (300 wavelengths x 2 angles), tolerance 0.01; thicknesses within 10-250 nm.
The starts are the same for every method: random thicknesses uniform within the bounds.

- jaxoptics: `jo.design(sample, targets, starts=S)`: a vmapped Levenberg-Marquardt (optimistix)
  over all starts in one compiled call; the first call's time (tracing and compilation included)
  and a second call's (the compiled program reused) are reported apart.
- scipy + NumPy: `least_squares(method="trf", max_nfev=200)` with the same bounds (at most as
  many evaluations as jaxoptics takes steps), the residuals from a characteristic-matrix
  transfer-matrix method written in NumPy, vectorized over all points (a loop over layers), and a
  finite-difference Jacobian (scipy's default).
- scipy + tmm: the same with tmm's `coh_tmm` at each point and polarization (a Python loop over
  points: what a tmm user writes), on fewer starts.

Per start: the time and the merit reached. The ratios compare the median time per start in the
same run, at the merits each method reached from the same starts (listed side by side).

The needle row: `python -m jaxoptics design --example`'s problem (a broadband AR coating on
N-BK7 from SiO2 and Si3N4) in-process, total time, rounds and time per round.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .bench_stack import numpy_stack

NH, NL, NS = 2.1, 1.46, 1.52
LAYERS = 24
LO, HI = 10.0, 250.0
TOL = 0.01
ANGLES = (0.0, 30.0)
MAX_STEPS = 200  # jaxoptics' Levenberg-Marquardt steps per start (its default); scipy's max_nfev


def problem(n, layers):
    """`(wavelengths, angles, values)` of every target point, concatenated (angle-major), and the
    jaxoptics sample and targets: `n` wavelengths per angle, `layers` layers."""
    import jaxoptics as jo

    refl = np.linspace(450.0, 530.0, n // 3)
    trans = np.linspace(600.0, 750.0, n - n // 3)
    targets, wl, ang, val = [], [], [], []
    for a in ANGLES:
        targets += [jo.Target("R", refl, 1.0, angle_deg=a, tolerance=TOL), jo.Target("R", trans, 0.0, angle_deg=a, tolerance=TOL)]
        wl += [refl, trans]
        ang += [np.full(refl.size, a), np.full(trans.size, a)]
        val += [np.ones(refl.size), np.zeros(trans.size)]
    stack = tuple(jo.Layer(NH if j % 2 == 0 else NL, jo.Free(100.0, LO, HI)) for j in range(layers))
    return np.concatenate(wl), np.concatenate(ang), np.concatenate(val), jo.Sample(stack, NS), targets


def numpy_R(d, wl, ang_deg):
    """Unpolarized R of the alternating stack with thicknesses `d` at every point: the `stack`
    section's vectorized NumPy characteristic matrices (`bench_stack.numpy_stack`)."""
    n = np.array([1.0] + [NH if j % 2 == 0 else NL for j in range(len(d))] + [NS], complex)
    out = numpy_stack(n, np.asarray(d, float), wl, np.cos(np.radians(ang_deg)))
    return (out["R_s"] + out["R_p"]) / 2


def tmm_R(d, wl, ang_deg):
    import tmm

    n = [1.0] + [NH if j % 2 == 0 else NL for j in range(len(d))] + [NS]
    dl = [np.inf] + list(d) + [np.inf]
    return np.array([(tmm.coh_tmm("s", n, dl, math.radians(a), w)["R"] + tmm.coh_tmm("p", n, dl, math.radians(a), w)["R"]) / 2
                     for w, a in zip(wl, ang_deg)])


def _scipy(model, starts, wl, ang, val):
    from scipy.optimize import least_squares

    sw = 1 / math.sqrt(wl.size)
    res = lambda d: (model(d, wl, ang) - val) / TOL * sw
    times, merits = [], []
    for x0 in starts:
        t = time.perf_counter()
        sol = least_squares(res, x0, bounds=(LO, HI), method="trf", max_nfev=MAX_STEPS)
        times.append(time.perf_counter() - t)
        merits.append(float(np.sqrt(np.sum(sol.fun**2))))
    return np.array(times), np.array(merits)


def bench_design(*, quick=False, progress=None, layers=LAYERS, sizes=None):
    """The section's rows; `sizes` = `(wavelengths per angle, starts, NumPy starts, tmm starts)`
    (default `(150, 100, 10, 1)`, quick `(40, 20, 5, 1)`)."""
    import jaxoptics as jo

    n, S, n_np, n_tmm = sizes or ((40, 20, 5, 1) if quick else (150, 100, 10, 1))
    wl, ang, val, sample, targets = problem(n, layers)
    rng = np.random.default_rng(0)
    starts = rng.uniform(LO, HI, (S, layers))
    # the two models agree: NumPy and tmm against jaxoptics at the first start
    fixed = jo.Sample(tuple(jo.Layer(NH if j % 2 == 0 else NL, float(t)) for j, t in enumerate(starts[0])), NS)
    R_jo = np.concatenate(jo.target_values(fixed, targets))
    agree = (float(np.max(np.abs(numpy_R(starts[0], wl, ang) - R_jo))), float(np.max(np.abs(tmm_R(starts[0], wl, ang) - R_jo))))
    rows = []
    t = time.perf_counter()
    d1 = jo.design(sample, targets, starts=starts)
    first = time.perf_counter() - t
    if progress:
        progress.update(1)
    t = time.perf_counter()
    d2 = jo.design(sample, targets, starts=starts)
    second = time.perf_counter() - t
    assert np.allclose(d1.merits, d2.merits, equal_nan=True)
    if progress:
        progress.update(1)
    rows.append({"method": f"jaxoptics design, {S} starts in one call", "starts": S, "seconds": second, "first_call": first,
                 "per_start": second / S, "merits": d2.merits.tolist()})
    ts, ms = _scipy(numpy_R, starts[:n_np], wl, ang, val)
    rows.append({"method": "scipy least_squares + vectorized NumPy TMM, one start at a time", "starts": n_np,
                 "seconds": float(ts.sum()), "per_start": float(np.median(ts)), "merits": ms.tolist()})
    if progress:
        progress.update(1)
    ts, ms = _scipy(tmm_R, starts[:n_tmm], wl, ang, val)
    rows.append({"method": "scipy least_squares + tmm, one start at a time", "starts": n_tmm, "seconds": float(ts.sum()),
                 "per_start": float(np.median(ts)), "merits": ms.tolist()})
    if progress:
        progress.update(1)
    # needle synthesis: the bundled example
    from pathlib import Path

    src = jo.load_design(Path(jo.__file__).parent / "data" / "example_ar_design.toml")
    t = time.perf_counter()
    dn = jo.design(src[0], src[1], **src[2])
    total = time.perf_counter() - t
    rounds = dn.history.size - 2
    rows.append({"method": "needle synthesis, design --example", "seconds": total, "rounds": rounds,
                 "per_round": total / max(rounds, 1), "layers": dn.layers, "merit": dn.merit,
                 "merit_start": float(jo.merit(src[0], src[1]))})
    if progress:
        progress.update(1)
    rows.append({"method": "agreement", "numpy_vs_jaxoptics": agree[0], "tmm_vs_jaxoptics": agree[1],
                 "points": int(wl.size), "layers": layers})
    return rows


def design_table(rows) -> str:
    agree = next(r for r in rows if r["method"] == "agreement")
    ours = rows[0]
    mine = np.asarray(ours["merits"])
    lines = [f"{agree['layers']} layers, {agree['points']} points (wavelengths x angles); the models agree with jaxoptics' to "
             f"{agree['numpy_vs_jaxoptics']:.1e} (NumPy) and {agree['tmm_vs_jaxoptics']:.1e} (tmm) in R. Merits: the median and "
             "the best over the method's starts, and jaxoptics' over the same starts.", "",
             "| method | starts | time per start | vs jaxoptics | merit reached (median, best) | jaxoptics from the same starts |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "merits" not in r:
            continue
        m = np.asarray(r["merits"])
        same = mine[:m.size]
        if r is ours:
            time_s = f"{1e3 * r['per_start']:.1f} ms (the first call {r['first_call'] - r['seconds']:.1f} s more: compilation)"
            ratio = "1"
        else:
            time_s = f"{1e3 * r['per_start']:.1f} ms"
            ratio = f"{r['per_start'] / ours['per_start']:.0f}x slower"
        lines.append(f"| {r['method']} | {r['starts']} | {time_s} | {ratio} | {np.median(m):.3g}, {np.min(m):.3g} | "
                     f"{'' if r is ours else f'{np.median(same):.3g}, {np.min(same):.3g}'} |")
    n = next(r for r in rows if r["method"].startswith("needle"))
    lines += ["", f"Needle synthesis (`design --example`): {n['rounds']} rounds to {n['layers']} layers, merit "
              f"{n['merit_start']:.3g} to {n['merit']:.3g}, in {n['seconds']:.1f} s ({n['per_round']:.2f} s per round, "
              "compilation included)."]
    return "\n".join(lines)
