"""Adaptive Gaussian-sum square-root cubature Kalman filter with split-merge (seed 001, AGSSCKF).

One time step of Table 1 is split over the two halves of a :class:`~gmjax.filters.Filter`:

* ``predict(state, t)`` is **Step 7** (eqs 40–41): every posterior component ``j'`` is paired with
  every process-noise component ``l`` (``q`` of them) and propagated by a square-root cubature
  predict (eqs 8–12) with noise ``N(w_l, Q_l)``; weight ``alpha_j' beta_l``; slot
  ``j = l N + j'`` (noise-major, as eq 41 numbers them).
* ``update(state, z, t)`` is **Steps 2–6**:

  - *Step 2–3, adaptive splitting.* While ``N < N_max``: the degree of nonlinearity (DON, eqs 26–29,
    :func:`degree_of_nonlinearity`) of every predicted component is computed from its cubature
    points through ``h(., t)``; the component with the largest DON is split by the split-decision
    model (eq 31, levels below) along the principal eigenvector of its covariance (eq 32,
    :func:`gmjax.split.split_gated`); the loop stops at the first component that is not split.
  - *Step 4*, square-root cubature update of every component (eqs 13–22, 33) and the weights of
    eqs 34–35: ``alpha^{m,f} ∝ p(z | m, f) alpha^m alpha^{m,f}``, i.e. a child's prior weight is its
    parent's weight times its split fraction; normalised in the log domain.
  - *Step 5*, the global estimate (eqs 36–38): the moments of the updated mixture (reported in
    :class:`AGSFInfo`, before Step 6, like :func:`gmjax.filters.gsf.build_gsf`).
  - *Step 6*, pruning and the three merge rules (eq 39), below.

**Split-decision levels (eq 31) and the gate.** For the selected component with DON ``psi``, level
``n = 1 .. max_level`` is *triggered* when ``gate_n = split_gate(psi, psi_th r^(n-1)) > 0`` and all
lower levels are triggered, and when the result still fits: ``N - 1 + 2^n <= min(N_max,
capacity)``. Triggered level ``n`` splits every current child in two with displacement
``l gate_n`` (eq 32 with ``l -> l gate_n``). With the default hard gate ``psi >= threshold``
(``split_gate=None``) this is exactly eq 31: ``N_F = 2^n`` for ``psi_th r^(n-1) <= psi <
psi_th r^n``, capped at ``2^max_level``; a component whose first gate is exactly 0 is not split and
ends the loop (Table 1's ``else end while``). A smooth gate (``gmjax.tune``) makes the split
displacement, hence the filter output, differentiable in ``psi_th``.

**Reading of N_max.** §4 says "N_max = 15 independent SCKFs are used": we read N_max as the largest
number of sub-filters, so a split is limited to the levels that keep ``N <= N_max`` (Table 1
only tests ``N_k < N_max`` before a split). Eq 31's ``n`` is unbounded in the paper; ``max_level``
caps it (default 3, ``N_F <= 8``).

**Capacity policy.** ``capacity`` (default ``N_max``) is the number of working slots of Steps 2–6
(the predicted, split and updated mixture). The posterior after Step 6 is kept in
``capacity // q`` slots, so that the next prediction (``N_{k+1/k} = N_{k/k} q``, eq 40) fits the
working slots. When more components survive Step 6, the heaviest ``capacity // q`` are kept and
renormalised and :attr:`AGSFInfo.truncated` says so (a designed cap, not a failure).

**Step 6, our reading.** The paper gives the three rules in words. "Before and after a time step"
is read as *at the previous time step's Step 6 and now*: every working slot remembers its ancestor
(the posterior slot it descends from through prediction and splitting), and the filter state
carries the previous posterior and the DON of each of its components.

1. *Pruning*: components with weight ``< prune_threshold`` are dropped (the heaviest is always
   kept) and the weights renormalised.
2. *Rule 1* (low weight): a component is *low* when its weight is ``< low_weight`` now and its
   ancestor's weight was ``< low_weight`` at the previous step; two low components are merged. A
   merged pair stays low only while its summed weight is ``< low_weight`` ("merged gradually").
3. *Rule 2* (closely approximate a Gaussian): the pair's weight-normalised Runnalls bound
   ``B_ij / (w_i + w_j)`` (the KL cost of replacing the pair by its moment-matched Gaussian) is
   ``< merge_threshold`` now, and so was their ancestors' at the previous step (0 for two
   descendants of one ancestor, which *was* one Gaussian).
4. *Rule 3* (low nonlinearity): both components have DON ``< merge_don`` now and had (their
   ancestors') DON ``< merge_don`` at the previous step. The paper's threshold is
   ``0.2 psi_th = 0.004``; we keep it as its own field so that ``psi_th = inf`` switches off
   splitting only (a merged component's DON is the larger of the pair's).

Eligible pairs are merged greedily, cheapest (smallest normalised Runnalls bound) first, with the
moment-preserving merge of eq 39 (eq 39 as printed omits the division by ``alpha_j + alpha_j'`` that
makes it moment-preserving; we divide), until no eligible pair remains.

**GSCKF and GSUKF peers.** The paper's GSCKF (Pei et al. 2013) is a Gaussian-sum CKF with its own,
non-adaptive split-merge. We take GSCKF = this engine *without splitting* (``psi_th = inf``): same
sub-filters, same pruning and merging (:func:`build_gsckf`), so the comparison isolates adaptive
splitting and AGSSCKF with ``psi_th = inf`` equals GSCKF exactly. GSUKF is the same engine with UKF
sub-filters (``kappa = 3 - n``, :func:`build_gsukf`).

The measurement noise must be a single Gaussian (as in both examples of §4).

**Loops.** The split loop (at most ``min(N_max, capacity)`` splits) and the merge loop (at most
``capacity - 1`` merges) have static bounds. With the hard gate they are ``lax.while_loop`` s that
exit at the first step with nothing to do (the hard gate has no useful gradient anyway); with a
custom ``split_gate`` they are ``lax.fori_loop`` s with a fixed trip count, so reverse-mode AD
works (``jax.grad`` with respect to ``psi_th``, ``r``, ``l``, ``w``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from gmjax import mixture as gmm
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, PRNGKey
from gmjax.filters._core import Filter, LocalFilter, check_model, is_missing, safe_chol
from gmjax.filters.gsf import local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.models._base import StateSpaceModel
from gmjax.reduction import _util
from gmjax.split import split_gated

__all__ = [
    "AGSFConfig",
    "AGSFState",
    "AGSFPredicted",
    "AGSFInfo",
    "degree_of_nonlinearity",
    "hard_gate",
    "build_agsf",
    "build_gsckf",
    "build_gsukf",
]


@pytree_dataclass
class AGSFConfig:
    """Configuration of :func:`build_agsf` (defaults: seed 001 §4).

    Static fields (changing them recompiles):
        n_max: ``N_max``, the largest number of sub-filters (15).
        capacity: working slots of Steps 2–6 (default ``None`` = ``n_max``); the posterior keeps
            ``capacity // q`` slots (``q`` process-noise components). See the module docstring.
        max_level: the largest ``n`` of eq 31 (``N_F <= 2^max_level``); 0 disables splitting.
        split_gate: ``(psi, threshold) -> gate in [0, 1]``; ``None`` is the hard step
            ``psi >= threshold`` (the paper).

    Traced fields (thresholds; differentiable, no recompilation):
        psi_th: ``psi_threshold`` of eqs 30–31 (0.02). ``inf`` disables splitting (GSCKF).
        r: common ratio of eq 31 (1.5).
        l: displacement of eq 32 (0.5).
        w: weight ``omega`` of eq 32 (0.5).
        prune_threshold: Step 6 pruning weight (1e-4; not given in the paper).
        low_weight: Step 6 rule 1, "low weight" (0.01; not given in the paper).
        merge_threshold: Step 6 rule 2, bound on the normalised Runnalls cost (0.1; not given).
        merge_don: Step 6 rule 3, "tolerable" DON (0.004 = 0.2 psi_th of §3 Step 6).
    """

    n_max: int = static_field(15)
    capacity: int | None = static_field(None)
    max_level: int = static_field(3)
    split_gate: Callable | None = static_field(None)
    psi_th: Any = 0.02
    r: Any = 1.5
    l: Any = 0.5  # noqa: E741
    w: Any = 0.5
    prune_threshold: Any = 1e-4
    low_weight: Any = 0.01
    merge_threshold: Any = 0.1
    merge_don: Any = 0.004


class AGSFState(NamedTuple):
    """Posterior of the AGSSCKF (the ``lax.scan`` carry).

    Attributes:
        mixture: posterior after Step 6, capacity ``capacity // q``.
        don: ``(K,)`` DON of each posterior component (at its Step 2; ``inf`` = unknown, e.g. the
            prior), used by merge rule 3 at the next step.
        key: PRNG key (unused by the algorithm; kept for the Filter protocol).
    """

    mixture: GaussianMixture
    don: Array
    key: PRNGKey


class AGSFPredicted(NamedTuple):
    """After Step 7: the predicted mixture and the history the next Step 6 needs.

    Attributes:
        mixture: predicted mixture, capacity ``capacity`` (working slots).
        parent: ``(capacity,)`` int32, the posterior slot each predicted slot descends from.
        previous: the :class:`AGSFState` it was predicted from ("before the time step").
    """

    mixture: GaussianMixture
    parent: Array
    previous: AGSFState


class AGSFInfo(NamedTuple):
    """Per-step report of :func:`build_agsf`'s update.

    Attributes:
        mean: ``(d,)`` global estimate (eq 36) of the updated mixture, before Step 6.
        cov: ``(d, d)`` its covariance (eqs 37–38).
        loglik: ``()`` ``log p(z_k | z_{1:k-1})`` under the split, predicted mixture.
        n_predicted: ``()`` live components after Step 7 (before splitting).
        n_split: ``()`` number of components split this step (Step 3).
        n_updated: ``()`` live components after splitting (the sub-filters of Step 4).
        n_components: ``()`` live components after Step 6.
        don_max: ``()`` the largest DON of the predicted components (before splitting).
        truncated: ``()`` bool, more than ``capacity // q`` components survived Step 6 (heaviest
            kept).
        repaired: ``()`` bool, a sub-filter repaired a covariance.
        degenerate: ``()`` bool, every likelihood underflowed (weights kept at their prior).
        flags: ``()`` bool, ``repaired | degenerate``.
    """

    mean: Array
    cov: Array
    loglik: Array
    n_predicted: Array
    n_split: Array
    n_updated: Array
    n_components: Array
    don_max: Array
    truncated: Array
    repaired: Array
    degenerate: Array
    flags: Array


# ---------------------------------------------------------------------------------------------
# Degree of nonlinearity (eqs 26–29)


def degree_of_nonlinearity(
    h: Callable[[Array, Array], Array],
    mean: Array,
    cov: Array,
    t: Array = 0,
    *,
    is_chol: bool = False,
) -> Array:
    """DON of one Gaussian component through ``h`` (seed 001 eqs 26–29).

    Cubature points ``X_i = m + S xi_i`` with ``xi = sqrt(d) [I, -I]`` (eq 26, ``S`` the lower
    Cholesky factor), ``X~_i = h(X_i)`` (eq 27),
    ``psi_t = 1/2 || X~_t + X~_{t+d} - 2 h(m) ||^2`` (eq 29) and ``psi = (1/d) sum_t psi_t`` (eq 28).
    Zero for an affine ``h`` (to rounding).

    Args:
        h: ``h(x (d,), t) -> (m,)``.
        mean: ``(d,)``. cov: ``(d, d)`` covariance, or its lower factor if ``is_chol``.
        t: time passed to ``h``.

    Returns:
        ``()`` the DON ``psi >= 0``.
    """
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov, mean.dtype)
    S = cov if is_chol else safe_chol(cov).factor
    d = mean.shape[-1]
    cols = math.sqrt(d) * S.T  # (d, d): row t is sqrt(d) S e_t
    hv = jax.vmap(h, in_axes=(0, None))
    zp = hv(mean[None, :] + cols, t)
    zm = hv(mean[None, :] - cols, t)
    z0 = h(mean, t)
    dev = zp + zm - 2.0 * z0[None, :]
    return jnp.mean(0.5 * jnp.sum(dev * dev, axis=-1))


def hard_gate(psi: Array, threshold: Array) -> Array:
    """The paper's split gate: ``1.0`` where ``psi >= threshold``, else ``0.0`` (eqs 30–31)."""
    return (psi >= threshold).astype(jnp.result_type(psi, float))


