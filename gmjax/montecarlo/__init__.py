"""Monte Carlo studies at any scale: streaming, resumable, split across runs and hosts, differentiable.

**Runs and keys.** Run ``i`` of a study with key ``key`` uses ``run_key(key, i) =
jax.random.fold_in(key, i)``, which under JAX's default (partitionable) threefry equals
``jax.random.split(key, n_runs)[i]`` (tested), split again into a simulation and a filter key. A run's
key depends on its index only, so a study can run any range of its runs (``runs=range(a, b)``), on any
number of processes, and the parts :func:`merge` into the whole.

**Streaming.** :func:`monte_carlo` runs the study in chunks of ``chunk_size`` runs. Two programs are
compiled for the chunk shape (the last chunk is padded and masked), so every chunk runs the same code:
the simulation of the chunk's runs, kept per scenario object, chunk size and devices so that every
filter studied on the same scenario object reuses it (as :func:`gmjax.studies.run_study` does), and the
filter with its scoring, kept per filter, scenario and params object. ``compile_s`` counts a program
only in the study that compiled it. Each device of a chunk sums its own **block** of ``chunk_size /
devices`` runs: per step, the sum and sum of squares of every score (squared error, position squared
error, NEES, component count, ISE, reducer cost, flags) about the block's first run, the ``(T, T)``
cross-products of the squared errors (for the ARMSE standard error, see ``accumulate._armse_and_stderr``),
log-spaced histograms of the NEES and of the position error (for the median NEES and the CEP) and the
number of runs with a flag. The host centres each block in float64 and combines the blocks (Chan et
al.'s pairwise update) in one fixed binary tree over the study's block indices (:class:`BlockSums`),
keeping only its complete nodes, so memory is ``O(chunk T + T² log2(N / block))`` whatever ``n_runs``
is; each node's ``(T, T)`` cross-moments cost 8 T² bytes twice (0.23 MB at T = 120, 16 MB at T = 1000).
Full per-run scores are kept for the first ``keep_runs`` runs.

**Medians.** ``median_nees`` and ``cep`` come from fixed histograms with 1000 bins per decade over
``[1e-10, 1e10]``: each middle order statistic is found in its bin and placed inside it by its rank
(log-linear), so the median's relative error is below ``10**(1/1000) - 1 = 0.23 %`` (values under
1e-10 read as 0, values above 1e10 as 1e10; a NaN anywhere gives NaN, as :func:`numpy.median` does).

**Determinism.** A study's numbers depend on its runs and its block size only. Block ``k`` always holds
runs ``[k b, (k + 1) b)``; each block is summed by the same per-device program (its scores materialised
before they are summed, and no division on the device, so no fused multiply-add or reciprocal of one
program's choosing enters the sums), and the tree combines the blocks in an order fixed by their
indices, never by their arrival. So with the same block size, a study is bit-identical (every field
of the result, every accumulator) whatever the split of its runs at block boundaries into parts
merged by :func:`merge` (in any order), an interruption and resume, and the number of devices and
processes: a chunk of 8 runs on 4 devices gives the bits of a chunk of 2 on one (tested, with two
processes under ``jax.distributed`` too). :func:`monte_carlo` refuses ranges off the block grid
(their partial blocks would be summed in other groups). Across block sizes, numbers agree to
rounding only: XLA compiles each batch shape on its own and may vectorise it differently. Measured on
seed 000's jump system (30 steps, 12-24 runs, CPU): per-run scores were identical for chunk sizes 5,
8, 12 and 24 with NL-, R- and PCM-GSFs and a PF, but a chunk of 1 (compiled unbatched) changed
PCM-GSF's per-run squared errors by up to 8e-5 relative in float32 and 2e-13 in float64; and the sums
are grouped otherwise (ARMSE: 3e-8 relative in float32, 1e-16 in float64). The test checks chunk
sizes to 1e-12 relative in float64.

**Resume.** ``checkpoint=path`` writes the block sums after every chunk (``.npz``, no pickle, with a
sha256 checksum of its arrays; a temporary file and ``os.replace``, temporary files of a killed
write removed on start and finish) with a hash of the configuration (filter params, scenario settings,
key, run range, block size, dtype, gmjax and JAX versions). Calling again with the same arguments
resumes after the last finished chunk and returns the bit-identical result, on any number of devices
with the same block size. A checkpoint that is truncated, empty, corrupt (checksum), written by
another gmjax or by a different configuration is refused with a ``ValueError`` naming the file, the
cause (what differs) and the remedy (delete it, or ``resume=False``).

**Many devices and hosts.** Each chunk's run axis is sharded over a 1-D mesh of ``devices`` (default
``jax.devices()``: every device of every process), one block per device. Under
``jax.distributed.initialize`` every process gathers every block's sums, so every process combines the
same blocks in the same tree and returns the same result. Launch one process per host with the same
script::

    # SLURM: srun --nodes=4 --ntasks-per-node=1 python study.py
    import jax
    jax.distributed.initialize()   # reads SLURM_* (or pass coordinator_address, num_processes, process_id)
    result = gmjax.monte_carlo(filt, scenario, 10**7, jax.random.key(0), progress=jax.process_index() == 0)
    if jax.process_index() == 0:
        result.save("study.npz")

On CPU hosts, the cross-process collectives are gloo (``jax_cpu_collectives_implementation``, JAX's
default).

**Differentiable studies.** :func:`study_scores` (per-run scores ``(N, T)``, ``vmap`` of
:func:`score_run`) and :func:`study_loss` are traceable: ``jax.grad`` of a study loss w.r.t. a
``params`` pytree that replaces ``filter.params`` (a relaxed reducer's threshold, a noise covariance)
goes through simulation, filtering and scoring. :mod:`gmjax.tune` is an optax loop over
:func:`study_loss`.

The modules: :mod:`~gmjax.montecarlo.runs` (one run and its scores), :mod:`~gmjax.montecarlo.losses`
(differentiable study losses), :mod:`~gmjax.montecarlo.accumulate` (streaming moments and the block
tree), :mod:`~gmjax.montecarlo.result` (the result, summaries, :func:`merge`),
``_files`` (checksummed ``.npz`` files), ``_checkpoint``
(resumable studies) and :mod:`~gmjax.montecarlo.driver` (:func:`monte_carlo`).
"""

