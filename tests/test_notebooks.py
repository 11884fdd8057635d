"""The teaching notebooks (notebooks/*.ipynb) run headless from a clean kernel, top to bottom, and
their executed copies (docs/notebooks/*.ipynb, written by `python notebooks/build.py`) are in sync.

Each notebook is executed with nbclient in a temporary folder; any error fails the test. The
notebooks' own assert cells check their numbers (e.g. that the LMP and the trajectory rebuild the
motion); then every control is moved once, which runs each redraw callback as a live front end would.
Notebooks that load a shipped model are skipped while it is not installed. The sync test executes
nothing: it compares the hashes each copy records with the sources and shipped models of today.
"""

from __future__ import annotations

import importlib.util
import os
import re
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

import odmo_cli
from odmo_cli.checkpoint import shipped_file

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"))
EXPECTED = ["01_lmp_decomposition", "02_spring_energy_prior", "03_gmm_mode_discovery", "04_lie_vs_xyz",
            "05_model_and_training", "06_evaluation_metrics", "07_long_motions"]
HELPERS = ("live", "draw_pose", "cube")  # odmo_cli.formats.viz's notebook helpers: imported, never copied
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


def load_build():
    """notebooks/build.py as a module (it is a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location("notebook_build", REPO / "notebooks" / "build.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_notebooks_are_there_and_stored_clean():
    assert [p.stem for p in NOTEBOOKS] == EXPECTED
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert all(not c.outputs and c.execution_count is None for c in code), f"{path.name} is stored with outputs"
        head = nb.cells[0]
        assert head.cell_type == "markdown" and "teaches" in head.source, path.name
        assert "Prerequisites" in head.source and "Run time" in head.source, f"{path.name}: say what it needs and how long it runs"
        install = code[0].source
        assert 'find_spec("odmo_cli") is None' in install and "%pip install" in install, f"{path.name}: no install cell first"
        assert nb.cells[-1].cell_type == "markdown" and "Exercise" in nb.cells[-1].source, path.name
        exercises = nb.cells[-1].source
        numbered = re.findall(r"^\d+\. ", exercises, flags=re.M)
        assert numbered and exercises.count("<summary>Hint</summary>") == len(numbered), \
            f"{path.name}: every exercise gets a hint"
        assert "from odmo_cli" in code_of(nb), path.name
        assert "nn.Module" not in code_of(nb), f"{path.name} defines a model: use odmo_cli's"
        copied = [h for h in HELPERS if f"def {h}(" in code_of(nb)]
        assert not copied, f"{path.name} defines {copied}: import them from odmo_cli.formats.viz"


def test_executed_copies_are_in_sync():
    """Each docs/notebooks/ copy exists, was built from today's source and with today's shipped models."""
    build = load_build()
    problems = [reason for source in NOTEBOOKS for reason in build.stale_reasons(source, build.COPIES / source.name)]
    extra = sorted({p.name for p in build.COPIES.glob("*.ipynb")} - {p.name for p in NOTEBOOKS})
    problems += [f"docs/notebooks/{name} has no source in notebooks/" for name in extra]
    assert not problems, ("executed copies are out of date: " + "; ".join(problems)
                          + f". Rebuild them with `{build.COMMAND}` (about 3 minutes) and commit docs/notebooks/")
    for source in NOTEBOOKS:
        copy = nbformat.read(build.COPIES / source.name, as_version=4)
        kinds = [key for cell in copy.cells for out in cell.get("outputs", []) for key in out.get("data", {})]
        assert "image/png" in kinds, f"docs/notebooks/{source.name} shows no figure"
        assert not any(out.get("output_type") == "error" for cell in copy.cells for out in cell.get("outputs", []))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_headless(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    if "load_odmo(None)" in code_of(nb) and shipped_file("humanact12") is None:
        pytest.skip(f"{path.name} needs the shipped default model odmo_cli/assets/models/odmo_humanact12.pt, "
                    "not in this install yet")
    if "shipped_classifier" in code_of(nb) and shipped_file("humanact12", "classifier") is None:
        pytest.skip(f"{path.name} needs the shipped classifier odmo_cli/assets/models/classifier_humanact12.pt, "
                    "not in this install yet")
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
