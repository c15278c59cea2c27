"""Write the traced programs shipped with the package: `python -m jaxoptics.tools.make_programs`.

They are the batched solve of `fit_eta` (`_index_stages._first`), each traced once for every
number of angles from 16 to 4096 and of curves up to 32 (`jax.export` with symbolic shapes), in
each form the command line's `fit` calls it: float64; a real or a complex (`--absorbing`) index;
with or without a sigma column; one polarization for all curves (s, p or unpolarized) or one per
curve. A process whose program store (`jaxoptics.enable_cache`) holds no such program compiles
the shipped one instead of tracing it, which is most of a first fit's time (`_cache`).

Shipped programs are keyed as stored ones are, by the package's source and the versions of jax,
jaxlib, optimistix, equinox, lineax and numpy among other things: a process with other versions
does not find them and traces as usual. After any change to the package's source, run this
again (`tests/test_cache.py` checks that the shipped programs are those of the source).
`data/programs/MANIFEST.json` lists them, with the source hash and the versions they were traced
with.
"""

from __future__ import annotations

import argparse
import json
import lzma
import sys
import tempfile
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "data" / "programs"
MANIFEST = "MANIFEST.json"


def forms():
    """The forms of `fit_eta` calls the command line's `fit` makes: (name, keyword arguments)."""
    for absorbing in (False, True):
        for sigma in (False, True):
            for pol in ("s", "p", "unpolarized", ("s", "p")):
                name = (f"{'complex' if absorbing else 'real'} index, {'sigma' if sigma else 'no sigma'}, "
                        + (f"{pol} for all curves" if isinstance(pol, str) else "a polarization per curve"))
                yield name, dict(absorbing=absorbing, sigma=sigma, polarization=pol)


def read_manifest(directory: Path = OUT) -> dict:
    """The manifest of the shipped programs: source hash, library versions, backend, programs."""
    return json.loads((directory / MANIFEST).read_text())


def _data(absorbing: bool, polarization, sigma: bool):
    """Curves of the command line's kind (NumPy arrays) for one form: only their shapes and dtypes matter."""
    import jaxoptics as jo

    theta = np.radians(np.linspace(5.0, 85.0, 40))
    eta = 0.2 + 3.4j if absorbing else 1.5
    pols = (polarization,) if isinstance(polarization, str) else polarization
    R = np.stack([np.asarray(jo.synthetic_reflectance(None, eta, theta, polarization=p)) for p in pols])
    kw: dict = dict(polarization=polarization if isinstance(polarization, str) else tuple(polarization),
                    absorbing=absorbing, eta1=1.0)
    if sigma:
        kw["sigma"] = np.full(R.shape, 2e-3)
    return theta, R, kw


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m jaxoptics.tools.make_programs", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(OUT), help="directory to write (default: the package's data/programs)")
    args = p.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)  # as the command line does
    import jaxoptics as jo
    from jaxoptics._runtime import _cache

    out = Path(args.out)
    todo = list(forms())
    listing = []
    with tempfile.TemporaryDirectory() as tmp:
        _cache.enable_store(tmp)
        _cache._SHIPPED[0] = None  # trace every one here
        try:
            for k, (name, form) in enumerate(todo):
                before = set(Path(tmp).glob("*" + _cache._SUFFIX))
                theta, R, kw = _data(**form)
                jo.fit_eta(theta, R, **kw)
                new = sorted(set(Path(tmp).glob("*" + _cache._SUFFIX)) - before)
                if len(new) != 1:
                    print(f"error: {name}: expected one program for all shapes, got {len(new)}", file=sys.stderr)
                    return 1
                listing.append(dict(file=new[0].name, form=name, **{k: v if isinstance(v, (bool, str)) else list(v)
                                                                     for k, v in form.items()}))
                print(f"[{k + 1}/{len(todo)}] {name}: {new[0].stat().st_size / 1024:.0f} KiB", flush=True)
        finally:
            _cache.disable_store()
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("*" + _cache.SHIPPED_SUFFIX):
            old.unlink()
        for item in listing:
            name = item["file"]
            item["file"] = name + ".xz"
            (out / item["file"]).write_bytes(lzma.compress((Path(tmp) / name).read_bytes(), preset=9))
    manifest = dict(source=_cache.source_hash(), versions=_cache.library_versions(), backend=jax.default_backend(),
                    programs=listing)
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"written: {len(listing)} programs and {MANIFEST} in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
