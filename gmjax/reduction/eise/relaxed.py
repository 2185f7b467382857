"""The smooth relaxation of the EISE in ``λ`` (soft memberships over a grid of hard clusterings),
built once per search from per-grid-point sums, and its value with first and second derivative by hand."""

from __future__ import annotations

import functools
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture
from gmjax.reduction.eise.ise import (
    _check_options,
    _cluster_sums,
    _sum_over_members,
    onehot_membership,
    penalty,
    self_overlaps,
)

__all__ = ["relaxed_membership", "relaxed_eise"]


def relaxed_membership(
    lam: ArrayLike, grid: Array, grid_labels: Array, temperature: ArrayLike
) -> tuple[Array, Array]:
    """Soft memberships ``A(λ) = Σ_k π_k(λ) A_k`` and the weights ``π(λ)``.

    Args:
        lam: ``()`` confidence multiplier.
        grid: ``(G,)`` grid of ``λ``.
        grid_labels: ``(G, K)`` hard labels at the grid points.
        temperature: ``τ > 0``, in units of ``λ``.
    """
    K = grid_labels.shape[1]
    dtype = grid.dtype
    logits = -0.5 * ((lam - grid) / temperature) ** 2
    pi = jax.nn.softmax(logits)
    A_k = jax.vmap(lambda lab: onehot_membership(lab, K, dtype))(grid_labels)  # (G, K, K)
    return jnp.einsum("g,gkc->kc", pi, A_k), pi


class _RelaxedParts(NamedTuple):
    """The ``λ``-independent parts of one mixture's relaxed EISE over one grid (built once per search).

    Every quantity the relaxation needs is linear (merge statistics) or bilinear (``J_hh``) in the
    soft membership ``A(λ) = Σ_k π_k(λ) A_k``, so it is a ``π``-weighted sum of per-grid-point sums:

    * ``weights`` ``(G, C)``: ``Σ_m [A_k]_mc w_m``;
    * ``first`` ``(G, C, d)`` and ``second`` ``(G, C, d, d)``: for ``"ci"`` ``Σ ω P_m^{-1} u_m`` and
      ``Σ ω P_m^{-1}``; for ``"moment"`` ``Σ ω (u_m - s_c)`` and ``Σ ω (P_m + (u_m - s_c)(u_m - s_c)^T)``
      about the head's mean ``s_c`` (``shift``), which keeps the spread free of cancellation;
    * ``hh`` ``(G, G)``: ``Σ_c (A_k w)_c^T S (A_l w)_c``, so ``Σ_c J_hh,c(λ) = π^T hh π``;
    * ``pairs``: ``J_hr``'s distinct (component, cluster) pairs (:class:`_Pairs`), or ``None`` for
      ``d = 1``.
    """

    gm: GaussianMixture
    grid: Array
    labels: Array
    counts: Array
    weights: Array
    first: Array
    second: Array
    shift: Array
    hh: Array
    pairs: _Pairs | None


class _Pairs(NamedTuple):
    """``J_hr``'s ``G K`` terms ``(g, m)`` pair component ``m`` with the cluster ``l_g(m)`` grid point
    ``g`` puts it in, and the pair's term does not depend on ``g``; neighbouring grid points mostly
    cluster alike, so few pairs are distinct (on the seed 000 4-D system about 7 of 220 on average,
    at most 81 in 10 × 1000). :func:`_over_pairs` evaluates each distinct pair once.

    Attributes:
        member, cluster: ``(n,)`` int32 (``n >= G K``, a whole number of :func:`_pair_chunk`), the
            distinct pairs ``(m, c)`` first (by ``m``, then by the first grid point that makes
            them), then ``(0, 0)``.
        of: ``(G, K)`` int32, the index of pair ``(g, m)`` in ``member`` / ``cluster`` (0 on padding).
        n_distinct: ``()`` int32, the number of distinct pairs.
    """

    member: Array
    cluster: Array
    of: Array
    n_distinct: Array


