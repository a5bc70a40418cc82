"""The notebooks in examples/notebooks run top to bottom in a real Jupyter kernel."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "examples" / "notebooks"
nbclient = pytest.importorskip("nbclient", reason="pip install 'rtloop[test]' (nbclient, nbformat, ipykernel)")
nbformat = pytest.importorskip("nbformat", reason="pip install 'rtloop[test]' (nbformat)")
pytest.importorskip("ipykernel", reason="pip install 'rtloop[test]' (ipykernel: the kernel the notebook runs in)")


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("name", sorted(p.name for p in NOTEBOOKS.glob("*.ipynb")))
def test_notebook_runs(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RTLOOP_NOTEBOOK_OUT", str(tmp_path / "runs"))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError, with the cell and its traceback, if any cell fails
    outputs = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 3, "the simulation, the sweep and the comparison are drawn"
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "setpoint pair: plant.speed_rad_s <- pi.setpoint_rad_s" in text
    assert "max |run − simulation|" in text
    assert (tmp_path / "runs" / "sweep" / "sweep.csv").is_file()
    if os.geteuid() == 0:
        assert (tmp_path / "runs" / "run" / "summary.json").is_file(), "as root the notebook runs for real"
        # under a name of its kernel's own: 'dcmotor' may be running here (a live app holds its name)
        ran_as = json.loads((tmp_path / "runs" / "run" / "summary.json").read_text())["app"]
        assert ran_as.startswith("dcmotor_nb_") and f"running as {ran_as}" in text, ran_as
