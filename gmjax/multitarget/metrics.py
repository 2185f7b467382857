"""Multi-target set metrics: OSPA and GOSPA over padded sets with masks, batched and jit-able.

A set of ``n`` points in ``R^d`` is stored as a padded array ``(N, d)`` with a mask ``(N,)`` (the same
convention as the mixtures, docs/design.md §2), so a batch of sets of different sizes is one array.

Both metrics are a minimum over assignments. We solve it **exactly** with the Hungarian algorithm
(Kuhn–Munkres with potentials and shortest augmenting paths, the ``O(n^3)`` form of Jonker & Volgenant)
written with ``lax.fori_loop`` / ``lax.while_loop`` over a square padded cost matrix of static size
``n = max(N_x, N_y)``: no permutation enumeration, no host callback, so it runs under ``jit`` and
``vmap`` (a batched ``while_loop`` runs until every problem of the batch is solved). The assignment
is computed on stopped values; the metric is the cost of that assignment, so its gradient with
respect to the point locations (and the existence weights of :func:`soft_gospa`) is the gradient of
the minimum where the optimal assignment is unique (envelope theorem).

Padding of the square cost matrix (``c`` the cut-off, ``p`` the order, ``d_c = min(d, c)``):

* OSPA (Schuhmacher, Vo & Vo 2008, eq 3): real–real ``d_c^p``, real–padding ``c^p``, padding–padding 0;
  ``OSPA = (min_cost / max(|X|, |Y|))^(1/p)`` (0 when both sets are empty).
* GOSPA with ``alpha = 2`` (Rahmathullah, García-Fernández & Svensson 2017, eq 2 / Prop. 1):
  real–real ``d_c^p``, real–padding ``c^p / 2``, padding–padding 0; ``GOSPA = min_cost^(1/p)``.
  A real–real pair with ``d >= c`` costs ``c^p`` = one missed plus one false target, so the
  decomposition counts it as such: localisation ``sum d^p`` over pairs with ``d < c``, missed
  ``c^p / 2 · #missed``, false ``c^p / 2 · #false`` (the three add up to ``GOSPA^p``).

A square matrix of side ``max(N_x, N_y)`` suffices for both: an optimal partial matching can be
completed into a perfect one at no extra cost, because pairing two unmatched real points never costs
more than leaving both unmatched.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._types import Array, ArrayLike

__all__ = [
    "linear_sum_assignment",
    "pairwise_distances",
    "ospa",
    "GOSPA",
    "gospa",
    "soft_gospa",
]


def _hungarian(cost: Array) -> Array:
    """Row-to-column assignment minimising ``sum cost[i, col[i]]`` of a square ``(n, n)`` matrix.

    The e-maxx / Jonker–Volgenant form: for each row, a Dijkstra-like search over columns with dual
    potentials ``u, v`` finds a shortest augmenting path (``while_loop``, at most ``n`` steps), then
    the path is flipped (``while_loop``). Slot 0 of ``p``/``way`` is the virtual source column.
    """
    n = cost.shape[0]
    dtype = cost.dtype
    inf = jnp.asarray(jnp.inf, dtype)
    # 1-based with a zero row/col in front, as in the classical formulation
    a = jnp.zeros((n + 1, n + 1), dtype).at[1:, 1:].set(cost)
    cols = jnp.arange(n + 1)
    i32 = jnp.int32

    def add_row(i, carry):
        u, v, p, way = carry
        p = p.at[0].set(i.astype(i32))
        minv = jnp.full(n + 1, inf, dtype)
        used = jnp.zeros(n + 1, bool)

        def search_cond(s):
            p, j0 = s[2], s[5]
            return p[j0] != 0

        def search_body(s):
            u, v, p, way, minv, j0, used = s
            used = used.at[j0].set(True)
            i0 = p[j0]
            cur = a[i0] - u[i0] - v
            better = (~used) & (cur < minv) & (cols > 0)
            minv = jnp.where(better, cur, minv)
            way = jnp.where(better, j0, way).astype(jnp.int32)
            cand = jnp.where((~used) & (cols > 0), minv, inf)
            j1 = jnp.argmin(cand).astype(jnp.int32)
            delta = cand[j1]
            # u[p[j]] += delta for used j; v[j] -= delta for used j; minv[j] -= delta otherwise
            u = u.at[jnp.where(used, p, n + 1)].add(delta, mode="drop")
            v = jnp.where(used, v - delta, v)
            minv = jnp.where(used, minv, minv - delta)
            return u, v, p, way, minv, j1, used

        u, v, p, way, minv, j0, used = jax.lax.while_loop(
            search_cond, search_body, (u, v, p, way, minv, jnp.zeros((), jnp.int32), used)
        )

        def flip_cond(s):
            _, j0 = s
            return j0 != 0

        def flip_body(s):
            p, j0 = s
            j1 = way[j0].astype(jnp.int32)
            return p.at[j0].set(p[j1]), j1

        p, _ = jax.lax.while_loop(flip_cond, flip_body, (p, j0))
        return u, v, p, way

    init = (
        jnp.zeros(n + 1, dtype),
        jnp.zeros(n + 1, dtype),
        jnp.zeros(n + 1, jnp.int32),
        jnp.zeros(n + 1, jnp.int32),
    )
    _, _, p, _ = jax.lax.fori_loop(1, n + 1, add_row, init)
    # p[j] = row assigned to column j (1-based); invert to row -> column (0-based)
    return jnp.zeros(n, jnp.int32).at[p[1:] - 1].set(jnp.arange(n, dtype=jnp.int32))


def linear_sum_assignment(cost: Array) -> Array:
    """Exact minimum-cost perfect assignment of a square ``(n, n)`` cost matrix (jit/vmap-able).

    Args:
        cost: ``(n, n)`` finite costs (``stop_gradient`` is applied: the assignment is a discrete
            choice).

    Returns:
        ``(n,)`` int32, the column assigned to each row (a permutation), as
        ``scipy.optimize.linear_sum_assignment(cost)[1]`` up to ties.
    """
    cost = jax.lax.stop_gradient(jnp.asarray(cost))
    if cost.ndim != 2 or cost.shape[0] != cost.shape[1]:
        raise ValueError(f"cost: expected a square (n, n) matrix, got shape {cost.shape}")
    if cost.shape[0] == 0:
        return jnp.zeros((0,), jnp.int32)
    # shift so the potentials start from small numbers (exact for any finite costs)
    return _hungarian(cost - jnp.min(cost))


def pairwise_distances(x: Array, y: Array) -> Array:
    """``(N_x, N_y)`` Euclidean distances, with a gradient that stays finite at coincident points."""
    diff = x[:, None, :] - y[None, :, :]
    sq = jnp.sum(diff * diff, axis=-1)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _check_set(points, mask, name):
    points = jnp.asarray(points)
    if points.ndim != 2:
        raise ValueError(f"{name}: expected a padded set of shape (N, d), got {points.shape}")
    if mask is None:
        mask = jnp.ones(points.shape[0], bool)
    mask = jnp.asarray(mask, bool)
    if mask.shape != points.shape[:1]:
        raise ValueError(f"{name}_mask: expected shape {points.shape[:1]}, got {mask.shape}")
    return points, mask


def _square(cost_real, x_mask, y_mask, pad_cost):
    """The ``(n, n)`` padded cost matrix (real–real ``cost_real``, real–padding ``pad_cost``)."""
    nx, ny = cost_real.shape
    n = max(nx, ny)
    xm = jnp.zeros(n, bool).at[:nx].set(x_mask)
    ym = jnp.zeros(n, bool).at[:ny].set(y_mask)
    full = jnp.zeros((n, n), cost_real.dtype).at[:nx, :ny].set(cost_real)
    both = xm[:, None] & ym[None, :]
    one = xm[:, None] ^ ym[None, :]
    return jnp.where(both, full, jnp.where(one, pad_cost, 0.0)), xm, ym, both


def _dtype(x, y):
    dt = jnp.result_type(x.dtype, y.dtype)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def ospa(
    x: ArrayLike,
    y: ArrayLike,
    x_mask: ArrayLike | None = None,
    y_mask: ArrayLike | None = None,
    *,
    c: Any = 100.0,
    p: Any = 1.0,
) -> Array:
    """OSPA distance of order ``p`` with cut-off ``c`` between two padded sets.

    Args:
        x: ``(N_x, d)`` estimated points; ``x_mask`` ``(N_x,)`` which rows are points (default all).
        y: ``(N_y, d)`` true points; ``y_mask`` ``(N_y,)``.
        c: cut-off ``> 0`` (may be traced); p: order ``>= 1`` (may be traced).

    Returns:
        ``()`` ``OSPA = ((min_π sum min(d, c)^p + c^p |n_x - n_y|) / max(n_x, n_y))^(1/p)``, 0 for
        two empty sets (Schuhmacher et al. 2008, eq 3). Batch with ``jax.vmap``.
    """
    x, x_mask = _check_set(x, x_mask, "x")
    y, y_mask = _check_set(y, y_mask, "y")
    dt = _dtype(x, y)
    x, y = x.astype(dt), y.astype(dt)
    c_, p_ = jnp.asarray(c, dt), jnp.asarray(p, dt)
    if x.shape[0] == 0 and y.shape[0] == 0:
        return jnp.zeros((), dt)
    dc = jnp.minimum(pairwise_distances(x, y), c_) ** p_
    C, _, _, _ = _square(dc, x_mask, y_mask, c_**p_)
    col = linear_sum_assignment(C)
    total = jnp.sum(C[jnp.arange(C.shape[0]), col])
    n = jnp.maximum(jnp.sum(x_mask), jnp.sum(y_mask)).astype(dt)
    ok = n > 0
    val = jnp.where(ok, total / jnp.where(ok, n, 1.0), 0.0)
    pos = val > 0
    return jnp.where(pos, jnp.where(pos, val, 1.0) ** (1.0 / p_), 0.0)


class GOSPA(NamedTuple):
    """GOSPA (``alpha = 2``) and its decomposition (all ``()``; ``distance^p = sum of the three``).

    Attributes:
        distance: ``GOSPA``.
        localisation: ``sum d(x, y)^p`` over assigned pairs with ``d < c``.
        missed: ``c^p / 2 ·`` the number of missed true points.
        false: ``c^p / 2 ·`` the number of false estimates.
        n_missed, n_false: the counts (floats, so that :func:`soft_gospa` can make them expected counts).
    """

    distance: Array
    localisation: Array
    missed: Array
    false: Array
    n_missed: Array
    n_false: Array


def gospa(
    x: ArrayLike,
    y: ArrayLike,
    x_mask: ArrayLike | None = None,
    y_mask: ArrayLike | None = None,
    *,
    c: Any = 100.0,
    p: Any = 1.0,
) -> GOSPA:
    """GOSPA with ``alpha = 2`` between estimates ``x`` and the truth ``y`` (padded sets).

    Args:
        x: ``(N_x, d)`` estimates; ``x_mask`` ``(N_x,)``.
        y: ``(N_y, d)`` true points; ``y_mask`` ``(N_y,)``.
        c: cut-off ``> 0``; p: order ``>= 1`` (both may be traced).

    Returns:
        :class:`GOSPA` (Rahmathullah et al. 2017, Prop. 1: ``GOSPA^p = sum_assigned d^p +
        c^p/2 (#missed + #false)``). Batch with ``jax.vmap``.
    """
    x, x_mask = _check_set(x, x_mask, "x")
    y, y_mask = _check_set(y, y_mask, "y")
    dt = _dtype(x, y)
    weights = x_mask.astype(dt)
    return _gospa(x.astype(dt), y.astype(dt), x_mask, y_mask, weights, jnp.asarray(c, dt), jnp.asarray(p, dt))


def soft_gospa(
    x: ArrayLike,
    y: ArrayLike,
    existence: ArrayLike,
    y_mask: ArrayLike | None = None,
    *,
    c: Any = 100.0,
    p: Any = 1.0,
) -> GOSPA:
    """GOSPA (``alpha = 2``) of estimates with existence weights ``e_i`` in ``[0, 1]``: differentiable.

    The cost of an assignment ``γ`` of estimates to true points is
    ``sum_{(i,j) in γ} [e_i min(d_ij, c)^p + (1 - e_i) c^p/2] + sum_{i unassigned} e_i c^p/2
    + c^p/2 · #(true points unassigned)``, i.e. the expected GOSPA^p under that assignment when estimate
    ``i`` exists with probability ``e_i``; it is minimised over ``γ`` (an assignment problem with the
    pair cost ``e_i (min(d, c)^p - c^p)``). With 0/1 weights it is :func:`gospa` of the estimates with
    ``e_i = 1`` exactly. The relaxed state extraction of the GM-PHD filter feeds it
    (:func:`gmjax.multitarget.phd.soft_estimates`).

    Args:
        x: ``(N_x, d)`` candidate estimates; existence: ``(N_x,)`` weights in ``[0, 1]`` (0 = absent).
        y: ``(N_y, d)`` true points; ``y_mask`` ``(N_y,)``.
        c, p: as :func:`gospa`.

    Returns:
        :class:`GOSPA` whose counts are expected counts.
    """
    x, _ = _check_set(x, None, "x")
    y, y_mask = _check_set(y, y_mask, "y")
    dt = _dtype(x, y)
    e = jnp.asarray(existence, dt)
    if e.shape != x.shape[:1]:
        raise ValueError(f"existence: expected shape {x.shape[:1]}, got {e.shape}")
    return _gospa(x.astype(dt), y.astype(dt), e > 0, y_mask, e, jnp.asarray(c, dt), jnp.asarray(p, dt))


def _gospa(x, y, x_mask, y_mask, e, c, p) -> GOSPA:
    dt = x.dtype
    e = jnp.where(x_mask, e, 0.0)
    half = c**p / 2.0
    n_true = jnp.sum(y_mask).astype(dt)
    if x.shape[0] == 0 or y.shape[0] == 0:
        n_missed = n_true
        n_false = jnp.sum(e)
        loc = jnp.zeros((), dt)
    else:
        d = pairwise_distances(x, y)
        within = d < c
        dcp = jnp.where(within, jnp.where(within, d, 0.0) ** p, c**p)
        gain = e[:, None] * (dcp - c**p)  # change of cost when pairing (i, j); <= 0
        C, xm, ym, both = _square(gain, x_mask, y_mask, 0.0)
        col = linear_sum_assignment(C)
        nx, ny = d.shape
        rows = jnp.arange(nx)
        col_x = col[:nx]
        paired = x_mask & (col_x < ny)
        paired = paired & jnp.where(paired, y_mask[jnp.minimum(col_x, ny - 1)], False)
        cj = jnp.minimum(col_x, ny - 1)
        pair_within = paired & within[rows, cj]
        # localisation: e_i d^p over pairs within the cut-off
        loc = jnp.sum(jnp.where(pair_within, e * jnp.where(pair_within, dcp[rows, cj], 0.0), 0.0))
        # a pair at distance >= c, or the (1 - e_i) share of a pair, is a missed truth and a false estimate
        matched_truth_mass = jnp.sum(jnp.where(pair_within, e, 0.0))
        n_missed = n_true - matched_truth_mass
        n_false = jnp.sum(e) - matched_truth_mass
    missed = half * n_missed
    false = half * n_false
    total = loc + missed + false
    pos = total > 0
    distance = jnp.where(pos, jnp.where(pos, total, 1.0) ** (1.0 / p), 0.0)
    return GOSPA(distance, loc, missed, false, n_missed, n_false)
