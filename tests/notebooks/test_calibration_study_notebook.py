"""`notebooks/calibration_study.ipynb` runs top to bottom and shows its figures (its own asserts hold)."""

from _run import run_notebook


def test_calibration_study_notebook(tmp_path, monkeypatch):
    run_notebook("calibration_study", tmp_path, monkeypatch)
