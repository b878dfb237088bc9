"""The notebooks execute from top to bottom (outputs are stripped in git).

Needs the `dev` extra's nbclient, nbformat and ipykernel. All notebooks run in **one
kernel**, in file order, each with a fresh namespace (`%reset -f` first): the programs a
notebook compiled (a joint calibration's solve, the measurement chain) stay compiled in
the kernel for the next one (03, 04 and 05 calibrate the same 4-view scene), and the test
session's compilation cache, shared with the kernel through `SCHEIMFLUX_CACHE_DIR`, serves
programs other tests compiled. 176 s in all from an empty compilation cache at load ~2 on
2 cores (01 5 s, 02 10 s, 03 51 s, 04 69 s, 05 39 s; docs/metrology.md, "Notebooks"); in
a fresh-clone CI run on 2026-12-03 (load ~3) 03 128 s, 04 181 s, 05 79 s, 02 25 s, so 02,
04 and 05 run with `-m slow` and the default suite runs 01 and 03.
"""

import glob
import json
import os

import pytest

NOTEBOOKS = sorted(glob.glob(os.path.join(os.path.dirname(__file__), "..", "notebooks", "*.ipynb")))
_RESET = (
    'get_ipython().run_line_magic("reset", "-f")\n'
    'import matplotlib.pyplot\nmatplotlib.pyplot.close("all")'
)


@pytest.fixture(scope="module")
def kernel():
    """One kernel for every notebook of this module (stopped at the end)."""
    pytest.importorskip("nbclient")
    jupyter_client = pytest.importorskip("jupyter_client")
    km = jupyter_client.KernelManager(kernel_name="python3")
    km.start_kernel(cwd=os.path.dirname(NOTEBOOKS[0]))
    yield km
    km.shutdown_kernel(now=True)


def _execute(path, km):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    with open(path, encoding="utf-8") as fh:
        nb = nbformat.read(fh, as_version=4)
    nb.cells.insert(0, nbformat.v4.new_code_cell(_RESET))
    client = nbclient.NotebookClient(
        nb, km=km, timeout=1800, kernel_name="python3",
        resources={"metadata": {"path": os.path.dirname(path)}},
    )
    try:
        client.execute()
    finally:  # the kernel stays for the next notebook; this client's sockets do not
        if client.kc is not None:
            client.kc.stop_channels()


def test_notebook_outputs_are_stripped():
    assert len(NOTEBOOKS) >= 5
    for path in NOTEBOOKS:
        with open(path, encoding="utf-8") as fh:
            nb = json.load(fh)
        for cell in nb["cells"]:
            if cell["cell_type"] == "code":
                assert cell.get("outputs", []) == [], path
                assert cell.get("execution_count") is None, path


# The table-3 step-gauge notebook is the longest (~3 min of its own compilation in CI) and
# the joint-calibration study next (79-210 s in CI runs on 2026-12-03; a radius's gradient
# is also checked in tests/test_metrology_fits.py, the derivative through the solve in
# tests/test_calibrate.py with -m slow): both run with `-m slow`. So does the figure-3
# notebook (27 s of the default suite on 2026-12-05; its numbers are tests/test_fig3.py's,
# which stays in the default suite); the model tour and the quick start run by default.
_SLOW = {
    "02_fig3_model_error.ipynb",
    "04_table3_step_gauge.ipynb",
    "05_joint_calibration_study.ipynb",
}


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(p, marks=pytest.mark.slow) if os.path.basename(p) in _SLOW else p
        for p in NOTEBOOKS
    ],
    ids=os.path.basename,
)
def test_notebook_executes(path, kernel):
    _execute(path, kernel)
