"""Benchmark section `stackfit`: a wafer map of film fits in one call against
scipy.optimize.least_squares over the same model, one spectrum at a time.

Each spectrum: psi and delta at 200 wavelengths (300-1000 nm) x 3 angles (65, 70, 75 degrees) of a
Cauchy film on the built-in Si; free: the thickness (searched over 0-2000 nm by `fit_stack`'s grid)
and the Cauchy A, B, C. The map's thickness varies smoothly around 480 nm, A and B slightly, and
noise of 0.02 degrees (psi) and 0.05 degrees (delta) is added.

The scipy baseline is the same model written in NumPy (the Airy formula of one film, the same
interpolated Si index), fitted with `least_squares(method="lm")` from a start 5 nm from the true
thickness: its best case, with no search over fringes. Its time per spectrum is the median over
a sample of the map; the ratio compares per-spectrum times measured in the same run. The same
loop from the sample model's start (100 nm) shows what a local fit without a fringe search
recovers.

A second scipy row puts pyElli's model (the peer most users fit ellipsometry with) in the same
loop, on fewer spectra: its model is the same to rounding, and slower to evaluate.

The section also times one evaluation of each model at a spectrum's points (NumPy: one call;
jaxoptics: the model, and the model with its Jacobian as `fit_stack` forms it, 64 spectra at a
time, in one call over 1024 spectra) and counts scipy's calls of the model per fit (those of its
finite-difference Jacobian included), so that each fit's cost can be read in evaluations of its
model.

A second table prices the models of real samples and instruments (`effect_rows`): the same map
(thickness and Cauchy A, B free) generated and fitted with a surface roughness layer (its
thickness free), an angle-of-incidence offset (free), a 4 nm spectral bandwidth (fixed, averaged
over 5 wavelengths) and all three together, each against the plain model in the same run.
"""

from __future__ import annotations

import math
import time

import numpy as np

ANGLES = (65.0, 70.0, 75.0)
SIGMA = (0.02, 0.05)


def _grid():
    wl1 = np.linspace(300.0, 1000.0, 200)
    return np.tile(wl1, len(ANGLES)), np.repeat(ANGLES, len(wl1))


def wafer(B, seed=0):
    """True parameters `(B, 4)`: A, B, C, thickness over a disc-shaped map of B sites."""
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.uniform(0, 1, B))
    phi = rng.uniform(0, 2 * np.pi, B)
    x, y = r * np.cos(phi), r * np.sin(phi)
    d = 480 + 35 * (x * x + y * y) + 8 * x
    A = 1.452 + 0.004 * y
    return np.stack([A, np.full(B, 0.0036), np.full(B, 1e-5), d], -1)


def numpy_psi_delta(x, lam_nm, ang_rad, N_sub):
    """psi, delta (degrees, instrument convention) of a Cauchy film on a substrate: NumPy."""
    A, B, C, d = x
    lu = lam_nm / 1000
    n1 = A + B / lu**2 + C / lu**4
    c0 = np.cos(ang_rad)
    s0 = 1 - c0**2
    c1 = np.sqrt(1 - s0 / n1**2 + 0j)
    c2 = np.sqrt(1 - s0 / N_sub**2 + 0j)
    c2 = np.where(c2.imag < 0, -c2, c2)
    rs01 = (c0 - n1 * c1) / (c0 + n1 * c1)
    rs12 = (n1 * c1 - N_sub * c2) / (n1 * c1 + N_sub * c2)
    rp01 = (n1 * c0 - c1) / (n1 * c0 + c1)
    rp12 = (N_sub * c1 - n1 * c2) / (N_sub * c1 + n1 * c2)
    e = np.exp(4j * np.pi * d * n1 * c1 / lam_nm)
    rs = (rs01 + rs12 * e) / (1 + rs01 * rs12 * e)
    rp = (rp01 + rp12 * e) / (1 + rp01 * rp12 * e)
    X = rp * np.conj(rs)
    psi = np.degrees(np.arctan2(np.abs(rp), np.abs(rs)))
    delta = np.degrees(np.arctan2(-X.imag, X.real))
    return np.concatenate([psi, delta])


