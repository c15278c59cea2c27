"""The `kernels` section of `python -m jaxoptics bench`: every kernel and formulation, speed against
error side by side with its peers (naive JAX, NumPy, Mitsuba 3), throughput against batch size,
what bounds XLA on the CPU, and the speed-versus-error chart."""

from __future__ import annotations

import statistics

import numpy as np

from ._measure import _mitsuba, _np_fresnel_unpolarized, timeit


def _naive_jax_fresnel(c, e1, e2):
    """The textbook formula transcribed directly (the naive peer)."""
    import jax.numpy as jnp

    sin2 = 1 - c * c
    ct2 = 1 - (e1 / e2) ** 2 * sin2
    ct = jnp.sqrt(jnp.maximum(ct2, 0))
    rs = (e1 * c - e2 * ct) / (e1 * c + e2 * ct)
    rp = (e2 * c - e1 * ct) / (e2 * c + e1 * ct)
    return jnp.where(ct2 < 0, 1.0, 0.5 * (rs * rs + rp * rp))


def _guarded_naive_jax_fresnel(c, e1, e2):
    """The textbook formula with the exact kernel's guards and none of its accuracy forms: NaN for
    invalid input, `|cos_i|`, the 0/0 of grazing incidence with `eta1 == eta2`, and a square root
    whose gradient stays finite at the critical angle (the double `where`). Side by side with the
    exact kernel and the bare formula, it splits the exact kernel's extra time into the price of
    the guards and the price of the accurate forms."""
    import jax.numpy as jnp

    c = jnp.abs(c)
    valid = (c < jnp.inf) & (e1 > 0) & (e1 < jnp.inf) & (e2 > 0) & (e2 < jnp.inf)
    ct2 = 1 - (e1 / e2) ** 2 * (1 - c * c)
    ct = jnp.where(ct2 > 0, jnp.sqrt(jnp.maximum(ct2, jnp.finfo(c.dtype).tiny)), 0)
    ds, dp = e1 * c + e2 * ct, e2 * c + e1 * ct
    ok = (ds * ds > 0) & (dp * dp > 0)
    rs = (e1 * c - e2 * ct) / jnp.where(ok, ds, 1)
    rp = (e2 * c - e1 * ct) / jnp.where(ok, dp, 1)
    R = jnp.where(ok, jnp.where(ct2 < 0, 1.0, 0.5 * (rs * rs + rp * rp)), jnp.where(e1 > e2, 1.0, 0.0))
    return jnp.where(valid, R, jnp.nan)


def _schlick_pow(c, e1, e2):
    import jax.numpy as jnp

    r0 = ((e1 - e2) / (e1 + e2)) ** 2
    return r0 + (1 - r0) * jnp.power(1 - c, jnp.asarray(5.0, c.dtype))


def _fresnel_reference(c, e1, e2):
    from . import mpref as _mpref

    out = []
    for x in c:
        d = _mpref.fresnel_ref(_mpref.mpf(x), _mpref.mpf(e1), _mpref.mpf(e2))
        out.append(float((d["R_s"] + d["R_p"]) / 2))
    return np.asarray(out)


def _schlick_reference(c, e1, e2):
    r0 = ((e1 - e2) / (e1 + e2)) ** 2
    return r0 + (1 - r0) * (1 - c.astype(np.float64)) ** 5