def _pair_chunk(n_pairs: int, runs: int = 1) -> int:
    """How many pairs :func:`_over_pairs` evaluates at a time: alone, a quarter of a run's
    ``n_pairs = G K``; under ``vmap`` over ``runs`` runs, a sixteenth of all runs' ``n_pairs``
    (the batch's distinct pairs side by side: on the seed 000 4-D system about 3 % of them)."""
    return -(-n_pairs * runs // (4 if runs == 1 else 16))


def _distinct_pairs(labels: Array) -> _Pairs:
    """:class:`_Pairs` of the hard clusterings ``labels`` ``(G, K)`` (``-1`` on padding)."""
    G, K = labels.shape
    chunk = _pair_chunk(G * K)
    size = -(-G * K // chunk) * chunk
    live = labels >= 0
    same = labels[:, None, :] == labels[None, :, :]  # (G, G, K): l_g(m) == l_h(m)
    first = jnp.argmax(same, axis=1)  # (G, K): the first grid point that makes pair (g, m)
    new = live & (first == jnp.arange(G)[:, None])
    number = (jnp.cumsum(new.T.ravel()) - 1).astype(jnp.int32).reshape(K, G).T  # by m, then g
    of = jnp.where(live, jnp.take_along_axis(number, first, axis=0), 0)
    slot = jnp.where(new, number, size)  # out of range: dropped
    members = jnp.broadcast_to(jnp.arange(K, dtype=jnp.int32), (G, K))
    member = jnp.zeros(size, jnp.int32).at[slot].set(members, mode="drop")
    cluster = jnp.zeros(size, jnp.int32).at[slot].set(labels.astype(jnp.int32), mode="drop")
    count = jax.lax.stop_gradient(jnp.sum(new.astype(jnp.int32)))
    return _Pairs(member, cluster, of, count)


def _over_pairs(fn, parts: _RelaxedParts, at_cluster) -> tuple[Array, ...]:
    """``fn(u, P, s)``'s arrays at ``J_hr``'s ``(G, K)`` pairs: component ``(u_m, P_m)`` and ``s``,
    the pytree ``at_cluster`` of per-cluster arrays ``(C, ...)`` at the cluster ``c = l_g(m)``
    (``fn`` elementwise in the pairs, over any leading shape).

    For ``d = 1`` over all ``G K`` pairs at once; otherwise once per distinct pair (:class:`_Pairs`),
    then gathered. Alone, a chunk of :func:`_pair_chunk` pairs at a time for as many chunks as the
    run needs. Under ``vmap`` the distinct pairs of all the batch's runs side by side, in chunks of a
    sixteenth of all runs' pairs (usually one), so that no run evaluates pairs it does not have.
    The same arithmetic on the same inputs, so equal to rounding (XLA may fuse the programs
    differently: a few ulps in ``tests/reduction/eise/test_relaxed.py``'s 2-D cases; on 5 × 1000 captured 4-D
    benchmark searches every result bit-identical). The loops have no reverse mode.
    """
    gm = parts.gm
    if parts.pairs is None:
        at_own = jax.tree_util.tree_map(lambda a: a[jnp.maximum(parts.labels, 0)], at_cluster)
        return fn(gm.means[None], gm.covs[None], at_own)

    def alone(member, cluster, of, count, means, covs, at_cluster):
        chunk = _pair_chunk(of.size)

        def at_chunk(j):
            m = jax.lax.dynamic_slice_in_dim(member, j * chunk, chunk)
            c = jax.lax.dynamic_slice_in_dim(cluster, j * chunk, chunk)
            return fn(means[m], covs[m], jax.tree_util.tree_map(lambda a: a[c], at_cluster))

        def next_chunk(state):
            j, buffers = state
            values = at_chunk(j)
            return j + 1, tuple(
                jax.lax.dynamic_update_slice_in_dim(b, v, j * chunk, 0) for b, v in zip(buffers, values)
            )

        buffers = tuple(jnp.zeros(member.shape + s.shape[1:], s.dtype) for s in jax.eval_shape(at_chunk, 0))
        _, buffers = jax.lax.while_loop(lambda s: s[0] * chunk < count, next_chunk, (0, buffers))
        return tuple(b[of] for b in buffers)

    side_by_side = jax.custom_batching.custom_vmap(alone)

    @side_by_side.def_vmap
    def _batch_rule(axis_size, in_batched, *operands):
        spread = lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))  # noqa: E731
        member, cluster, of, count, means, covs, at_cluster = (
            jax.tree_util.tree_map(spread, a, b) for a, b in zip(operands, in_batched)
        )
        B, size = member.shape
        chunk = _pair_chunk(of.shape[1] * of.shape[2], B)
        ends = jnp.cumsum(count)  # the batch's distinct pairs, run after run
        total = ends[-1] if B else jnp.zeros((), count.dtype)

        def at_chunk(j):  # the batch's pairs j chunk, …, (j + 1) chunk - 1: run r, its pair k
            flat = j * chunk + jnp.arange(chunk, dtype=count.dtype)
            r = jnp.minimum(jnp.searchsorted(ends, flat, side="right"), B - 1)
            k = jnp.clip(flat - (ends[r] - count[r]), 0, size - 1)
            m, c = member[r, k], cluster[r, k]
            s = jax.tree_util.tree_map(lambda a: a[r, c], at_cluster)
            return fn(means[r, m], covs[r, m], s), jnp.where(flat < total, r, B), k  # r = B: dropped

        def next_chunk(state):
            j, buffers = state
            values, r, k = at_chunk(j)
            return j + 1, tuple(b.at[r, k].set(v, mode="drop") for b, v in zip(buffers, values))

        shapes = jax.eval_shape(at_chunk, 0)[0]
        buffers = tuple(jnp.zeros((B, size) + s.shape[1:], s.dtype) for s in shapes)
        _, buffers = jax.lax.while_loop(lambda s: s[0] * chunk < total, next_chunk, (0, buffers))
        out = tuple(jax.vmap(lambda b, o: b[o])(b, of) for b in buffers)
        return out, tuple(True for _ in out)

    pairs = parts.pairs
    return side_by_side(
        pairs.member, pairs.cluster, pairs.of, pairs.n_distinct, gm.means, gm.covs, at_cluster
    )


