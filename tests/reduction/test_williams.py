"""gmjax.reduction.williams: actions (merges and deletions) and outputs against a NumPy reference that scores
every candidate by a direct ISE evaluation."""

from __future__ import annotations

import numpy as np
from test_reduction_utils import (
    batch,
    index,
    random_components,
)

from gmjax import reduction as R
from references import reduction_np as ref


def test_williams_matches_numpy():
    """Same actions (merges and deletions) and outputs as a reference that scores every
    candidate with a direct ISE evaluation."""
    rng = np.random.default_rng(41)
    comps = [random_components(rng, int(rng.integers(5, 8)), 2) for _ in range(12)]
    for w, m, P in comps:
        gm = batch([(w, m, P)], 9)
        out, info = R.williams(index(gm, 0), 3)
        r = ref.williams(w, m, P, 3)
        acts = [tuple(int(v) for v in row) for row in np.asarray(info.aux["actions"]) if row[0] >= 0]
        assert acts == r["actions"]
        n_out = int(info.n_out)
        np.testing.assert_allclose(np.asarray(out.weights[:n_out]), r["w"], atol=1e-10)
        np.testing.assert_allclose(np.asarray(out.means[:n_out]), r["m"], atol=1e-10)
        np.testing.assert_allclose(np.asarray(out.covs[:n_out]), r["P"], atol=1e-10)
        np.testing.assert_allclose(float(info.cost), r["cost"], rtol=1e-8, atol=1e-13)
