"""Merging primitives: moment-preserving merge, covariance intersection, and label-wise merging.

Signatures (other modules, e.g. the prune-cluster-merge reducer, import these):

* ``merge_moment(gm) -> (weight (), mean (d,), cov (d, d))`` — moment-preserving merge of all live
  components, weights as stored; ``weight`` is their sum (seed 002 eqs 70–72, seed 003 eqs 16–18).
* ``merge_ci(gm, *, optimize=False, n_steps=10) -> (weight, mean, cov)`` — covariance
  intersection with the normalised weights (seed 000 eqs 38–39, 41), optionally the trace-minimising
  weights of eq 40.
* ``merge_labels(gm, labels, num_out, method="moment" | "ci", *, optimize=False, n_steps=10)
  -> GaussianMixture`` of capacity ``num_out``: merges every cluster of an integer label vector
  (``labels[k]`` in ``[0, num_out)`` or ``-1`` = drop; padded input slots are ignored) with segment
  sums. Output slot ``c`` holds cluster ``c``; empty clusters are padded slots.

All three are traceable, dtype-generic, never produce NaN for padded/empty inputs, and preserve
the total weight exactly (up to rounding of a sum).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._types import Array
from gmjax.mixture import GaussianMixture, sanitize

__all__ = ["merge_moment", "merge_ci", "merge_labels", "ci_trace_weights"]


def _safe_div(num, den, fill=0.0):
    ok = den > 0
    den_b = jnp.where(ok, den, 1.0)
    ok_b = ok.reshape(ok.shape + (1,) * (num.ndim - ok.ndim))
    den_b = den_b.reshape(den_b.shape + (1,) * (num.ndim - den_b.ndim))
    return jnp.where(ok_b, num / den_b, fill)


def merge_moment(gm: GaussianMixture) -> tuple[Array, Array, Array]:
    """Moment-preserving merge of every live component (seed 002 eqs 70–72; seed 003 eqs 16–18).

    ``w_C = sum_i w_i`` (eq 70), ``mu_C = sum_i w_i mu_i / w_C`` (eq 71) and
    ``Sigma_C = sum_i w_i [Sigma_i + (mu_i - mu_C)(mu_i - mu_C)^T] / w_C`` — seed 003 eq 18, which
    equals seed 002 eq 72 but avoids the cancellation of ``E[x x^T] - mu mu^T``.

    Args:
        gm: mixture of capacity ``K``; weights are used as stored (need not sum to 1).

    Returns:
        ``(weight (), mean (d,), cov (d, d))``. With zero total weight the live components are
        averaged with equal weights (and ``weight`` is 0); with no live component the result is
        ``(0, 0, I)``.
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    W = jnp.sum(w)
    n = jnp.sum(gm.mask.astype(w.dtype))
    lam = jnp.where(W > 0, _safe_div(w, W), _safe_div(gm.mask.astype(w.dtype), n))
    mu = lam @ gm.means
    dev = gm.means - mu
    cov = jnp.einsum("k,kij->ij", lam, gm.covs) + jnp.einsum("k,ki,kj->ij", lam, dev, dev)
    cov = 0.5 * (cov + cov.T)
    d = gm.dim
    cov = jnp.where(n > 0, cov, jnp.eye(d, dtype=cov.dtype))
    return W, mu, cov


def _ci_from_lambda(lam, means, covs_inv):
    info = jnp.einsum("k,kij->ij", lam, covs_inv)
    P = gaussian.spd_inv(info)
    P = 0.5 * (P + P.T)
    m = P @ jnp.einsum("k,kij,kj->i", lam, covs_inv, means)
    return m, P


def _project_simplex(x, live):
    """Euclidean projection of ``x`` onto the probability simplex over ``live`` (Duchi et al. 2008)."""
    big = jnp.asarray(-1e30, x.dtype)
    y = jnp.where(live, x, big)
    u = -jnp.sort(-y)
    css = jnp.cumsum(jnp.where(u > big, u, 0.0))
    j = jnp.arange(1, x.shape[0] + 1, dtype=x.dtype)
    cond = (u > big) & (u - (css - 1.0) / j > 0)
    rho = jnp.maximum(jnp.sum(cond.astype(jnp.int32)), 1)
    theta = (css[rho - 1] - 1.0) / rho.astype(x.dtype)
    return jnp.where(live, jnp.maximum(x - theta, 0.0), 0.0)


