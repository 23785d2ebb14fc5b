"""`notebooks/discrepancy.ipynb` runs top to bottom and shows its figures (its own asserts hold)."""

from _run import run_notebook


def test_discrepancy_notebook(tmp_path, monkeypatch):
    run_notebook("discrepancy", tmp_path, monkeypatch)