def one_film_with_jacobian(lam_nm, ang_rad, N_sub):
    """`x -> (m, J)`: psi and delta (degrees, concatenated as `numpy_psi_delta`'s) of a Cauchy film
    with a real index and their Jacobian in `x = (A, B, C, d)`, in JAX, written for this case alone:
    every term that depends on no parameter (the substrate's, the angles') computed once, and the
    derivatives in the film's index and thickness derived by hand (the Cauchy terms scale the first
    by `1/lambda^2` and `1/lambda^4`). The benchmark times it as a lower bound on what a model with
    its Jacobian costs at a spectrum's points in XLA: it omits what `fit_stack`'s general model
    carries (an absorbing film, more layers, other quantities, total internal reflection)."""
    import jax
    import jax.numpy as jnp

    inv_l2 = jnp.asarray(1e6 / lam_nm**2)
    k4 = jnp.asarray(4 * np.pi / lam_nm)
    s0 = np.sin(ang_rad) ** 2
    c2 = np.sqrt(1 - s0 / N_sub**2 + 0j)
    c2 = np.where(c2.imag < 0, -c2, c2)
    c0, s0, c2, N2, q2 = (jnp.asarray(a) for a in (np.cos(ang_rad), s0, c2, N_sub, N_sub * c2))

    def total(r01, dr01, r12, dr12, e, de_dn, de_dd):
        """The film's r = (r01 + r12 e) / (1 + r01 r12 e) and its derivatives in n and d."""
        den = 1 + r01 * r12 * e
        r = (r01 + r12 * e) / den
        dr_n = (dr01 + dr12 * e + r12 * de_dn - r * ((dr01 * r12 + r01 * dr12) * e + r01 * r12 * de_dn)) / den
        dr_d = r12 * de_dd * (1 - r * r01) / den
        return r, dr_n, dr_d

    def f(x):
        # real and complex terms mix throughout, as in the NumPy transcription
        with jax.numpy_dtype_promotion("standard"):
            return g(x)

    def g(x):
        A, B, C, d = x
        n1 = A + inv_l2 * (B + C * inv_l2)
        c1 = jnp.sqrt(1 - s0 / (n1 * n1))
        dc1 = s0 / (n1**3 * c1)
        q1, dq1 = n1 * c1, c1 + n1 * dc1
        a = n1 * c0
        u, v = N2 * c1, n1 * c2
        ph = k4 * d * q1
        e = jnp.cos(ph) + 1j * jnp.sin(ph)
        rs = total((c0 - q1) / (c0 + q1), -2 * c0 * dq1 / (c0 + q1) ** 2, (q1 - q2) / (q1 + q2), 2 * q2 * dq1 / (q1 + q2) ** 2,
                   e, 1j * k4 * d * dq1 * e, 1j * k4 * q1 * e)
        rp = total((a - c1) / (a + c1), 2 * (c0 * c1 - a * dc1) / (a + c1) ** 2, (u - v) / (u + v),
                   2 * (N2 * dc1 * v - u * c2) / (u + v) ** 2, e, 1j * k4 * d * dq1 * e, 1j * k4 * q1 * e)
        rho = rp[0] / rs[0]
        ar = jnp.abs(rho)
        # d log(rho) = drp/rp - drs/rs; psi = atan|rho|, delta = -arg(rho)
        lg_n, lg_d = rp[1] / rp[0] - rs[1] / rs[0], rp[2] / rp[0] - rs[2] / rs[0]
        m = jnp.degrees(jnp.concatenate([jnp.arctan(ar), -jnp.angle(rho)]))
        w = ar / (1 + ar * ar)
        dn = jnp.degrees(jnp.concatenate([w * lg_n.real, -lg_n.imag]))
        dd = jnp.degrees(jnp.concatenate([w * lg_d.real, -lg_d.imag]))
        il = jnp.concatenate([inv_l2, inv_l2])
        return m, jnp.stack([dn, dn * il, dn * il**2, dd], -1)

    return f