def ci_trace_weights(lam0: Array, covs_inv: Array, live: Array, n_steps: int = 10) -> Array:
    """Trace-minimising CI weights on the simplex over ``live`` (seed 000 eq 40).

    Minimises ``tr[(sum_j w_j P_j^{-1})^{-1}]`` — eq 40 as printed reads ``[sum_j w_j P_j]^{-1}``,
    which contradicts eqs 36 and 38; we take the trace of the fused covariance of eq 38, the
    standard CI criterion. Each of the ``n_steps`` steps evaluates a projected-gradient step
    (Euclidean projection onto the simplex) for 12 step sizes ``4^{-k} / max|g|`` and a
    Frank–Wolfe step (towards the vertex of steepest descent) for 17 lengths on ``[0, 1]``, and
    keeps the best candidate, the current point included — so the objective never increases. The
    objective is convex in ``w`` (matrix inversion is operator convex).

    Args:
        lam0: ``(K,)`` starting weights on the simplex (0 off ``live``).
        covs_inv: ``(K, d, d)`` inverse covariances.
        live: ``(K,)`` bool, the components that may carry weight.
        n_steps: static number of steps.

    Returns:
        ``(K,)`` weights.
    """
    dtype = lam0.dtype
    fw_grid = jnp.linspace(0.0, 1.0, 17, dtype=dtype)
    pg_grid = 4.0 ** (-jnp.arange(12, dtype=dtype))

    def objective(lam):
        info = jnp.einsum("k,kij->ij", lam, covs_inv)
        return jnp.trace(gaussian.spd_inv(info))

    def step(lam, _):
        g = jax.grad(objective)(lam)
        g = jnp.where(live, g, 0.0)
        gmax = jnp.max(jnp.abs(g))
        t0 = jnp.where(gmax > 0, 1.0 / jnp.where(gmax > 0, gmax, 1.0), 0.0)
        pg = jax.vmap(lambda t: _project_simplex(lam - t * t0 * g, live))(pg_grid)
        j = jnp.argmin(jnp.where(live, g, jnp.inf))
        vertex = jax.nn.one_hot(j, lam.shape[0], dtype=dtype)
        fw = lam[None, :] + fw_grid[:, None] * (vertex - lam)[None, :]
        cands = jnp.concatenate([fw, pg], axis=0)  # fw[0] is the current point
        vals = jax.vmap(objective)(cands)
        vals = jnp.where(jnp.isfinite(vals), vals, jnp.inf)
        return cands[jnp.argmin(vals)], None

    lam, _ = jax.lax.scan(step, lam0, None, length=n_steps)
    return lam


def merge_ci(gm: GaussianMixture, *, optimize: bool = False, n_steps: int = 10) -> tuple[Array, Array, Array]:
    """Covariance-intersection merge of every live component (seed 000 eqs 38–39, 41).

    ``P^{-1} = sum_j w_j P_j^{-1}`` (eq 38), ``u = P sum_j w_j P_j^{-1} u_j`` (eq 39) with the
    normalised weights ``w_j / sum w`` (eq 41 — the paper uses the normalised weights "instead of
    searching for the optimal weighted coefficients"); with ``optimize=True`` the coefficients are
    the trace-minimising weights of eq 40 (see :func:`ci_trace_weights`).

    Args:
        gm: mixture of capacity ``K``; weights used as stored.
        optimize: static; use eq 40 instead of eq 41.
        n_steps: static number of Frank–Wolfe steps for ``optimize``.

    Returns:
        ``(weight (), mean (d,), cov (d, d))``; ``weight`` is the sum of the live weights. With zero
        total weight, equal coefficients are used; with no live component, ``(0, 0, I)``.
    """
    w = jnp.where(gm.mask, gm.weights, 0.0)
    W = jnp.sum(w)
    n = jnp.sum(gm.mask.astype(w.dtype))
    lam = jnp.where(W > 0, _safe_div(w, W), _safe_div(gm.mask.astype(w.dtype), n))
    covs = jnp.where(gm.mask[:, None, None], gm.covs, jnp.eye(gm.dim, dtype=gm.covs.dtype))
    covs_inv = gaussian.spd_inv(covs)
    if optimize:
        live = gm.mask & (lam > 0)
        lam = ci_trace_weights(lam, covs_inv, live, n_steps)
    m, P = _ci_from_lambda(lam, gm.means, covs_inv)
    m = jnp.where(n > 0, m, 0.0)
    P = jnp.where(n > 0, P, jnp.eye(gm.dim, dtype=P.dtype))
    return W, m, P


