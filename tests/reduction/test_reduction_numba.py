"""The compiled per-mixture loops of references/reduction_numba.py against gmjax.reduction.

Runnalls, West (KL, ISE, enhanced) and GMRC on random mixtures of capacity 60 reduced to 20 in
d = 1, 2, 4: one with every slot live, the others padded (30-59 live components scattered among
padded slots): outputs (weights, means,
covariances, mask, labels) equal to 1e-12, the same merge sequence (Runnalls, West) or the same
k-means iteration count (GMRC), costs to rounding. The default tests run the loops' ``.py_func``
(plain Python, no compilation; numba need not be installed); the ``slow`` test runs the numba
``prange`` batch drivers on a larger batch.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_reduction_utils import batch, index, random_components, scatter_padding

from gmjax import reduction as R
from references import reduction_numba as rn

K_IN = 60
NUM_OUT = 20
ATOL = 1e-12

GMJAX = {
    "runnalls": lambda g: R.runnalls(g, NUM_OUT),
    "west": lambda g: R.west(g, NUM_OUT),
    "west_ise": lambda g: R.west(g, NUM_OUT, metric="ise"),
    "west_enhanced": lambda g: R.west(g, NUM_OUT, enhanced=True),
    "gmrc": lambda g: R.gmrc(g, NUM_OUT),
}
# every West call passes both flags, so the compiled drivers see one signature (fewer compilations)
OPTS = {
    "west": {"metric_ise": False, "enhanced": False},
    "west_ise": {"metric_ise": True, "enhanced": False},
    "west_enhanced": {"metric_ise": False, "enhanced": True},
}


def _numba_fn(name, batched):
    base = "west" if name.startswith("west") else name
    return getattr(rn, f"{base}_batch" if batched else base), OPTS.get(name, {})


def _mixtures(d, n, seed):
    """``n`` mixtures of capacity ``K_IN``: the first with every slot live, the others with 30-59 live
    components scattered among padded slots."""
    rng = np.random.default_rng(seed)
    gms = [index(batch([random_components(rng, K_IN, d)], K_IN), 0)]
    for b in range(1, n):
        n_live = int(rng.integers(30, K_IN))
        gms.append(
            scatter_padding(index(batch([random_components(rng, n_live, d)], K_IN), 0), K_IN, seed + b)
        )
    return jax.tree_util.tree_map(lambda *a: np.stack(a), *gms)


def _compare(name, out, info, r, b=None):
    """Max abs differences; asserts the discrete parts (mask, labels, merges / iterations)."""
    pick = (lambda a: np.asarray(a)) if b is None else (lambda a: np.asarray(a)[b])
    np.testing.assert_array_equal(pick(out.mask), r[3])
    np.testing.assert_array_equal(pick(info.labels), r[4])
    if name == "gmrc":
        assert int(pick(info.aux["iterations"])) == r[5]
        assert bool(pick(info.aux["converged"])) == r[6]
    else:
        np.testing.assert_array_equal(pick(info.aux["merges"]), r[5], err_msg="merge sequence differs")
    diffs = {
        "weights": np.abs(pick(out.weights) - r[0]).max(),
        "means": np.abs(pick(out.means) - r[1]).max(),
        "covs": np.abs(pick(out.covs) - r[2]).max(),
    }
    for field, v in diffs.items():
        assert v <= ATOL, f"{name}: {field} differ by {v:.2e}"
    np.testing.assert_allclose(float(pick(info.cost)), r[-1], rtol=1e-10, atol=1e-12)
    return diffs


def _run_py(name, gm):
    """gmjax (one vmapped call) against the loops' ``.py_func`` on every mixture of ``gm``; the first
    (fully live) one is also run with the mask omitted."""
    fn, opts = _numba_fn(name, batched=False)
    out, info = jax.vmap(GMJAX[name])(gm)
    W, M, P, mask = (np.asarray(a) for a in gm)
    assert mask[0].all() and not mask[1:].all()
    _compare(name, out, info, fn.py_func(W[0], M[0], P[0], NUM_OUT, **opts), 0)
    for b in range(W.shape[0]):
        _compare(name, out, info, fn.py_func(W[b], M[b], P[b], NUM_OUT, mask=mask[b], **opts), b)


@pytest.mark.parametrize("d", [1, 2, 4])
@pytest.mark.parametrize("name", ["runnalls", "west", "gmrc"])
def test_py_loop_matches_gmjax(name, d):
    """The loops (run by the interpreter) give gmjax's outputs on one full and three padded mixtures."""
    _run_py(name, _mixtures(d, 4, seed=100 * d + len(name)))