def bench_stack_fit(*, quick=False, progress=None, repeats=None):
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    B = 500 if quick else 10_000
    n_scipy = 20 if quick else 100
    wl, ang = _grid()
    truth = wafer(B)
    si = jo.material("Si")
    lam_um = wl / 1000
    N_sub = np.interp(lam_um, *si.n_table) + 1j * np.interp(lam_um, *si.k_table)
    ang_r = np.radians(ang)

    model = jo.Sample([jo.Layer(jo.Cauchy(A=jo.Free(1.46, 1.3, 1.7), B=jo.Free(0.0, -0.05, 0.1), C=jo.Free(0.0, -0.01, 0.01)),
                                jo.Free(100.0, 0.0, 2000.0), name="film")], si)

    # data: the jaxoptics model at the true parameters (checked against the NumPy model below)
    def clean(x):
        return model.with_values([x[0], x[1], x[2], x[3]]).quantities(("psi_deg", "delta_deg"), jnp.asarray(wl),
                                                                       jnp.asarray(ang_r), flat=True)

    Q = np.asarray(jax.jit(jax.vmap(clean))(jnp.asarray(truth)))
    agree = float(np.max(np.abs((Q[0] - numpy_psi_delta(truth[0], wl, ang_r, N_sub) + 180) % 360 - 180)))
    P = len(wl)
    rng = np.random.default_rng(1)
    sig = np.repeat(SIGMA, P)
    V = Q + rng.normal(size=Q.shape) * sig
    spectra = jo.make_spectra(wl, ang, {"psi_deg": V[:, :P], "delta_deg": V[:, P:]},
                              sigma={"psi_deg": np.full((B, P), SIGMA[0]), "delta_deg": np.full((B, P), SIGMA[1])})
    if progress:
        progress.update(1)
    # one evaluation of the model (and of the model with its Jacobian) per spectrum, 64 at a time
    # as fit_stack's lanes run them, for 16 blocks in one call: as in the fit, which evaluates
    # them in a loop inside one compiled call, the call's buffers are allocated once for many
    # evaluations (one call per block would time the allocation of its temporary arrays too)
    from jaxoptics._fitting._stack_jacobian import _model_and_jacobian

    X = jnp.asarray(wafer(1024, seed=2)).reshape(16, 64, 4)
    kinds = ("psi_deg", "delta_deg")
    evals = {}
    model_jac = _model_and_jacobian(model, kinds, jnp.asarray(wl), jnp.asarray(ang_r))
    bound = one_film_with_jacobian(wl, ang_r, N_sub)
    progs = {name: jax.jit(lambda X, f=f: jax.lax.map(jax.vmap(f), X))
             for name, f in (("model", clean), ("model_jac", model_jac), ("bound_jac", bound))}
    for g in progs.values():
        jax.block_until_ready(g(X))
    ts = {name: [] for name in progs}
    for _ in range(3 if quick else 15):  # in turns, so that the machine's drift falls on each alike
        for name, g in progs.items():
            t = time.perf_counter()
            jax.block_until_ready(g(X))
            ts[name].append(time.perf_counter() - t)
    for name in progs:
        evals[name] = float(np.median(ts[name])) / (X.shape[0] * X.shape[1])
    # the bound computes what fit_stack's model does: its largest differences (delta mod 360; the
    # Jacobian relative to the largest entry of each column)
    (m1, J1), (m2, J2) = (jax.jit(jax.vmap(f))(X[0]) for f in (model_jac, bound))
    J1, J2 = np.asarray(J1), np.asarray(J2)
    evals["bound_agree"] = (float(np.max(np.abs((np.asarray(m1) - np.asarray(m2) + 180) % 360 - 180))),
                            float(np.max(np.abs(J1 - J2) / np.max(np.abs(J1), axis=1, keepdims=True))))
    ts = []
    for _ in range(5 if quick else 50):
        t = time.perf_counter()
        numpy_psi_delta(truth[0], wl, ang_r, N_sub)
        ts.append(time.perf_counter() - t)
    evals["numpy_model"] = float(np.median(ts))
    rows = []
    for dtype in ("float64",):
        t = time.perf_counter()
        fit = jo.fit_stack(model, spectra)
        jax.block_until_ready(fit.values)
        first = time.perf_counter() - t
        runs = []
        for _ in range(repeats or (1 if quick else 2)):
            t = time.perf_counter()
            fit = jo.fit_stack(model, spectra)
            jax.block_until_ready(fit.values)
            runs.append(time.perf_counter() - t)
        run = float(np.median(runs))
        d = np.asarray(fit["film.thickness_nm"], np.float64)
        sd = np.asarray(fit.stderr_of("film.thickness_nm"), np.float64)
        rows.append(dict(method=f"jaxoptics fit_stack, one call ({dtype})", spectra=B, compile_s=max(first - run, 0.0), run_s=run,
                         per_spectrum_s=run / B, converged=float(np.mean(np.asarray(fit.converged))),
                         recovered=float(np.mean(np.abs(d - truth[:, 3]) < 4 * sd)),
                         median_stderr_nm=float(np.median(sd)), model_eval_s=evals["model"],
                         model_jac_eval_s=evals["model_jac"], bound_jac_eval_s=evals["bound_jac"],
                         bound_agree=evals["bound_agree"]))
        if progress:
            progress.update(1)

    # scipy, one spectrum at a time: from 5 nm off the true thickness (its best case: no fringe
    # search), and from the sample model's start (100 nm), as a user without a fringe search runs it
    idx = np.linspace(0, B - 1, n_scipy).astype(int)
    model_np = lambda x: numpy_psi_delta(x, wl, ang_r, N_sub)
    scipy_loop = lambda start_nm: _scipy_loop(model_np, V, truth, sig, idx, start_nm)

    per, conv, rec, calls = scipy_loop(lambda i: truth[i, 3] + 5.0)
    rows.append(dict(method="scipy least_squares (lm), NumPy model, loop, start 5 nm from the truth", spectra=n_scipy, compile_s=None,
                     run_s=per * B, per_spectrum_s=per, converged=conv, recovered=rec, median_stderr_nm=None,
                     model_eval_s=evals["numpy_model"], median_calls=calls,
                     note=f"scipy rows: run time for {B} spectra extrapolated from the median over the spectra fitted; the NumPy "
                          f"model agrees with jaxoptics' to {agree:.1e} degrees"))
    per, conv, rec, calls = scipy_loop(lambda i: 100.0)
    rows.append(dict(method="scipy least_squares (lm), NumPy model, loop, start 100 nm (the sample model's)", spectra=n_scipy,
                     compile_s=None, run_s=per * B, per_spectrum_s=per, converged=conv, recovered=rec, median_stderr_nm=None,
                     model_eval_s=evals["numpy_model"], median_calls=calls))
    if progress:
        progress.update(1)
    rows.append(_pyelli_row(V, truth, wl, ang, si, sig, B, 5 if quick else 20))
    if progress:
        progress.update(1)
    return rows + effect_rows(quick=quick, progress=progress)