# ---------------------------------------------------------------------------------------------
# Step 6 helpers


def _pair_costs(w: Array, m: Array, P: Array) -> Array:
    """``(K, K)`` weight-normalised Runnalls bound ``B_ij / (w_i + w_j)`` of merging ``i`` and ``j``.

    ``= 1/2 [log det P_ij - l_i log det P_i - l_j log det P_j]`` with ``l_i = w_i / (w_i + w_j)``
    and ``P_ij`` the moment-matched covariance; 0 on the diagonal.
    """
    W, _, Pij = jax.vmap(
        jax.vmap(_util.merge_pair, (None, None, None, 0, 0, 0)), (0, 0, 0, None, None, None)
    )(w, m, P, w, m, P)
    ok = W > 0
    Ws = jnp.where(ok, W, 1.0)
    li = jnp.where(ok, w[:, None] / Ws, 0.5)
    lj = jnp.where(ok, w[None, :] / Ws, 0.5)
    ld = _util.logdet(P)
    c = 0.5 * (_util.logdet(Pij) - li * ld[:, None] - lj * ld[None, :])
    K = w.shape[0]
    return jnp.where(jnp.eye(K, dtype=bool), 0.0, jnp.maximum(c, 0.0))


def _bounded_loop(n: int, body: Callable, carry: Any, *, differentiable: bool) -> Any:
    """Run ``carry, go = body(carry)`` at most ``n`` times, stopping after the first ``go = False``.

    ``differentiable=True``: a ``fori_loop`` with a static trip count that keeps running (as a
    no-op) after the stop, so reverse-mode AD works. Otherwise a ``while_loop`` that exits early
    (much faster when splits and merges are rare; forward-mode only).
    """
    if n <= 0:
        return carry
    if differentiable:
        def fbody(_, c):
            carry, go = c
            new, did = body(carry)
            new = jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), new, carry)
            return new, go & did

        return jax.lax.fori_loop(0, n, fbody, (carry, jnp.asarray(True)))[0]

    def cond(c):
        i, _, go = c
        return (i < n) & go

    def wbody(c):
        i, carry, _ = c
        new, did = body(carry)
        return i + 1, new, did

    return jax.lax.while_loop(cond, wbody, (jnp.zeros((), jnp.int32), carry, jnp.asarray(True)))[1]


