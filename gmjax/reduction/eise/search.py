"""The search for the confidence multiplier ``λ`` (seed 000 Table 1 step 7): hard EISE on a grid,
Newton on the relaxation from the grid's best, the hard EISE at Newton's ``λ``, the better of the two."""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple, Sequence, TypedDict

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture
from gmjax.reduction import _util
from gmjax.reduction._greedy import _tied, _zero_of
from gmjax.reduction.clustering import centre_distances, gauss_cluster, judgment_matrix, similarity_thresholds
from gmjax.reduction.eise.ise import _check_options, _merge_hard, hard_eise, self_overlaps
from gmjax.reduction.eise.newton import _newton
from gmjax.reduction.eise.relaxed import _relaxed_at, _relaxed_parts, _relaxed_slopes_jit

__all__ = ["SearchResult", "EISECriterion", "ConfidenceSearch", "SearchOptions", "search_confidence"]


class SearchResult(NamedTuple):
    """Outcome of :func:`search_confidence` (all arrays; batch with vmap).

    Attributes:
        lam: ``()`` the chosen ``λ*``.
        eise: ``()`` hard EISE at ``λ*``.
        labels: ``(K,)`` hard clustering at ``λ*`` (head slots, ``-1`` on padding).
        merged: capacity-``K`` mixture of the merged clusters at ``λ*``, indexed by head slot.
        n_clusters: ``()`` int32 ``N'`` at ``λ*``.
        grid: ``(G,)`` the grid; grid_eise: ``(G,)`` hard EISE on it; grid_counts: ``(G,)`` ``N'``.
        lam_grid: ``()`` the grid's best ``λ``; eise_grid: ``()`` its hard EISE.
        lam_newton: ``()`` where Newton stopped; eise_newton: ``()`` hard EISE there.
        relaxed_newton: ``()`` relaxed EISE there.
        iterations: ``()`` int32 Newton steps taken.
        newton_ok: ``()`` bool, Newton converged (``|Δλ| < tol``) without a failed step.
        used_fallback: ``()`` bool, the grid's best was kept.
    """

    lam: Array
    eise: Array
    labels: Array
    merged: GaussianMixture
    n_clusters: Array
    grid: Array
    grid_eise: Array
    grid_counts: Array
    lam_grid: Array
    eise_grid: Array
    lam_newton: Array
    eise_newton: Array
    relaxed_newton: Array
    iterations: Array
    newton_ok: Array
    used_fallback: Array


_CLUSTER_BLOCK = 16  # runs per block when a batch clusters only the runs that need it


