"""The code on the documentation's "bring your own model" and "learn the model" pages runs as written
(docs/*.md python blocks)."""

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"


def python_blocks(page: Path) -> str:
    """The page's fenced ```python blocks, joined in order (they form one script)."""
    return "\n".join(re.findall(r"^```python\n(.*?)^```", page.read_text(), flags=re.S | re.M))


def test_bring_your_own_model_page_runs():
    source = python_blocks(DOCS / "bring_your_own_model.md")
    assert "build_gsf" in source and "monte_carlo" in source  # the page still shows the full path
    namespace: dict = {}
    exec(compile(source, "bring_your_own_model.md", "exec"), namespace)
    result = namespace["result"]
    assert result.n_runs == 200
    assert result.armse == pytest.approx(float(result.rmse.mean()))
    assert 0.0 < result.armse < float("inf")
    assert namespace["infos"].n_components.max() <= 4


def test_learn_the_model_page_runs():
    source = python_blocks(DOCS / "fitting.md")
    assert "gmjax.fit(" in source
    namespace: dict = {"__name__": "fitting_md"}
    exec(compile(source, "fitting.md", "exec"), namespace)
    kf_fit, gm_fit, thr_fit = namespace["kf_fit"], namespace["gm_fit"], namespace["thr_fit"]
    assert kf_fit.converged and gm_fit.converged
    assert (
        abs(float(kf_fit.values["Q"][0, 0]) - 0.3) < 0.3 and abs(float(kf_fit.values["R"][0, 0]) - 1.5) < 0.6
    )
    learned = namespace["learned"]
    assert learned.weights.sum() == pytest.approx(1.0) and bool(learned.mask.all())
    assert thr_fit.n_skipped == 0 and 1e-4 < namespace["threshold"] < 0.9
    assert namespace["hard"].params.reducer.threshold == namespace["threshold"]