class _MergeCarry(NamedTuple):
    w: Array
    m: Array
    P: Array
    mask: Array
    parent: Array
    low_before: Array
    low_don: Array
    don: Array
    n_merged: Array


def _merge_step6(
    carry: _MergeCarry, prev_cost: Array, cfg: AGSFConfig, *, differentiable: bool
) -> _MergeCarry:
    """Greedy pairwise merging under rules 1–3 (see the module docstring), at most ``K - 1`` merges."""
    K = carry.w.shape[0]
    ar = jnp.arange(K)
    upper = ar[:, None] < ar[None, :]
    eye = jnp.eye(carry.m.shape[-1], dtype=carry.P.dtype)

    def body(c: _MergeCarry):
        cost = _pair_costs(c.w, c.m, c.P)
        same = c.parent[:, None] == c.parent[None, :]
        before = jnp.where(same, 0.0, prev_cost[c.parent[:, None], c.parent[None, :]])
        low = (c.w < cfg.low_weight) & c.low_before
        rule1 = low[:, None] & low[None, :]
        rule2 = (cost < cfg.merge_threshold) & (before < cfg.merge_threshold)
        rule3 = c.low_don[:, None] & c.low_don[None, :]
        elig = (rule1 | rule2 | rule3) & upper & c.mask[:, None] & c.mask[None, :]
        flat = jnp.where(elig, cost, jnp.inf).reshape(-1)
        k = jnp.argmin(flat)
        do = jnp.isfinite(flat[k])
        i, j = k // K, k % K
        W, mm, PP = _util.merge_pair(c.w[i], c.m[i], c.P[i], c.w[j], c.m[j], c.P[j])
        at_i = (ar == i) & do
        at_j = (ar == j) & do
        heavier = jnp.where(c.w[j] > c.w[i], c.parent[j], c.parent[i])
        return _MergeCarry(
            w=jnp.where(at_i, W, jnp.where(at_j, 0.0, c.w)),
            m=jnp.where(at_i[:, None], mm, jnp.where(at_j[:, None], 0.0, c.m)),
            P=jnp.where(at_i[:, None, None], PP, jnp.where(at_j[:, None, None], eye, c.P)),
            mask=c.mask & ~at_j,
            parent=jnp.where(at_i, heavier, c.parent),
            low_before=jnp.where(at_i, c.low_before[i] & c.low_before[j], c.low_before),
            low_don=jnp.where(at_i, c.low_don[i] & c.low_don[j], c.low_don),
            don=jnp.where(at_i, jnp.maximum(c.don[i], c.don[j]), c.don),
            n_merged=c.n_merged + do.astype(jnp.int32),
        ), do

    return _bounded_loop(K - 1, body, carry, differentiable=differentiable)


