"""Greedy pairwise merging: Runnalls (KL bound), Salmond (joining) and West (smallest weight first).

All three repeatedly merge one pair with the moment-preserving merge (seed 002 eqs 70–72) until
``num_out`` components remain or the selected pair's cost exceeds ``threshold``. The loop is a
``lax.fori_loop`` with the static trip count ``K - num_out`` and a "done" flag, so it runs under
``jit``/``vmap`` and is reverse-mode differentiable (the threshold's gradient is 0 almost
everywhere, but finite).

Conventions shared with the NumPy references in ``benchmarks/reference/reduction_np.py``:

* The merged component of the pair ``(i, j)`` goes to slot ``i`` and slot ``j`` is emptied. For
  Runnalls and Salmond ``i < j`` is the first minimiser of the cost over the upper triangle in
  row-major slot order; for West ``i`` is the (first) smallest-weight slot and ``j`` its nearest
  neighbour (first minimiser).
* Merging continues while the selected cost is ``<= threshold`` (``threshold = inf``: to the count).
* ``info.aux["merges"]`` is the ``(K - num_out, 2)`` merge sequence in input slot indices (``-1``
  rows after the last merge), ``info.cost`` the sum of the selected costs.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._pytree import pytree_dataclass, static_field
from gmjax.mixture import GaussianMixture, moments
from gmjax.reduction import _util
from gmjax.reduction._base import ReductionInfo, Stateless, make_info

__all__ = [
    "runnalls",
    "salmond",
    "west",
    "runnalls_cost",
    "salmond_cost",
    "Runnalls",
    "Salmond",
    "West",
]


# ----------------------------------------------------------------------------- pair costs


def runnalls_cost(wi, mi, Pi, wj, mj, Pj, ldi=None, ldj=None):
    """Runnalls' upper bound on the KL discrimination caused by merging ``i`` and ``j``.

    ``B(i, j) = 1/2 [(w_i + w_j) log det P_ij - w_i log det P_i - w_j log det P_j]`` with ``P_ij``
    the moment-merged covariance (Runnalls 2007, IEEE TAES 43(3), Theorem 3 / eq 21). Weights as
    stored; broadcasts over leading axes. ``ldi``/``ldj`` are optional precomputed
    ``log det P_i`` / ``log det P_j``.
    """
    W, _, Pij = _merge_broadcast(wi, mi, Pi, wj, mj, Pj)
    ldi = _util.logdet(Pi) if ldi is None else ldi
    ldj = _util.logdet(Pj) if ldj is None else ldj
    return 0.5 * (W * _util.logdet(Pij) - wi * ldi - wj * ldj)


def _merge_broadcast(wi, mi, Pi, wj, mj, Pj):
    """Broadcasting version of :func:`_util.merge_pair` (weights ``(...)``, means ``(..., d)``)."""
    W = wi + wj
    ok = W > 0
    Ws = jnp.where(ok, W, 1.0)
    l1 = jnp.where(ok, wi / Ws, 0.5)
    l2 = jnp.where(ok, wj / Ws, 0.5)
    diff = mi - mj
    m = l1[..., None] * mi + l2[..., None] * mj
    P = (
        l1[..., None, None] * Pi
        + l2[..., None, None] * Pj
        + (l1 * l2)[..., None, None] * diff[..., :, None] * diff[..., None, :]
    )
    return W, m, 0.5 * (P + jnp.swapaxes(P, -1, -2))


def salmond_cost(wi, mi, wj, mj, Pinv_total):
    """Salmond's joining distance ``D^2 = w_i w_j / (w_i + w_j) (m_i - m_j)^T P^{-1} (m_i - m_j)``.

    ``P`` is the covariance of the whole (normalised) mixture (Salmond 1990, "Mixture reduction
    algorithms for target tracking in clutter", SPIE 1305, the joining algorithm). Moment-preserving
    merges leave ``P`` unchanged, so it is computed once.
    """
    s = wi + wj
    ok = s > 0
    coef = jnp.where(ok, wi * wj / jnp.where(ok, s, 1.0), 0.0)
    diff = mi - mj
    return coef * jnp.einsum("...i,ij,...j->...", diff, Pinv_total, diff)


def west_distance(mi, Pi, mj, Pj, metric: str):
    """West's nearness of component ``j`` to the selected component ``i``.

    ``"kl"``: ``KL(N_i || N_j)``; ``"ise"``: ``ISE(N_i, N_j) = J_ii + J_jj - 2 J_ij`` of the
    unit-weight Gaussians (the ISE-cost variant).
    """
    if metric == "kl":
        return _util.kl_gauss(mi, Pi, mj, Pj)
    jij = jnp.exp(_util.log_gauss(mi, mj, Pi + Pj))
    jii = jnp.exp(_util.log_gauss(mi, mi, 2.0 * Pi))
    jjj = jnp.exp(_util.log_gauss(mj, mj, 2.0 * Pj))
    return jii + jjj - 2.0 * jij


# ----------------------------------------------------------------------------- the greedy loop


class _GState(NamedTuple):
    w: jax.Array
    m: jax.Array
    P: jax.Array
    mask: jax.Array
    labels: jax.Array
    C: jax.Array
    lb: jax.Array
    merges: jax.Array
    total: jax.Array
    n_live: jax.Array


def _greedy(gm, num_out, threshold, select, row_cost):
    """Run ``K - num_out`` guarded merge steps.

    ``select(state) -> (i, j, cost)``; ``row_cost(state, i) -> (K,)`` costs of the new slot ``i``
    against every slot (or None when ``select`` does not use the cost matrix).

    The pair-cost matrix ``C`` is kept "clean" (``+inf`` on and below the diagonal and in the rows
    and columns of dead slots) together with ``lb``, a lower bound of every row minimum, so a step
    costs ``O(K)`` instead of ``O(K^2)`` (see :func:`_upper_argmin`): after a merge only row ``i``
    and column ``i`` change (``lb`` lowered where column ``i`` decreased) and row/column ``j`` die.
    """
    K = gm.capacity
    n_steps = K - num_out
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    ar = jnp.arange(K)
    threshold = jax.lax.stop_gradient(threshold)

    def body(step, s):
        i, j, c, lb = select(s)
        do = (s.n_live > num_out) & (c <= threshold) & jnp.isfinite(c)
        W, mm, PP = _util.merge_pair(s.w[i], s.m[i], s.P[i], s.w[j], s.m[j], s.P[j])
        at_i = (ar == i) & do
        at_j = (ar == j) & do
        w = jnp.where(at_i, W, jnp.where(at_j, 0.0, s.w))
        m = jnp.where(at_i[:, None], mm, jnp.where(at_j[:, None], 0.0, s.m))
        P = jnp.where(at_i[:, None, None], PP, jnp.where(at_j[:, None, None], eye, s.P))
        mask = s.mask & ~at_j
        labels = jnp.where(do & (s.labels == j), i, s.labels)
        C = s.C
        if row_cost is not None:
            s2 = s._replace(w=w, m=m, P=P, mask=mask)
            row = jnp.where(mask & (ar != i), row_cost(s2, i), jnp.inf)
            row_up = jnp.where(ar > i, row, jnp.inf)  # C[i, k], k > i
            col_lo = jnp.where(ar < i, row, jnp.inf)  # C[k, i], k < i
            # out-of-range index + mode="drop" when no merge happens: pure in-place writes
            ii = jnp.where(do, i, K)
            jj = jnp.where(do, j, K)
            inf_row = jnp.full((K,), jnp.inf, C.dtype)
            C = C.at[ii, :].set(row_up, mode="drop").at[:, ii].set(col_lo, mode="drop")
            C = C.at[jj, :].set(inf_row, mode="drop").at[:, jj].set(inf_row, mode="drop")
            lb = jnp.where(do, jnp.minimum(lb, col_lo), lb)
            lb = jnp.where(at_i, jnp.min(row_up), jnp.where(at_j, jnp.inf, lb))
        merges = s.merges.at[step].set(jnp.where(do, jnp.stack([i, j]), -1).astype(jnp.int32))
        return _GState(
            w, m, P, mask, labels, C, lb, merges,
            s.total + jnp.where(do, c, 0.0), s.n_live - do.astype(jnp.int32),
        )

    return body, n_steps


def _clean(C, mask):
    K = C.shape[0]
    upper = jnp.arange(K)[:, None] < jnp.arange(K)[None, :]
    return jnp.where(upper & mask[:, None] & mask[None, :], C, jnp.inf)


def _upper_argmin(s: _GState):
    """The first minimiser of ``C`` in row-major order, from the row lower bounds ``lb``.

    Repeatedly take the row with the smallest bound (lowest index on ties) and tighten its bound to
    the true row minimum; once the chosen row's bound is tight it is the global minimum, and no
    row before it can hold an equal value (its bound would be <= and it would have been chosen),
    so the result equals ``argmin(C.reshape(-1))``. A ``while_loop`` (at most ``K + 1`` rounds);
    returns ``(i, j, cost, lb)``.
    """
    K = s.w.shape[0]
    cost_matrix = s.C

    def cond(c):
        _, _, tight, n = c
        return (~tight) & (n <= K)

    def body(c):
        lb, _, _, n = c
        i = jnp.argmin(lb)
        true = jnp.min(s.C[i, :])
        tight = (true == lb[i]) | jnp.isinf(lb[i])
        return lb.at[i].set(true), i.astype(jnp.int32), tight, n + 1

    # the search only picks indices: it runs on stopped values (a while_loop is not reverse-mode
    # differentiable), and the selected cost is read from the differentiable matrix afterwards
    C = jax.lax.stop_gradient(s.C)
    s = s._replace(C=C)
    lb, i, _, _ = jax.lax.while_loop(
        cond, body,
        (jax.lax.stop_gradient(s.lb), jnp.zeros((), jnp.int32), jnp.asarray(False), jnp.zeros((), jnp.int32)),
    )
    j = jnp.argmin(C[i, :]).astype(jnp.int32)
    return i, j, cost_matrix[i, j], lb


def _init_state(gm, C):
    K = gm.capacity
    n_steps = K
    w = jnp.where(gm.mask, gm.weights, 0.0)
    return _GState(
        w, gm.means, gm.covs, gm.mask, _util.identity_labels(gm), C, jnp.min(C, axis=1),
        jnp.full((max(n_steps, 1), 2), -1, jnp.int32), jnp.zeros((), w.dtype),
        jnp.sum(gm.mask.astype(jnp.int32)),
    )


def _finish(gm, s, n_steps, capacity):
    work = GaussianMixture(s.w, s.m, s.P, s.mask)
    out, labels, overflow, dropped = _util.finalize(gm, work, s.labels, capacity)
    aux = {"merges": s.merges[:n_steps]}
    return out, make_info(gm, out, labels, pruned_mass=dropped, overflow=overflow, cost=s.total, aux=aux)


def _sequential(core):
    """Batch ``core`` under ``vmap`` as a sequential ``lax.map`` (``custom_batching``).

    The O(K)-per-step greedy loop updates single rows and columns of the cost matrix in place;
    a vmapped version turns these into batched scatters over ``(B, K, K)`` and runs several times
    slower than mapping the per-mixture kernel over the batch.

    A ``custom_vmap`` has no differentiation rule, so the sequential kernel is wrapped in a
    ``custom_jvp`` whose rule differentiates ``core`` itself: ``jax.grad`` / ``jax.jacfwd`` work
    (under ``vmap`` the derivative runs batched, the value sequentially).
    """
    seq = jax.custom_batching.sequential_vmap(core)
    fn = jax.custom_jvp(lambda *args: seq(*args))
    fn.defjvp(lambda primals, tangents: jax.jvp(core, primals, tangents))
    return fn


@partial(jax.jit, static_argnames=("num_out", "capacity"))
def _runnalls(gm, num_out, threshold, capacity):
    threshold = jax.lax.stop_gradient(threshold)  # piecewise constant: zero gradient a.e.
    return _sequential(lambda g, t: _runnalls_core(g, num_out, t, capacity))(gm, threshold)


def _runnalls_core(gm, num_out, threshold, capacity):
    w = jnp.where(gm.mask, gm.weights, 0.0)
    ld = _util.logdet(gm.covs)
    C = runnalls_cost(
        w[:, None], gm.means[:, None], gm.covs[:, None], w[None, :], gm.means[None], gm.covs[None],
        ld[:, None], ld[None, :],
    )

    def row_cost(s, i):
        ld = _util.logdet(s.P)
        return runnalls_cost(s.w[i], s.m[i], s.P[i], s.w, s.m, s.P, ld[i], ld)

    body, n_steps = _greedy(gm, num_out, threshold, _upper_argmin, row_cost)
    s = jax.lax.fori_loop(0, n_steps, body, _init_state(gm, _clean(C, gm.mask)))
    return _finish(gm, s, n_steps, capacity)


@partial(jax.jit, static_argnames=("num_out", "capacity"))
def _salmond(gm, num_out, threshold, capacity):
    threshold = jax.lax.stop_gradient(threshold)
    return _sequential(lambda g, t: _salmond_core(g, num_out, t, capacity))(gm, threshold)


def _salmond_core(gm, num_out, threshold, capacity):
    w = jnp.where(gm.mask, gm.weights, 0.0)
    _, Ptot = moments(gm)
    Pinv = _util.inv(Ptot)
    C = salmond_cost(w[:, None], gm.means[:, None], w[None, :], gm.means[None], Pinv)

    def row_cost(s, i):
        return salmond_cost(s.w[i], s.m[i], s.w, s.m, Pinv)

    body, n_steps = _greedy(gm, num_out, threshold, _upper_argmin, row_cost)
    s = jax.lax.fori_loop(0, n_steps, body, _init_state(gm, _clean(C, gm.mask)))
    out, info = _finish(gm, s, n_steps, capacity)
    return out, info


@partial(jax.jit, static_argnames=("num_out", "capacity", "metric", "enhanced"))
def _west(gm, num_out, threshold, capacity, metric, enhanced):
    K = gm.capacity

    def select(s):
        # West (1993) Sec. 2.3: the smallest weight; the "enhanced" variant (Chen, Chang & Smith
        # 2010, Sec. 3.2) ranks by w / det P instead.
        score = s.w / jnp.exp(_util.logdet(s.P)) if enhanced else s.w
        i = jnp.argmin(jnp.where(s.mask, score, jnp.inf)).astype(jnp.int32)
        dist = west_distance(s.m[i], s.P[i], s.m, s.P, metric)
        dist = jnp.where(s.mask & (jnp.arange(K) != i), dist, jnp.inf)
        j = jnp.argmin(dist).astype(jnp.int32)
        return i, j, dist[j], s.lb

    body, n_steps = _greedy(gm, num_out, threshold, select, None)
    s = jax.lax.fori_loop(0, n_steps, body, _init_state(gm, jnp.zeros((1, 1), gm.weights.dtype)))
    return _finish(gm, s, n_steps, capacity)


def _prep(gm, num_out, threshold, capacity):
    _util.validate_mixture(gm)
    num_out = _util.validate_count(num_out, "num_out", 1, gm.capacity)
    cap = _util.validate_capacity(capacity, gm, minimum=num_out)
    _util.validate_nonneg(threshold, "threshold")
    threshold = jnp.asarray(jnp.inf if threshold is None else threshold, gm.weights.dtype)
    return num_out, threshold, cap


def runnalls(
    gm: GaussianMixture,
    num_out: int,
    threshold: Any = None,
    *,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Runnalls' greedy KL-bound reduction (Runnalls 2007; the R-GMR baseline of seed 000).

    Repeatedly merges the pair with the smallest :func:`runnalls_cost` (an upper bound on the KL
    discrimination of the merge) until ``num_out`` components remain or the smallest cost exceeds
    ``threshold``.

    Args:
        gm: input mixture, capacity ``K``.
        num_out: static target count, ``1 <= num_out <= K`` (``1`` with a threshold = threshold only).
        threshold: ``()`` non-negative cost bound (default ``inf``), may be traced.
        capacity: static output capacity ``>= num_out`` (default ``K``).
        key: unused.

    Returns:
        ``(reduced mixture, info)``; ``info.cost`` is the summed bound, ``info.aux["merges"]`` the
        merge sequence.
    """
    del key
    num_out, threshold, cap = _prep(gm, num_out, threshold, capacity)
    return _runnalls(gm, num_out, threshold, cap)


def salmond(
    gm: GaussianMixture,
    num_out: int,
    threshold: Any = None,
    *,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Salmond's joining algorithm (Salmond 1990).

    Repeatedly merges the pair with the smallest :func:`salmond_cost` (weighted squared distance of
    the means in the metric of the whole mixture's covariance) until ``num_out`` remain or the
    smallest distance exceeds ``threshold``. Arguments as in :func:`runnalls`.
    """
    del key
    num_out, threshold, cap = _prep(gm, num_out, threshold, capacity)
    return _salmond(gm, num_out, threshold, cap)


def west(
    gm: GaussianMixture,
    num_out: int,
    threshold: Any = None,
    *,
    metric: str = "kl",
    enhanced: bool = False,
    capacity: int | None = None,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """West's reduction (West 1993, JRSS-B 55(2), Sec. 2.3): merge the smallest-weight component
    with its nearest neighbour, repeatedly.

    "Nearest" is ``KL(N_i || N_j)`` (``metric="kl"``) or the ISE between the two unit-weight
    Gaussians (``metric="ise"``, the ISE-cost variant), following the Tracker Component Library's
    ``WestGaussReduction``. ``enhanced=True`` selects by ``w / det P`` (the enhanced West of Chen,
    Chang & Smith 2010). Merging stops at ``num_out`` components or when the nearest distance exceeds
    ``threshold``. Other arguments as in :func:`runnalls`.
    """
    del key
    if metric not in ("kl", "ise"):
        raise ValueError(f"metric: expected 'kl' or 'ise', got {metric!r}")
    num_out, threshold, cap = _prep(gm, num_out, threshold, capacity)
    return _west(gm, num_out, threshold, cap, metric, bool(enhanced))


# ----------------------------------------------------------------------------- configs


@pytree_dataclass
class Runnalls(Stateless):
    """Reducer config for :func:`runnalls` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return runnalls(gm, self.num_out, self.threshold, capacity=self.capacity, key=key)


@pytree_dataclass
class Salmond(Stateless):
    """Reducer config for :func:`salmond` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return salmond(gm, self.num_out, self.threshold, capacity=self.capacity, key=key)


@pytree_dataclass
class West(Stateless):
    """Reducer config for :func:`west` (``threshold`` dynamic)."""

    num_out: int = static_field(10)
    threshold: Any = float("inf")
    metric: str = static_field("kl")
    enhanced: bool = static_field(False)
    capacity: int | None = static_field(None)

    def __call__(self, gm, *, key=None):
        return west(
            gm, self.num_out, self.threshold, metric=self.metric, enhanced=self.enhanced,
            capacity=self.capacity, key=key,
        )
