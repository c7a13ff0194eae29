"""Every notebook runs top to bottom without an error: CI executes the first; the others, whose
calls CI tests elsewhere, run with the costly cases (`-m costly`)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3


# Notebooks with the costly cases, each with its calls tested in CI elsewhere:
# - 02 (gradients, `saltation_matrix`, `variational_jacobian`, the rimless wheel's `periodic_orbit`):
#   test_gradients.py, test_saltation.py, test_long_derivatives.py, test_periodic_gradients.py;
# - 03 (Zeno completion, chattering, blocking, `check_properties`, `monte_carlo`):
#   test_zeno_blocking.py, test_zeno_options.py, test_property_checks.py, test_batched_coverage.py;
# - 04 (`accuracy_preset` against a reference at each preset): test_stress.py;
# - 05 (shooting from three guesses, hybrid iLQR): test_shooting.py and test_ilqr.py;
# - 06 (the wedge particle's batch, the rod, `animate_scene`): test_scenes.py, test_scene_animation.py;
# - 07 (`SaltedKalmanFilter`, `sobol_indices`, `morris_effects`): test_kalman.py, test_sensitivity.py.
COSTLY = {"02_gradients_and_saltation", "03_zeno_and_blocking", "04_speed_versus_accuracy", "05_trajectory_optimisation",
          "06_scenes", "07_estimation_and_sensitivity"}


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
