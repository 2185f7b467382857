"""Extended ISE (EISE) of a cluster-merge and the search for the confidence multiplier ``λ``.

The EISE of a clustering (Xu et al., PCM = seed 000 eqs 29–35; Xu et al. 2019 = seed 003 eqs 10–15) is the sum over clusters of the
integrated squared error between the cluster's sub-mixture ``f_c = Σ_{m∈c} w_m N(u_m, P_m)`` and its
merged Gaussian ``q_c = W_c N(ū_c, P̄_c)``, plus a penalty on the number of clusters ``N'``:

* seed 000 eq 29: ``J = ½ Σ_c ∫ (f_c - q_c)² + α e^{N'/N}`` (``N`` = components after pruning),
* seed 003 eq 10: ``J = Σ_c ∫ (f_c - q_c)² + α lg N'``.

Each integral is ``J_hh - 2 J_hr + J_rr`` (eq 31) in closed form through
``∫ N(u_1, P_1) N(u_2, P_2) = N(u_1; u_2, P_1 + P_2)`` (eqs 34–35).

**Why a relaxation.** The hard clustering changes only where ``λ`` crosses one of the finitely many
similarity thresholds ``δ_ij`` (see :mod:`gmjax.reduction.clustering`), so the hard EISE is
*piecewise constant* in ``λ``: its derivative is 0 almost everywhere and undefined at the jumps, and
the Newton–Raphson iteration of seed 000 (Table 1 step 7, "the classic Newton–Raphson method") has
nothing to work with. We therefore run Newton on a smooth relaxation with *soft memberships*:

* the hard clusterings ``A_k`` (one-hot ``(K, K)`` membership, clusters indexed by head slot) are
  computed on a grid ``λ_1 < … < λ_G`` over the search scope;
* at any ``λ`` the soft membership is ``A(λ) = Σ_k π_k(λ) A_k`` with temperature weights
  ``π_k(λ) = softmax_k(-(λ - λ_k)² / (2τ²))``; every component is spread over the clusters that
  claim it near ``λ``, each cluster is merged with these fractional weights (the same CI or moment
  formula), and the closed-form EISE is evaluated on the soft clusters, with the soft count
  ``N'(λ) = Σ_k π_k N'_k`` in the penalty;
* as ``τ → 0`` the relaxation tends to the hard EISE of the nearest grid point; for ``τ > 0`` it is
  ``C^∞`` in ``λ``. The Newton step takes its first and second derivative from the chain rule
  through ``π(λ)`` worked out by hand (``_relaxed_value_and_slopes``; equal to ``jax.jvp`` of the value to
  rounding, and cheaper), and ``jax.grad`` differentiates through all of it.

**Cost.** ``A(λ)`` enters the merge statistics linearly and ``J_hh`` bilinearly, so the search
builds the per-grid-point sums once (``_RelaxedParts``: ``Σ ω``, ``Σ ω P^{-1}``, ``Σ ω P^{-1} u``
or the moment sums per cluster, and the ``(G, G)`` matrix of ``J_hh`` cross sums); each relaxed
evaluation then combines them with ``π(λ)`` and needs ``J_hr`` only for the ``G K`` pairs (component,
the cluster a grid point puts it in). Equal to the dense soft merge to rounding
(``tests/reduction/eise/test_relaxed.py``). Neighbouring grid points mostly cluster alike, so few of those pairs are
distinct; for ``d >= 2`` the search evaluates each distinct pair once (``_Pairs``, ``_over_pairs``;
under ``vmap`` the distinct pairs of all runs side by side): in 4-D, where the pairs' ``d × d``
algebra dominates, a relaxed evaluation costs a little over a quarter of one over all pairs. The
grid's hard EISE likewise costs each run of equal consecutive clusterings once under ``vmap``
(``search._grid_costs``: the run starts of the whole batch, gathered into blocks).

Newton starts at the grid's best ``λ`` and takes damped steps (trust radius ``τ``, backtracking; see
``newton._newton``; every candidate ``λ`` is evaluated with its derivatives, which the next step
starts from, so a step whose full length is accepted costs one evaluation); it fails when a
derivative is not finite or no step decreases the relaxation. The hard EISE at Newton's ``λ`` is
then computed, and the grid's best is kept whenever Newton failed or did not do at least as well
(``used_fallback`` in the result).
The clustering at Newton's ``λ`` is a grid point's wherever the two judgment matrices are equal
(the clustering depends on ``λ`` only through it); only the other runs run the overlap sweep
(``search._cluster_unless_known``; under ``vmap`` gathered into blocks).
Newton's loops exit early (under ``vmap`` each pass steps only the runs still stepping, gathered
into chunks, until every run of the batch is done, and only the few runs whose full step was
rejected halve it, gathered into blocks); a custom JVP differentiates the
equivalent fixed-length ``scan``, so values and derivatives are those of ``newton_steps`` masked
steps. For that, a run's relaxed value and slopes must not depend on the batch they are evaluated
in: ``_relaxed_value_and_slopes`` sums elementwise in a fixed order (XLA:CPU gives large reductions
and dots to other kernels that sum in another order), except its three ``π``-weighted grid sums

The modules: :mod:`~gmjax.reduction.eise.ise` (the hard EISE), :mod:`~gmjax.reduction.eise.relaxed`
(the relaxation and its slopes), :mod:`~gmjax.reduction.eise.newton` (Newton's loops and their batching
rules), :mod:`~gmjax.reduction.eise.search` (the search).
"""

from gmjax.reduction.eise.ise import (
    cluster_ise,
    eise,
    hard_eise,
    merge_membership,
    onehot_membership,
    penalty,
    self_overlaps,
)
from gmjax.reduction.eise.relaxed import relaxed_eise, relaxed_membership
from gmjax.reduction.eise.search import (
    ConfidenceSearch,
    EISECriterion,
    SearchOptions,
    SearchResult,
    search_confidence,
)

__all__ = [
    "ConfidenceSearch",
    "EISECriterion",
    "SearchOptions",
    "SearchResult",
    "onehot_membership",
    "merge_membership",
    "cluster_ise",
    "self_overlaps",
    "eise",
    "penalty",
    "hard_eise",
    "relaxed_membership",
    "relaxed_eise",
    "search_confidence",
]
