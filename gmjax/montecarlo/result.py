"""The aggregated result of a study: its fields, summaries, saving and loading, and :func:`merge` of
parts into the whole."""

from __future__ import annotations

import json
import math
import os
from typing import Any, NamedTuple, Sequence, cast

import jax
import numpy as np

from gmjax.montecarlo._files import _pack, _read_npz, _unpack, _write_npz
from gmjax.montecarlo.accumulate import (
    BlockSums,
    StudyMoments,
    _armse_and_stderr,
    _block_sums,
    _centre,
    _chan_merge,
    _fold,
    _hist_median,
    _insert_node,
    _shifted_sums,
)
from gmjax.montecarlo.runs import SCORE_NAMES, RunScores

__all__ = ["MonteCarloResult", "load_result", "merge", "summarize", "json_safe"]

# ----------------------------------------------------------------------------- results


class MonteCarloResult(NamedTuple):
    """Aggregated Monte Carlo study (NumPy arrays, ready to print, plot, save and merge).

    Attributes:
        rmse: ``(T,)`` RMSE over runs per step (seed 000 eq 44 / seed 001 eq 42).
        position_rmse: ``(T,)`` the same for the position components.
        armse: ``()`` time average of ``rmse`` (ARMSE); ``armse_stderr`` its Monte Carlo standard
            error (delta method over runs; ``nan`` for one run).
        position_armse, position_armse_stderr: the same for ``position_rmse``.
        nees: ``(T,)`` average NEES per step; ``anees``: ``()`` over runs and steps;
            ``median_nees``: ``()`` median over runs and steps (histogram, < 0.23 % relative error),
            robust to the rare step where a particle cloud collapses and one NEES explodes.
        cep: ``()`` median position error over all runs and steps (seed 004 eq 24; histogram).
        mean_cost: ``()`` time/run average of the reducer's own cost (``ReductionInfo.cost``): the
            AEISE for PCM / GMRCM, a summed KL bound for Runnalls, 0 for pruning; ``mean_ise`` the
            time/run average of the ISE of each reduction (``nan`` when the filter does not report
            ``extra["ise"]``, e.g. a GSF built without ``track_ise``).
        n_components: ``(T,)`` mean live components per step.
        flag_rate: ``()`` fraction of steps with any flag; ``n_runs_flagged``: runs with any flag.
        n_runs: runs in the result; ``runs``: ``(start, stop)`` of the run indices.
        moments: the :class:`StudyMoments` behind every number (what :func:`merge` combines).
        scores: :class:`RunScores` ``(k, T)`` of the first ``k = keep_runs`` runs, or ``None``.
        config: the study's configuration (dtype, key, runs, chunk size, versions, ...; JSON-ready).
        compile_s, run_s: seconds of compilation (the filter's program, plus the simulation's when
            this study compiled it: see "Streaming" above) and of execution; ``resumed_runs``: runs
            taken from a checkpoint.
        sums: the :class:`BlockSums` that ``moments`` folds (what :func:`merge` combines, bit for
            bit); ``None`` for a result of :func:`summarize`.
    """

    rmse: np.ndarray
    position_rmse: np.ndarray
    armse: float
    armse_stderr: float
    position_armse: float
    position_armse_stderr: float
    nees: np.ndarray
    anees: float
    median_nees: float
    cep: float
    mean_cost: float
    mean_ise: float
    n_components: np.ndarray
    flag_rate: float
    n_runs_flagged: int
    n_runs: int
    runs: tuple[int, int]
    moments: StudyMoments
    scores: RunScores | None = None
    config: dict | None = None
    compile_s: float = 0.0
    run_s: float = 0.0
    resumed_runs: int = 0
    sums: BlockSums | None = None

    def to_json(self) -> dict:
        """JSON-ready summary (no per-run data; NaN / inf as ``None``)."""
        out = {}
        for name in (
            "armse",
            "armse_stderr",
            "position_armse",
            "position_armse_stderr",
            "anees",
            "median_nees",
            "cep",
            "mean_cost",
            "mean_ise",
            "flag_rate",
            "n_runs_flagged",
            "n_runs",
            "compile_s",
            "run_s",
            "resumed_runs",
        ):
            out[name] = getattr(self, name)
        for name in ("rmse", "position_rmse", "nees", "n_components"):
            out[name] = np.asarray(getattr(self, name)).tolist()
        out["runs"] = list(self.runs)
        out["config"] = self.config
        return json_safe(out)

    def save(self, path: str | os.PathLike) -> None:
        """Write the result to ``path`` (``.npz``: accumulators, block sums, kept runs, a JSON header
        and a sha256 checksum of all of it; no pickle)."""
        arrays = _pack(self.moments, self.sums, self.scores)
        meta = {
            "runs": list(self.runs),
            "config": self.config,
            "compile_s": self.compile_s,
            "run_s": self.run_s,
            "resumed_runs": self.resumed_runs,
            "ise_tracked": not np.isnan(self.mean_ise),
        }
        arrays["meta"] = np.asarray(json.dumps(json_safe(meta)))
        _write_npz(path, arrays)

    @staticmethod
    def load(path: str | os.PathLike) -> MonteCarloResult:
        """Read a result written by :meth:`save`."""
        return load_result(path)