def _relaxed_parts(
    gm: GaussianMixture,
    grid: Array,
    grid_labels: Array,
    grid_counts: Array,
    method: str,
    *,
    overlaps: Array | None = None,
    info: Array | None = None,
    distinct_pairs: bool = False,
) -> _RelaxedParts:
    """The per-grid-point sums of ``gm``'s hard clusterings ``grid_labels`` ``(G, K)`` at ``grid``
    ``(G,)`` with ``N'`` ``grid_counts`` ``(G,)``; ``overlaps`` and ``info`` as in :func:`hard_eise`.
    ``distinct_pairs``: find ``J_hr``'s distinct pairs (:class:`_Pairs`; for ``d >= 2``: in 1-D the
    gathers cost what they save). The evaluations then loop over them, which has no reverse mode.

    The merge statistics are sums over the members of each cluster (:func:`_cluster_sums`), and
    ``hh[g, h] = Σ_n w_n U_g[l_h(n), n]`` with ``U_g[c, n] = Σ_{m ∈ c} w_m S_mn`` (``l_g(m)`` the
    cluster grid point ``g`` puts ``m`` in), its ``(G, G, K)`` terms ``U_g[l_h(n), n]`` summed
    member by member in slot order: ``O(G² K²)`` selections and additions instead of a one-hot
    product's ``O(G K² C)`` multiply-adds, and no scatter-add into ``U`` (under ``vmap`` on CPU
    that cost several times as much: 24 of 34 µs per mixture, K = 20, 1000 mixtures). Equal to the
    one-hot sums to rounding.
    """
    dtype = gm.means.dtype
    K = gm.capacity
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    labels = jnp.where(gm.mask[None, :], grid_labels, -1)  # (G, K)
    sums = jax.vmap(partial(_cluster_sums, num_clusters=K), in_axes=(None, 0))
    S = self_overlaps(gm) if overlaps is None else overlaps
    own = jnp.maximum(labels, 0)
    wS = w[:, None] * S

    def U_own_term(m):  # member m's part of U[g, l_h(n), n], U[g, c, n] = Σ_{m: l_g(m) = c} w_m S_mn
        return jnp.where(labels[:, None, m, None] == own[None], wS[m][None, None], 0.0)

    U_own = _sum_over_members(U_own_term, K)  # (G, G, K): U[g, l_h(n), n], member by member
    hh = jnp.einsum("ghn,n->gh", jnp.where(labels[None, :, :] >= 0, U_own, 0.0), w)
    if method == "ci":
        info = gaussian.spd_inv(gm.covs) if info is None else info
        w_info = jnp.where(gm.mask[:, None, None], info, 0.0) * w[:, None, None]
        shift = jnp.zeros_like(gm.means)
        first = sums(jnp.einsum("mij,mj->mi", w_info, gm.means), labels)
        second = sums(w_info, labels)
    else:
        shift = jnp.where(gm.mask[:, None], gm.means, 0.0)  # cluster c's head is slot c
        dev = gm.means[None, :, :] - shift[own]  # (G, K, d): u_m - s_c, c = the cluster of m
        wdev = w[None, :, None] * dev
        per_grid_point = jax.vmap(partial(_cluster_sums, num_clusters=K))
        first = per_grid_point(wdev, labels)
        spread = w[None, :, None, None] * gm.covs[None] + wdev[:, :, :, None] * dev[:, :, None, :]
        second = per_grid_point(spread, labels)
    pairs = _distinct_pairs(labels) if distinct_pairs and gm.dim > 1 else None
    return _RelaxedParts(
        gm, grid, grid_labels, grid_counts.astype(dtype), sums(w, labels), first, second, shift, hh, pairs
    )