def _fit(w, m, P, mask, don, K_post: int):
    """Keep the live slots (in order) in ``K_post`` slots; the heaviest if too many. Renormalised."""
    n_live = jnp.sum(mask.astype(jnp.int32))
    truncated = n_live > K_post
    order_keep = jnp.argsort(~mask, stable=True)[:K_post]
    _, order_top = jax.lax.top_k(jnp.where(mask, w, -jnp.inf), K_post)
    idx = jnp.where(truncated, order_top, order_keep)
    live = mask[idx]
    gm = gmm.sanitize(GaussianMixture(jnp.where(live, w[idx], 0.0), m[idx], P[idx], live))
    return gmm.normalize(gm), jnp.where(live, don[idx], jnp.inf), truncated


# ---------------------------------------------------------------------------------------------
# The filter


def _resolve_local(model: StateSpaceModel, local: LocalFilter | str) -> LocalFilter:
    if isinstance(local, str):
        return local_filter_for(model, local)
    if not isinstance(local, LocalFilter):
        raise ValueError(f"local: expected a LocalFilter or a name, got {type(local).__name__}")
    return local


def _check_config(config: AGSFConfig) -> None:
    if not isinstance(config, AGSFConfig):
        raise ValueError(f"config: expected an AGSFConfig, got {type(config).__name__}")
    if isinstance(config.n_max, bool) or not isinstance(config.n_max, int) or config.n_max < 1:
        raise ValueError(f"config.n_max: must be a positive int, got {config.n_max!r}")
    if not isinstance(config.max_level, int) or config.max_level < 0:
        raise ValueError(f"config.max_level: must be a non-negative int, got {config.max_level!r}")
    if config.capacity is not None and (
        not isinstance(config.capacity, int) or config.capacity < 1
    ):
        raise ValueError(f"config.capacity: must be a positive int or None, got {config.capacity!r}")
    if config.split_gate is not None and not callable(config.split_gate):
        raise ValueError("config.split_gate: must be a callable (psi, threshold) -> gate or None")
    concrete = _util.is_concrete(config.psi_th, config.r, config.l, config.w)
    if concrete:
        if not float(config.psi_th) >= 0:
            raise ValueError(f"config.psi_th: must be >= 0 (inf allowed), got {config.psi_th!r}")
        if not float(config.r) >= 1:
            raise ValueError(f"config.r: eq 31 needs r >= 1, got {config.r!r}")
        if not 0 < float(config.l) < 1:
            raise ValueError(f"config.l: eq 32 needs 0 < l < 1, got {config.l!r}")
        if not 0 < float(config.w) < 1:
            raise ValueError(f"config.w: eq 32 needs 0 < omega < 1, got {config.w!r}")


