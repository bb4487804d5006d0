"""The notebooks under ``notebooks/``: committed without outputs, and they run.

The walkthrough simulates a small grid on the demo survey, fits it, plots C and S with
credible bands, reads the selection-function file with glaciar and with the documented
astropy/scipy recipe (its own asserts require both to agree), computes V_eff for an area
and writes the HTML report.  It is executed here with nbclient in a fresh kernel.

To strip a notebook's outputs before committing it::

    python -c "import nbformat as n, sys; p = sys.argv[1]; nb = n.read(p, 4); \
[c.update(outputs=[], execution_count=None) for c in nb.cells if c.cell_type == 'code']; \
n.write(nb, p)" notebooks/walkthrough.ipynb
"""
from pathlib import Path

import nbformat
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_there_is_a_walkthrough():
    assert "walkthrough.ipynb" in [p.name for p in NOTEBOOKS]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    dirty = [i for i, c in enumerate(nb.cells)
             if c.cell_type == "code" and (c.get("outputs") or c.get("execution_count") is not None)]
    assert dirty == [], (f"{path.name}: cells {dirty} hold outputs; strip them (see this test "
                         "module's docstring) before committing")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    # A fresh kernel of this interpreter, in a scratch directory; any failing cell (or
    # assert inside the notebook) raises CellExecutionError here.
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    # the C/S figure is shown, and the report was written
    assert any("image/png" in o.get("data", {}) for o in outputs)
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "report.html" in text and "without glaciar" in text
