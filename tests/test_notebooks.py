"""Every notebook runs top to bottom on a fresh install, with no error cell.

The longest cells take about 30 s on a quiet 2-core machine and several times that when the suite
shares the machine; the per-cell timeout only catches a hang, so it is far above both (time is not
what these tests judge)."""

import pathlib

import nbclient
import nbformat
import pytest

pytestmark = pytest.mark.slow  # the quick subset (-m "not slow") leaves this file out

CELL_TIMEOUT_S = 900
NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    client.execute()
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    images = sum(1 for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {}))
    assert images >= 2, "a notebook that teaches with figures shows them"


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3
