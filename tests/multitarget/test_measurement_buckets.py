"""Measurement capacities in buckets: a study whose clutter rate varies per run compiles one program per
bucket (a handful), not one per rate, and a bucket larger than a scan needs changes nothing."""

from __future__ import annotations

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import poisson

from gmjax import multitarget as mt


def test_bucket_capacity_is_the_next_power_of_two_and_refuses_bad_sizes():
    assert [mt.bucket_capacity(n) for n in (0, 1, 8, 9, 16, 17, 100, 128, 129)] == [
        8,
        8,
        8,
        16,
        16,
        32,
        128,
        128,
        256,
    ]
    assert mt.bucket_capacity(3, minimum=1) == 4 and mt.bucket_capacity(1, minimum=1) == 1
    for bad in (-1, 2.5, True, "8"):
        with pytest.raises(ValueError, match="n: expected a non-negative int"):
            mt.bucket_capacity(bad)
    with pytest.raises(ValueError, match="minimum: expected a positive int"):
        mt.bucket_capacity(4, minimum=0)


@pytest.mark.parametrize("rate", [0.0, 0.3, 5.0, 30.0, 100.0, 150.0])
def test_clutter_capacity_holds_a_scan_but_for_the_stated_probability(rate):
    """``P(n_targets + Poisson(rate) > M) <= overflow_prob`` by SciPy's Poisson tail, and ``M`` is the
    smallest bucket with that property."""
    n_targets, p = 10, 1e-6
    M = mt.clutter_capacity(rate, n_targets, overflow_prob=p)
    assert M == mt.bucket_capacity(M)
    assert poisson.sf(M - n_targets, rate) <= p if rate > 0 else M >= n_targets
    smaller = M // 2
    if smaller >= 8 and rate > 0:
        assert poisson.sf(smaller - n_targets, rate) > p


def test_clutter_capacity_refuses_bad_arguments():
    with pytest.raises(ValueError, match="clutter_rate"):
        mt.clutter_capacity(-1.0, 3)
    with pytest.raises(ValueError, match="clutter_rate"):
        mt.clutter_capacity(float("nan"), 3)
    with pytest.raises(ValueError, match="n_targets"):
        mt.clutter_capacity(5.0, -2)
    with pytest.raises(ValueError, match="overflow_prob"):
        mt.clutter_capacity(5.0, 3, overflow_prob=0.0)


DOCS_PAGE = Path(__file__).resolve().parents[2] / "docs" / "reproductions" / "phd.md"


def _docs_block(heading: str) -> str:
    """The first ``python`` block after ``heading`` on the GM-PHD reproduction page."""
    text = DOCS_PAGE.read_text()
    return re.findall(r"^```python\n(.*?)^```", text[text.index(heading) :], flags=re.S | re.M)[0]


def test_a_study_with_clutter_drawn_per_run_compiles_one_program_per_bucket():
    """The docs block as written: 16 runs with clutter rates drawn from U(2, 80), grouped by the
    bucket of their rate, each bucket simulated and filtered in one vmapped program; the jitted study
    function compiles once per bucket (4 here: 16 to 128 rows), not once per rate, and no scan
    overflows."""
    namespace: dict = {}
    exec(compile(_docs_block("## Measurement sets of any size"), str(DOCS_PAGE), "exec"), namespace)
    results, buckets, program = namespace["results"], namespace["buckets"], namespace["program"]
    assert program._cache_size() == len(set(buckets)) == len(results) <= 5
    assert sum(int(flags.sum()) for _, flags in results.values()) == 0
    assert all(np.all(np.isfinite(np.asarray(card))) for card, _ in results.values())
    assert sum(card.shape[0] for card, _ in results.values()) == 16


def test_a_larger_bucket_changes_nothing():
    """The same run filtered at its own capacity and padded to twice as many NaN rows: the same
    cardinality and estimates (absent rows are no measurements)."""
    sc = mt.vo_ma_linear(n_steps=4, clutter_rate=12.0)
    sc = sc._replace(max_measurements=mt.clutter_capacity(12.0, sc.n_targets))
    phd = mt.gm_phd(sc.model, **sc.filter_kwargs(), capacity=20)
    sample = mt.simulate(sc, jax.random.key(3))
    M = sc.max_measurements
    wider = jnp.concatenate([sample.zs, jnp.full_like(sample.zs, jnp.nan)], axis=1)
    assert wider.shape[1] == 2 * M
    _, a = mt.run(phd, sample.zs)
    _, b = mt.run(phd, wider)
    np.testing.assert_allclose(a.extra["cardinality"], b.extra["cardinality"], rtol=1e-12)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-10, atol=1e-9)


def test_pad_scans_without_a_capacity_takes_the_bucket_of_the_largest_scan():
    scans = [np.ones((3, 2)), np.zeros((0, 2)), np.full((11, 2), 2.0)]
    padded = mt.pad_scans(scans)
    assert padded.zs.shape == (3, 16, 2)
    assert not bool(np.any(padded.overflow))
    np.testing.assert_array_equal(padded.n_measurements, [3, 0, 11])
    np.testing.assert_array_equal(np.asarray(mt.phd.measurement_mask(padded.zs)).sum(-1), [3, 0, 11])
    assert mt.pad_scans([np.ones((17, 2))]).zs.shape == (1, 32, 2)