def load_result(path: str | os.PathLike) -> MonteCarloResult:
    """Read a :class:`MonteCarloResult` written by :meth:`MonteCarloResult.save` (no pickle).

    Raises:
        ValueError: naming ``path`` and the cause, when the file is missing, truncated, corrupt
            (checksum) or not a saved result.
    """
    f = _read_npz(path, "result", required=("meta",))
    meta = json.loads(str(f["meta"]))
    moments, sums, scores = _unpack(f)
    return _finalize(
        moments,
        runs=tuple(meta["runs"]),
        scores=scores,
        config=meta["config"],
        compile_s=meta["compile_s"] or 0.0,
        run_s=meta["run_s"] or 0.0,
        resumed_runs=meta["resumed_runs"],
        ise_tracked=meta.get("ise_tracked", True),
        sums=sums,
    )


def json_safe(obj: Any) -> Any:
    """``obj`` with NaN / inf floats replaced by ``None`` and NumPy scalars by Python ones (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def _finalize(
    m: StudyMoments,
    *,
    runs: tuple[int, int],
    scores: RunScores | None = None,
    config: dict | None = None,
    compile_s: float = 0.0,
    run_s: float = 0.0,
    resumed_runs: int = 0,
    ise_tracked: bool = True,
    sums: BlockSums | None = None,
) -> MonteCarloResult:
    n = int(m.n)
    i = SCORE_NAMES.index
    rmse, armse, se = _armse_and_stderr(m.mean[i("sq_error")], m.sq_cross, n)
    prmse, parmse, pse = _armse_and_stderr(m.mean[i("position_sq_error")], m.position_sq_cross, n)

    def avg(name):
        row = m.mean[i(name)]
        return float(row.mean()) if row.size else float("nan")

    return MonteCarloResult(
        rmse=rmse,
        position_rmse=prmse,
        armse=armse,
        armse_stderr=se,
        position_armse=parmse,
        position_armse_stderr=pse,
        nees=m.mean[i("nees")].copy(),
        anees=avg("nees"),
        median_nees=_hist_median(m.hist[0]),
        cep=_hist_median(m.hist[1]),
        mean_cost=avg("cost"),
        mean_ise=avg("ise") if ise_tracked else float("nan"),
        n_components=m.mean[i("n_components")].copy(),
        flag_rate=avg("flags"),
        n_runs_flagged=int(m.n_flagged_runs),
        n_runs=n,
        runs=(int(runs[0]), int(runs[1])),
        moments=m,
        scores=scores,
        config=config,
        compile_s=float(compile_s),
        run_s=float(run_s),
        resumed_runs=int(resumed_runs),
        sums=sums,
    )


def summarize(
    scores: RunScores, *, n_runs: int | None = None, compile_s: float = 0.0, run_s: float = 0.0
) -> MonteCarloResult:
    """Aggregate per-run scores ``(N, T)`` (e.g. of :func:`study_scores`) into a :class:`MonteCarloResult`."""
    sq = np.asarray(scores.sq_error, np.float64)
    N, T = sq.shape
    if n_runs is not None and n_runs != N:
        raise ValueError(f"n_runs: {n_runs} but the scores hold {N} runs")

    def col(x: Any, default: float = 0.0) -> Any:  # host (N, T) float64 columns
        return np.full((N, T), default) if x is None else np.asarray(x, np.float64)

    s = RunScores(
        col(sq),
        col(scores.position_sq_error),
        col(scores.nees),
        col(scores.cost),
        cast(Any, np.asarray(scores.flags, bool)),
        col(scores.n_components, 1.0),
        col(scores.ise),
    )
    moments = _centre(_shifted_sums(s, np.ones(N, bool), np))
    return _finalize(
        moments,
        runs=(0, N),
        scores=scores,
        compile_s=compile_s,
        run_s=run_s,
        ise_tracked=scores.ise is not None,
    )


_SAME_STUDY = ("key", "filter", "scenario", "dtype", "n_runs")  # what makes results parts of one study
_SAME_SUMS = ("block_size", "gmjax_version", "jax_version")  # and what makes their sums combine exactly


def merge(results: Sequence[MonteCarloResult], *, exact: bool = True) -> MonteCarloResult:
    """Combine results of adjoining run ranges of one study into the result of their union.

    With ``exact=True`` (the default) the parts' :class:`BlockSums` are combined in the study's one
    fixed tree, so the merged numbers are bit-identical to one study over all the runs, however the
    runs were split (at block boundaries; :func:`monte_carlo` refuses ranges off them) and in whatever
    order the parts come. ``exact=False`` also takes results without block sums (of :func:`summarize`,
    or saved by an older gmjax) or with different block sizes or versions, and combines their
    accumulators in run order: equal to the whole study to rounding only. Kept runs are concatenated
    in run order (each part's first ``keep_runs``).

    Raises:
        ValueError: no results; overlapping ranges; a gap (a merged result never has a hole: the
            message names the missing runs); parts of different studies (``key``, ``filter``,
            ``scenario``, ``dtype`` or ``n_runs`` differ) or, with ``exact``, whose sums do not
            combine bit for bit (``block_size``, ``gmjax_version`` or ``jax_version`` differ, or no
            block sums): each message names the field.
    """
    results = sorted(results, key=lambda r: r.runs[0])
    if not results:
        raise ValueError("results: nothing to merge")
    for a, b in zip(results, results[1:]):
        if b.runs[0] < a.runs[1]:
            raise ValueError(f"results: run ranges {a.runs} and {b.runs} overlap")
        if b.runs[0] > a.runs[1]:
            raise ValueError(
                f"results: runs {a.runs[1]}..{b.runs[0] - 1} are missing between the parts {a.runs} and "
                f"{b.runs}; run runs=range({a.runs[1]}, {b.runs[0]}) of the study and merge it too"
            )
    fields = _SAME_STUDY + (_SAME_SUMS if exact else ())
    ref = results[0].config or {}
    for r in results[1:]:
        cfg = r.config or {}
        for field in fields:
            if ref.get(field) != cfg.get(field):
                what = "different studies" if field in _SAME_STUDY else "sums that do not combine exactly"
                hint = "" if field in _SAME_STUDY else "; merge(..., exact=False) combines them to rounding"
                raise ValueError(
                    f"results: {what} ({field} differs: {ref.get(field)!r} in {results[0].runs} vs "
                    f"{cfg.get(field)!r} in {r.runs}){hint}"
                )
    n_steps = results[0].moments.mean.shape[1]
    sums = None
    if exact:
        for r in results:
            if r.sums is None:
                raise ValueError(
                    f"results: the part with runs {r.runs} has no block sums (a result of summarize, or saved "
                    "by an older gmjax), so it cannot be merged bit for bit; merge(..., exact=False) "
                    "combines its accumulators to rounding"
                )
        block, n_blocks = results[0].sums.block_size, results[0].sums.n_blocks  # type: ignore[union-attr]
        nodes: dict[tuple[int, int], StudyMoments] = {}
        for r in results:
            for level, index, node in r.sums.nodes:  # type: ignore[union-attr]
                _insert_node(nodes, level, index, node, n_blocks)
        sums = _block_sums(block, n_blocks, nodes)
        m = _fold(sums, n_steps)
    else:
        m = StudyMoments.empty(n_steps)
        for r in results:
            m = _chan_merge(m, r.moments)
    kept = [r.scores for r in results if r.scores is not None]
    scores = None
    if kept:
        scores = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *kept)
    runs = (results[0].runs[0], results[-1].runs[1])
    config = dict(ref, runs=list(runs), merged_from=[list(r.runs) for r in results], exact=exact)
    return _finalize(
        m,
        runs=runs,
        scores=scores,
        config=config,
        compile_s=sum(r.compile_s for r in results),
        run_s=sum(r.run_s for r in results),
        ise_tracked=not any(np.isnan(r.mean_ise) for r in results),
        sums=sums,
    )