def _cluster_unless_known(cluster, known: Array, known_labels: Array, *operands) -> Array:
    """``cluster(*operands)``'s labels ``(K,)``, or ``known_labels`` where ``known`` says they are
    equal already (:func:`search_confidence`: Newton's ``λ`` has the judgment matrix of a grid point).

    Alone, a ``cond`` skips the overlap sweep. Under ``vmap`` a ``cond`` runs both sides and the
    sweep runs as long as its slowest run, so the batch rule gathers the runs that need a clustering
    and sweeps them in blocks of :data:`_CLUSTER_BLOCK` (usually one block, or none). The labels
    are integers of a piecewise-constant map: no derivative flows through them.
    """
    operands = jax.lax.stop_gradient(operands)

    def alone(known, known_labels, *operands):
        return jax.lax.cond(known, lambda: known_labels, lambda: cluster(*operands))

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _only_those_needed(axis_size, in_batched, known, known_labels, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        known, labels, *operands = jax.tree_util.tree_map(
            spread, [known, known_labels, *operands], list(in_batched)
        )
        if axis_size == 0:
            return labels, True
        block = min(_CLUSTER_BLOCK, axis_size)
        n_blocks = -(-axis_size // block)
        need = ~known
        order = _util.first_where(need, n_blocks * block)  # the runs that need a clustering, then axis_size

        def one_block(state):
            j, labels = state
            rows = jax.lax.dynamic_slice(order, (j * block,), (block,))
            take = lambda a: jnp.take(a, rows, axis=0, mode="clip")  # noqa: E731
            new = jax.vmap(cluster)(*jax.tree_util.tree_map(take, operands))
            new = jnp.where(take(need)[:, None], new, take(labels))
            return j + 1, labels.at[rows].set(new, mode="drop")

        n_need = jnp.sum(need.astype(jnp.int32))
        _, labels = jax.lax.while_loop(lambda s: s[0] * block < n_need, one_block, (0, labels))
        return labels, True

    return batched(known, known_labels, *operands)


_EISE_BLOCK = 64  # clusterings per block when a batch costs only the first of each run


def _costed(labels, gm, alpha, overlaps, info, *, criterion):
    """:func:`hard_eise` of one clustering under ``criterion``: ``(eise, merged, N')``."""
    return hard_eise(
        gm,
        labels,
        alpha=alpha,
        method=criterion.method,
        regularizer=criterion.regularizer,
        ise_scale=criterion.ise_scale,
        overlaps=overlaps,
        info=info,
    )


def _eise_and_count(labels, gm, alpha, overlaps, info, *, criterion):
    """The hard EISE of one clustering and its ``N'`` (:func:`_costed` without the merge)."""
    value, _, n = _costed(labels, gm, alpha, overlaps, info, criterion=criterion)
    return value, n


def _grid_costs(evaluate, grid_labels: Array, *operands) -> tuple[Array, Array]:
    """``evaluate(labels, *operands)`` at every clustering of ``grid_labels`` ``(G, K)``: ``(G,)``
    values and ``(G,)`` counts, with each run of equal consecutive clusterings costed once.

    Neighbouring grid points often cluster alike (a judgment matrix grows with ``λ`` by the few
    ``δ_ij`` it crosses): in ``bench_reducer_limit``'s draw, 1.4 distinct runs of 11 grid points at
    ``d = 4``, 6.8 at ``d = 2``. Alone, every grid point is costed (a ``vmap``). Under ``vmap`` the
    batch rule gathers the first clustering of every run of every mixture of the batch and costs
    those, in blocks of :data:`_EISE_BLOCK`; each grid point then takes its run's value, which is
    the value its own clustering has (the same arithmetic on the same labels; bit for bit with the
    CI merge, to rounding with the moment merge, whose one-hot products XLA sums in an order it
    picks by the batch's shape). A ``custom_vmap`` has no differentiation rule, so the costs are a
    ``custom_jvp`` whose rule differentiates the plain evaluation of every grid point (as
    ``_greedy.chunked`` does).
    """

    def alone(grid_labels, *operands):
        return jax.vmap(lambda labels: evaluate(labels, *operands))(grid_labels)

    batched = jax.custom_batching.custom_vmap(alone)

    @batched.def_vmap
    def _first_of_each_run(axis_size, in_batched, grid_labels, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        grid_labels, *operands = jax.tree_util.tree_map(spread, [grid_labels, *operands], list(in_batched))
        B, G, K = grid_labels.shape
        n = B * G
        # the shapes of one evaluation; ``zeros_like`` keeps an operand's weak type (a Python
        # ``alpha``), so a float32 mixture gives float32 values, as it does alone
        one = lambda a, lead=1: jnp.zeros_like(a, shape=a.shape[lead:])  # noqa: E731
        value_shape = jax.eval_shape(evaluate, one(grid_labels, 2), *jax.tree_util.tree_map(one, operands))
        if n == 0:
            empty = tuple(jnp.zeros((B, G) + v.shape, v.dtype) for v in value_shape)
            return empty, (True, True)
        first = jnp.concatenate(
            [jnp.ones((B, 1), bool), jnp.any(grid_labels[:, 1:] != grid_labels[:, :-1], axis=-1)], axis=1
        )  # (B, G): a run starts here
        run_start = jax.lax.cummax(jnp.where(first, jnp.arange(G), 0), axis=1)  # (B, G)
        flat_labels = grid_labels.reshape(n, K)
        block = min(_EISE_BLOCK, n)
        order = _util.first_where(first.reshape(n), -(-n // block) * block)  # run starts first, then n

        def one_block(state):
            j, *outs = state
            at = jax.lax.dynamic_slice(order, (j * block,), (block,))
            take = lambda a: jnp.take(a, jnp.minimum(at // G, B - 1), axis=0)  # noqa: E731
            labels = jnp.take(flat_labels, at, axis=0, mode="clip")
            new = jax.vmap(evaluate)(labels, *jax.tree_util.tree_map(take, operands))
            return (j + 1, *(o.at[at].set(v, mode="drop") for o, v in zip(outs, new)))

        n_first = jnp.sum(first.astype(jnp.int32))
        init = tuple(jnp.zeros((n,) + v.shape, v.dtype) for v in value_shape)
        _, *outs = jax.lax.while_loop(lambda s: s[0] * block < n_first, one_block, (0, *init))
        source = (jnp.arange(B)[:, None] * G + run_start).reshape(n)
        return tuple(o[source].reshape((B, G) + o.shape[1:]) for o in outs), (True, True)

    costs = jax.custom_jvp(lambda *args: batched(*args))

    @costs.defjvp
    def _derivatives(primals, tangents):
        out, out_dot = jax.jvp(alone, primals, tangents)
        zero = _zero_of(primals)  # batch every output as the value's rule does (_greedy._zero_of)
        return _tied(out, zero), _tied(out_dot, zero)

    return costs(grid_labels, *operands)


class EISECriterion(NamedTuple):
    """The static settings in which seed 000's PCM and seed 003's GMRCM differ (hashable).

    Attributes:
        method: the cluster merge: ``"ci"`` (covariance intersection, seed 000 eqs 38–39) or
            ``"moment"`` (seed 003 eqs 16–18).
        regularizer: the penalty on ``N'``: ``"exp"`` (seed 000 eq 29, ``α e^{N'/N}``) or ``"log10"``
            (seed 003 eq 10, ``α lg N'``).
        ise_scale: the factor on the ISE sum (seed 000 eq 29: ½; seed 003 eq 10: 1).
        triangular: upper-triangular judgment matrix (seed 003 eqs 4–6).
        subset_rule: how a subset of a cluster is resolved (:func:`~gmjax.reduction.clustering.gauss_cluster`).
    """

    method: str = "ci"
    regularizer: str = "exp"
    ise_scale: float = 0.5
    triangular: bool = False
    subset_rule: str = "split"

    @classmethod
    def seed000(cls, merge: str = "ci") -> EISECriterion:
        """PCM's criterion (seed 000 eq 29) with the merge ``merge``."""
        return cls(merge, "exp", 0.5, False, "split")

    @classmethod
    def seed003(cls) -> EISECriterion:
        """GMRCM's criterion (seed 003 eq 10, moment merge, triangular judgment matrix)."""
        return cls("moment", "log10", 1.0, True, "absorb")


@pytree_dataclass
class _SearchSettings:
    """The settings of a confidence search (:class:`SearchOptions`), with seed 000's values: the
    fields :class:`ConfidenceSearch` and the reducer configs :class:`~gmjax.reduction.pcm.PCM` and
    :class:`~gmjax.reduction.gmrcm.GMRCM` share, declared once (a config overrides a default by
    declaring the field again)."""

    lambda_range: Any = (1.0, 3.0)
    alpha: Any = 0.001
    temperature: Any = 0.2
    tol: Any = 1e-6
    range_scale: Any = 0.5
    grid_size: int = static_field(11)
    newton_steps: int = static_field(8)
    dims: tuple[int, ...] | None = static_field(None)


@pytree_dataclass
class ConfidenceSearch(_SearchSettings):
    """How the confidence multiplier ``λ`` is chosen (seed 000 Table 1 step 7; seed 003 Algorithm 1
    steps 5–7).

    A frozen pytree: the scope, ``α``, the temperature, the tolerance and the range scale are traced
    leaves (differentiable, batchable); the grid size, the Newton steps, the clustering dimensions
    and the :class:`EISECriterion` are static.

    Attributes:
        lambda_range: the search scope ``(low, high)`` (seed 000: ``[1, 3]``; seed 003: ``[0.5, 3]``).
        alpha: the penalty's constant ``α`` (seed 000 eq 29; seed 003 eq 10).
        temperature: relaxation temperature ``τ`` (about the grid spacing); also Newton's trust radius.
        tol: Newton stops when ``|Δλ| < tol`` or the relative change of the relaxed EISE is below.
        range_scale: the confidence scope is ``range_scale · λσ`` (:mod:`gmjax.reduction.clustering`).
        grid_size: static ``G >= 2`` grid points. newton_steps: static (0: the grid only).
        dims: static state dimensions to cluster on (default all).
        criterion: static :class:`EISECriterion`.
    """

    criterion: EISECriterion = static_field(EISECriterion())

    @classmethod
    def seed000(cls, merge: str = "ci") -> ConfidenceSearch:
        """PCM's search (seed 000): scope ``[1, 3]`` (§IV-A), ``α = 0.001`` (§IV), ``τ = 0.2``,
        :meth:`EISECriterion.seed000` with the merge ``merge`` (the declared defaults are seed 000's)."""
        return cls(criterion=EISECriterion.seed000(merge))

    @classmethod
    def seed003(cls) -> ConfidenceSearch:
        """GMRCM's search (seed 003): scope ``[0.5, 3]`` (§4.1), ``α = 0.3`` (§4.2), ``τ = 0.25``,
        :meth:`EISECriterion.seed003`."""
        return cls((0.5, 3.0), 0.3, 0.25, criterion=EISECriterion.seed003())

    def at(self, gm: GaussianMixture, lam: ArrayLike) -> SearchResult:
        """The clustering at a given ``λ`` and its hard EISE, as a :class:`SearchResult` (no search)."""
        c = self.criterion
        labels = gauss_cluster(
            gm,
            lam,
            dims=self.dims,
            triangular=c.triangular,
            subset_rule=c.subset_rule,
            range_scale=self.range_scale,
        ).labels
        value, merged, n = _costed(labels, gm, self.alpha, None, None, criterion=c)
        return _fixed_result(gm, lam, labels, value, merged, n)

    def __call__(self, gm: GaussianMixture, lam: ArrayLike | None = None) -> SearchResult:
        """:func:`search_confidence` when ``lam`` is ``None``, else the clustering at ``lam`` (:meth:`at`)."""
        return search_confidence(gm, self) if lam is None else self.at(gm, lam)


class SearchOptions(TypedDict, total=False):
    """The keyword arguments that set a reducer's :class:`ConfidenceSearch` (its fields but the
    criterion): ``pcm(gm, **search)`` and ``gmrcm(gm, **search)`` take any of them, each reducer
    starting from its paper's values (:meth:`ConfidenceSearch.seed000`, :meth:`~ConfidenceSearch.seed003`).
    """

    lambda_range: Sequence[Any]
    alpha: Any
    temperature: Any
    tol: Any
    range_scale: Any
    grid_size: int
    newton_steps: int
    dims: Sequence[int] | None


def _fixed_result(
    gm: GaussianMixture, lam: ArrayLike, labels: Array, value: Array, merged: GaussianMixture, n: Array
) -> SearchResult:
    dtype = gm.means.dtype
    lam = jnp.asarray(lam, dtype)
    nan = jnp.asarray(jnp.nan, dtype)
    zero_i, false = jnp.zeros((), jnp.int32), jnp.zeros((), bool)
    return SearchResult(
        lam,
        value,
        labels,
        merged,
        n,
        lam[None],
        value[None],
        n[None],
        lam,
        value,
        lam,
        value,
        nan,
        zero_i,
        false,
        false,
    )


def _first_minimiser(values: Array, n_terms: int) -> Array:
    """The first grid point whose EISE is the smallest up to rounding: within ``n_terms · eps`` of
    the minimum, relative (a sum of ``n_terms`` non-negative cluster terms in another order differs
    by less). Two grid points can give the same partition under other head rows, so their EISE
    differ only by the summation order, and a plain ``argmin`` would pick between them by rounding,
    differently under ``vmap`` than alone; the smallest such ``λ`` is kept, as exact arithmetic
    would. A NaN EISE is picked as ``argmin`` picks it."""
    at_min = jnp.argmin(values)
    smallest = values[at_min]
    near = values <= smallest + n_terms * jnp.finfo(values.dtype).eps * jnp.abs(smallest)
    return jnp.where(jnp.any(near), jnp.argmax(near), at_min)


@jax.jit
def search_confidence(gm: GaussianMixture, search: ConfidenceSearch) -> SearchResult:
    """Search the confidence multiplier ``λ`` minimising the EISE (seed 000 Table 1 step 7).

    (a) Hard EISE on a grid of ``search.grid_size`` points over ``search.lambda_range``; (b)
    ``search.newton_steps`` Newton–Raphson steps on the relaxed EISE from the grid's best (0 skips
    them), falling back to the grid's best unless Newton converged to a ``λ`` whose *hard* EISE is
    no worse. See the package docstring.

    Args:
        gm: mixture of capacity ``K`` to cluster (pruned already, weights normalised).
        search: the :class:`ConfidenceSearch` (scope, ``α``, ``τ``, tolerance, sizes, criterion).
    """
    lam_lo, lam_hi = search.lambda_range
    grid_size, newton_steps, dims = search.grid_size, search.newton_steps, search.dims
    temperature, tol, alpha, range_scale = search.temperature, search.tol, search.alpha, search.range_scale
    method, regularizer, ise_scale, triangular, subset_rule = search.criterion
    _check_options(method, regularizer)
    if grid_size < 2:
        raise ValueError(f"grid_size: must be >= 2, got {grid_size}")
    if newton_steps < 0:
        raise ValueError(f"newton_steps: must be >= 0, got {newton_steps}")
    dtype = gm.means.dtype
    delta = similarity_thresholds(gm, dims)
    dist = centre_distances(gm, dims)
    lo = jnp.asarray(lam_lo, dtype)
    hi = jnp.asarray(lam_hi, dtype)
    grid = lo + (hi - lo) * jnp.linspace(0.0, 1.0, grid_size, dtype=dtype)
    # the clustering-independent parts of every grid point's EISE and merge, once
    overlaps = self_overlaps(gm)
    info = gaussian.spd_inv(gm.covs) if method == "ci" else None

    def cluster(gm, lam, delta, dist, range_scale):
        return gauss_cluster(
            gm,
            lam,
            triangular=triangular,
            subset_rule=subset_rule,
            range_scale=range_scale,
            delta=delta,
            dist=dist,
        )

    def evaluate_labels(labels):
        value, merged, n = _costed(labels, gm, alpha, overlaps, info, criterion=search.criterion)
        return value, labels, merged, n

    # all grid clusterings in one overlap sweep, then the EISE of each run of equal clusterings once
    grid_clusters = cluster(gm, grid, delta, dist, range_scale)
    grid_labels = grid_clusters.labels
    grid_eise, grid_counts = _grid_costs(
        partial(_eise_and_count, criterion=search.criterion), grid_labels, gm, alpha, overlaps, info
    )
    best = _first_minimiser(grid_eise, gm.capacity)
    lam_grid, eise_grid, labels_grid, n_grid = (
        grid[best],
        grid_eise[best],
        grid_labels[best],
        grid_counts[best],
    )
    merged_grid = _merge_hard(gm, labels_grid, method, info)

    if newton_steps == 0:
        zero_i = jnp.zeros((), jnp.int32)
        return SearchResult(
            lam_grid,
            eise_grid,
            labels_grid,
            merged_grid,
            n_grid,
            grid,
            grid_eise,
            grid_counts,
            lam_grid,
            eise_grid,
            lam_grid,
            eise_grid,
            jnp.asarray(jnp.nan, dtype),
            zero_i,
            jnp.zeros((), bool),
            jnp.ones((), bool),
        )

    parts = _relaxed_parts(
        gm, grid, grid_labels, grid_counts, method, overlaps=overlaps, info=info, distinct_pairs=True
    )

    relaxed = partial(_relaxed_at, method=method, regularizer=regularizer, ise_scale=ise_scale)
    slopes = partial(_relaxed_slopes_jit, method=method, regularizer=regularizer, ise_scale=ise_scale)
    tau = jnp.asarray(temperature, dtype)
    lam_newton, relaxed_newton, newton_ok, iterations = _newton(
        relaxed,
        (parts, tau, jnp.asarray(alpha, dtype)),
        lam_grid,
        lo,
        hi,
        newton_steps,
        jnp.asarray(tol, dtype),
        tau,
        slopes=slopes,
        differentiable=lambda args: (args[0]._replace(pairs=None), *args[1:]),
    )
    # the clustering depends on λ only through the judgment matrix, and a judgment matrix grows
    # with λ (r_ij = [δ_ij <= s λ]): as many entries as a grid point's means the same matrix
    entries = lambda r: jnp.sum(r.astype(jnp.int32), axis=(-2, -1))  # noqa: E731
    newton_judgment = judgment_matrix(
        delta, jnp.asarray(range_scale, dtype) * lam_newton, gm.mask, triangular=triangular
    )
    same = entries(grid_clusters.judgment) == entries(newton_judgment)  # (G,)
    labels_known = grid_labels[jnp.argmax(same)]
    newton_labels = _cluster_unless_known(
        lambda *a: cluster(*a).labels, jnp.any(same), labels_known, gm, lam_newton, delta, dist, range_scale
    )
    eise_newton, labels_newton, merged_newton, n_newton = evaluate_labels(newton_labels)
    slack = 8 * jnp.finfo(dtype).eps * jnp.abs(eise_grid)  # rounding of an identical clustering
    use_newton = newton_ok & (eise_newton <= eise_grid + slack)
    pick = lambda a, b: jnp.where(use_newton, a, b)  # noqa: E731
    return SearchResult(
        lam=pick(lam_newton, lam_grid),
        eise=pick(eise_newton, eise_grid),
        labels=pick(labels_newton, labels_grid),
        merged=jax.tree_util.tree_map(pick, merged_newton, merged_grid),
        n_clusters=pick(n_newton, n_grid),
        grid=grid,
        grid_eise=grid_eise,
        grid_counts=grid_counts,
        lam_grid=lam_grid,
        eise_grid=eise_grid,
        lam_newton=lam_newton,
        eise_newton=eise_newton,
        relaxed_newton=relaxed_newton,
        iterations=iterations,
        newton_ok=newton_ok,
        used_fallback=~use_newton,
    )
