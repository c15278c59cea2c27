"""The `stack` section of `python -m jaxoptics bench`: coherent stacks of 1, 10 and 100 layers over
(wavelength, angle) points, in the cases users have, against NumPy and tmm, and against a floor.

Cases, each measured in one run (medians over repeats, the first call's extra time reported as
compile time; the six programs of one layer count and dtype are timed round-robin, so that their
ratios are measured under the same conditions):

- indices **shared** by all points (`n` of shape `(L+2,)`) or **per point** (`(N, L+2)`: what a
  dispersive material gives, one index per wavelength, and what a fit whose indices depend on
  the wavelength passes);
- outputs: the **reflectances** `R_s, R_p` alone, or **all** of `StackResult` (`R`, `T`, the
  absorption in each layer, the amplitudes `r`, `t` and `rp_rs`);
- float64 and float32; the forward pass and the **gradient** of `sum(R)` in every `n`, `k` and `d`.

Peers: a vectorized NumPy transcription (characteristic matrices over all points at once, as a
textbook writes them) computing the same outputs, and tmm (`coh_tmm`, one point at a time, s and
p, float64).

The floor: the floating-point operations per point that the algorithm needs (`flops_per_point`,
counted operation by operation from `jaxoptics._films._layers`), divided by the throughput this
machine reaches in XLA on a plain fused loop of complex multiply-adds over the same number of
points (`fma_throughput`). A case's "x floor" is its time over that; it is what is left to gain
by any reformulation that keeps the arithmetic.
"""

from __future__ import annotations

import functools
import time

import numpy as np

from ._measure import timeit, timeit_round_robin

LAYERS = (1, 10, 100)


def example_stack(dtype=np.float64, layers=10):
    """A coherent stack on silicon: alternating TiO2/SiO2-like films (the fourth weakly absorbing),
    thicknesses 40-160 nm."""
    rng = np.random.default_rng(0)
    inner = np.where(np.arange(layers) % 2 == 0, 2.35, 1.46) + 0j
    if layers > 3:
        inner[3] = 2.0 + 0.05j
    n = np.r_[1.0, inner, 3.9 + 0.02j]
    d = rng.uniform(40, 160, layers)
    cdt = np.complex128 if dtype == np.float64 else np.complex64
    return n.astype(cdt), d.astype(dtype)


def per_point(n, wl):
    """The indices of `n` at each point, `(N, L+2)`: a mild normal dispersion, 1% over the band
    (the incident medium stays 1)."""
    out = n[None, :] * (1 + 0.01 * (600 / wl[:, None] - 1)).astype(n.real.dtype)
    out[:, 0] = 1
    return out.astype(n.dtype)


