"""`notebooks/weighting_schemes.ipynb` runs top to bottom and shows its figures (its own asserts hold)."""

from _run import run_notebook


def test_weighting_schemes_notebook(tmp_path, monkeypatch):
    run_notebook("weighting_schemes", tmp_path, monkeypatch)
