"""The thin-film section of `python -m jaxoptics stress`: `stack` over adversarial stacks.

For every category:

- the float32 error of R, against float64 evaluated on the same, float32-rounded inputs (so only
  the float32 arithmetic is measured), and how far it exceeds what a 2-ulp relative change of the
  inputs causes (first order, `2 eps sum_i |x_i dR/dx_i|` from the float64 gradient): a stack near a
  resonance is ill-conditioned, and no float32 evaluation can do better than that bound there;
- the float32 error of T, A, and of psi where both polarizations reflect (psi of a sample that
  does not reflect is a ratio of two roundings);
- the energy balance |R + T + sum(A) - 1| in both dtypes;
- NaN/inf counts of values and of reverse- and forward-mode gradients, both dtypes;
- float64 against a reference on a sample: a 40-digit mpmath transfer-matrix evaluation
  (`mpref.stack_ref`); for stacks with incoherent layers tmm's `inc_tmm` (float64, within about
  1e-12 of the exact values itself); R = 0 and T = 1 for a stack with no interface.
"""

from __future__ import annotations

import functools

import numpy as np

CATEGORIES = ("random", "thick absorbers", "TIR and frustrated TIR", "inner layer at its critical angle",
              "grazing incidence", "zero thicknesses", "index-matched layers", "metals", "incoherent layers",
              "no interface, near grazing")
L_CHOICES = (3, 5, 8, 12)
# incoherent inner layers (0-based among the L - 2) by number of media, in the categories that have them
_INCOHERENT = {3: (0,), 5: (1,), 8: (1, 4), 12: (2, 6, 9)}


def incoherent_of(category, L):
    """The static `incoherent` positions of a category's stacks of L media."""
    if category == "incoherent layers" or (category == "no interface, near grazing" and L in (5, 12)):
        return _INCOHERENT[L]
    return ()


def reference_of(category, L):
    """What float64 is compared with: "mpmath", "tmm" (incoherent layers) or "closed form"."""
    if category == "no interface, near grazing":
        return "closed form"
    return "tmm" if incoherent_of(category, L) else "mpmath"


def make_stacks(category, K, L, rng):
    """(n complex (K, L), d (K, L-2), wavelength (K,), cos_i (K,)) in float64."""
    n = rng.uniform(1.0, 3.0, (K, L)) + 1j * np.where(rng.random((K, L)) < 0.3, rng.uniform(0, 0.5, (K, L)), 0)
    n[:, 0] = rng.uniform(1.0, 2.0, K)
    d = rng.uniform(0, 300, (K, L - 2))
    wl = rng.uniform(300, 1200, K)
    th = rng.uniform(0, np.deg2rad(85), K)
    if category == "thick absorbers":
        d = 10 ** rng.uniform(3, 7, (K, L - 2))
        n[:, 1:] = n[:, 1:].real + 1j * rng.uniform(1e-3, 1.0, (K, L - 1))
    elif category == "TIR and frustrated TIR":
        n[:, 0] = rng.uniform(2.0, 3.0, K)
        n[:, 1:] = rng.uniform(1.0, 1.8, (K, L - 1))
        th = rng.uniform(np.deg2rad(60), np.deg2rad(89.9), K)
        d = rng.uniform(0, 2000, (K, L - 2))
    elif category == "inner layer at its critical angle":
        n[:, 0] = rng.uniform(1.5, 2.5, K)
        j = rng.integers(1, L - 1, K)
        nj = rng.uniform(1.0, n[:, 0].real - 0.05)
        th = np.arcsin(nj / n[:, 0].real)
        n[np.arange(K), j] = n[:, 0].real * np.sin(th)  # n0 sin(theta), to rounding
    elif category == "grazing incidence":
        th = np.pi / 2 - 10 ** rng.uniform(-12, -1, K)
        th[::7] = np.pi / 2
    elif category == "zero thicknesses":
        d = np.where(rng.random((K, L - 2)) < 0.5, 0.0, d)
    elif category == "index-matched layers":
        m = rng.random((K, L)) < 0.5
        m[:, 0] = False
        n = np.where(m, n[:, :1].real + 0j, n)
    elif category == "metals":
        n[:, 1:] = np.where(rng.random((K, L - 1)) < 0.5, rng.uniform(0.05, 0.5, (K, L - 1))
                            + 1j * rng.uniform(2, 8, (K, L - 1)), n[:, 1:])
    elif category == "incoherent layers":  # thick, some weakly absorbing
        for j in _INCOHERENT[L]:
            d[:, j] = rng.uniform(2e3, 5e4, K)
            n[:, j + 1] = n[:, j + 1].real + 1j * np.where(rng.random(K) < 0.5, rng.uniform(0, 1e-3, K), 0)
    elif category == "no interface, near grazing":  # every medium of the incident index
        n = np.repeat(n[:, :1].real, L, axis=1) + 0j
        th = np.arccos(10 ** rng.uniform(-20, -1, K))
        th[::7] = np.pi / 2
        if incoherent_of(category, L):
            d[:, list(_INCOHERENT[L])] = rng.uniform(2e3, 5e4, (K, len(_INCOHERENT[L])))
    c = np.cos(th)
    if category == "no interface, near grazing":
        c[::7] = 0.0
    return n, d, wl, c


