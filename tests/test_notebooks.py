"""The notebooks execute from top to bottom (outputs are stripped in git).

Needs the `dev` extra's nbclient, nbformat and ipykernel. The default suite executes
the notebooks that neither calibrate nor ray-trace a grid (01: the model's equations);
the others simulate and calibrate (a joint-calibration compile is ~1 min on an idle
2-core machine, several under load) and run with `-m slow`. Measured times are in
docs/metrology.md ("Notebooks").
"""

import glob
import json
import os

import pytest

NOTEBOOKS = sorted(glob.glob(os.path.join(os.path.dirname(__file__), "..", "notebooks", "*.ipynb")))
# the notebooks cheap enough for the default suite (no calibration, no ray tracing)
FAST = ("01_thick_lens_model.ipynb",)


def _execute(path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    with open(path, encoding="utf-8") as fh:
        nb = nbformat.read(fh, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=1800, kernel_name="python3",
        resources={"metadata": {"path": os.path.dirname(path)}},
    )
    client.execute()


def test_notebook_outputs_are_stripped():
    assert len(NOTEBOOKS) >= 5
    for path in NOTEBOOKS:
        with open(path, encoding="utf-8") as fh:
            nb = json.load(fh)
        for cell in nb["cells"]:
            if cell["cell_type"] == "code":
                assert cell.get("outputs", []) == [], path
                assert cell.get("execution_count") is None, path


@pytest.mark.parametrize(
    "path", [p for p in NOTEBOOKS if os.path.basename(p) in FAST], ids=os.path.basename
)
def test_fast_notebook_executes(path):
    _execute(path)


@pytest.mark.slow
@pytest.mark.parametrize(
    "path", [p for p in NOTEBOOKS if os.path.basename(p) not in FAST], ids=os.path.basename
)
def test_notebook_executes(path):
    _execute(path)
