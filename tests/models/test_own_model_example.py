"""The README's "bring your own model" block runs as written and its estimates are good."""

import re
import shutil
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def readme_block(heading: str) -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return "\n".join(re.findall(r"^```python\n(.*?)^```", section, flags=re.S | re.M))


def test_readme_own_model_example_runs(tmp_path, monkeypatch):
    source = readme_block("Bring your own model")
    assert "inputs_from_times" in source and "gaussian_sum_smoother" in source and "angle_dims" in source
    (tmp_path / "examples" / "data").mkdir(parents=True)
    shutil.copy(ROOT / "examples" / "data" / "bearing_range.csv", tmp_path / "examples" / "data")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(source, "README.md", "exec"), namespace)
    out = np.genfromtxt(tmp_path / "estimates.csv", delimiter=",", names=True)
    truth = np.genfromtxt(ROOT / "examples" / "data" / "bearing_range_truth.csv", delimiter=",", names=True)
    assert len(out) == len(truth) == 40
    data = namespace["data"]
    assert np.isnan(data["bearing"]).any() and np.nanmax(np.abs(data["bearing"])) > 3.1  # crosses ±pi
    err_f = np.hypot(out["x"] - truth["x"], out["y"] - truth["y"])
    err_s = np.hypot(out["xs"] - truth["x"], out["ys"] - truth["y"])
    rmse_f, rmse_s = np.sqrt(np.mean(err_f**2)), np.sqrt(np.mean(err_s**2))
    # bearing noise 0.01 rad at ~120 m and range noise 1 m: a few metres, never lost at the crossing
    print("max error", err_f.max(), "RMSE filter", rmse_f, "smoother", rmse_s)
    assert err_f.max() < 10.0, err_f.max()
    assert rmse_s < rmse_f, (rmse_s, rmse_f)
