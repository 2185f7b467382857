"""gmjax.reduction.kmeans: outputs, labels and iteration counts against the NumPy reference."""

from __future__ import annotations

import jax
import pytest
from test_reduction_utils import (
    assert_equals_reference,
    reference_batch,
)

from gmjax import reduction as R
from references import reduction_np as ref

NUM_OUT = 4


@pytest.mark.parametrize("d", [1, 2])
def test_kmeans_matches_numpy(d):
    comps, gm = reference_batch(d, seed=5 + d)
    out, info = jax.jit(jax.vmap(lambda g: R.kmeans(g, NUM_OUT)))(gm)
    for b, (w, m, P) in enumerate(comps):
        r = ref.kmeans(w, m, P, NUM_OUT)
        assert_equals_reference(out, info, r, b, len(w))
        assert int(info.aux["iterations"][b]) == r["iterations"]