def points(N, dtype=np.float64):
    """N (wavelength, cos_i) points on a grid (N a multiple of 100): 400-800 nm, 0-80 degrees."""
    wl, th = np.meshgrid(np.linspace(400, 800, N // 100), np.deg2rad(np.linspace(0, 80, 100)), indexing="ij")
    return wl.ravel().astype(dtype), np.cos(th.ravel()).astype(dtype)


def numpy_stack(n, d, wl, cos_i, outputs="R"):
    """Plain vectorized characteristic matrices over all points at once (`n` of shape `(L+2,)` or
    `(N, L+2)`), as a textbook writes them in NumPy. `outputs="R"`: `(R_s, R_p)`; `"all"`: also
    `T_s, T_p`, the absorption per inner layer `A_s, A_p` (`(N, L)`, from the power flux at each
    interface), the amplitudes `r_s, r_p, t_s, t_p` (conventions of `jo.stack`: `t_p` of the whole
    field, `r_p = -r_s` at normal incidence) and `rp_rs = r_p conj(r_s)`."""
    L = n.shape[-1]
    col = lambda j: n[..., j]
    n0 = col(0).real
    s2 = (n0 ** 2) * (1 - cos_i ** 2)
    kz = [np.sqrt(col(j) ** 2 - s2 + 0j).astype(n.dtype) for j in range(L)]
    kz = [np.where(k.imag < 0, -k, k) for k in kz]
    out = {}
    for pol in "sp":
        eta = [k if pol == "s" else col(j) ** 2 / k for j, k in enumerate(kz)]
        # fields (E, H) from the back: the outgoing wave (1, eta_exit), through each layer's matrix
        E = np.ones_like(kz[0])
        H = eta[-1] * E
        flux = []
        for j in range(L - 2, 0, -1):
            if outputs == "all":
                flux.append((E * np.conj(H)).real)
            dl = 2 * np.pi * d[..., j - 1] / wl * kz[j]
            c, s = np.cos(dl), np.sin(dl)
            E, H = c * E - 1j * s / eta[j] * H, -1j * eta[j] * s * E + c * H
        D = eta[0] * E + H
        r = (eta[0] * E - H) / D
        out["R_" + pol] = np.abs(r) ** 2
        if outputs == "all":
            norm = 4 * eta[0].real / np.abs(D) ** 2
            fl = [(E * np.conj(H)).real] + flux[::-1] + [eta[-1].real]  # at each interface, front to back
            fl = [f * norm for f in fl]
            out["T_" + pol] = fl[-1]
            out["A_" + pol] = np.stack([fl[j] - fl[j + 1] for j in range(L - 2)], axis=-1)
            t = 2 * eta[0] / D
            if pol == "p":  # Hecht's signs (r_p = -r_s at normal incidence); t_p of the whole in-plane field
                r = -r
                t = t * (kz[0] / col(0)) / (kz[-1] / col(L - 1))
            out["r_" + pol], out["t_" + pol] = r, t
    if outputs == "all":
        out["rp_rs"] = out["r_p"] * np.conj(out["r_s"])
    return out


def flops_per_point(layers, outputs="R", gradient=False):
    """Real floating-point operations per point of the coherent stack kernel, counted from its
    algorithm (`jaxoptics._films._layers`; a complex multiplication is 6, a complex addition 2, a
    real division or square root 1).

    Per inner layer (the scan step): `q = n^2 - n0^2 + k_i^2` (8); its decaying root, Kahan's form
    (12, with a hypot and two square roots); the phase `a k_z` (2); one argument reduction and the
    sine and cosine polynomials (about 40); `expm1` (about 15); the entries `c` and
    `s = a g sin(delta) / delta` (20); `q s`, `(q / n^2) s`, `n^2 s` (26, with `1 / n^2` per point);
    the fields of both polarizations through the matrices (4 outputs of two complex products and a
    sum: 56). About 180. With every output, the flux at each interface (2 x 3) and the
    attenuation (2): 188. Once per point: the exit medium's `k_z` (20), the front's `D`, `r` and
    `R` of both polarizations (about 50); with every output also `t`, `T`, the flux
    normalizations, `A` per layer (3 per layer) and `rp_rs` (about 60 + 3 per layer).

    The gradient in every `n`, `k`, `d`: the forward pass recomputed block by block, then the
    transposed tangent scan (per layer: the entry derivatives `dc`, `ds` (about 40 with the
    closed form of `ds/dq`), the tangent fields (4 outputs of four complex products: 104), the
    cotangents of `q`, `n`, `d` (about 40)): about 3x the forward pass's per-layer count."""
    per_layer = 180 + (8 if outputs == "all" else 0)
    once = 70 + (60 + 3 * layers if outputs == "all" else 0)
    fwd = layers * per_layer + once
    return fwd + (layers * 184 + once) * 2 if gradient else fwd


def fma_throughput(N, dtype=np.float64, repeats=9):
    """Real flops per second of XLA on this machine for a plain fused loop of complex
    multiply-adds (`z = z * a + b`, 64 in a row, over N points: one fused loop, vectorized, bound
    by arithmetic), the median over repeats."""
    import jax
    import jax.numpy as jnp

    cdt = np.complex128 if dtype == np.float64 else np.complex64
    rng = np.random.default_rng(1)
    z0 = jnp.asarray((rng.uniform(-1, 1, N) + 1j * rng.uniform(-1, 1, N)).astype(cdt))
    a = jnp.asarray((0.6 + 0.7j) * np.ones(N, cdt))
    b = jnp.asarray((0.1 - 0.2j) * np.ones(N, cdt))
    K = 64

    @jax.jit
    def f(z, a, b):
        for _ in range(K):
            z = z * a + b
        return z

    _, t, _ = timeit(lambda: f(z0, a, b), repeats=repeats)
    return K * 8 * N / t  # a complex multiply-add: 6 + 2 real flops


def _tmm_per_point(layers, K):
    import tmm

    n, d = example_stack(np.float64, layers)
    wl, c = points(max(100, K // 100 * 100))
    idx = np.linspace(0, len(c) - 1, K).astype(int)
    dl = [np.inf] + list(d) + [np.inf]
    runs = []
    for _ in range(3):
        t = time.perf_counter()
        for i in idx:
            th = np.arccos(c[i])
            tmm.coh_tmm("s", n, dl, th, wl[i])
            tmm.coh_tmm("p", n, dl, th, wl[i])
        runs.append((time.perf_counter() - t) / K)
    return float(np.median(runs))


def _max_diff(got, ref):
    return float(max(np.max(np.abs(np.asarray(got[k]) - ref[k])) for k in ref))


def bench_stack(*, quick=False, progress=None, repeats=None, layers=LAYERS, N=None, dtypes=("float64", "float32")):
    """Rows of the stack section: one per (layers, dtype, indices, outputs, pass), each with the
    kernel's time per point, NumPy's for the same outputs (forward rows), tmm's (per point, float64,
    same layer count), the floor and the gradient's ratio to its forward pass."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    N = N or (20_000 if quick else 100_000)
    reps = repeats or (3 if quick else 7)
    rows = []
    floor_rate = {}
    dtypes = [np.dtype(t).type for t in dtypes]
    for dtype in dtypes:
        floor_rate[np.dtype(dtype).name] = fma_throughput(N, dtype, repeats=2 * reps + 1)
    tmm_pp = {L: _tmm_per_point(L, 20 if quick else 100) for L in layers}
    if progress:
        progress.update(1)

    def R_only(n, d, w, c):
        r = jo.stack(n, d, w, c)
        return {"R_s": r.R_s, "R_p": r.R_p}

    def every(n, d, w, c):
        r = jo.stack(n, d, w, c)
        return {k: getattr(r, k) for k in ("R_s", "R_p", "T_s", "T_p", "A_s", "A_p", "r_s", "r_p", "t_s", "t_p", "rp_rs")}

    grad = jax.jit(jax.grad(lambda n, d, w, c: jnp.sum(jo.stack(n, d, w, c).R), argnums=(0, 1)))
    fwd = {"R": jax.jit(R_only), "all": jax.jit(every)}
    for L in layers:
        for dtype in dtypes:
            name = np.dtype(dtype).name
            n1, d = example_stack(dtype, L)
            wl, c = points(N, dtype)
            ns = {"shared": n1, "per point": per_point(n1, wl)}
            args = {k: tuple(jnp.asarray(x) for x in (n, d, wl, c)) for k, n in ns.items()}
            # the six programs of this layer count and dtype, timed round-robin (their ratios are
            # then measured under the same conditions)
            cases = {(ind, out, p): functools.partial(grad if p == "gradient" else fwd[out], *args[ind])
                     for ind in ns for out, p in (("R", "forward"), ("all", "forward"), ("R", "gradient"))}
            timed = timeit_round_robin(cases, repeats=reps)
            med = {key: t for key, (_, t, _) in timed.items()}
            for (ind, out, p), (comp, t, _) in timed.items():
                n = ns[ind]
                row = dict(layers=L, dtype=name, indices=ind, points=N, tmm_per_point_s=tmm_pp[L], outputs=out, pass_=p,
                           compile_s=comp, run_s=t, per_point_s=t / N)
                flops = flops_per_point(L, out, gradient=p == "gradient")
                row.update(flops=flops, floor_per_point_s=flops / floor_rate[name])
                if p == "gradient":
                    row["vs_forward"] = t / med[ind, "R", "forward"]
                else:
                    _, t_np, _ = timeit(lambda: numpy_stack(n, d, wl, c, out), repeats=max(1, reps - 2))
                    K = min(N, 2000)  # agreement with NumPy on the first K points: the rows compute the same thing
                    got = {k: v[:K] for k, v in fwd[out](*args[ind]).items()}
                    row.update(numpy_per_point_s=t_np / N,
                               max_abs_diff_vs_numpy=_max_diff(got, numpy_stack(n[:K] if n.ndim == 2 else n, d, wl[:K], c[:K], out)))
                rows.append(row)
            if progress:
                progress.update(1)
    for r in rows:
        r["fma_flops_per_s"] = floor_rate[r["dtype"]]
    return rows


def stack_table(rows) -> str:
    """The section's table: ns per point, and ratios to NumPy (same outputs), tmm and the floor;
    gradient rows give their ratio to the forward pass of the reflectances. Then the ratios the
    kernel is held to: per-point over shared indices, every output over the reflectances."""
    out = ["| layers | dtype | indices | outputs | pass | compile (s) | ns per point | vs NumPy | vs tmm | floor (ns) | x floor | notes |",
           "| ---: | --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in rows:
        vn = f"{r['numpy_per_point_s'] / r['per_point_s']:.1f}x faster" if "numpy_per_point_s" in r else "-"
        vt = f"{r['tmm_per_point_s'] / r['per_point_s']:.3g}x faster"
        notes = []
        if "vs_forward" in r:
            notes.append(f"{r['vs_forward']:.2f}x the forward pass of R")
        if r.get("max_abs_diff_vs_numpy") is not None:
            notes.append(f"max abs diff vs NumPy {r['max_abs_diff_vs_numpy']:.1e}")
        outputs = "R_s, R_p" if r["outputs"] == "R" else "all"
        what = "grad of sum(R) in every n, k, d" if r["pass_"] == "gradient" else "forward"
        out.append(f"| {r['layers']} | {r['dtype']} | {r['indices']} | {outputs} | {what} | {r['compile_s']:.2f} | "
                   f"{1e9 * r['per_point_s']:.0f} | {vn} | {vt} | {1e9 * r['floor_per_point_s']:.0f} | "
                   f"{r['per_point_s'] / r['floor_per_point_s']:.1f} | {'; '.join(notes)} |")
    rate = {r["dtype"]: r["fma_flops_per_s"] for r in rows}
    out += ["", "Floor: the flops per point counted from the algorithm (`bench_stack.flops_per_point`) at the rate of "
            "a plain fused loop of complex multiply-adds in XLA on this machine: "
            + ", ".join(f"{v / 1e9:.1f} Gflop/s ({k})" for k, v in rate.items()) + ".", ""]
    key = lambda r: (r["layers"], r["dtype"])
    ratios = ["| layers | dtype | per point / shared (R) | per point / shared (all) | all / R (per point) | "
              "grad / forward (per point) |", "| ---: | --- | ---: | ---: | ---: | ---: |"]
    for L, dt in dict.fromkeys(key(r) for r in rows):
        g = {(r["indices"], r["outputs"], r["pass_"]): r["per_point_s"] for r in rows if key(r) == (L, dt)}
        ratios.append(f"| {L} | {dt} | {g['per point', 'R', 'forward'] / g['shared', 'R', 'forward']:.2f} | "
                      f"{g['per point', 'all', 'forward'] / g['shared', 'all', 'forward']:.2f} | "
                      f"{g['per point', 'all', 'forward'] / g['per point', 'R', 'forward']:.2f} | "
                      f"{g['per point', 'R', 'gradient'] / g['per point', 'R', 'forward']:.2f} |")
    return "\n".join(out + ratios)


def stack_chart(rows, path):
    """Time per point against the number of layers, one panel per dtype: the kernel's cases,
    NumPy computing the same outputs, tmm, and the floor (log-log)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dtypes = list(dict.fromkeys(r["dtype"] for r in rows))
    fig, axes = plt.subplots(1, len(dtypes), figsize=(6 * len(dtypes), 4.8), squeeze=False)
    for ax, dt in zip(axes[0], dtypes):
        rs = [r for r in rows if r["dtype"] == dt]
        Ls = sorted({r["layers"] for r in rs})

        def line(select, value, label, **kw):
            ys = [1e9 * value(next(r for r in rs if r["layers"] == L and select(r))) for L in Ls]
            ax.plot(Ls, ys, marker="o", label=label, **kw)

        for ind, ls in (("shared", "--"), ("per point", "-")):
            line(lambda r, i=ind: r["indices"] == i and r["outputs"] == "R" and r["pass_"] == "forward",
                 lambda r: r["per_point_s"], f"stack, {ind} n, R", color="C0", ls=ls)
            line(lambda r, i=ind: r["indices"] == i and r["outputs"] == "all" and r["pass_"] == "forward",
                 lambda r: r["per_point_s"], f"stack, {ind} n, all outputs", color="C2", ls=ls)
            line(lambda r, i=ind: r["indices"] == i and r["pass_"] == "gradient",
                 lambda r: r["per_point_s"], f"grad of sum(R), {ind} n", color="C4", ls=ls)
        for out, color in (("R", "C1"), ("all", "C3")):
            line(lambda r, o=out: r["indices"] == "per point" and r["outputs"] == o and r["pass_"] == "forward",
                 lambda r: r["numpy_per_point_s"], f"NumPy, per-point n, {'R' if out == 'R' else 'all outputs'}",
                 color=color, ls=":")
        line(lambda r: r["pass_"] == "forward" and r["outputs"] == "R", lambda r: r["tmm_per_point_s"],
             "tmm (float64, per point)", color="C7", ls="-.")
        line(lambda r: r["pass_"] == "forward" and r["outputs"] == "R", lambda r: r["floor_per_point_s"],
             "floor (flops at the complex-FMA rate), R", color="k", ls=":")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("inner layers")
        ax.set_ylabel("time per (wavelength, angle) point (ns)")
        ax.set_title(f"{dt}, {rs[0]['points']:,} points")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
