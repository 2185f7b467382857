"""Issue 48's Done-when at scale: a 10^5-run study split in 2 and 3 parts, killed and resumed, and run by two
processes under ``jax.distributed``, each bit-identical to the whole (``benchmarks/bench_exact_study.py``).

The default suite checks the same properties on small studies (``tests/montecarlo/test_montecarlo.py``).
"""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))


@pytest.mark.slow
def test_a_1e5_run_study_is_bit_identical_however_it_is_done():
    from bench_exact_study import check

    out = check(100_000, 30, 1000, kills=4, seed=1)  # raises, naming the fields, if any way differs
    assert out["kills"] >= 1 and len(out["ways"]) == 5
    assert out["whole"].n_runs == 100_000
