"""The README's "A first example" block, docs/getting_started.md and docs/scaling.md run as written.

Each page's fenced ```python blocks, joined in order, form one script. As written, the README block and
the getting-started page run a 100-run PCM-GSF study and two reverse-mode gradients of a whole PCM-GSF
run (about 95 s and 90 s on a 2-core CPU), so those runs are ``slow``; the default suite runs the same
scripts with the PCM-GSF replaced by a small keep-the-heaviest GSF on a shorter horizon (each
replacement checked to apply once, so the scripts cannot drift from the tested ones). docs/scaling.md's
block continues the getting-started page (it uses its ``gsf``, ``zs``, ``ts``). docs/design.md's
blocks are signatures, not code to run; docs/bring_your_own_model.md runs in test_docs_examples.py.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gmjax

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# the small stand-ins of the default suite: (as written, replacement)
SMALL = [
    ("jump_system()", "jump_system(n_steps=8)"),
    (
        "reduction.PCM(max_components=20, capacity=20), capacity=20",
        "reduction.PruneTop(num_out=5), capacity=5",
    ),
    ("100, jax.random.key(0)", "8, jax.random.key(0)"),
]


def _python_blocks(text: str) -> str:
    return "\n".join(re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M))


def readme_section(heading: str) -> str:
    text = (ROOT / "README.md").read_text()
    return _python_blocks(text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0])


def page(name: str) -> str:
    return _python_blocks((DOCS / name).read_text())


def small(source: str) -> str:
    for written, replacement in SMALL:
        assert source.count(written) == 1, written
        source = source.replace(written, replacement)
    return source


def run_script(source: str, filename: str, namespace: dict | None = None) -> tuple[dict, list]:
    """Execute ``source``; return its namespace and the values of its top-level expression statements
    (``jax.grad(total_loglik)(1.0)``, ...) in order."""
    tree = ast.parse(source, filename)
    for i, node in enumerate(tree.body):
        if isinstance(node, ast.Expr):
            call = ast.parse("_values.append(None)").body[0]
            call.value.args[0] = node.value
            tree.body[i] = ast.copy_location(call, node)
    ast.fix_missing_locations(tree)
    values: list = []
    namespace = dict(namespace or {}, _values=values)
    exec(compile(tree, filename, "exec"), namespace)
    return namespace, values


def check_filter_example(namespace: dict, values: list) -> None:
    """The study's numbers are finite, and the two gradients of the run's log-likelihood agree:
    d/d(process-noise variance scale) at 1 = <whole-params gradient, process-noise covs>."""
    result, gsf = namespace["result"], namespace["gsf"]
    assert 0.0 < float(result.armse) < float("inf") and float(result.armse_stderr) > 0.0
    grads = values[-1]
    assert grads.model.prior.mask is None and grads.model.process_noise.mask is None
    assert tree_structure_with_none(grads) == tree_structure_with_none(gsf.params)  # PCM: lam None
    covs = gsf.params.model.process_noise.covs
    np.testing.assert_allclose(values[-2], jnp.sum(grads.model.process_noise.covs * covs), rtol=1e-9)


def tree_structure_with_none(tree):
    return jax.tree_util.tree_structure(tree, is_leaf=lambda x: x is None)


def test_readme_first_example_runs_on_a_small_filter():
    source = readme_section("A first example")
    assert "gmjax.grad(" in source and "jax.grad(total_loglik)" in source
    namespace, values = run_script(small(source), "README.md")
    check_filter_example(namespace, values)


@pytest.mark.slow
def test_readme_first_example_runs_as_written():
    namespace, values = run_script(readme_section("A first example"), "README.md")
    check_filter_example(namespace, values)
    assert namespace["result"].n_runs == 100


def test_getting_started_runs_on_a_small_filter_and_scaling_continues_it():
    source = page("getting_started.md")
    assert "gmjax.grad(" in source and "jax.grad(total_loglik)" in source
    namespace, values = run_script(small(source), "getting_started.md")
    check_filter_example(namespace, values)
    namespace, values = run_script(page("scaling.md"), "scaling.md", namespace)
    sweep = values[-1]
    assert sweep.shape == (16,) and bool(jnp.all(jnp.isfinite(sweep)))
    # the sweep at scale 1 is the run's log-likelihood (linspace(0.5, 2, 16) has 1.0 at index 5)
    gsf, zs, ts = namespace["gsf"], namespace["zs"], namespace["ts"]
    loglik = gmjax.filters.run(gsf, zs, ts)[1].loglik.sum()
    np.testing.assert_allclose(sweep[5], loglik, rtol=1e-9)


@pytest.mark.slow
def test_getting_started_runs_as_written():
    namespace, values = run_script(page("getting_started.md"), "getting_started.md")
    check_filter_example(namespace, values)
    assert namespace["result"].n_runs == 100


# the "Learn the model" block's small stand-in: a GSF that keeps the heaviest components (it compiles in a
# fraction of the Runnalls step's time) on a shorter sequence
SMALL_FIT = [
    ("reduction.Runnalls(num_out=6), capacity=6", "reduction.PruneTop(num_out=4), capacity=4"),
    ("[0.3, 0.6]), 300)", "[0.3, 0.6]), 100)"),
]


@pytest.mark.parametrize("as_written", [pytest.param(True, marks=pytest.mark.slow), False])
def test_readme_learn_the_model_block_runs(tmp_path, monkeypatch, as_written):
    """The README's "Learn the model" block (as written: a 300-step Runnalls GSF fit, slow; by default
    with SMALL_FIT's stand-ins), in a temporary directory for its checkpoint; run twice, the second call
    resumes from the finished fit."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    source = readme_section("Learn the model")
    assert "gmjax.fit(" in source and 'checkpoint="fit.npz"' in source
    if not as_written:
        for written, replacement in SMALL_FIT:
            assert source.count(written) == 1, written
            source = source.replace(written, replacement)
    namespace, values = run_script(source, "README.md")
    fitted = namespace["fitted"]
    weights, converged = values[1]  # values[0] is jax.config.update's None
    assert converged and weights.sum() == pytest.approx(1.0)
    assert (tmp_path / "fit.npz").exists()
    again, _ = run_script(source, "README.md")
    assert again["fitted"].n_steps == fitted.n_steps
    np.testing.assert_array_equal(again["fitted"].history.loss, fitted.history.loss)
