"""The compiled PCM loop of references/pcm_numba.py against ``gmjax.reduction.pcm(newton_steps=0)``.

Random mixtures of capacity 60 (one with every slot live, the others with 10-59 live components
scattered among padded slots, one of them with skewed weights so that fewer than ``N_u = 20``
survive the pruning) reduced with ``max_components=20, capacity=20`` in d = 1, 2, 4, with and
without clustering dimensions ``dims``; and a variant with no cap, an output capacity below the
cluster count (overflow: the heaviest clusters, heaviest first) and non-default ``ρ``, ``α``, scope,
grid and range scale. Outputs (weights, means, covariances), mask, labels, ``λ*`` and its EISE equal
gmjax's to 1e-12, with and without ``skip_repeats``.

One exception is checked rather than excused: when two grid points give the same *partition* with
different head rows (hence another output order), their EISE is the same number but for the
summation order; the loop sums in an order independent of the heads and keeps the first, gmjax keeps
the first within ``K eps`` of the minimum (until 620bbd7 its plain ``argmin`` picked by rounding,
differently under ``vmap`` than alone). Should they still differ, the partition, the EISE, and the
output mixture up to the order of its slots must agree (:func:`_compare`).

The default tests run the loop's ``.py_func`` (plain Python; numba need not be installed); the
``slow`` test runs the numba ``prange`` batch driver on a larger batch.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_reduction_utils import batch, index, random_components, scatter_padding

from gmjax import reduction as R
from references import pcm_numba as pn

K_IN = 60
N_U = 20
ATOL = 1e-12


def _mixtures(d, n, seed):
    """``n`` mixtures of capacity ``K_IN``: the first fully live, the second with skewed weights
    (1e-3 to 1) and 30 live components, the others with 10-59 live components; padded slots
    scattered."""
    rng = np.random.default_rng(seed)
    gms = [index(batch([random_components(rng, K_IN, d)], K_IN), 0)]
    for b in range(1, n):
        skewed = b == 1
        n_live = 30 if skewed else int(rng.integers(10, K_IN))
        comps = random_components(rng, n_live, d, wr=(1e-3, 1.0) if skewed else (1e-2, 0.2))
        gms.append(scatter_padding(index(batch([comps], K_IN), 0), K_IN, seed + b))
    return jax.tree_util.tree_map(lambda *a: np.stack(a), *gms)


def _canonical(w, m, P, mask, labels):
    """The output slots ordered by the lowest input slot of each cluster, and the labels in that order."""
    slots = [p for p in range(len(mask)) if mask[p]]
    lowest = {p: int(np.flatnonzero(labels == p)[0]) for p in slots}
    order = sorted(slots, key=lambda p: lowest[p])
    rename = {p: i for i, p in enumerate(order)}
    lab = np.array([rename.get(int(v), -1) for v in labels])
    return w[order], m[order], P[order], lab


def _compare(out, info, r, b):
    """Asserts the loop's ``r`` equals gmjax's mixture ``b``; returns whether it was a tie (same
    partition under other heads, picked by gmjax's rounding)."""
    got = [np.asarray(a)[b] for a in (out.weights, out.means, out.covs, out.mask, info.labels)]
    lam, cost = float(np.asarray(info.aux["lambda"])[b]), float(np.asarray(info.cost)[b])
    np.testing.assert_allclose(r[6], cost, rtol=0, atol=ATOL, err_msg="EISE differs")
    if r[5] == lam:
        np.testing.assert_array_equal(r[3], got[3])
        np.testing.assert_array_equal(r[4], got[4])
        for field, x, y in zip(("weights", "means", "covs"), r[:3], got[:3]):
            assert np.abs(x - y).max() <= ATOL, f"{field} differ by {np.abs(x - y).max():.2e}"
        return False
    # a tie: the same partition of the input slots, the same mixture up to slot order
    assert int(r[3].sum()) == int(got[3].sum())
    ours, theirs = _canonical(*r[:5]), _canonical(*got)
    np.testing.assert_array_equal(ours[3], theirs[3], err_msg=f"λ {r[5]} vs {lam}: other partition")
    for x, y in zip(ours[:3], theirs[:3]):
        assert np.abs(x - y).max() <= ATOL
    return True


def _gmjax(gm, **kw):
    return jax.vmap(lambda g: R.pcm(g, newton_steps=0, **kw))(gm)


CASES = [(1, None), (2, None), (4, (0, 1))]  # (d, dims): position-only clustering in 4-D (§IV-D)


@pytest.mark.parametrize("d, dims", CASES)
def test_py_loop_matches_gmjax(d, dims):
    """The loop (run by the interpreter) gives gmjax's outputs on one full, one skewed and two padded
    mixtures, with the mask given and (the full one) omitted, with and without ``skip_repeats``."""
    gm = _mixtures(d, 4, seed=10 * d + (0 if dims is None else 1))
    out, info = _gmjax(gm, max_components=N_U, capacity=N_U, dims=dims)
    assert int(np.asarray(info.aux["n_reference"]).min()) < N_U  # the pruning, not the cap, decides
    W, M, P, mask = (np.asarray(a) for a in gm)
    kw = {"max_components": N_U, "capacity": N_U, "dims": None if dims is None else np.array(dims)}
    fn = pn.pcm.py_func
    assert not _compare(out, info, fn(W[0], M[0], P[0], **kw), 0)
    ties = 0
    for b in range(W.shape[0]):
        r = fn(W[b], M[b], P[b], mask=mask[b], **kw)
        ties += _compare(out, info, r, b)
        naive = fn(W[b], M[b], P[b], mask=mask[b], skip_repeats=False, **kw)
        for x, y in zip(r, naive):
            np.testing.assert_array_equal(x, y)
    assert ties == 0


def test_py_loop_options_and_overflow():
    """No cap (``Kw = K``), capacity 4 below the cluster count (the heaviest clusters, heaviest
    first; labels of the dropped clusters -1), clustering on the second of two dimensions, and every
    search option away from its default."""
    opts = {"rho": 0.99, "alpha": 0.01, "lambda_range": (0.5, 2.5), "grid_size": 7, "range_scale": 0.8}
    gm = _mixtures(2, 3, seed=5)
    gm = jax.tree_util.tree_map(lambda a: a[:, :30], gm)  # capacity 30: 10-30 live
    out, info = _gmjax(gm, capacity=4, dims=(1,), **opts)
    assert np.asarray(info.overflow).all()
    W, M, P, mask = (np.asarray(a) for a in gm)
    kw = {
        "capacity": 4,
        "rho": 0.99,
        "alpha": 0.01,
        "lam_lo": 0.5,
        "lam_hi": 2.5,
        "grid_size": 7,
        "range_scale": 0.8,
        "dims": np.array([1]),
    }
    for b in range(W.shape[0]):
        assert not _compare(out, info, pn.pcm.py_func(W[b], M[b], P[b], mask=mask[b], **kw), b)


def test_module_runs_without_numba(monkeypatch):
    """With numba not importable the module still imports; the batch driver is a plain loop with the
    ``.py_func``'s results."""
    import importlib.util
    import sys
    from pathlib import Path

    from references import reduction_numba as rn

    monkeypatch.setitem(sys.modules, "numba", None)  # `import numba` raises ImportError
    monkeypatch.setitem(sys.modules, "numba.extending", None)
    plain = {}
    for mod in (rn, pn):
        spec = importlib.util.spec_from_file_location(f"references.{Path(mod.__file__).stem}", mod.__file__)
        plain[mod] = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, spec.name, plain[mod])  # pcm_numba imports the plain helpers
        spec.loader.exec_module(plain[mod])
    plain_pn = plain[pn]
    assert not plain_pn.HAVE_NUMBA and plain_pn.pcm.py_func is plain_pn.pcm
    gm = _mixtures(2, 2, seed=3)
    W, M, P, mask = (np.asarray(a) for a in gm)
    r = plain_pn.pcm_batch(W, M, P, N_U, N_U, mask=mask)
    for b in range(2):
        want = pn.pcm.py_func(W[b], M[b], P[b], N_U, N_U, mask=mask[b])
        for x, y in zip(want, r):
            np.testing.assert_array_equal(x, y[b])