def merge_labels(
    gm: GaussianMixture,
    labels: jax.Array,
    num_out: int,
    method: str = "moment",
    *,
    optimize: bool = False,
    n_steps: int = 10,
) -> GaussianMixture:
    """Merge every cluster of a label vector into one component (segment sums, no loops).

    Args:
        gm: input mixture, capacity ``K``.
        labels: ``(K,)`` int; ``labels[k]`` in ``[0, num_out)`` is the cluster of slot ``k``; ``-1``
            (or any out-of-range value) drops the slot. Padded slots are ignored whatever their label.
        num_out: static output capacity; output slot ``c`` holds cluster ``c``.
        method: ``"moment"`` (seed 002 eqs 70–72) or ``"ci"`` (seed 000 eqs 38–39 with eq 41
            weights, or eq 40 with ``optimize``).
        optimize: for ``"ci"``, the trace-minimising weights (eq 40).
        n_steps: Frank–Wolfe steps for ``optimize``.

    Returns:
        A :class:`GaussianMixture` of capacity ``num_out``: weight of cluster ``c`` = sum of its
        weights; clusters without live members are padded slots.
    """
    if method not in ("moment", "ci"):
        raise ValueError(f"method: expected 'moment' or 'ci', got {method!r}")
    labels = jnp.asarray(labels, jnp.int32)
    if labels.shape != (gm.capacity,):
        raise ValueError(f"labels: expected shape ({gm.capacity},), got {labels.shape}")
    d = gm.dim
    dtype = gm.means.dtype
    valid = gm.mask & (labels >= 0) & (labels < num_out)
    seg = jnp.where(valid, labels, num_out)  # out-of-range bucket, dropped by the one-hot
    onehot = (seg[:, None] == jnp.arange(num_out)[None, :]).astype(dtype)  # (K, num_out)

    def ssum(x):
        # segment sum as a one-hot contraction: cheap to compile and batches well under vmap
        return jnp.tensordot(onehot, x, axes=((0,), (0,)))

    w = jnp.where(valid, gm.weights, 0.0)
    W = ssum(w)
    count = ssum(valid.astype(dtype))
    out_mask = count > 0
    # per-slot averaging coefficient: w / W_c, or 1 / n_c for a cluster of zero total weight
    Wk = W[jnp.minimum(seg, num_out - 1)]
    nk = count[jnp.minimum(seg, num_out - 1)]
    lam = jnp.where(valid, jnp.where(Wk > 0, _safe_div(w, Wk), _safe_div(jnp.ones_like(w), nk)), 0.0)
    eye = jnp.eye(d, dtype=dtype)
    covs = jnp.where(valid[:, None, None], gm.covs, eye)
    if method == "moment":
        mu = ssum(lam[:, None] * gm.means)
        dev = gm.means - mu[jnp.minimum(seg, num_out - 1)]
        cov = ssum(lam[:, None, None] * (covs + dev[:, :, None] * dev[:, None, :]))
    else:
        covs_inv = gaussian.spd_inv(covs)
        if optimize:
            member = (seg[None, :] == jnp.arange(num_out)[:, None]) & valid[None, :]
            lam_c = jnp.where(member, lam[None, :], 0.0)
            lam_c = jax.vmap(lambda l0, live: ci_trace_weights(l0, covs_inv, live, n_steps))(
                lam_c, member & (lam_c > 0)
            )
            lam = jnp.sum(jnp.where(member, lam_c, 0.0), axis=0)
        info = ssum(lam[:, None, None] * covs_inv)
        info = jnp.where(out_mask[:, None, None], info, eye)
        cov = gaussian.spd_inv(info)
        vec = ssum(lam[:, None] * jnp.einsum("kij,kj->ki", covs_inv, gm.means))
        mu = jnp.einsum("cij,cj->ci", cov, vec)
    cov = 0.5 * (cov + jnp.swapaxes(cov, -1, -2))
    return sanitize(GaussianMixture(W, mu, cov, out_mask))
