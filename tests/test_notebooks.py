"""The notebooks execute from top to bottom (outputs are stripped in git).

Slow: they simulate and calibrate (several minutes on 2 cores); needs the `dev` extra's
nbclient, nbformat and ipykernel.
"""

import glob
import json
import os

import pytest

NOTEBOOKS = sorted(glob.glob(os.path.join(os.path.dirname(__file__), "..", "notebooks", "*.ipynb")))


def test_notebook_outputs_are_stripped():
    for path in NOTEBOOKS:
        with open(path, encoding="utf-8") as fh:
            nb = json.load(fh)
        for cell in nb["cells"]:
            if cell["cell_type"] == "code":
                assert cell.get("outputs", []) == [], path
                assert cell.get("execution_count") is None, path


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=os.path.basename)
def test_notebook_executes(path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    with open(path, encoding="utf-8") as fh:
        nb = nbformat.read(fh, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=1800, kernel_name="python3",
        resources={"metadata": {"path": os.path.dirname(path)}},
    )
    client.execute()
