"""Write the bundled layered-sample example (`jaxoptics/data/example_sio2_si.csv`): a thermal
SiO2 film on Si, psi/delta at 65, 70 and 75 degrees from 300 to 1000 nm, computed with tmm
(independent of jaxoptics' kernels) for a Cauchy film (coefficients fitted to Malitson's fused
silica) on the built-in Si (Green 2008),
with Gaussian noise of 0.02 degrees on psi and 0.05 degrees on delta (seed 0).

Run by a maintainer: `python -m jaxoptics.tools.make_examples`.
"""

from __future__ import annotations

import math

import numpy as np

from .._films._rii import material
from .._io._spectra import Spectra, save_spectra

D_NM = 512.4
SIGMA = (0.02, 0.05)
# the film's index: Cauchy's law fitted (least squares, 300-1000 nm) to Malitson's fused silica
CAUCHY = (1.44721, 0.0038613, -2.3392e-05)


def main():
    from importlib.metadata import version

    import jax
    import jax.numpy as jnp
    import tmm

    jax.config.update("jax_enable_x64", True)
    from pathlib import Path

    wl1 = np.arange(300.0, 1000.0 + 1e-9, 5.0)
    angles = (65.0, 70.0, 75.0)
    wl = np.tile(wl1, len(angles))
    ang = np.repeat(angles, len(wl1))
    film = CAUCHY[0] + CAUCHY[1] / (wl / 1000) ** 2 + CAUCHY[2] / (wl / 1000) ** 4
    sub = np.asarray(material("Si").nk(jnp.asarray(wl / 1000)))
    psi, delta = [], []
    for i in range(len(wl)):
        e = tmm.ellips([1.0, film[i], sub[i]], [np.inf, D_NM, np.inf], math.radians(ang[i]), wl[i])
        psi.append(math.degrees(e["psi"]))
        delta.append((180 - math.degrees(e["Delta"])) % 360)  # instrument convention, 0..360
    rng = np.random.default_rng(0)
    V = np.stack([np.array(psi) + SIGMA[0] * rng.normal(size=len(wl)), np.array(delta) + SIGMA[1] * rng.normal(size=len(wl))])
    S = np.stack([np.full(len(wl), SIGMA[0]), np.full(len(wl), SIGMA[1])])
    out = Path(__file__).resolve().parent.parent / "data" / "example_sio2_si.csv"
    save_spectra(out, Spectra(wl, ang, ("psi_deg", "delta_deg"), V, S))
    head = ("# Synthetic ellipsometry of a thermal SiO2 film on Si (jaxoptics example).\n"
            f"# Computed with tmm {version('tmm')} (not with jaxoptics): SiO2 {D_NM} nm with Cauchy index A, B, C = {CAUCHY} "
            "(um; fitted to Malitson's fused silica), on Si (Green 2008), ambient air.\n"
            f"# Psi and Delta in degrees, instrument convention (rho = r_p/r_s = tan Psi exp(i Delta)); noise {SIGMA[0]} deg on psi,"
            f" {SIGMA[1]} deg on delta (seed 0).\n")
    out.write_text(head + out.read_text())
    print(out)


if __name__ == "__main__":
    main()
