"""Every notebook runs top to bottom on a fresh install, with no error cell.

The longest cells take about 30 s on a quiet 2-core machine and several times that when the suite
shares the machine; the per-cell timeout only catches a hang, so it is far above both (time is not
what these tests judge)."""

import os
import pathlib

import nbclient
import nbformat
import pytest

pytestmark = pytest.mark.slow  # the quick subset (-m "not slow") leaves this file out

CELL_TIMEOUT_S = 900
NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
# Notebooks whose time goes into running compiled programs rather than compiling them: their
# kernels compile at XLA's default optimization level instead of the suite's level 0
# (`conftest.py`). Measured on the 2-core machine, whole notebook, one at a time: 09 (the coating
# designs' refinements) 64 s at the default level and 87 s at level 0; 05, 07 and 08 are faster at
# level 0 (40, 39, 67 s against 61, 61, 91 s).
RUN_TIME_BOUND = ("09_coating_design.ipynb",)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    env = dict(os.environ)
    if path.name in RUN_TIME_BOUND:
        from helpers import xla_flags_without

        env["XLA_FLAGS"] = xla_flags_without("xla_backend_optimization_level")
    client.execute(env=env)
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    images = sum(1 for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {}))
    assert images >= 2, "a notebook that teaches with figures shows them"


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3