def bench_kernels(*, quick=False, progress=None, sizes=None, mitsuba=True, repeats=None):
    """Throughput and error of every Fresnel model and refraction method, float32 and float64,
    side by side with NumPy, a naive JAX transcription and Mitsuba 3, plus a copy kernel."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    sizes = sizes or ((1_000, 100_000, 1_000_000) if quick else (1_000, 100_000, 10_000_000))
    repeats = repeats or (3 if quick else 7)
    e1, e2 = 1.5, 1.0  # leaving glass: the critical angle and TIR are in the sweep
    rows = []
    rng = np.random.default_rng(0)
    sample = rng.uniform(0, 1, 400)
    ref_exact = _fresnel_reference(sample, e1, e2)
    ref_schlick = _schlick_reference(sample, e1, e2)
    models = {
        "fresnel, exact (jaxoptics)": (lambda c: jo.fresnel(c, e1, e2), ref_exact),
        "naive JAX textbook fresnel": (lambda c: _naive_jax_fresnel(c, e1, e2), ref_exact),
        "schlick, multiplications (jaxoptics)": (lambda c: jo.schlick(c, e1, e2), ref_exact),
        "schlick, pow": (lambda c: _schlick_pow(c, e1, e2), ref_exact),
        "schlick_tir (jaxoptics)": (lambda c: jo.schlick_tir(c, e1, e2), ref_exact),
        "copy (x * 2), the memory-bound limit": (lambda c: c * 2, None),
    }
    for dtype in (np.float32, np.float64):
        for name, (f, ref) in models.items():
            fj = jax.jit(f)
            err = {}
            if ref is not None:
                got = np.asarray(fj(jnp.asarray(sample.astype(dtype))), np.float64)
                err = dict(max_err=float(np.max(np.abs(got - ref))), mean_err=float(np.mean(np.abs(got - ref))))
                if "schlick" in name:  # its error against its own formula too (numerical stability)
                    err["max_err_vs_own_formula"] = float(np.max(np.abs(got - ref_schlick))) if "tir" not in name else None
            for N in sizes:
                c = jnp.asarray(rng.uniform(0, 1, N).astype(dtype))
                comp, run, _ = timeit(lambda: fj(c), repeats=repeats)
                rows.append(dict(group="fresnel", method=name, dtype=np.dtype(dtype).name, n=N, compile_s=comp, run_s=run,
                                 ns_per_element=1e9 * run / N, bytes_per_element=2 * np.dtype(dtype).itemsize, **err))
            if progress:
                progress.update(1)
        # NumPy peer (the same textbook formula)
        err_np = np.asarray(_np_fresnel_unpolarized(sample.astype(dtype), dtype(e1), dtype(e2)), np.float64)
        for N in sizes:
            c = rng.uniform(0, 1, N).astype(dtype)
            comp, run, _ = timeit(lambda: _np_fresnel_unpolarized(c, dtype(e1), dtype(e2)), repeats=repeats, warmup=True)
            rows.append(dict(group="fresnel", method="NumPy textbook fresnel", dtype=np.dtype(dtype).name, n=N, compile_s=None,
                             run_s=run, ns_per_element=1e9 * run / N, max_err=float(np.max(np.abs(err_np - ref_exact))),
                             mean_err=float(np.mean(np.abs(err_np - ref_exact)))))
        # gradients with respect to the index: reverse mode (of the sum) and forward mode (per element)
        for mode in ("jax.grad", "forward mode (jvp)"):
            if mode == "jax.grad":
                g = jax.jit(jax.grad(lambda e, c: jnp.sum(jo.fresnel(c, e1, e))))
                call = lambda c: g(jnp.asarray(e2, dtype), c)
            else:
                g = jax.jit(lambda e, c: jax.jvp(lambda e: jo.fresnel(c, e1, e), (e,), (jnp.ones_like(e),))[1])
                e_full = {}  # the per-element index is made once per size, outside the timed region
                call = lambda c: g(e_full.setdefault(c.shape, jnp.full(c.shape, e2, dtype)), c)
            for N in sizes:
                c = jnp.asarray(rng.uniform(0, 1, N).astype(dtype))
                comp, run, _ = timeit(lambda: call(c), repeats=repeats)
                rows.append(dict(group="gradient", method=f"d fresnel / d eta2, {mode}", dtype=np.dtype(dtype).name, n=N,
                                 compile_s=comp, run_s=run, ns_per_element=1e9 * run / N))
        if progress:
            progress.update(1)
        # refraction methods (vectors)
        th = rng.uniform(0, np.pi / 2, 300)
        iv = np.stack([np.sin(th), np.zeros_like(th), -np.cos(th)], -1)
        nz = np.array([0.0, 0.0, 1.0])
        from . import mpref as _mpref

        ref_t = np.array([[float(v) for v in _mpref.refract_ref([_mpref.mpf(x) for x in row], [_mpref.mpf(0), _mpref.mpf(0), _mpref.mpf(1)],
                                                                _mpref.mpf(e1), _mpref.mpf(e2))[0]] for row in iv.astype(dtype)])
        for method in ("degreve", "bec", "heckbert", "oliveira"):
            f = jax.jit(lambda i, m=method: jo.refract(i, jnp.asarray(nz, dtype), e1, e2, method=m).t)
            got = np.asarray(f(jnp.asarray(iv.astype(dtype))), np.float64)
            d = np.max(np.abs(got - ref_t), axis=1)
            for N in sizes:
                t_ = rng.uniform(0, np.pi / 2, N)
                i = jnp.asarray(np.stack([np.sin(t_), np.zeros_like(t_), -np.cos(t_)], -1).astype(dtype))
                comp, run, _ = timeit(lambda: f(i), repeats=repeats)
                rows.append(dict(group="refract", method=f"refract, {method}", dtype=np.dtype(dtype).name, n=N, compile_s=comp,
                                 run_s=run, ns_per_element=1e9 * run / N, max_err=float(np.max(d)), mean_err=float(np.mean(d)),
                                 bytes_per_element=6 * np.dtype(dtype).itemsize))
        if progress:
            progress.update(1)
        # scene specializations of the fused kernel, against the separate kernels
        specs = {
            "interface, full (r, t, tir, R, T)": jo.InterfaceSpec(),
            "interface, R only": jo.InterfaceSpec(outputs=("R",)),
            "interface, R only, no input checks": jo.InterfaceSpec(outputs=("R",), check_inputs=False),
            "interface, t and R, schlick, no TIR": jo.InterfaceSpec(outputs=("t", "R"), fresnel="schlick", tir_possible=False),
            "separate: refract": None,
            "separate: fresnel_rt of |i.n|": None,
            "separate: fresnel of |i.n| (R only)": None,
            "separate: reflect": None,
        }
        for name, spec in specs.items():
            if spec is not None:
                f = jax.jit(lambda i, s=spec: jo.interface(i, jnp.asarray(nz, dtype), e1, e2, spec=s))
            elif "refract" in name:
                f = jax.jit(lambda i: jo.refract(i, jnp.asarray(nz, dtype), e1, e2))
            elif "fresnel_rt" in name:
                f = jax.jit(lambda i: jo.fresnel_rt(jnp.abs(i[..., 2]), e1, e2))
            elif "fresnel of" in name:
                f = jax.jit(lambda i: jo.fresnel(jnp.abs(i[..., 2]), e1, e2))
            else:
                f = jax.jit(lambda i: jo.reflect(i, jnp.asarray(nz, dtype)))
            N = sizes[-1]
            t_ = rng.uniform(0, np.pi / 2, N)
            i = jnp.asarray(np.stack([np.sin(t_), np.zeros_like(t_), -np.cos(t_)], -1).astype(dtype))
            comp, run, _ = timeit(lambda: f(i), repeats=repeats)
            rows.append(dict(group="scene", method=name, dtype=np.dtype(dtype).name, n=N, compile_s=comp, run_s=run,
                             ns_per_element=1e9 * run / N))
        if progress:
            progress.update(1)
    # Mitsuba 3 (float32 only: its llvm_ad_rgb variant)
    mi, dr = _mitsuba() if mitsuba else (None, "not requested")
    if mi is None:
        rows.append(dict(group="fresnel", method=f"Mitsuba 3 fresnel (skipped: {dr})", dtype="float32", n=0))
    else:
        got = np.asarray(mi.fresnel(mi.Float(sample.astype(np.float32)), mi.Float(e2 / e1))[0], np.float64)
        err = dict(max_err=float(np.max(np.abs(got - ref_exact))), mean_err=float(np.mean(np.abs(got - ref_exact))))
        for N in sizes:
            c = mi.Float(rng.uniform(0, 1, N).astype(np.float32))
            eta = mi.Float(e2 / e1)

            def mitsuba_call(c=c, eta=eta):
                r = mi.fresnel(c, eta)[0]
                dr.eval(r)
                dr.sync_thread()

            comp, run, _ = timeit(mitsuba_call, repeats=repeats)
            rows.append(dict(group="fresnel", method="Mitsuba 3 fresnel (Dr.Jit LLVM)", dtype="float32", n=N, compile_s=comp,
                             run_s=run, ns_per_element=1e9 * run / N, **err))
    if progress:
        progress.update(1)
    return rows


def _fusions(compiled) -> int:
    """Number of fused loops XLA emitted for a compiled program (each reads and writes memory)."""
    text = compiled.as_text()
    entry = text.split("ENTRY", 1)[1] if "ENTRY" in text else text
    return entry.count(" fusion(")


def bench_limits(*, quick=False, progress=None, n=None):
    """What bounds XLA on the CPU, measured (float32, one size): output allocation (the same
    kernels with the input buffer donated, so no fresh output pages are touched), the fusion split
    of a kernel with two outputs sharing divisions and square roots, and a reduction over a
    length-3 minor axis against the same dot product written out. Fresh inputs are made for every
    donated call, outside the timed region."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    N = n or (1_000_000 if quick else 10_000_000)
    repeats = 3 if quick else 7
    e1, e2 = 1.5, 1.0
    rng = np.random.default_rng(1)
    base = rng.uniform(0, 1, N).astype(np.float32)
    rows = []

    def run_rows(name, f, donate, arg, suffix=""):
        fj = jax.jit(f, donate_argnums=0) if donate else jax.jit(f)
        inputs = [jnp.array(arg) for _ in range(repeats + 1)] if donate else None
        compiled = fj.lower(arg).compile()
        if donate:
            jax.block_until_ready(inputs)
            it = iter(inputs)
            comp, run, _ = timeit(lambda: compiled(next(it)), repeats=repeats)
        else:
            comp, run, _ = timeit(lambda: compiled(arg), repeats=repeats, settle=10 if suffix else 0)
        rows.append(dict(group="limits", method=name + (", input donated" if donate else "") + suffix, dtype="float32", n=N,
                         compile_s=comp, run_s=run, ns_per_element=1e9 * run / N, fusions=_fusions(compiled)))

    def numpy_row(suffix):
        comp, run, _ = timeit(lambda: _np_fresnel_unpolarized(base, np.float32(e1), np.float32(e2)), repeats=repeats,
                              warmup=True, settle=10 if suffix else 0)
        rows.append(dict(group="limits", method="NumPy textbook fresnel" + suffix, dtype="float32", n=N, compile_s=None,
                         run_s=run, ns_per_element=1e9 * run / N, fusions=None))

    c = jnp.asarray(base)
    kernels = (("copy (x * 2)", lambda c: c * 2),
               ("fresnel, exact (jaxoptics)", lambda c: jo.fresnel(c, e1, e2)),
               ("naive JAX textbook fresnel", lambda c: _naive_jax_fresnel(c, e1, e2)),
               ("naive JAX textbook fresnel with the exact kernel's guards", lambda c: _guarded_naive_jax_fresnel(c, e1, e2)))
    for name, f in kernels:
        for donate in (False, True):
            run_rows(name, f, donate, c)
        if progress:
            progress.update(1)
    numpy_row("")
    # the kernels as part of a caller's program: reduced (a loss, a radiance sum), where XLA fuses
    # the kernel's loop into the reduction
    consumers = (("fresnel, exact (jaxoptics), consumed by jnp.sum", lambda c: jnp.sum(jo.fresnel(c, e1, e2))),
                 ("naive JAX textbook fresnel, consumed by jnp.sum", lambda c: jnp.sum(_naive_jax_fresnel(c, e1, e2))),
                 ("naive JAX textbook fresnel with the exact kernel's guards, consumed by jnp.sum",
                  lambda c: jnp.sum(_guarded_naive_jax_fresnel(c, e1, e2))))
    for name, f in consumers:
        run_rows(name, f, False, c)
    # the fused interface kernel against its most expensive part (vector outputs: 3x the bytes)
    t_ = rng.uniform(0, np.pi / 2, N)
    iv = jnp.asarray(np.stack([np.sin(t_), np.zeros_like(t_), -np.cos(t_)], -1).astype(np.float32))
    nz = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    # and the floor under each: the same output arrays from trivial arithmetic (XLA on the CPU
    # writes each output in a loop of its own, reading the inputs again)
    vector_kernels = (("refract (degreve)", lambda i: jo.refract(i, nz, e1, e2)),
                      ("interface, full (r, t, tir, R, T)", lambda i: jo.interface(i, nz, e1, e2, spec=jo.InterfaceSpec())),
                      ("output floor of refract: (t, tir) from trivial arithmetic",
                       lambda i: (i * 2 + nz[None, :], i[..., 0] > i[..., 2])),
                      ("output floor of interface: (r, t, tir, R, T) from trivial arithmetic",
                       lambda i: (i * 2 + nz[None, :], i - nz[None, :], i[..., 0] > i[..., 2], i[..., 0] * i[..., 2],
                                  i[..., 1] * i[..., 2])))
    for name, f in vector_kernels:
        run_rows(name, f, False, iv)
    from .._interface._fresnel_terms import _sp_rt

    def shared_rt(c):  # R and T from one graph: the quotients both need feed two outputs
        R_s, R_p, T_s, T_p = _sp_rt(c, jnp.full_like(c, e1), jnp.full_like(c, e2))
        return 0.5 * (R_s + R_p), 0.5 * (T_s + T_p)

    run_rows("R and T from one shared graph (two outputs sharing quotients)", shared_rt, False, c)
    run_rows("the same, consumed as 0.3 R + 0.7 T (one output)", lambda c: (lambda R, T: 0.3 * R + 0.7 * T)(*shared_rt(c)), False, c)
    run_rows("jo.fresnel_rt (R and T as two loops)", lambda c: jo.fresnel_rt(c, e1, e2), False, c)
    v = jnp.asarray(np.stack([base, 1 - base, base * 0.5], -1))
    w = jnp.asarray(np.array([0.2, 0.3, 0.5], np.float32))
    run_rows("dot of 3-vectors, jnp.sum(a * b, axis=-1)", lambda v: jnp.sum(v * w[None, :], axis=-1), False, v)
    run_rows("dot of 3-vectors, written out", lambda v: v[..., 0] * w[0] + v[..., 1] * w[1] + v[..., 2] * w[2], False, v)
    # The same with freed memory kept mapped (glibc mallopt, `jo.keep_freed_memory`): no page
    # faults on fresh output buffers, for JAX and NumPy alike. Last: glibc's values are restored
    # after, but not its dynamic mmap threshold (see `run`).
    if jo.keep_freed_memory():
        try:
            for name, f in kernels:
                run_rows(name, f, False, c, ", freed memory kept")
            run_rows("jo.fresnel_rt (R and T as two loops)", lambda c: jo.fresnel_rt(c, e1, e2),
                     False, c, ", freed memory kept")
            for name, f in consumers:
                run_rows(name, f, False, c, ", freed memory kept")
            numpy_row(", freed memory kept")
            for name, f in vector_kernels:
                run_rows(name, f, False, iv, ", freed memory kept")
        finally:
            jo.keep_freed_memory(enable=False)
    else:
        rows.append(dict(group="limits", method="freed memory kept: not available (not glibc), skipped", n=0))
    if progress:
        progress.update(2)
    return rows