# (name, roughness layer, angle offset, bandwidth): the models of `effect_rows`; a quick run
# prices the plain model and all three effects together, on 4 spectra at a quarter of the wavelengths
EFFECTS = (("plain model", False, False, False), ("+ surface roughness (thickness free)", True, False, False),
           ("+ angle-of-incidence offset (free)", False, True, False), ("+ 4 nm bandwidth (fixed, 5 wavelengths)", False, False, True),
           ("+ all three", True, True, True))
_TRUE_ROUGHNESS_NM, _TRUE_OFFSET_DEG, _BANDWIDTH_NM = 3.0, 0.3, 4.0


def effect_sample(roughness, offset, bandwidth):
    """The effects bench's model: a Cauchy film (A, B and the thickness free, C fixed) on Si, with
    the effects asked for. The roughness layer mixes the film's nominal Cauchy index (fixed) with
    half void."""
    import jaxoptics as jo

    nominal = jo.Cauchy(A=1.452, B=0.0036, C=1e-5)
    film = jo.Layer(jo.Cauchy(A=jo.Free(1.46, 1.3, 1.7), B=jo.Free(0.0, -0.05, 0.1), C=1e-5), jo.Free(100.0, 0.0, 2000.0),
                    name="film")
    layers = ([jo.roughness(nominal, jo.Free(1.0, 0.0, 20.0))] if roughness else []) + [film]
    instrument = None
    if offset or bandwidth:
        instrument = jo.Instrument(angle_offset_deg=jo.Free(0.0, -2.0, 2.0) if offset else 0.0,
                                   bandwidth_nm=_BANDWIDTH_NM if bandwidth else 0.0)
    return jo.Sample(layers, jo.material("Si"), instrument=instrument)


