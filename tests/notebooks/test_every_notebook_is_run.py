"""Each notebook has its test file here (a new notebook is not left out of the suite)."""

from pathlib import Path

from _run import NOTEBOOKS


def test_every_notebook_has_a_test_file():
    here = Path(__file__).parent
    missing = [p.stem for p in NOTEBOOKS if not (here / f"test_{p.stem}_notebook.py").exists()]
    assert NOTEBOOKS and not missing, missing