def bench_fresnel_ratio(*, quick=False, progress=None, n=None, rounds=None):
    """The exact `fresnel` against the naive transcription of the textbook formula, as a kernel on
    its own (an array output) and consumed by a reduction (`jnp.sum`), float32, with freed memory
    kept (so page faults on fresh outputs do not dilute the difference). The kernels are timed in
    interleaved rounds (exact, naive, naive with the exact kernel's guards; again and again), so a
    drift of the machine's speed reaches all of them alike; each kernel's time is the median over
    its rounds, and the ratios are taken between those medians."""
    import jax
    import jax.numpy as jnp

    import jaxoptics as jo

    N = n or (1_000_000 if quick else 10_000_000)
    rounds = rounds or (2 if quick else 5)
    e1, e2 = 1.5, 1.0
    c = jnp.asarray(np.random.default_rng(2).uniform(0, 1, N).astype(np.float32))
    forms = {"exact": lambda c: jo.fresnel(c, e1, e2), "naive": lambda c: _naive_jax_fresnel(c, e1, e2),
             "guarded": lambda c: _guarded_naive_jax_fresnel(c, e1, e2)}
    uses = {"on its own (array output)": lambda f: f, "consumed by jnp.sum": lambda f: lambda c: jnp.sum(f(c))}
    if not jo.keep_freed_memory():
        return [dict(use="freed memory kept: not available (not glibc), skipped", n=0)]
    try:
        compiled = {(u, k): jax.jit(wrap(f)).lower(c).compile() for u, wrap in uses.items() for k, f in forms.items()}
        times: dict = {key: [] for key in compiled}
        for _ in range(rounds):
            for key, fn in compiled.items():
                times[key].append(timeit(lambda fn=fn: fn(c), repeats=7, settle=3)[1])
    finally:
        jo.keep_freed_memory(enable=False)
    rows = []
    for u in uses:
        ns = {k: 1e9 * statistics.median(times[(u, k)]) / N for k in forms}
        rows.append(dict(use=u, n=N, rounds=rounds, exact_ns=ns["exact"], naive_ns=ns["naive"], guarded_ns=ns["guarded"],
                         exact_over_naive=ns["exact"] / ns["naive"], guarded_over_naive=ns["guarded"] / ns["naive"]))
    if progress:
        progress.update(1)
    return rows


