"""The code on the documentation's "bring your own model" page runs as written (docs/*.md python blocks)."""

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