from gmjax.montecarlo.accumulate import BlockSums as BlockSums
from gmjax.montecarlo.accumulate import StudyMoments as StudyMoments
from gmjax.montecarlo.driver import default_chunk_size as default_chunk_size
from gmjax.montecarlo.driver import monte_carlo as monte_carlo
from gmjax.montecarlo.losses import aeise_loss as aeise_loss
from gmjax.montecarlo.losses import anees_loss as anees_loss
from gmjax.montecarlo.losses import armse_loss as armse_loss
from gmjax.montecarlo.losses import count_loss as count_loss
from gmjax.montecarlo.losses import study_loss as study_loss
from gmjax.montecarlo.losses import study_scores as study_scores
from gmjax.montecarlo.losses import weighted_loss as weighted_loss
from gmjax.montecarlo.result import MonteCarloResult as MonteCarloResult
from gmjax.montecarlo.result import json_safe as json_safe
from gmjax.montecarlo.result import load_result as load_result
from gmjax.montecarlo.result import merge as merge
from gmjax.montecarlo.result import summarize as summarize
from gmjax.montecarlo.runs import FilteredRun as FilteredRun
from gmjax.montecarlo.runs import RunScores as RunScores
from gmjax.montecarlo.runs import filter_run as filter_run
from gmjax.montecarlo.runs import run_key as run_key
from gmjax.montecarlo.runs import score_filtered as score_filtered
from gmjax.montecarlo.runs import score_run as score_run

__all__ = [
    "RunScores",
    "StudyMoments",
    "MonteCarloResult",
    "BlockSums",
    "FilteredRun",
    "monte_carlo",
    "default_chunk_size",
    "merge",
    "summarize",
    "load_result",
    "run_key",
    "filter_run",
    "score_run",
    "score_filtered",
    "study_scores",
    "study_loss",
    "armse_loss",
    "anees_loss",
    "aeise_loss",
    "count_loss",
    "weighted_loss",
]