def fresnel_ratio_table(rows) -> str:
    out = ["| use | exact (ns/element) | naive (ns/element) | naive with the guards (ns/element) | exact / naive "
           "| guarded / naive |", "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if not r.get("n"):
            out.append(f"| {r['use']} | | | | | |")
            continue
        out.append(f"| {r['use']} | {r['exact_ns']:.3g} | {r['naive_ns']:.3g} | {r['guarded_ns']:.3g} "
                   f"| {r['exact_over_naive']:.2f}x | {r['guarded_over_naive']:.2f}x |")
    return "\n".join(out)


def limits_table(rows) -> str:
    out = ["| what | elements/s | ns/element | XLA fused loops |", "| --- | ---: | ---: | ---: |"]
    for r in rows:
        if not r.get("n"):
            out.append(f"| {r['method']} | | | |")
            continue
        fus = "" if r.get("fusions") is None else r["fusions"]
        out.append(f"| {r['method']} | {r['n'] / r['run_s']:.3g} | {r['ns_per_element']:.3g} | {fus} |")
    return "\n".join(out)


def kernels_table(rows, size) -> str:
    out = ["| group | method | dtype | elements/s | ns/element | compile (s) | max error | mean error | GB/s |",
           "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if r.get("n") != size:
            if r.get("n") == 0:
                out.append(f"| {r['group']} | {r['method']} | {r['dtype']} | | | | | | |")
            continue
        eps = r["n"] / r["run_s"]
        gbs = f"{r['bytes_per_element'] * eps / 1e9:.1f}" if r.get("bytes_per_element") else ""
        comp = "" if r.get("compile_s") is None else f"{r['compile_s']:.2f}"
        me = "" if r.get("max_err") is None else f"{r['max_err']:.2e}"
        mn = "" if r.get("mean_err") is None else f"{r['mean_err']:.2e}"
        out.append(f"| {r['group']} | {r['method']} | {r['dtype']} | {eps:.3g} | {r['ns_per_element']:.3g} | {comp} | {me} | {mn} | {gbs} |")
    return "\n".join(out)


def scaling_table(rows, sizes) -> str:
    head = "| method | dtype | " + " | ".join(f"N = {n:.0e}" for n in sizes) + " |"
    out = [head, "| --- | --- | " + " | ".join("---:" for _ in sizes) + " |"]
    keys = []
    for r in rows:
        k = (r["method"], r["dtype"])
        if r.get("n") and r["group"] in ("fresnel", "refract", "gradient") and k not in keys:
            keys.append(k)
    for k in keys:
        cells = []
        for n in sizes:
            m = [r for r in rows if (r["method"], r["dtype"]) == k and r.get("n") == n]
            cells.append(f"{n / m[0]['run_s']:.3g}/s" if m else "")
        out.append(f"| {k[0]} | {k[1]} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def pareto_chart(rows, size, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 6))
    markers = {"float32": "o", "float64": "s"}
    for r in rows:
        if r.get("n") != size or r.get("max_err") is None or r["group"] not in ("fresnel", "refract"):
            continue
        err = max(r["max_err"], 1e-17)
        color = "C0" if "jaxoptics" in r["method"] or r["group"] == "refract" else ("C3" if "Mitsuba" in r["method"] else "C1")
        ax.scatter(r["ns_per_element"], err, marker=markers[r["dtype"]], color=color, s=40)
        ax.annotate(f"{r['method'].replace(' (jaxoptics)', '')} [{r['dtype'][-2:]}]", (r["ns_per_element"], err),
                    fontsize=6.5, xytext=(4, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"time per element (ns), N = {size:,}")
    ax.set_ylabel("max abs error against 50-digit mpmath")
    ax.set_title("Speed against error (lower left is better); circles float32, squares float64")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