def build_agsf(
    model: StateSpaceModel,
    config: AGSFConfig = AGSFConfig(),
    *,
    local: LocalFilter | str = "sckf",
) -> Filter:
    """Build the AGSSCKF of seed 001 (Table 1) as a :class:`~gmjax.filters.Filter`.

    Args:
        model: GM prior (eq 23) and GM process noise (eq 24); a single-Gaussian measurement noise.
        config: an :class:`AGSFConfig`.
        local: the sub-filter (default ``"sckf"``, eqs 8–22); ``"ukf"`` / ``"ckf"`` or any
            :class:`LocalFilter` give the GSUKF / GSCKF variants. The DON always uses the cubature
            points of eq 26.

    Returns:
        ``Filter(init, predict, update, moments)``: ``init(prior=None, *, key=None) -> AGSFState``,
        ``predict(AGSFState, t) -> AGSFPredicted``, ``update(state, z, t) -> (AGSFState,
        AGSFInfo)`` (``state`` an :class:`AGSFPredicted`, or an :class:`AGSFState` when no
        prediction precedes), ``moments(state)``.

    Raises:
        ValueError: bad model or config, a multi-component measurement noise, or a capacity that
            cannot hold one posterior component per process-noise component.
    """
    check_model(model)
    _check_config(config)
    local = _resolve_local(model, local)
    rn = model.measurement_noise
    if _util.is_concrete(rn.mask) and int(np.sum(np.asarray(rn.mask))) != 1:
        raise ValueError(
            f"model.measurement_noise: AGSSCKF (seed 001) assumes one Gaussian measurement noise, "
            f"got {int(np.sum(np.asarray(rn.mask)))} components"
        )
    r_mean, r_cov = gmm.moments(rn)
    qn = model.process_noise
    q_logw = gmm.log_weights(qn)
    q_logw = q_logw - logsumexp(q_logw)
    Q = qn.capacity
    C = config.n_max if config.capacity is None else config.capacity
    if C < Q:
        raise ValueError(
            f"config.capacity: {C} working slots cannot hold the {Q} children of one component "
            f"(process noise has {Q} components)"
        )
    K_post = C // Q
    N_lim = min(config.n_max, C)
    L = config.max_level
    gate = hard_gate if config.split_gate is None else config.split_gate
    # the hard gate has zero gradient anyway: loops may exit early (while_loop); a custom gate gets
    # fixed-trip-count loops so that reverse-mode AD reaches psi_th, r, l, w
    differentiable = config.split_gate is not None
    h = model.h
    cfg = config

    def dons(gm: GaussianMixture, t) -> Array:
        eye = jnp.eye(gm.dim, dtype=gm.covs.dtype)
        covs = jnp.where(gm.mask[:, None, None], gm.covs, eye)
        means = jnp.where(gm.mask[:, None], gm.means, 0.0)
        psi = jax.vmap(lambda mu, P: degree_of_nonlinearity(h, mu, P, t))(means, covs)
        return jnp.where(gm.mask, psi, 0.0)

    def init(prior: GaussianMixture | None = None, *, key: PRNGKey | None = None) -> AGSFState:
        prior = model.prior if prior is None else prior
        if not isinstance(prior, GaussianMixture):
            raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
        n_live = gmm.n_active(prior)
        if _util.is_concrete(n_live) and int(n_live) > K_post:
            raise ValueError(
                f"prior: {int(n_live)} live components exceed the posterior capacity {K_post} "
                f"(= capacity {C} // {Q} process-noise components); raise config.capacity"
            )
        fitted = gmm.pad(gmm.normalize(gmm.compact(prior)), max(K_post, prior.capacity))
        fitted = jax.tree_util.tree_map(lambda a: a[:K_post], fitted)
        don = jnp.full((K_post,), jnp.inf, fitted.means.dtype)
        return AGSFState(fitted, don, jax.random.key(0) if key is None else key)

    def predict(state: AGSFState, t: Array) -> AGSFPredicted:
        gm = state.mixture

        def one(mean, cov, qm, qP):
            return local.moments(local.predict(local.init(mean, cov), t, qm, qP))

        # noise-major (eq 41): slot j = l N + j'
        pair = jax.vmap(jax.vmap(one, (0, 0, None, None)), (None, None, 0, 0))
        means, covs = pair(gm.means, gm.covs, qn.means, qn.covs)  # (Q, K, d), (Q, K, d, d)
        log_w = q_logw[:, None] + gmm.log_weights(gm)[None, :]
        mask = qn.mask[:, None] & gm.mask[None, :]
        d = gm.dim
        flat = GaussianMixture(
            jnp.where(mask, jnp.exp(log_w), 0.0).reshape(-1),
            means.reshape(-1, d),
            covs.reshape(-1, d, d),
            mask.reshape(-1),
        )
        flat = gmm.pad(gmm.sanitize(flat), C)
        parent = jnp.concatenate(
            [jnp.tile(jnp.arange(K_post, dtype=jnp.int32), Q), jnp.zeros(C - Q * K_post, jnp.int32)]
        )
        return AGSFPredicted(flat, parent, state)

    def split_stage(gm: GaussianMixture, parent: Array, t, enabled: Array):
        """Steps 2–3: split the most nonlinear component while ``N < N_max``."""
        n_split0 = jnp.zeros((), jnp.int32)
        if L == 0:
            return gm, parent, n_split0
        dtype = gm.means.dtype
        levels = jnp.arange(1, L + 1)
        sizes = 2 ** levels

        def body(carry):
            gm, parent, n_split = carry
            psi_all = jnp.where(gm.mask, dons(gm, t), -jnp.inf)
            m = jnp.argmax(psi_all)
            psi = psi_all[m]
            N = gmm.n_active(gm)
            thresholds = jnp.asarray(cfg.psi_th, dtype) * jnp.asarray(cfg.r, dtype) ** (
                levels - 1
            ).astype(dtype)
            psi_safe = jnp.where(jnp.isfinite(psi), psi, 0.0)
            g = gate(psi_safe, thresholds)
            fits = N - 1 + sizes <= N_lim
            trig = jnp.cumprod(((g > 0) & fits).astype(jnp.int32)).astype(bool)
            do = trig[0] & enabled & jnp.isfinite(psi)
            disp = jnp.asarray(cfg.l, dtype) * jnp.where(trig, g, 0.0)
            kids = split_gated(gm.weights[m], gm.means[m], gm.covs[m], disp, trig, cfg.w)
            # child 0 replaces slot m, the other live children fill free slots in order
            free = jnp.nonzero(~gm.mask, size=C, fill_value=C)[0]
            rank = jnp.cumsum(kids.mask[1:].astype(jnp.int32)) - 1
            dest_rest = jnp.where(kids.mask[1:], free[jnp.clip(rank, 0, C - 1)], C)
            dest = jnp.concatenate([jnp.full((1,), m), dest_rest])
            dest = jnp.where(do, dest, C)
            new = GaussianMixture(
                gm.weights.at[dest].set(kids.weights, mode="drop"),
                gm.means.at[dest].set(kids.means, mode="drop"),
                gm.covs.at[dest].set(kids.covs, mode="drop"),
                gm.mask.at[dest].set(True, mode="drop"),
            )
            parent = parent.at[dest].set(parent[m], mode="drop")
            return (new, parent, n_split + do.astype(jnp.int32)), do

        return _bounded_loop(N_lim, body, (gm, parent, n_split0), differentiable=differentiable)

    def update(state: AGSFPredicted | AGSFState, z: Array, t: Array) -> tuple[AGSFState, AGSFInfo]:
        if isinstance(state, AGSFState):  # no prediction before this update
            parent = jnp.concatenate(
                [jnp.arange(K_post, dtype=jnp.int32), jnp.zeros(C - K_post, jnp.int32)]
            )
            state = AGSFPredicted(gmm.pad(state.mixture, C), parent, state)
        gm, parent, previous = state
        z = jnp.asarray(z)
        missing = is_missing(z)
        n_predicted = gmm.n_active(gm)
        don_max = jnp.max(jnp.where(gm.mask, dons(gm, t), 0.0))

        # Steps 2-3
        gm, parent, n_split = split_stage(gm, parent, t, ~missing)
        don_now = dons(gm, t)

        # Step 4 (eqs 13-22, 33-35)
        def one(mean, cov):
            new, info = local.update(local.init(mean, cov), z, t, r_mean, r_cov)
            mu, P = local.moments(new)
            return mu, P, info.loglik, info.repaired

        means, covs, loglik, repaired = jax.vmap(one)(gm.means, gm.covs)
        log_prior = jnp.where(gm.mask, gmm.log_weights(gm), -jnp.inf)
        log_w = jnp.where(gm.mask, log_prior + jnp.where(missing, 0.0, loglik), -jnp.inf)
        log_norm = logsumexp(log_w)
        degenerate = ~jnp.isfinite(log_norm)
        log_w = jnp.where(degenerate, log_prior, log_w)
        log_w_norm = jnp.where(degenerate, logsumexp(log_prior), log_norm)
        weights = jnp.where(gm.mask, jnp.exp(log_w - log_w_norm), 0.0)
        updated = gmm.sanitize(GaussianMixture(weights, means, covs, gm.mask))

        # Step 5 (eqs 36-38)
        mean, cov = gmm.moments(updated)

        # Step 6: pruning, then rules 1-3 (eq 39)
        w = updated.weights
        heaviest = jnp.arange(C) == jnp.argmax(jnp.where(updated.mask, w, -jnp.inf))
        keep = updated.mask & ((w >= cfg.prune_threshold) | heaviest)
        w = jnp.where(keep, w, 0.0)
        w = w / jnp.sum(w)
        eye = jnp.eye(gm.dim, dtype=covs.dtype)
        pm = previous.mixture
        prev_cost = _pair_costs(pm.weights, pm.means, pm.covs)
        low_before = pm.weights[parent] < cfg.low_weight
        prev_don = previous.don[parent]
        low_don = (don_now < cfg.merge_don) & (prev_don < cfg.merge_don)
        carry = _MergeCarry(
            w=w,
            m=jnp.where(keep[:, None], updated.means, 0.0),
            P=jnp.where(keep[:, None, None], updated.covs, eye),
            mask=keep,
            parent=parent,
            low_before=low_before,
            low_don=low_don,
            don=don_now,
            n_merged=jnp.zeros((), jnp.int32),
        )
        merged = _merge_step6(carry, prev_cost, cfg, differentiable=differentiable)
        post, post_don, truncated = _fit(
            merged.w, merged.m, merged.P, merged.mask, merged.don, K_post
        )
        rep = jnp.any(repaired & gm.mask) & ~missing
        info = AGSFInfo(
            mean=mean,
            cov=cov,
            loglik=jnp.where(missing, 0.0, log_norm),
            n_predicted=n_predicted,
            n_split=n_split,
            n_updated=gmm.n_active(gm),
            n_components=gmm.n_active(post),
            don_max=don_max,
            truncated=truncated,
            repaired=rep,
            degenerate=degenerate,
            flags=rep | degenerate,
        )
        return AGSFState(post, post_don, previous.key), info

    def moments(state: AGSFState | AGSFPredicted) -> tuple[Array, Array]:
        return gmm.moments(state.mixture)

    return Filter(init, predict, update, moments)


def build_gsckf(model: StateSpaceModel, config: AGSFConfig = AGSFConfig()) -> Filter:
    """GSCKF peer of seed 001 Tables 2–3: :func:`build_agsf` with ``psi_th = inf`` (no splitting).

    Same square-root cubature sub-filters, pruning and merge rules as the AGSSCKF (see the module
    docstring for why this reading of the paper's GSCKF).
    """
    return build_agsf(model, dataclasses.replace(config, psi_th=math.inf), local="sckf")


def build_gsukf(model: StateSpaceModel, config: AGSFConfig = AGSFConfig()) -> Filter:
    """GSUKF peer of seed 001 Tables 2–3: the GSCKF engine with UKF sub-filters (``kappa = 3 - n``)."""
    return build_agsf(model, dataclasses.replace(config, psi_th=math.inf), local="ukf")