def _relaxed_value(
    parts: _RelaxedParts,
    lam: ArrayLike,
    *,
    temperature: ArrayLike,
    alpha: ArrayLike,
    method: str,
    regularizer: str,
    ise_scale: float,
) -> Array:
    """The relaxed EISE at ``λ`` from its parts: ``O(G K d²)`` merges and ``G K`` cross terms."""
    gm = parts.gm
    dtype = gm.means.dtype
    d = gm.dim
    eye = jnp.eye(d, dtype=dtype)
    pi = jax.nn.softmax(-0.5 * ((lam - parts.grid) / temperature) ** 2)  # (G,)
    W = pi @ parts.weights  # (C,)
    live = W > 0
    W_safe = jnp.where(live, W, 1.0)
    first = jnp.einsum("g,gci->ci", pi, parts.first) / W_safe[:, None]
    second = jnp.einsum("g,gcij->cij", pi, parts.second) / W_safe[:, None, None]
    if method == "ci":  # seed 000 eqs 38-39 with normalised weights
        cov = gaussian.spd_inv(jnp.where(live[:, None, None], second, eye))
        mu = jnp.einsum("cij,cj->ci", cov, first)
    else:  # seed 003 eqs 16-18, about the head's mean
        mu = parts.shift + first
        cov = gaussian.symmetrize(second - first[:, :, None] * first[:, None, :])
    mu = jnp.where(live[:, None], mu, 0.0)
    cov = jnp.where(live[:, None, None], cov, eye)
    # J_hr: component m against the cluster that grid point k puts it in, weighted by π_k (eq 35)
    own = jnp.maximum(parts.labels, 0)  # (G, K)
    valid = (parts.labels >= 0) & gm.mask[None, :] & live[own]
    (log_cross,) = _over_pairs(lambda u, P, s: (gaussian.spd_logpdf(u, s[0], P + s[1]),), parts, (mu, cov))
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    cross = jnp.exp(jnp.where(valid, log_cross, -jnp.inf)) * W[own] * w[None, :]
    j_hr = pi @ jnp.sum(cross, axis=1)
    j_rr = jnp.sum(jnp.where(live, W * W * jnp.exp(gaussian.spd_logpdf(mu, mu, 2.0 * cov)), 0.0))
    j_hh = pi @ parts.hh @ pi
    n_soft = pi @ parts.counts
    n_ref = jnp.sum(gm.mask.astype(jnp.int32))
    return ise_scale * (j_hh - 2.0 * j_hr + j_rr) + penalty(n_soft, n_ref, alpha, regularizer)