@pytest.mark.parametrize("name", ["west_ise", "west_enhanced"])
def test_py_loop_west_variants(name):
    _run_py(name, _mixtures(2, 3, seed=7 + len(name)))


@pytest.mark.parametrize("name", ["runnalls", "west"])
def test_py_loop_threshold_and_overflow(name):
    """A finite threshold stops at the same step; with more live slots than ``capacity`` the heaviest
    are kept, heaviest first (gmjax's finalize), and the labels of the dropped slots are -1."""
    thr = {"runnalls": 0.01, "west": 0.5}[name]
    rng = np.random.default_rng(5)
    comps = [random_components(rng, int(rng.integers(12, 30)), 2) for _ in range(6)]
    gm = batch(comps, 32)
    out, info = jax.vmap(lambda g: getattr(R, name)(g, 3, thr, capacity=8))(gm)
    assert np.asarray(info.overflow).any()
    W, M, P, mask = (np.asarray(a) for a in gm)
    fn = getattr(rn, name).py_func
    for b in range(len(comps)):
        r = fn(W[b], M[b], P[b], 3, thr, capacity=8, mask=mask[b])
        _compare(name, out, info, r, b)


def test_module_runs_without_numba(monkeypatch):
    """With numba not importable the module still imports; the batch drivers are plain loops."""
    import importlib.util
    import sys
    from pathlib import Path

    monkeypatch.setitem(sys.modules, "numba", None)  # `import numba` raises ImportError
    monkeypatch.setitem(sys.modules, "numba.extending", None)
    path = Path(rn.__file__)
    spec = importlib.util.spec_from_file_location("reduction_numba_plain", path)
    plain = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(plain)
    assert not plain.HAVE_NUMBA
    gm = _mixtures(2, 2, seed=3)
    W, M, P, mask = (np.asarray(a) for a in gm)
    out, info = jax.vmap(GMJAX["runnalls"])(gm)
    r = plain.runnalls_batch(W, M, P, NUM_OUT, mask=mask)
    for b in range(2):
        _compare("runnalls", out, info, [a[b] for a in r], b)
    assert plain.gmrc.py_func is plain.gmrc


@pytest.mark.slow
@pytest.mark.parametrize("d", [1, 2, 4])
def test_numba_batch_matches_gmjax(d):
    """The compiled ``prange`` batch drivers on 64 mixtures (one full, 63 padded) per reducer."""
    pytest.importorskip("numba")
    gm = _mixtures(d, 64, seed=900 + d)
    W, M, P, mask = (np.asarray(a) for a in gm)
    for name, kernel in GMJAX.items():
        fn, opts = _numba_fn(name, batched=True)
        out, info = jax.jit(jax.vmap(kernel))(gm)
        r = fn(W, M, P, NUM_OUT, mask=mask, **opts)
        for b in range(W.shape[0]):
            _compare(name, out, info, [a[b] for a in r], b)
        r_all = fn(W[:1], M[:1], P[:1], NUM_OUT, **opts)  # mask omitted: every slot live
        _compare(name, out, info, [a[0] for a in r_all], 0)
        fn1, _ = _numba_fn(name, batched=False)
        _compare(name, out, info, fn1(W[0], M[0], P[0], NUM_OUT, **opts), 0)
