"""Every notebook runs top to bottom without an error (CI executes them)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3


# The trajectory-optimisation notebook (shooting from three guesses, hybrid iLQR) with the costly
# cases: its calls are the tests' own in test_shooting.py and test_ilqr.py.
COSTLY = {"05_trajectory_optimisation"}


@pytest.mark.slow
@pytest.mark.parametrize(
    "path", [pytest.param(p, marks=pytest.mark.costly) if p.stem in COSTLY else p for p in NOTEBOOKS],
    ids=lambda p: p.stem,
)
def test_notebook_executes(path):
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(path.parent)}}).execute()
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    images = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert images  # every notebook draws
