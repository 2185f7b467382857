"""The GM-LMB update's posterior density of every track (Reuter, Vo, Vo & Dietmayer 2014, Sec. III-C).

Track ``i``'s posterior is the mixture of its missed-detection density (weight ``beta_i1 / r'_i``) and
its densities updated with each measurement ``z_j`` (weight ``beta_i(1+j) / r'_i``, shared among the
components by ``w_ic q_ic(z_j)``), optionally through a per-track Reducer, then thresholded and cut to
the ``J`` heaviest components. Used by :func:`gmjax.multitarget.lmb.update_tracks`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from gmjax import mixture as gmm
from gmjax._types import Array
from gmjax.mixture import GaussianMixture
from gmjax.multitarget.hypotheses import _log, log_mixture_likelihood

__all__ = ["posterior_density", "reduce_track"]


def posterior_density(
    params: Any,
    tracks: Any,
    r_post: Array,
    beta: Array,
    means: Array,
    covs: Array,
    log_q: Array,
    z_mask: Array,
    n_components: int,
) -> tuple[GaussianMixture, Array]:
    """Steps 6-7 of the spec (``references/lmb_np.py``) for every track at once.

    Args:
        params: the filter's ``LMBParams`` (``reducer``, ``component_threshold``).
        tracks: the predicted ``LMBState``, ``N`` tracks of ``J`` components.
        r_post: ``(N,)`` posterior existence probabilities.
        beta: ``(N, M + 2)`` association marginals (not existing, missed, ``z_1 .. z_M``).
        means, covs, log_q: the pair updates, ``(N, J, M, d)``, ``(N, J, M, d, d)``, ``(N, J, M)``.
        z_mask: ``(M,)`` present measurements.
        n_components: static ``J``, the components kept per track.

    Returns:
        ``(density, reducer_overflow)``: the ``(1 + M) J`` candidates per track, thresholded, the
        ``J`` heaviest kept (ties: lower flat slot) and renormalised, as a track-batched
        ``GaussianMixture``; whether the reducer overflowed on any track.
    """
    dtype = tracks.existence.dtype
    N, J = tracks.density.weights.shape
    M = z_mask.shape[0]
    d = means.shape[-1]
    w = jnp.where(tracks.density.mask, tracks.density.weights, 0.0)
    ok = r_post > 0
    r_safe = jnp.where(ok, r_post, 1.0)
    log_s = log_mixture_likelihood(w, log_q)  # (N, M)
    # w_ic q_icj / sum_c' w_ic' q_ic'j, in the log domain
    valid = (log_q > -jnp.inf) & (log_s > -jnp.inf)[:, None, :] & (w > 0)[:, :, None]
    log_share = jnp.where(
        valid,
        _log(w)[:, :, None] + jnp.where(valid, log_q, 0.0) - jnp.where(valid, log_s[:, None, :], 0.0),
        -jnp.inf,
    )
    missed_w = (beta[:, :1] / r_safe[:, None]) * w  # (N, J)
    det_w = (beta[:, None, 1:] / r_safe[:, None, None]) * jnp.exp(log_share)  # (N, J, M)
    det_live = tracks.density.mask[:, :, None] & z_mask[None, None, :]
    # flat slot b J + c: block 0 missed, block 1 + j detected by z_j
    cand_w = jnp.concatenate([missed_w, jnp.swapaxes(det_w, 1, 2).reshape(N, M * J)], axis=1)
    cand_live = jnp.concatenate([tracks.density.mask, jnp.swapaxes(det_live, 1, 2).reshape(N, M * J)], axis=1)
    cand_means = jnp.concatenate(
        [tracks.density.means, jnp.moveaxis(means, 2, 1).reshape(N, M * J, d)], axis=1
    )
    cand_covs = jnp.concatenate(
        [tracks.density.covs, jnp.moveaxis(covs, 2, 1).reshape(N, M * J, d, d)], axis=1
    )
    reducer_overflow = jnp.zeros((), bool)
    if params.reducer is not None:  # each track's candidates through the reducer (a normalised mixture)
        cand_live = cand_live & ok[:, None] & tracks.mask[:, None]
        cand = jax.vmap(gmm.sanitize)(
            GaussianMixture(jnp.where(cand_live, cand_w, 0.0), cand_means, cand_covs, cand_live)
        )
        reduced, overflow = jax.vmap(lambda g: reduce_track(params.reducer, g, n_components))(cand)
        cand_w, cand_live, cand_means, cand_covs = reduced.weights, reduced.mask, reduced.means, reduced.covs
        reducer_overflow = jnp.any(overflow)
    order = jnp.argsort(jnp.where(cand_live, -cand_w, jnp.inf), axis=1, stable=True)[:, :n_components]
    top_w = jnp.take_along_axis(cand_w, order, axis=1)
    top_live = jnp.take_along_axis(cand_live, order, axis=1)
    passes = top_live & ~(top_w < jnp.asarray(params.component_threshold, dtype))
    keep = passes | (
        top_live & (jnp.arange(n_components) == 0)[None, :] & ~jnp.any(passes, axis=1, keepdims=True)
    )
    keep = keep & ok[:, None] & tracks.mask[:, None]
    kept_w = jnp.where(keep, top_w, 0.0)
    total = jnp.sum(kept_w, axis=1, keepdims=True)
    n_kept = jnp.sum(keep, axis=1, keepdims=True)
    weights = jnp.where(
        keep,
        jnp.where(total > 0, kept_w / jnp.where(total > 0, total, 1.0), 1.0 / jnp.maximum(n_kept, 1)),
        0.0,
    )
    m_out = jnp.where(keep[..., None], jnp.take_along_axis(cand_means, order[..., None], axis=1), 0.0)
    eye = jnp.eye(d, dtype=dtype)
    c_out = jnp.where(
        keep[..., None, None], jnp.take_along_axis(cand_covs, order[..., None, None], axis=1), eye
    )
    return GaussianMixture(weights, m_out, c_out, keep), reducer_overflow


def reduce_track(reducer: Any, gm: GaussianMixture, n_components: int) -> tuple[GaussianMixture, Array]:
    """One track's candidate mixture through a Reducer config (a fresh state, no key), padded to at
    least ``n_components`` slots; ``(reduced, overflow)``."""
    out, _, info = reducer.reduce(gm, reducer.init(gm.capacity), key=None)
    if out.capacity < n_components:
        out = gmm.pad(out, n_components)
    return out, info.overflow
