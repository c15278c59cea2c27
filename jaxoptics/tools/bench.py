"""`python -m jaxoptics bench`: speed measured side by side on this machine.

Conventions of every measurement here: warm-up call first (its time, minus a run, is reported as
compile time), `block_until_ready`, the median over repeats, ratios taken between numbers measured
in the same run.
"""

from __future__ import annotations

import json
from pathlib import Path

from ._measure import machine_description, run_stamp
from .bench_fit import bench_devices, bench_fit_in_subprocess, devices_table, fit_table
from .bench_kernels import bench_fresnel_ratio, bench_kernels, bench_limits, fresnel_ratio_table, kernels_table, limits_table, pareto_chart, scaling_table
from .bench_stack import LAYERS, stack_chart


def _sections(sections):
    """(name, title, measure, table) of the requested sections after "kernels", in report order."""
    from .bench_design import bench_design, design_table
    from .bench_latency import bench_latency, latency_table
    from .bench_stack import bench_stack, stack_table
    from .bench_stack_fit import bench_stack_fit, stack_fit_table

    known = [
        ("fit", "Index fits: 90 angles per curve, float64, noise 1e-3", bench_fit_in_subprocess, fit_table),
        ("stack", f"Thin-film stacks: {', '.join(map(str, LAYERS))} coherent layers on Si, (wavelength, angle) points; "
         "indices shared or per point, reflectances or every output, forward and gradient", bench_stack, stack_table),
        ("stackfit", "Film fits over a wafer map: psi/delta, 200 wavelengths x 3 angles per spectrum; thickness and Cauchy "
         "A, B, C free", bench_stack_fit, stack_fit_table),
        ("design", "Coating design: refinement from many starts, and needle synthesis", bench_design, design_table),
        ("latency", "Latency: from the command to the answer (fresh processes)", bench_latency, latency_table),
        ("devices", "Sharding over devices (forced host devices sharing this machine's cores)", bench_devices,
         devices_table),
    ]
    return [k for k in known if k[0] in sections]


def run(*, quick=False, sections=("kernels", "fit", "stack", "stackfit", "design", "devices", "latency"), out_dir="bench_out", sizes=None,
        mitsuba=True) -> dict:
    import jax
    from tqdm.auto import tqdm

    jax.config.update("jax_enable_x64", True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine_description(), "quick": quick, "date": run_stamp()}
    cmd = "python -m jaxoptics bench" + (" --quick" if quick else "") + f" --sections {','.join(sections)}"
    md = [f"Measured by `{cmd}` on {report['date']}. Machine: {report['machine']}.", ""]
    total = (6 * ("fit" in sections) + 3 * ("devices" in sections) + 25 * ("kernels" in sections) + (1 + 2 * len(LAYERS)) * ("stack" in sections)
             + (5 + (2 if quick else 5)) * ("stackfit" in sections)  # the map, scipy, pyElli; the effects (EFFECTS)
             + 9 * ("latency" in sections) + 5 * ("design" in sections))
    with tqdm(total=total, desc="bench", unit="step") as bar:
        if "kernels" in sections:
            rows = bench_kernels(quick=quick, progress=bar, sizes=sizes, mitsuba=mitsuba)
            report["kernels"] = rows
            size = max(r["n"] for r in rows if r.get("n"))
            pareto_chart(rows, size, out / "pareto.png")
            md += [f"### Kernels at N = {size:,} (eta1 = 1.5, eta2 = 1: TIR included; median of repeats)", "",
                   kernels_table(rows, size), "", "### Throughput against batch size", "",
                   scaling_table(rows, sorted({r["n"] for r in rows if r.get("n")})), ""]
            lim = bench_limits(quick=quick, progress=bar, n=max(sizes) if sizes else None)
            report["limits"] = lim
            md += [f"### What bounds XLA on the CPU (float32, N = {lim[0]['n']:,})", "", limits_table(lim), ""]
            ratio = bench_fresnel_ratio(quick=quick, progress=bar, n=max(sizes) if sizes else None)
            report["fresnel_vs_naive"] = ratio
            md += [f"### Exact fresnel against the naive formula (float32, N = {ratio[0]['n']:,}, freed memory kept, "
                   f"{ratio[0].get('rounds', 0)} interleaved rounds)", "", fresnel_ratio_table(ratio), ""]
        for name, title, measure, table in _sections(sections):
            rows = measure(quick=quick, progress=bar)
            report[name] = rows
            md += [f"### {title}", "", table(rows), ""]
            if name == "stack":
                stack_chart(rows, out / "stack.png")
    text = "\n".join(md)
    (out / "bench.md").write_text(text + "\n")
    (out / "bench.json").write_text(json.dumps(report, indent=2))
    print(text)
    chart = (f", {out / 'pareto.png'}" if "kernels" in sections else "") + (f", {out / 'stack.png'}" if "stack" in sections else "")
    print(f"\nwritten: {out / 'bench.md'}, {out / 'bench.json'}{chart}")
    return report




