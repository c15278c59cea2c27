"""The `latency` section of `python -m jaxoptics bench`: how long a user waits, from the command
to the answer, each case in fresh processes, side by side in one run.

- `import jaxoptics`;
- the main job of the README without the plot (`python -m jaxoptics fit --example`), with the
  cache cold (a new, empty cache directory each repeat), warm, and turned off;
- a plain SciPy script doing the same fit end to end: it reads the same CSV file and fits each
  curve with `scipy.optimize.least_squares` on the textbook Fresnel reflectance;
- the layered-sample example (`fit-stack --example`) with the cache warm and turned off;
- inside a fresh process, the first `fit_eta` call on one curve (tracing, compilation and run) and
  the second call, with the cache off and warm (`jaxoptics.enable_cache`).

"Cache" is `jaxoptics.enable_cache`'s directory: JAX's persistent compilation cache and the fits'
traced programs.

Each row is the median over repeats of the wall time of a whole subprocess (or, for the `fit_eta`
rows, of the time the process measures around the call).

The package's modules are byte-compiled first (`compileall`), as `pip install` does and as an
editable install's first import does, so that no case compiles jaxoptics' Python source, as none
compiles SciPy's: where `PYTHONDONTWRITEBYTECODE` is set, an editable install would otherwise
compile it in every process (about 0.15 s).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SCIPY_SCRIPT = r"""
import csv, sys
import numpy as np
from scipy.optimize import least_squares

rows = [r for r in csv.DictReader(l for l in open(sys.argv[1]) if not l.startswith("#"))]
for pol in ("s", "p"):
    sel = [r for r in rows if r["polarization"] == pol]
    th = np.deg2rad([float(r["angle_deg"]) for r in sel])
    R = np.array([float(r["R"]) for r in sel])
    sig = np.array([float(r["sigma"]) for r in sel])

    def model(n):
        c = np.cos(th)
        ct = np.sqrt(1 - (np.sin(th) / n) ** 2 + 0j)
        r = (c - n * ct) / (c + n * ct) if pol == "s" else (n * c - ct) / (n * c + ct)
        return np.abs(r) ** 2

    fit = least_squares(lambda x: (model(x[0]) - R) / sig, x0=[1.5])
    J = fit.jac
    err = np.sqrt(np.linalg.inv(J.T @ J)[0, 0] * max(1.0, 2 * fit.cost / (len(R) - 1)))
    print(pol, fit.x[0], err)
"""

FIRST_CALL_SCRIPT = r"""
import sys, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import jaxoptics as jo
if sys.argv[1] != "off":
    jo.enable_cache(path=sys.argv[1])
c = jo.load_reflectance(jo.example_path()).curves()[0]
t1 = time.perf_counter()
jax.block_until_ready(jo.fit_eta(c.theta, c.R, polarization=c.polarization, sigma=c.sigma).eta)
t2 = time.perf_counter()
jax.block_until_ready(jo.fit_eta(c.theta, c.R, polarization=c.polarization, sigma=c.sigma).eta)
t3 = time.perf_counter()
print(t2 - t1, t3 - t2)
"""


def _wall(cmd, env=None) -> float:
    t = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
    return time.perf_counter() - t


def _env(**kw):
    env = dict(os.environ)
    env.update(kw)
    return env


def bench_latency(*, quick=False, progress=None, repeats=None) -> list[dict]:
    import compileall

    import jaxoptics as jo

    compileall.compile_dir(str(Path(jo.__file__).parent), quiet=1)
    reps = repeats or (3 if quick else 5)
    py = sys.executable
    csv_path = str(jo.example_path())
    rows = []

    def row(name, times, note=""):
        rows.append(dict(case=name, median_s=statistics.median(times), runs=times, note=note))
        if progress:
            progress.update(1)

    row("import jaxoptics", [_wall([py, "-c", "import jaxoptics"]) for _ in range(reps)])
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        script = tmp / "scipy_fit.py"
        script.write_text(SCIPY_SCRIPT)
        cli = [py, "-m", "jaxoptics", "fit", "--example"]
        cold = []
        for k in range(reps):
            cold.append(_wall(cli, _env(JAXOPTICS_CACHE_DIR=str(tmp / f"cold{k}"))))
        row("CLI fit --example, cache cold (empty)", cold)
        warm_dir = str(tmp / "warm")
        _wall(cli, _env(JAXOPTICS_CACHE_DIR=warm_dir))  # fills it
        row("CLI fit --example, cache warm", [_wall(cli, _env(JAXOPTICS_CACHE_DIR=warm_dir)) for _ in range(reps)])
        row("CLI fit --example --no-cache", [_wall(cli + ["--no-cache"]) for _ in range(reps)])
        row("SciPy script: same CSV, least_squares per curve", [_wall([py, str(script), csv_path]) for _ in range(reps)])
        stack_cli = [py, "-m", "jaxoptics", "fit-stack", "--example"]
        stack_dir = str(tmp / "stack")
        _wall(stack_cli, _env(JAXOPTICS_CACHE_DIR=stack_dir))  # fills it
        row("CLI fit-stack --example, cache warm", [_wall(stack_cli, _env(JAXOPTICS_CACHE_DIR=stack_dir)) for _ in range(reps)])
        row("CLI fit-stack --example --no-cache", [_wall(stack_cli + ["--no-cache"]) for _ in range(reps)])
        for label, cache in (("cache off", "off"), ("cache warm", str(tmp / "fitcache"))):
            if cache != "off":
                subprocess.run([py, "-c", FIRST_CALL_SCRIPT, cache], check=True, capture_output=True)
            firsts, seconds = [], []
            for _ in range(reps):
                out = subprocess.run([py, "-c", FIRST_CALL_SCRIPT, cache], check=True, capture_output=True, text=True)
                a, b = (float(x) for x in out.stdout.split())
                firsts.append(a)
                seconds.append(b)
            row(f"first fit_eta call, one curve, in a fresh process ({label})", firsts, "tracing, compilation, run")
            row(f"second fit_eta call, same shapes ({label})", seconds)
    return rows


def latency_table(rows) -> str:
    by = {r["case"]: r["median_s"] for r in rows}
    scipy = by.get("SciPy script: same CSV, least_squares per curve")
    out = ["| case | median (s) | runs (s) | vs the SciPy script |", "| --- | ---: | --- | ---: |"]
    for r in rows:
        vs = f"{r['median_s'] / scipy:.1f}x" if scipy and r["case"].startswith(("CLI fit --", "SciPy")) else ""
        runs = ", ".join(f"{t:.2f}" for t in r["runs"])
        out.append(f"| {r['case']} | {r['median_s']:.3f} | {runs} | {vs} |")
    return "\n".join(out)
