"""Every notebook runs top to bottom (nbclient) and shows its figures."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
#: notebooks that read data outside the repository, skipped where it is absent
NEEDS_DATA = {"real_ur10": ROOT.parent / "shared" / "data" / "ipa-robot-accuracy"}


def _param(path):
    data = NEEDS_DATA.get(path.stem)
    absent = data is not None and not data.is_dir()
    mark = pytest.mark.skipif(absent, reason=f"{data} not present")
    return pytest.param(path, id=path.stem, marks=mark)


@pytest.mark.parametrize("path", [_param(p) for p in NOTEBOOKS])
def test_notebook_runs_and_shows_figures(path, tmp_path, monkeypatch):
    nb = nbformat.read(path, as_version=4)
    # the kernel inherits the environment: draw inline, not with the suite's Agg backend
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    images = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if "image/png" in o.get("data", {})
    ]
    assert images, f"{path.name} shows no figure"
