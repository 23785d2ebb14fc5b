"""`notebooks/real_ur10.ipynb` runs top to bottom and shows its figures (its own asserts hold)."""

from _run import run_notebook


def test_real_ur10_notebook(tmp_path, monkeypatch):
    run_notebook("real_ur10", tmp_path, monkeypatch)