def _relaxed_at(lam, args, *, method: str, regularizer: str, ise_scale: float) -> Array:
    """:func:`_relaxed_value` with its traced arguments ``args = (parts, temperature, alpha)``."""
    parts, temperature, alpha = args
    return _relaxed_value(
        parts,
        lam,
        temperature=temperature,
        alpha=alpha,
        method=method,
        regularizer=regularizer,
        ise_scale=ise_scale,
    )


def _mv(a: Array, x: Array) -> Array:
    """``a @ x`` for ``(..., d, d)`` matrices and ``(..., d)`` vectors."""
    if a.shape[-1] > gaussian._UNROLL_MAX_DIM:
        return jnp.einsum("...ij,...j->...i", a, x)
    return functools.reduce(jnp.add, [a[..., :, k] * x[..., k, None] for k in range(a.shape[-1])])


def _dot(x: Array, y: Array) -> Array:
    """``xᵀ y`` over the last axis."""
    return functools.reduce(jnp.add, [x[..., k] * y[..., k] for k in range(x.shape[-1])])


def _trace_of_product(a: Array, b: Array) -> Array:
    """``tr(a b)`` for ``(..., d, d)`` matrices."""
    return functools.reduce(jnp.add, [_dot(a[..., i, :], b[..., :, i]) for i in range(a.shape[-1])])


# Newton's evaluations of the relaxation run on a whole vmap batch, and its halvings on blocks of the
# runs that need them (_halvings); XLA:CPU hands reductions and dots above some size to other kernels
# (YNNPACK, Eigen), which sum in another order, so a run's value would depend on the batch it is
# evaluated in. The evaluation therefore sums elementwise, left to right (unrolled at trace time),
# except the three π-weighted grid sums, whose dots keep one order from 32 runs up (tests/reduction/eise/test_relaxed.py)
# and are faster than unrolled sums.
def _sum_last(x: Array) -> Array:
    """``Σ_i x[..., i]``, left to right."""
    return functools.reduce(jnp.add, [x[..., i] for i in range(x.shape[-1])])


def _softmax(logits: Array) -> Array:
    """:func:`jax.nn.softmax` over the last axis with its max and sum unrolled."""
    top = functools.reduce(jnp.maximum, [logits[..., i] for i in range(logits.shape[-1])])
    unnormalized = jnp.exp(logits - top[..., None])
    return unnormalized / _sum_last(unnormalized)[..., None]


def _softmax_slopes(pi: Array, a: Array) -> tuple[Array, Array]:
    """``π'`` and ``π''`` of ``π = softmax(l)`` ``(G,)`` with ``l' = a`` and ``l''`` the same for every
    entry (the Gaussian kernel's ``-1/τ²``): ``π' = π (a - ā)``, ``π'' = π ((a - ā)² - Var_π a)``."""
    centred = a - _dot(pi, a)
    return pi * centred, pi * (centred**2 - _dot(pi, centred**2))