def effect_rows(*, quick=False, progress=None):
    """`fit_stack` over the map with each model of `EFFECTS`, on data generated by that model (the
    map's thickness and A, B; 3 nm of roughness, a 0.3 degree offset): compile and run time of one
    call, the run time per spectrum against the plain model's, convergence and recovery."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    B = 4 if quick else 10_000  # (a quick run's fits are small: compiled with QUICK_COMPILE)
    wl, ang = _grid()
    if quick:  # every fourth wavelength
        wl, ang = wl[::4], ang[::4]
    P = len(wl)
    truth = wafer(B, seed=3)
    rng = np.random.default_rng(4)
    rows = []
    for name, rough, offset, bandwidth in (e for e in EFFECTS if not quick or e[0] in ("plain model", "+ all three")):
        model = effect_sample(rough, offset, bandwidth)
        known = {"film.A": truth[:, 0], "film.B": truth[:, 1], "film.thickness_nm": truth[:, 3],
                 "roughness.thickness_nm": np.full(B, _TRUE_ROUGHNESS_NM), "instrument.angle_offset_deg": np.full(B, _TRUE_OFFSET_DEG)}
        X = np.stack([known[n] for n in model.free_names()], -1)
        clean = jax.jit(jax.vmap(lambda x, m=model: m.with_values(list(x)).quantities(("psi_deg", "delta_deg"), jnp.asarray(wl),
                                                                                      jnp.deg2rad(jnp.asarray(ang)), flat=True)))
        V = np.asarray(clean(jnp.asarray(X))) + rng.normal(size=(B, 2 * P)) * np.repeat(SIGMA, P)
        spectra = jo.make_spectra(wl, ang, {"psi_deg": V[:, :P], "delta_deg": V[:, P:]},
                                  sigma={"psi_deg": np.full((B, P), SIGMA[0]), "delta_deg": np.full((B, P), SIGMA[1])})
        t = time.perf_counter()
        jax.block_until_ready(jo.fit_stack(model, spectra).values)
        first = time.perf_counter() - t
        t = time.perf_counter()
        fit = jo.fit_stack(model, spectra)
        jax.block_until_ready(fit.values)
        run = time.perf_counter() - t
        d = np.asarray(fit["film.thickness_nm"], np.float64)
        sd = np.asarray(fit.stderr_of("film.thickness_nm"), np.float64)
        rows.append(dict(method=f"effect: {name}", effect=name, spectra=B, free=len(model.free_names()),
                         compile_s=max(first - run, 0.0), run_s=run, per_spectrum_s=run / B,
                         converged=float(np.mean(np.asarray(fit.converged))),
                         recovered=float(np.mean(np.abs(d - truth[:, 3]) < 4 * sd))))
        if progress:
            progress.update(1)
    return rows


def effects_table(rows) -> str:
    rows = [r for r in rows if "effect" in r]
    if not rows:
        return ""
    base = rows[0]
    out = [f"### The models of real samples and instruments: the same map, thickness and Cauchy A, B free, "
           f"{base['spectra']} spectra in one call each",
           "",
           "| model | free parameters | compile (s) | run (s) | per spectrum (ms) | cost vs plain | converged | recovered |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        out.append(f"| {r['effect']} | {r['free']} | {r['compile_s']:.1f} | {r['run_s']:.2f} | {1e3 * r['per_spectrum_s']:.3f} | "
                   f"{r['per_spectrum_s'] / base['per_spectrum_s']:.2f}x | {100 * r['converged']:.1f}% | {100 * r['recovered']:.1f}% |")
    out += ["", f"Each model fitted to data it generated (the map's thickness, A and B; {_TRUE_ROUGHNESS_NM:g} nm of roughness, "
                f"a {_TRUE_OFFSET_DEG:g} degree offset; the noise of the table above). recovered: the film's thickness within 4 "
                "standard errors of the truth. The bandwidth averages each point's intensities over 5 wavelengths "
                "(Gauss-Hermite nodes)."]
    return "\n".join(out)


def _scipy_loop(model, V, truth, sig, idx, start_nm):
    """`least_squares(method="lm")` on the spectra `idx`, one at a time, with `model(x) -> (psi,
    delta)` (degrees, concatenated) from `x = (A, B, C, start_nm(i))`: the median time per fit,
    the fractions converged and recovered (`_recovered`), and the median calls of the model."""
    from scipy.optimize import least_squares

    P = V.shape[1] // 2
    times, ok, rec, calls = [], [], [], []
    for i in idx:
        count = [0]

        def resid(x, y=V[i], count=count):
            count[0] += 1
            r = model(x) - y
            r[P:] = (r[P:] + 180) % 360 - 180  # delta wraps
            return r / sig

        x0 = np.array([1.46, 0.0, 0.0, start_nm(i)])
        t = time.perf_counter()
        res = least_squares(resid, x0, method="lm", xtol=1e-9, ftol=1e-9)
        times.append(time.perf_counter() - t)
        ok.append(res.success)
        calls.append(count[0])
        rec.append(_recovered(res, truth[i, 3], P))
    return float(np.median(times)), float(np.mean(ok)), float(np.mean(rec)), float(np.median(calls))


def _recovered(res, d_true, P):
    """Whether a scipy fit's thickness lies within 4 of its standard errors of the truth."""
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * max(1.0, np.sum(res.fun**2) / (2 * P - 4))
    except np.linalg.LinAlgError:
        return False
    return bool(abs(res.x[3] - d_true) < 4 * math.sqrt(abs(cov[3, 3])))


