"""The compiled R-GSF loop of references/gsf_numba.py against gmjax's R-GSF (issue 46).

``bench_gsf_numba.py`` reports gmjax / numba per run-step only if both filters compute the same
thing: gmjax's ``run(build_gsf(model, "ekf", Runnalls(num_out=20), capacity=20))`` and the numba
per-run loop, on the same simulated measurements of the seed 000 1-D jump system and the 4-D
range-bearing system, give per-step estimate means and covariances equal to 1e-9 (float64). The
default tests run the loop's ``.py_func`` (plain Python, no compilation; numba need not be installed)
on 2 runs x a few steps, Runnalls merging from the second step on; the 1-D windows cover
both measurement functions (``x^2 / 20`` up to step 80, ``3 x - 4`` after). The ``slow`` test runs
the compiled ``prange`` batch driver on every step of more runs.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_gsf_numba import gmjax_filter, numba_filter, problem  # noqa: E402

from references import gsf_numba  # noqa: E402

ATOL = 1e-9
STEPS = {"1-D": 6, "4-D": 4}  # the default tests' window lengths (one gmjax compilation per system)


@functools.cache
def _gmjax(system):
    """gmjax's R-GSF as ``jit(vmap(...))`` over the runs, the times an argument (so every window of a
    system's length shares one compilation): ``(zs, ts) -> (means, covs, n_updated)``."""
    from gmjax.filters import run
    from gmjax.filters.gsf import build_gsf
    from gmjax.reduction import Runnalls

    model = problem(system, 2, 1)[0]
    filt = build_gsf(model, "ekf", Runnalls(num_out=20), capacity=20)

    def one(z, ts):
        info = run(filt, z, ts)[1]
        return info.mean, info.cov, info.extra["n_updated"]

    return jax.jit(jax.vmap(one, (0, None)))


def _check(system, gm_out, nb_out):
    gm_m, gm_P = (np.asarray(a) for a in gm_out)
    nb_m, nb_P = nb_out
    assert nb_m.shape == gm_m.shape and nb_P.shape == gm_P.shape
    assert np.isfinite(gm_m).all() and np.isfinite(gm_P).all()
    dm, dP = np.abs(nb_m - gm_m).max(), np.abs(nb_P - gm_P).max()
    assert dm <= ATOL, f"{system}: estimate means differ by {dm:.2e}"
    assert dP <= ATOL, f"{system}: estimate covariances differ by {dP:.2e}"


@pytest.mark.parametrize(
    "system, start", [("1-D", 0), ("1-D", 77), ("4-D", 0)], ids=["1-D-first", "1-D-switch", "4-D"]
)
def test_py_loop_matches_gmjax(system, start):
    """2 runs, a window of a few steps, interpreted; Runnalls merges in the window (more than 20
    updated components: 1-D 5 x 3 = 15 after the first step, 45 after the second; 4-D 2 x 4 = 8, then
    32)."""
    _, zs, ts, args = problem(system, 2, STEPS[system], start)
    means, covs, n_updated = _gmjax(system)(zs, ts)
    assert int(np.max(n_updated)) > 20
    _check(system, (means, covs), numba_filter(args, batched=False)(np.asarray(zs)))


def test_module_runs_without_numba(monkeypatch):
    """With numba not importable the module (and the Runnalls core it imports) still imports and
    runs as plain Python."""
    import importlib.util

    monkeypatch.setitem(sys.modules, "numba", None)  # `import numba` raises ImportError
    monkeypatch.setitem(sys.modules, "numba.extending", None)
    # imported afresh under the blocked numba; sys.modules and the package attribute restored after
    monkeypatch.delitem(sys.modules, "references.reduction_numba", raising=False)
    monkeypatch.delattr(sys.modules["references"], "reduction_numba", raising=False)
    path = Path(gsf_numba.__file__)
    spec = importlib.util.spec_from_file_location("gsf_numba_plain", path)
    plain = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(plain)
    assert not plain.HAVE_NUMBA
    assert plain.gsf_batch.py_func is plain.gsf_batch
    assert not sys.modules["references.reduction_numba"].HAVE_NUMBA
    _, zs, ts, (head, ts64) = problem("1-D", 2, STEPS["1-D"])
    _check("1-D", _gmjax("1-D")(zs, ts)[:2], plain.gsf_batch(*head, np.asarray(zs, np.float64), ts64))


@pytest.mark.slow
@pytest.mark.parametrize("system", ["1-D", "4-D"])
def test_numba_batch_matches_gmjax(system):
    """The compiled ``prange`` batch driver on 24 runs, every step (1-D 120, 4-D 100)."""
    pytest.importorskip("numba")
    model, zs, ts, args = problem(system, 24)
    _check(system, gmjax_filter(model, ts)(zs), numba_filter(args)(np.asarray(zs)))