def _quotient_slopes(num: Array, den: Array) -> Array:
    """``(3, ...)`` value, first and second derivative of ``num / den`` from those of ``num``
    ``(3, C, ...)`` and of ``den`` ``(3, C)`` (``den[0] > 0``)."""
    den = den.reshape(den.shape + (1,) * (num.ndim - den.ndim))
    q0 = num[0] / den[0]
    q1 = (num[1] - q0 * den[1]) / den[0]
    q2 = (num[2] - 2.0 * q1 * den[1] - q0 * den[2]) / den[0]
    return jnp.stack([q0, q1, q2])


def _penalty_slopes(n: Array, n_ref: Array, alpha: ArrayLike, regularizer: str) -> tuple[Array, Array]:
    """First and second derivative of :func:`penalty` along a path with soft counts ``n`` ``(3,)``
    (value, first and second derivative)."""
    if regularizer == "exp":
        scale = 1.0 / jnp.where(n_ref > 0, n_ref, 1).astype(n.dtype)
        p = alpha * jnp.exp(n[0] * scale)
        return p * n[1] * scale, p * ((n[1] * scale) ** 2 + n[2] * scale)
    positive = n[0] > 0  # penalty() holds lg N' constant (at lg 1) otherwise
    safe = jnp.where(positive, n[0], 1.0)
    r1, r2 = n[1] / safe, n[2] / safe
    return (
        jnp.where(positive, alpha * r1 / jnp.log(10.0), 0.0),
        jnp.where(positive, alpha * (r2 - r1**2) / jnp.log(10.0), 0.0),
    )