@pytest.mark.slow
@pytest.mark.parametrize("d, dims", CASES + [(2, (1,)), (4, None)])
def test_numba_batch_matches_gmjax(d, dims):
    """The compiled ``prange`` batch driver on 64 mixtures (one full, one skewed, 62 padded), and the
    compiled one-mixture function; ties (see the module docstring) checked and at most a few."""
    pytest.importorskip("numba")
    gm = _mixtures(d, 64, seed=900 + d + (0 if dims is None else 1))
    out, info = jax.jit(
        jax.vmap(lambda g: R.pcm(g, max_components=N_U, capacity=N_U, newton_steps=0, dims=dims))
    )(gm)
    W, M, P, mask = (np.asarray(a) for a in gm)
    dd = None if dims is None else np.array(dims)
    r = pn.pcm_batch(W, M, P, N_U, N_U, dims=dd, mask=mask)
    naive = pn.pcm_batch(W, M, P, N_U, N_U, dims=dd, mask=mask, skip_repeats=False)
    for x, y in zip(r, naive):
        np.testing.assert_array_equal(x, y)
    ties = sum(_compare(out, info, [a[b] for a in r], b) for b in range(W.shape[0]))
    assert ties <= 3
    r_all = pn.pcm_batch(W[:1], M[:1], P[:1], N_U, N_U, dims=dd)  # mask omitted: every slot live
    assert not _compare(out, info, [a[0] for a in r_all], 0)
    assert not _compare(out, info, pn.pcm(W[0], M[0], P[0], N_U, N_U, dims=dd), 0)
