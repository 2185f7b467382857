"""Seed 001's split decision (eq 31) and its gated principal-axis split (eq 32), traceable.

:func:`~gmjax.split.split_count` gives the split level ``n`` (``N_F = 2^n``) of a component from its degree
of nonlinearity, :func:`~gmjax.split.principal_axis` the largest eigenpair of a covariance with a
deterministic sign, and :func:`~gmjax.split.split_gated` applies eq 32 level by level with per-level
displacements and an on/off gate per level, so that a partial split is differentiable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gmjax import gaussian
from gmjax._types import Array, ArrayLike
from gmjax.mixture import GaussianMixture, sanitize

# ----------------------------------------------------------------------------------------------
# Seed 001: split-decision model (eq 31) and gated principal-axis splitting (eq 32, traceable)
# ----------------------------------------------------------------------------------------------


def split_count(psi: ArrayLike, psi_th: ArrayLike, r: ArrayLike, max_level: int) -> Array:
    """Seed 001 eq 31: the split level ``n`` (``N_F = 2^n``) of a component with DON ``psi``.

    ``n`` is the largest ``1 <= n <= max_level`` with ``psi >= psi_th r^(n-1)`` (so
    ``psi_th r^(n-1) <= psi < psi_th r^n`` gives ``N_F = 2^n``), and ``0`` (no split,
    ``N_F = 1``) when ``psi < psi_th``. The paper's ``n`` is unbounded; ``max_level`` (static)
    caps it. Traceable and broadcasting over ``psi``; ``psi_th = inf`` gives 0.

    Returns:
        int32 array of the broadcast shape of ``psi``.
    """
    if int(max_level) != max_level or max_level < 0:
        raise ValueError(f"max_level: must be a non-negative integer, got {max_level!r}")
    psi = jnp.asarray(psi)
    levels = jnp.arange(1, int(max_level) + 1, dtype=psi.dtype)
    thresholds = jnp.asarray(psi_th, psi.dtype) * jnp.asarray(r, psi.dtype) ** (levels - 1)
    hit = psi[..., None] >= thresholds
    # thresholds increase with n (r >= 1), so the hits are a prefix: count them
    return jnp.sum(jnp.cumprod(hit.astype(jnp.int32), axis=-1), axis=-1).astype(jnp.int32)


def principal_axis(cov: ArrayLike) -> tuple[Array, Array]:
    """``(lambda_max, e_v)`` of a covariance with a deterministic eigenvector sign.

    The sign of ``e_v`` is fixed so that its entry of largest magnitude is positive (the first
    such entry on ties), so that NumPy and JAX references split in the same direction.
    """
    cov = gaussian.symmetrize(jnp.asarray(cov))
    lam, vecs = jnp.linalg.eigh(cov)
    e = vecs[:, -1]
    i = jnp.argmax(jnp.abs(e))
    e = jnp.where(e[i] < 0, -e, e)
    return jnp.maximum(lam[-1], 0.0), e


def split_gated(
    weight: ArrayLike,
    mean: ArrayLike,
    cov: ArrayLike,
    displacements: ArrayLike,
    active: ArrayLike,
    w: ArrayLike = 0.5,
) -> GaussianMixture:
    """Seed 001 eq 32 applied level by level with per-level displacements (traceable).

    Level ``n`` (``n = 1 .. L``, ``L = len(displacements)`` static) splits every current child
    ``N(mu, Sigma)`` that is live into ``omega N(mu + l_n sqrt(lambda) e_v, Sigma - l_n^2 lambda e_v
    e_v^T) + (1 - omega) N(mu - l_n sqrt(lambda) e_v, same)`` along the principal eigenvector of its
    own covariance (:func:`principal_axis`), when ``active[n-1]``; an inactive level leaves the
    children unchanged. With ``l_n = l`` for the first ``n`` levels this is exactly
    :func:`split_principal` with ``n_split = n`` (``N_F = 2^n``, eq 31); a smaller ``l_n`` (e.g.
    ``l`` times a soft gate) gives a partial, differentiable split.

    Args:
        weight: ``()``. mean: ``(d,)``. cov: ``(d, d)``.
        displacements: ``(L,)`` displacement ``l_n`` of each level (``0 <= l_n < 1``).
        active: ``(L,)`` bool, which levels split.
        w: the weight ``omega`` of the ``+`` child (paper: 0.5).

    Returns:
        A mixture of capacity ``2^L``: the children in tree order (child ``c`` of level ``n`` has
        children ``2c`` and ``2c + 1`` at level ``n + 1``; an inactive level keeps ``2c`` and pads
        ``2c + 1``). The live weights sum to ``weight``.
    """
    mean = jnp.asarray(mean)
    dtype = mean.dtype
    cov = jnp.asarray(cov, dtype)
    disp = jnp.asarray(displacements, dtype)
    active = jnp.asarray(active, bool)
    if disp.ndim != 1 or active.shape != disp.shape:
        raise ValueError(
            f"displacements/active: expected two (L,) arrays, got {disp.shape} and {active.shape}"
        )
    d = mean.shape[-1]
    w = jnp.asarray(w, dtype)
    ws = jnp.asarray(weight, dtype)[None]
    ms = mean[None]
    Ps = cov[None]
    live = jnp.ones(1, bool)
    eye = jnp.eye(d, dtype=dtype)
    for n in range(disp.shape[0]):
        ln = disp[n]
        on = active[n]
        safe_P = jnp.where(live[:, None, None], Ps, eye)
        lam, e = jax.vmap(principal_axis)(safe_P)
        a = jnp.sqrt(lam)[:, None] * e  # (c, d): sqrt(lambda) e_v
        child_P = gaussian.symmetrize(Ps - (ln * ln) * jnp.einsum("ci,cj->cij", a, a))
        plus_m = ms + ln * a
        minus_m = ms - ln * a
        # interleave: child 2c is the "+" child (or the parent), 2c + 1 the "-" child (or padding)
        m_new = jnp.stack([jnp.where(on, plus_m, ms), jnp.where(on, minus_m, 0.0)], 1).reshape(-1, d)
        P_new = jnp.stack(
            [jnp.where(on, child_P, Ps), jnp.where(on, child_P, jnp.broadcast_to(eye, Ps.shape))], 1
        ).reshape(-1, d, d)
        w_new = jnp.stack([jnp.where(on, w * ws, ws), jnp.where(on, (1.0 - w) * ws, 0.0)], 1).reshape(-1)
        live = jnp.stack([live, live & on], 1).reshape(-1)
        ws, ms, Ps = w_new, m_new, P_new
    return sanitize(GaussianMixture(jnp.where(live, ws, 0.0), ms, Ps, live))