def stress_stack(*, n_points=100_000, mp_samples=200, progress=None, seed=0, media=L_CHOICES):
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    rng = np.random.default_rng(seed)
    rows = []
    per = max(n_points // (len(CATEGORIES) * len(media)), 8)

    def loss(nr, ni, d, w, c, inc):
        return jnp.sum(jo.stack(jax.lax.complex(nr, ni), d, w, c, incoherent=inc).R)

    @functools.partial(jax.jit, static_argnums=4)
    def evaluate(n, d, w, c, inc):
        """Everything the sweep looks at for one batch, one compiled program per dtype and
        `incoherent`: the stack's and the ellipsometry kernel's results, the gradient of sum(R) in
        every input, and the derivative along every input at once in forward mode."""
        args = (jnp.real(n), jnp.imag(n), d, w, c)
        grad = jax.grad(loss, argnums=(0, 1, 2, 3, 4))(*args, inc)
        fwd = jax.jvp(lambda *a: loss(*a, inc), args, tuple(jnp.ones_like(a) for a in args))[1]
        return jo.stack(n, d, w, c, incoherent=inc), jo.ellipsometry(n, d, w, c, incoherent=inc), grad, fwd

    for cat in CATEGORIES:
        row = dict(category=cat, n=0, f32_max_abs_err_R=0.0, f32_p999_abs_err_R=0.0, f32_max_excess_R=0.0,
                   f32_max_abs_err_T=0.0, f32_max_abs_err_A=0.0, f32_max_abs_err_psi=0.0, energy_f64=0.0,
                   energy_f32=0.0, nan_inf_values=0, nan_inf_grad_rev=0, nan_inf_grad_fwd=0, mp_max_abs_diff=0.0,
                   mp_compared=0)
        errs = []
        for L in media:
            n, d, wl, c = make_stacks(cat, per, L, rng)
            inc = incoherent_of(cat, L)
            # inputs rounded to float32 once; float64 then evaluates exactly those
            n32, d32, w32, c32 = n.astype(np.complex64), d.astype(np.float32), wl.astype(np.float32), c.astype(np.float32)
            n64, d64, w64, c64 = n32.astype(np.complex128), d32.astype(np.float64), w32.astype(np.float64), c32.astype(np.float64)
            (r64, e64, g64, fwd64), (r32, e32, g32, fwd32) = evaluate(n64, d64, w64, c64, inc), evaluate(n32, d32, w32, c32, inc)
            row["n"] += per
            for res, key in ((r64, "energy_f64"), (r32, "energy_f32")):
                for pol in "sp":
                    tot = getattr(res, f"R_{pol}") + getattr(res, f"T_{pol}") + getattr(res, f"A_{pol}").sum(-1)
                    row[key] = max(row[key], float(jnp.max(jnp.abs(tot.astype(jnp.float64) - 1))))
            for res in (r64, r32):
                row["nan_inf_values"] += int(sum(np.sum(~np.isfinite(np.asarray(x))) for x in
                                                 (res.R_s, res.R_p, res.T_s, res.T_p, res.A_s, res.A_p)))
            errR = np.abs(np.asarray(r32.R, np.float64) - np.asarray(r64.R))
            errs.append(errR)
            row["f32_max_abs_err_R"] = max(row["f32_max_abs_err_R"], float(errR.max()))
            row["f32_max_abs_err_T"] = max(row["f32_max_abs_err_T"], float(np.max(np.abs(np.asarray(r32.T, np.float64) - np.asarray(r64.T)))))
            row["f32_max_abs_err_A"] = max(row["f32_max_abs_err_A"], float(np.max(np.abs(np.asarray(r32.A, np.float64) - np.asarray(r64.A)))))
            reflects = (np.asarray(r64.R_s) > 1e-6) & (np.asarray(r64.R_p) > 1e-6)
            dpsi = np.abs(np.asarray(e32.psi, np.float64) - np.asarray(e64.psi))[reflects]
            row["f32_max_abs_err_psi"] = max(row["f32_max_abs_err_psi"], float(dpsi.max(initial=0.0)))
            for g, fwd in ((g64, fwd64), (g32, fwd32)):
                row["nan_inf_grad_rev"] += int(sum(np.sum(~np.isfinite(np.asarray(x))) for x in g))
                row["nan_inf_grad_fwd"] += int(not np.isfinite(float(fwd)))
            # first-order effect of a 2-ulp relative change of every float32 input
            eps = float(np.finfo(np.float32).eps)
            sens = sum(np.abs(np.asarray(x) * np.asarray(gx)).reshape(per, -1).sum(-1)
                       for x, gx in zip((n64.real, n64.imag, d64, w64, c64), g64))
            excess = np.maximum(errR - 2 * eps * sens, 0)
            row["f32_max_excess_R"] = max(row["f32_max_excess_R"], float(excess.max()))
            k = min(mp_samples // len(media), per)
            worst, compared = _reference_diff(reference_of(cat, L), inc, n64, d64, w64, c64, r64, k)
            row["mp_max_abs_diff"] = max(row["mp_max_abs_diff"], worst)
            row["mp_compared"] += compared
            row.setdefault("reference", [])
            if reference_of(cat, L) not in row["reference"]:
                row["reference"].append(reference_of(cat, L))
        row["f32_p999_abs_err_R"] = float(np.quantile(np.concatenate(errs), 0.999))
        rows.append(row)
        if progress:
            progress.update(1)
    return rows


def _reference_diff(reference, inc, n, d, wl, c, res, k):
    """(max |difference| of R_s, R_p, T_s, T_p from the reference (`reference_of`), stacks compared)
    over the first k stacks. tmm is not asked about an incoherent layer in which the wave is
    evanescent (it divides by the layer's zero flux there) nor where it raises."""
    import warnings

    import mpmath as mp

    from .mpref import stack_ref

    worst, compared = 0.0, 0
    for i in range(k):
        refs = {}
        for pol in "sp":
            if reference == "closed form":
                refs[pol] = (0.0, 1.0)
            elif reference == "tmm":
                import tmm

                s2 = (n[i, 0].real * np.sqrt(max(0.0, 1 - c[i] ** 2))) ** 2
                if any(abs(np.sqrt(n[i, j + 1] ** 2 - s2).real) < 1e-6 for j in inc):
                    break
                kinds = ["i"] + ["i" if j in inc else "c" for j in range(len(d[i]))] + ["i"]
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        ref = tmm.inc_tmm(pol, list(n[i]), [np.inf, *d[i], np.inf], kinds, float(np.arccos(c[i])), wl[i])
                except (AssertionError, ValueError, ZeroDivisionError, FloatingPointError):
                    break
                refs[pol] = (ref["R"], ref["T"])
            else:
                with mp.workdps(40):
                    theta = mp.acos(mp.mpf(float(c[i])))
                refs[pol] = stack_ref(pol, n[i], d[i], wl[i], theta)[2:]
        if len(refs) < 2:
            continue
        compared += 1
        for pol, (R, T) in refs.items():
            got = (float(getattr(res, f"R_{pol}")[i]), float(getattr(res, f"T_{pol}")[i]))
            worst = max(worst, abs(got[0] - R), abs(got[1] - T))
    return worst, compared


def stack_stress_table(rows) -> str:
    out = ["| category | stacks | float32 max abs err R | p99.9 | beyond 2-ulp input change | T | A | psi (rad) | "
           "float64 vs reference (stacks) | R+T+sum(A)-1 float64 / float32 | NaN/inf values | NaN/inf grads rev / fwd |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        out.append(f"| {r['category']} | {r['n']:,} | {r['f32_max_abs_err_R']:.2g} | {r['f32_p999_abs_err_R']:.2g} | "
                   f"{r['f32_max_excess_R']:.2g} | {r['f32_max_abs_err_T']:.2g} | {r['f32_max_abs_err_A']:.2g} | "
                   f"{r['f32_max_abs_err_psi']:.2g} | {r['mp_max_abs_diff']:.2g} ({r['mp_compared']}, {' + '.join(r.get('reference', []))}) | "
                   f"{r['energy_f64']:.2g} / {r['energy_f32']:.2g} | {r['nan_inf_values']} | "
                   f"{r['nan_inf_grad_rev']} / {r['nan_inf_grad_fwd']} |")
    return "\n".join(out)