def _relaxed_value_and_slopes(
    lam, args, *, method: str, regularizer: str, ise_scale: float
) -> tuple[Array, Array, Array]:
    """Value, first and second derivative in ``λ`` of :func:`_relaxed_at`, derived by hand.

    Forward-over-forward ``jax.jvp`` of the relaxation carries every intermediate through two
    tangent orders; the chain rule through ``π(λ)`` (:func:`_softmax_slopes`) needs only the
    derivatives of the merged clusters ``(W_c, ū_c, P̄_c)`` and, per pair ``(m, c)`` of ``J_hr``
    with ``S = P_m + P̄_c``, ``r = u_m - ū_c``, ``v = S^{-1} r`` and ``ℓ = log N(r; 0, S)``:

    * ``ℓ' = -½ tr(S^{-1} S') + vᵀū' + ½ vᵀ S' v``,
    * ``ℓ'' = -½ tr(S^{-1} S'') + ½ tr(S^{-1} S' S^{-1} S') - zᵀ S^{-1} z + vᵀ ū'' + ½ vᵀ S'' v``
      with ``z = S' v + ū'``,

    and the same with ``S = 2 P̄_c``, ``r = 0`` for ``J_rr``. The value comes with them at little
    cost (the merged clusters and ``ℓ`` are the value's own). Equal to :func:`_relaxed_at` and its
    ``jvp`` derivatives to rounding (``tests/reduction/eise/test_relaxed.py``); Newton's step uses these.
    """
    parts, temperature, alpha = args
    gm = parts.gm
    dtype = gm.means.dtype
    eye = jnp.eye(gm.dim, dtype=dtype)
    t = (lam - parts.grid) / temperature
    pi = _softmax(-0.5 * t**2)
    pis = jnp.stack([pi, *_softmax_slopes(pi, -t / temperature)])  # (3, G): π, π', π''
    W = pis @ parts.weights  # (3, C)
    live = W[0] > 0
    W = W.at[0].set(jnp.where(live, W[0], 1.0))
    first = _quotient_slopes(jnp.einsum("ng,gci->nci", pis, parts.first), W)  # (3, C, d)
    second = _quotient_slopes(jnp.einsum("ng,gcij->ncij", pis, parts.second), W)  # (3, C, d, d)
    if method == "ci":  # P̄ = Q^{-1}: P̄' = -P̄ Q' P̄, P̄'' = -P̄ Q'' P̄ - 2 P̄' Q' P̄; ū = P̄ F
        prec = jnp.where(live[:, None, None], second[0], eye)
        cov = gaussian.spd_inv(prec, fixed_order=True)
        cov1 = -gaussian.small_matmul(cov, gaussian.small_matmul(second[1], cov))
        cov2 = -gaussian.small_matmul(
            cov, gaussian.small_matmul(second[2], cov)
        ) - 2.0 * gaussian.small_matmul(cov1, gaussian.small_matmul(second[1], cov))
        mu = jnp.stack(
            [
                _mv(cov, first[0]),
                _mv(cov1, first[0]) + _mv(cov, first[1]),
                _mv(cov2, first[0]) + 2.0 * _mv(cov1, first[1]) + _mv(cov, first[2]),
            ]
        )
    else:  # ū = s + F, P̄ = Q - F Fᵀ
        outer = lambda a, b: a[:, :, None] * b[:, None, :]  # noqa: E731
        mu = first.at[0].add(parts.shift)
        cov = gaussian.symmetrize(second[0] - outer(first[0], first[0]))
        cov1 = second[1] - outer(first[1], first[0]) - outer(first[0], first[1])
        cov2 = (
            second[2]
            - outer(first[2], first[0])
            - 2.0 * outer(first[1], first[1])
            - outer(first[0], first[2])
        )
        cov = jnp.where(live[:, None, None], cov, eye)
        prec = gaussian.spd_inv(cov, fixed_order=True)
    mu = jnp.where(live[None, :, None], mu, 0.0)
    cov1 = jnp.where(live[:, None, None], cov1, 0.0)
    cov2 = jnp.where(live[:, None, None], cov2, 0.0)
    covs = jnp.stack([jnp.where(live[:, None, None], cov, eye), cov1, cov2])  # (3, C, d, d)
    W = jnp.where(live, W, 0.0)

    # J_rr = Σ_c W_c² N(0; 0, 2 P̄_c): ρ = log N, ρ' = -½ tr(P̄^{-1} P̄'), ρ'' as ℓ'' (S = 2 P̄, r = 0)
    e_rr = jnp.exp(gaussian.spd_logpdf(mu[0], mu[0], 2.0 * covs[0], fixed_order=True))
    pc1 = gaussian.small_matmul(prec, covs[1])
    rho1 = -0.5 * _trace_of_product(prec, covs[1])
    rho2 = -0.5 * _trace_of_product(prec, covs[2]) + 0.5 * _trace_of_product(pc1, pc1)
    W0, W1, W2 = W
    j_rr = _sum_last(e_rr * W0**2)
    j_rr1 = _sum_last(e_rr * (2.0 * W0 * W1 + W0**2 * rho1))
    j_rr2 = _sum_last(e_rr * (2.0 * W1**2 + 2.0 * W0 * W2 + 4.0 * W0 * W1 * rho1 + W0**2 * (rho1**2 + rho2)))

    # J_hr = Σ_k π_k Σ_m w_m W_c N(u_m; ū_c, P_m + P̄_c), c = the cluster grid point k puts m in
    own = jnp.maximum(parts.labels, 0)  # (G, K)
    valid = (parts.labels >= 0) & gm.mask[None, :] & live[own]

    def pair_terms(u, P, s):  # ℓ, ℓ', ℓ'' of component (u, P) against cluster s = (ū, P̄ and slopes)
        (m0, m1, m2), (S0, S1, S2) = s
        S = P + S0
        Si = gaussian.spd_inv(S, fixed_order=True)
        v = _mv(Si, u - m0)
        Si_S1 = gaussian.small_matmul(Si, S1)
        S1_v = _mv(S1, v)
        z = S1_v + m1
        ell1 = -0.5 * _trace_of_product(Si, S1) + _dot(v, m1) + 0.5 * _dot(v, S1_v)
        ell2 = (
            -0.5 * _trace_of_product(Si, S2)
            + 0.5 * _trace_of_product(Si_S1, Si_S1)
            - _dot(z, _mv(Si, z))
            + _dot(v, m2)
            + 0.5 * _dot(v, _mv(S2, v))
        )
        return gaussian.spd_logpdf(u, m0, S, fixed_order=True), ell1, ell2

    log_cross, ell1, ell2 = _over_pairs(pair_terms, parts, (tuple(mu), tuple(covs)))  # (G, K) each
    w = jnp.where(gm.mask, gm.weights, 0.0).astype(dtype)
    e = jnp.exp(jnp.where(valid, log_cross, -jnp.inf)) * w[None, :]
    Wo0, Wo1, Wo2 = W0[own], W1[own], W2[own]
    h0 = _sum_last(e * Wo0)
    h1 = _sum_last(jnp.where(valid, e * (Wo1 + Wo0 * ell1), 0.0))
    h2 = _sum_last(jnp.where(valid, e * (Wo2 + 2.0 * Wo1 * ell1 + Wo0 * (ell1**2 + ell2)), 0.0))
    pi0, pi1, pi2 = pis
    j_hr = _dot(pi0, h0)
    j_hr1 = _dot(pi1, h0) + _dot(pi0, h1)
    j_hr2 = _dot(pi2, h0) + 2.0 * _dot(pi1, h1) + _dot(pi0, h2)

    # J_hh = πᵀ H π (H symmetric)
    hh_pi0, hh_pi1 = _dot(parts.hh, pi0), _dot(parts.hh, pi1)  # (G,): H π, H π'
    j_hh = _dot(pi0, hh_pi0)
    j_hh1 = 2.0 * _dot(pi1, hh_pi0)
    j_hh2 = 2.0 * _dot(pi2, hh_pi0) + 2.0 * _dot(pi1, hh_pi1)

    n_ref = jnp.sum(gm.mask.astype(jnp.int32))
    n_soft = _dot(pis, parts.counts)
    p1, p2 = _penalty_slopes(n_soft, n_ref, alpha, regularizer)
    f = ise_scale * (j_hh - 2.0 * j_hr + j_rr) + penalty(n_soft[0], n_ref, alpha, regularizer)
    g = ise_scale * (j_hh1 - 2.0 * j_hr1 + j_rr1) + p1
    h = ise_scale * (j_hh2 - 2.0 * j_hr2 + j_rr2) + p2
    return f, g, h


