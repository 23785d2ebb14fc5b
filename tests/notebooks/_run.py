"""Runs a notebook top to bottom (nbclient) and checks that it shows its figures.

One test file per notebook (`test_<stem>_notebook.py`), so that the suite's workers, which take
whole files, can run notebooks side by side.
"""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
#: notebooks that read data outside the repository, skipped where it is absent
NEEDS_DATA = {"real_ur10": ROOT.parent / "shared" / "data" / "ipa-robot-accuracy"}


def run_notebook(stem: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = ROOT / "notebooks" / f"{stem}.ipynb"
    data = NEEDS_DATA.get(stem)
    if data is not None and not data.is_dir():
        pytest.skip(f"{data} not present")
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