def _pyelli_row(V, truth, wl, ang, si, sig, B, n_fits):
    """The same scipy loop with pyElli's model (its `Solver2x2`, one call per angle) in place of
    the NumPy one: the fit a pyElli user runs per spectrum (lmfit's default method, `leastsq`, is
    the same MINPACK Levenberg-Marquardt). The substrate is pyElli's `Table` of the same Si data."""
    import elli

    P = len(wl)
    wl1 = wl[: P // len(ANGLES)]
    lam_nm = np.asarray(si.n_table[0]) * 1000
    N_tab = np.asarray(si.n_table[1]) + 1j * np.interp(si.n_table[0], *si.k_table)
    sub = elli.IsotropicMaterial(elli.Table(lbda=lam_nm, n=N_tab))

    def psi_delta(x):
        A, Bc, C, d = x  # Cauchy A, B (um^2), C (um^4); pyElli's n1, n2 are in 100 nm^2 and 1e7 nm^4
        film = elli.IsotropicMaterial(elli.Cauchy(n0=A, n1=Bc * 1e4, n2=C * 1e5))
        s = elli.Structure(elli.AIR, [elli.Layer(film, d)], sub)
        res = [s.evaluate(wl1, a, solver=elli.Solver2x2) for a in ANGLES]
        return np.concatenate([r.psi for r in res] + [r.delta for r in res])

    ref = numpy_psi_delta(truth[0], wl, np.radians(ang), np.interp(wl / 1000, *si.n_table) + 1j * np.interp(wl / 1000, *si.k_table))
    agree = float(np.max(np.abs((psi_delta(truth[0]) - ref + 180) % 360 - 180)))
    ts = []
    for _ in range(10):
        t = time.perf_counter()
        psi_delta(truth[0])
        ts.append(time.perf_counter() - t)
    per, conv, rec, calls = _scipy_loop(psi_delta, V, truth, sig, np.linspace(0, B - 1, n_fits).astype(int),
                                        lambda i: truth[i, 3] + 5.0)
    return dict(method="scipy least_squares (lm), pyElli model, loop, start 5 nm from the truth", spectra=n_fits, compile_s=None, run_s=per * B,
                per_spectrum_s=per, converged=conv, recovered=rec, median_stderr_nm=None,
                model_eval_s=float(np.median(ts)), median_calls=calls, agree_deg=agree)


def stack_fit_table(rows) -> str:
    effects = effects_table(rows)
    rows = [r for r in rows if "effect" not in r]
    base = next(r for r in rows if r["method"].startswith("scipy"))
    out = ["| method | spectra | compile (s) | run (s) | per spectrum (ms) | converged | recovered | vs scipy |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        comp = "-" if r["compile_s"] is None else f"{r['compile_s']:.1f}"
        ratio = base["per_spectrum_s"] / r["per_spectrum_s"]
        out.append(f"| {r['method']} | {r['spectra']} | {comp} | {r['run_s']:.2f} | {1e3 * r['per_spectrum_s']:.3f} | "
                   f"{100 * r['converged']:.1f}% | {100 * r['recovered']:.1f}% | {ratio:.1f}x |")
    pe = next((r for r in rows if "pyElli" in r["method"]), None)
    note = base.get("note", "") + (f", pyElli's to {pe['agree_deg']:.1e} degrees" if pe is not None else "")
    out += ["", "recovered: the fitted thickness within 4 standard errors of the truth. " + note]
    jx = next((r for r in rows if r["method"].startswith("jaxoptics") and "model_jac_eval_s" in r), None)
    if jx is not None and "median_calls" in base:
        points = len(_grid()[0])
        us = lambda t: f"{1e6 * t:.0f} us"
        out += ["", f"One evaluation of the model at a spectrum's {points} points: NumPy {us(base['model_eval_s'])}, jaxoptics "
                    f"{us(jx['model_eval_s'])}, {us(jx['model_jac_eval_s'])} with its Jacobian (64 spectra at a time, in one call over 1024). "
                    f"scipy's fit calls its model {base['median_calls']:.0f} times (median; its finite-difference "
                    f"Jacobian's calls included); jaxoptics' fit costs as much as {jx['per_spectrum_s'] / jx['model_jac_eval_s']:.1f} "
                    f"evaluations of the model with its Jacobian, grid search and standard errors included. At "
                    f"{base['per_spectrum_s'] / 100 / jx['model_jac_eval_s']:.2f} of them, a fit would be 100x faster "
                    f"than scipy's. A one-film model written for this case alone ({us(jx['bound_jac_eval_s'])} with its "
                    f"Jacobian: a real film index, the substrate's terms computed once, the derivatives derived by hand; "
                    f"it agrees with jaxoptics' model to {jx['bound_agree'][0]:.0e} degrees and its Jacobian to "
                    f"{jx['bound_agree'][1]:.0e} of each column's largest entry) would allow "
                    f"{base['per_spectrum_s'] / 100 / jx['bound_jac_eval_s']:.2f} of its evaluations; a fit that reports "
                    f"standard errors needs one at its solution, and the steps that reach it."]
    if jx is not None and pe is not None:
        out += ["", f"pyElli's model (its 2x2 solver, one call per angle) takes {1e3 * pe['model_eval_s']:.2f} ms per evaluation, "
                    f"and the same scipy loop calls it {pe['median_calls']:.0f} times: {1e3 * pe['per_spectrum_s']:.0f} ms per spectrum, "
                    f"{pe['per_spectrum_s'] / jx['per_spectrum_s']:.0f}x jaxoptics' time."]
    if effects:
        out += ["", effects]
    return "\n".join(out)
