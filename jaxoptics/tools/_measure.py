"""What the measuring tools share: the machine's description, the timing convention, the run's
date, and two peers (the textbook Fresnel formula in NumPy, and Mitsuba 3 where it is
installed). Imports nothing else of `jaxoptics.tools`."""

from __future__ import annotations

import os
import platform
import statistics
import time

import numpy as np


def machine_description() -> str:
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"jax {jax.__version__} ({jax.default_backend()}), numpy {np.__version__}")


def timeit(fn, *, repeats=5, warmup=True, settle=0):
    """(compile_s, median_run_s, all runs): the first call (tracing + compilation + one run) is
    timed apart; compile time is reported as first call minus the median run. `settle` more
    untimed calls follow it (with freed memory kept, each thread's malloc arena grows to its
    working size in the first few calls, and those still page-fault)."""
    import jax

    first = None
    if warmup:
        t = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t
    for _ in range(settle):
        jax.block_until_ready(fn())
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t)
    med = statistics.median(runs)
    return (None if first is None else max(first - med, 0.0)), med, runs


def timeit_round_robin(fns: dict, *, repeats=5) -> dict:
    """`timeit` for several functions timed in turn: each one's first call, then `repeats` rounds
    calling each once, so a drift of the machine's speed reaches all of them alike. Returns, per
    key, `timeit`'s (compile_s, median_run_s, all runs)."""
    import jax

    first = {}
    for key, fn in fns.items():
        t = time.perf_counter()
        jax.block_until_ready(fn())
        first[key] = time.perf_counter() - t
    runs: dict = {key: [] for key in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn())
            runs[key].append(time.perf_counter() - t)
    out = {}
    for key, r in runs.items():
        med = statistics.median(r)
        out[key] = (max(first[key] - med, 0.0), med, r)
    return out


def run_stamp() -> str:
    """The date and time of a run, UTC, for the tables the tools write."""
    import datetime

    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def _mitsuba():
    try:
        if "DRJIT_LIBLLVM_PATH" not in os.environ:
            for cand in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/aarch64-linux-gnu/libLLVM-19.so"):
                if os.path.exists(cand):
                    os.environ["DRJIT_LIBLLVM_PATH"] = cand
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        return mi, dr
    except Exception as e:  # noqa: BLE001 - the peer is optional; say why it was skipped
        return None, f"{type(e).__name__}: {str(e)[:100]}"


def _np_fresnel_unpolarized(cos_i, eta1, eta2):
    """NumPy transcription of the textbook formula (the peer for scipy's model function)."""
    sin2 = 1 - cos_i**2
    ct2 = 1 - (eta1 / eta2) ** 2 * sin2
    ct = np.sqrt(np.maximum(ct2, 0))
    rs = (eta1 * cos_i - eta2 * ct) / (eta1 * cos_i + eta2 * ct)
    rp = (eta2 * cos_i - eta1 * ct) / (eta2 * cos_i + eta1 * ct)
    return np.where(ct2 < 0, 1.0, 0.5 * (rs * rs + rp * rp))