# Newton's evaluation, traced once per mixture shape: the search's loops and batch rules trace it
# again and again (a while_loop under vmap traces its body until the batching settles), which a jit
# answers from its cache; the compiled program is the same (XLA inlines the call)
_relaxed_slopes_jit = jax.jit(
    _relaxed_value_and_slopes, static_argnames=("method", "regularizer", "ise_scale")
)


def relaxed_eise(
    lam: ArrayLike,
    gm: GaussianMixture,
    grid: Array,
    grid_labels: Array,
    grid_counts: Array,
    *,
    temperature: ArrayLike,
    alpha: ArrayLike,
    method: str = "ci",
    regularizer: str = "exp",
    ise_scale: float = 0.5,
) -> Array:
    """The smooth relaxation of the EISE at ``λ`` (module docstring); differentiable in ``λ``.

    Equal (to rounding) to :func:`eise` with ``clip=False`` of the soft clusters
    :func:`merge_membership` makes of :func:`relaxed_membership`'s ``A(λ)``, computed from
    ``λ``-independent per-grid-point sums: ``O(G K d²)`` work per ``λ`` instead of the dense
    soft merge's ``O(K² d³)`` (the module docstring's *Cost*).
    """
    _check_options(method, regularizer)
    parts = _relaxed_parts(gm, grid, grid_labels, grid_counts, method)
    args = (parts, temperature, alpha)
    return _relaxed_at(lam, args, method=method, regularizer=regularizer, ise_scale=ise_scale)
