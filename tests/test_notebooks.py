"""The teaching notebooks (notebooks/*.ipynb) run headless from a clean kernel, top to bottom.

Each notebook is executed with nbclient in a temporary folder; any error fails the test. The
notebooks' own assert cells check their numbers (e.g. that the LMP and the trajectory rebuild the
motion); then every control is moved once, which runs each redraw callback as a live front end would.
"""

from __future__ import annotations

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

import odmo_cli

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"))
EXPECTED = ["01_lmp_decomposition", "02_spring_energy_prior", "03_gmm_mode_discovery", "04_lie_vs_xyz"]
WIDGET = "application/vnd.jupyter.widget-view+json"
PACKAGE_ROOT = Path(odmo_cli.__file__).resolve().parents[1]


# Run after a notebook, in its kernel: move every control to the end of its range, so that each redraw
# path runs once more as it would in a live front end (a failing callback raises in this cell).
NUDGE = """
import ipywidgets as _widgets
_nudged = []
for _name, _w in list(globals().items()):
    if isinstance(_w, _widgets.Play) or not isinstance(_w, _widgets.ValueWidget):
        continue  # Play is linked to its slider in the browser only
    if isinstance(_w, _widgets.Dropdown):
        _w.index = len(_w.options) - 1
    elif isinstance(_w, _widgets.FloatLogSlider):
        _w.value = _w.base ** _w.max
    else:
        _w.value = _w.max
    _nudged.append(_name)
print(len(_nudged))
"""


def code_of(nb) -> str:
    return "\n".join(c.source for c in nb.cells if c.cell_type == "code")


def test_the_four_notebooks_are_there_and_stored_clean():
    assert [p.stem for p in NOTEBOOKS] == EXPECTED
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert all(not c.outputs and c.execution_count is None for c in code), f"{path.name} is stored with outputs"
        assert nb.cells[0].cell_type == "markdown" and "teaches" in nb.cells[0].source, path.name
        assert nb.cells[-1].cell_type == "markdown" and "Exercise" in nb.cells[-1].source, path.name
        assert "from odmo_cli" in code_of(nb), path.name
        assert "nn.Module" not in code_of(nb), f"{path.name} defines a model: use odmo_cli's"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_headless(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    # the kernel must import the odmo_cli under test, whether installed or on the test's path
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(PACKAGE_ROOT), os.environ.get("PYTHONPATH")])))
    nb.cells.append(nbformat.v4.new_code_cell(NUDGE))
    nb.cells.append(nbformat.v4.new_code_cell("import odmo_cli; print(odmo_cli.__file__)"))
    client = NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}})
    client.execute(env=env)  # raises CellExecutionError on the first failing cell

    assert nb.cells[-1].outputs[0]["text"].strip() == odmo_cli.__file__
    assert int(nb.cells[-2].outputs[-1]["text"].split()[-1]) >= 2, "the notebook has too few controls"
    shown = 0
    for cell in nb.cells:
        kinds = {key for out in cell.get("outputs", []) for key in out.get("data", {})}
        if WIDGET in kinds:
            # widgets degrade to static output: the cell also shows its figure for the default values
            assert "image/png" in kinds, f"{path.name}: a widget cell shows no static figure:\n{cell.source[:300]}"
        shown += "image/png" in kinds
    assert shown >= 2, f"{path.name} shows {shown} figures"
