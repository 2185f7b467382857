"""gmjax.reduction.gmrc: outputs and labels against the NumPy reference."""

from __future__ import annotations

import jax
from test_reduction_utils import (
    assert_equals_reference,
    reference_batch,
)

from gmjax import reduction as R
from references import reduction_np as ref

NUM_OUT = 4


def test_gmrc_matches_numpy():
    comps, gm = reference_batch(2, seed=31, n=40)
    out, info = jax.jit(jax.vmap(lambda g: R.gmrc(g, NUM_OUT)))(gm)
    for b, (w, m, P) in enumerate(comps):
        r = ref.gmrc(w, m, P, NUM_OUT)
        assert_equals_reference(out, info, r, b, len(w))
