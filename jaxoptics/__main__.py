"""Command line: `python -m jaxoptics <command>`.

Commands:
  demo    print R_s, R_p, R and T across angles for air -> glass and glass -> air, with the
          critical and Brewster angles (a quick check that the install works).
"""

from __future__ import annotations

import argparse
import sys


def _demo(args) -> int:
    import jax
    import numpy as np

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jaxoptics", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="Fresnel table for air/glass in both directions")
    p.add_argument("--eta", type=float, default=1.5, help="index of the glass (default 1.5)")
    p.set_defaults(func=_demo)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
