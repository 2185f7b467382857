"""The Gaussian-mixture labeled multi-Bernoulli (GM-LMB) filter (Reuter, Vo, Vo & Dietmayer 2014), batched.

A labeled multi-Bernoulli (LMB) set is a list of tracks; track ``i`` has a label ``l_i`` (here the pair
``(birth step k, birth slot b)``), an existence probability ``r_i`` and a spatial density ``p_i`` (a
Gaussian mixture). S. Reuter, B.-T. Vo, B.-N. Vo & K. Dietmayer, "The labeled multi-Bernoulli filter",
IEEE TSP 62(12), 2014:

* **predict** (Prop. 2, Sec. III-A; no spawning, constant ``P_S``): ``r_i <- P_S r_i`` and every
  component through the local filter's prediction; the **birth** LMB is appended: live slot ``b`` of
  ``params.birth`` is a new track with ``r = birth.weights[b]`` (an existence probability, ``<= 1``),
  the one component ``N(birth.means[b], birth.covs[b])`` and the label ``(k, b)``. The predicted set
  has ``T + B`` track slots (survivors first).
* **update** (Sec. III-B/C): the predicted LMB as a delta-GLMB, updated with the measurement set ``Z``,
  and approximated by an LMB again (matching the first moment). A joint hypothesis gives every track
  ``gamma_i in {0: does not exist, 1: exists and missed, 1 + j: exists and detected by z_j}``, no
  measurement twice; its weight is ``prod_i eta_i(gamma_i)`` with

  ``eta_i(0) = 1 - r_i``, ``eta_i(1) = r_i (1 - P_D)``,
  ``eta_i(1 + j) = r_i P_D sum_c w_ic q_ic(z_j) / kappa(z_j)``

  (``q_ic(z)`` component ``c``'s predicted measurement density, ``kappa = lambda_c c(z)`` the Poisson
  clutter intensity). Then ``r'_i = sum_gamma W(gamma) [gamma_i >= 1]`` and ``p'_i`` is the mixture of
  the missed-detection density (weight ``beta_i1``) and the densities updated with each ``z_j``
  (weights ``beta_i(1+j)``), ``beta_ia = sum_gamma W(gamma) [gamma_i = a]``.
* **truncation**: the sum runs over the distinct hypotheses drawn by a Gibbs sampler with a budget of
  ``n_samples`` rows (Vo, Vo & Hoang 2017, instead of Murty's ranked assignments, as Vo's public LMB
  code does; :mod:`gmjax.multitarget.hypotheses`), weighted exactly and renormalised: exact once every
  hypothesis is drawn (``tests/multitarget/test_lmb.py`` checks it against an enumeration).
* **reduction**: per track, components with weight ``< component_threshold`` are dropped and the
  ``J`` heaviest kept (renormalised; a track whose every component is below the threshold keeps its
  heaviest); tracks with ``r' < existence_threshold`` are dropped and the ``T`` most probable kept, in
  their order (a probable track cut by the capacity raises ``overflow``).
* **state extraction** (Sec. IV): the MAP cardinality of the LMB (Poisson binomial of the ``r``'s),
  then the ``n_hat`` most probable tracks; each estimate is the mean of the track's heaviest component,
  **with its label**, so estimates carry identities from scan to scan
  (:func:`gmjax.multitarget.tracks.ospa2`, :func:`~gmjax.multitarget.tracks.label_switches`).

Numerics: every array is padded (``T`` track slots of ``J`` components, ``T + B`` predicted,
``G = n_samples`` Gibbs rows), so ``jit`` and ``vmap`` go through, and the likelihoods are summed in
the log domain. The sampler's choices are discrete; gradients flow through the exact weights of the
drawn hypotheses to every parameter (``P_D``, ``lambda_c``, noises, birth): the derivative of the
truncated update at the fixed drawn set. ``loglik = log sum_{drawn} prod eta - lambda_c + m_z log
kappa`` is ``log p(Z_k | Z_{1:k-1})`` when every hypothesis is drawn, a lower bound otherwise. The
spec shared with the NumPy reference (``references/lmb_np.py``, whose docstring lists every tie rule)
fixes the order of operations.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs
from gmjax.filters.local import LocalFilter, gaussian_moments, local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.models.base import StateSpaceModel
from gmjax.multitarget._lmb_density import posterior_density
from gmjax.multitarget.hypotheses import (
    _log,
    distinct_rows,
    gibbs_sample,
    gibbs_uniforms,
    hypothesis_marginals,
    log_mixture_likelihood,
)
from gmjax.multitarget.phd import _check_model_and_birth, _check_prob, _fit, _model_noises
from gmjax.multitarget.scans import measurement_mask

__all__ = [
    "LMBParams",
    "LMBState",
    "LMBUpdate",
    "LabeledEstimates",
    "gm_lmb",
    "empty_tracks",
    "predict_tracks",
    "joint_costs",
    "update_tracks",
    "cardinality_pmf",
    "extract_tracks",
]


class LMBParams(NamedTuple):
    """The numeric parameters of a GM-LMB filter (a pytree: vmap, differentiate or tune any leaf).

    Attributes:
        birth: the birth LMB, ``B`` slots: slot ``b`` is a track with existence ``birth.weights[b]``.
        survival_prob, detection_prob: ``()`` ``P_S``, ``P_D``.
        clutter_rate: ``()`` ``lambda_c > 0``; clutter_density: ``()`` ``c(z)``.
        process_noise, measurement_noise: ``(mean, cov)``.
        existence_threshold: ``()`` tracks with ``r' <`` it are dropped.
        component_threshold: ``()`` components with weight ``<`` it are dropped (per track).
        reducer: ``None``, or a Reducer config applied to each track's ``(1 + M) J`` updated
            components before the threshold and the ``J`` heaviest are taken (e.g. Runnalls merging).
    """

    birth: GaussianMixture
    survival_prob: Array
    detection_prob: Array
    clutter_rate: Array
    clutter_density: Array
    process_noise: Any
    measurement_noise: Any
    existence_threshold: Array
    component_threshold: Array
    reducer: Any = None


class LMBState(NamedTuple):
    """A padded LMB set of ``T`` track slots (``T + B`` after a prediction).

    Attributes:
        existence: ``(T,)`` ``r_i`` (0 in an empty slot).
        labels: ``(T, 2)`` int32 ``(birth step, birth slot)``; ``(-1, -1)`` in an empty slot.
        mask: ``(T,)`` bool, which slots hold a track.
        density: the spatial densities, a :class:`~gmjax.mixture.GaussianMixture` with a leading track
            axis: weights ``(T, J)`` (summing to 1 per live track), means ``(T, J, d)``, covs
            ``(T, J, d, d)``, mask ``(T, J)``.
        step: ``()`` int32, the time step of the last prediction (births of step ``k`` are labelled
            ``(k, b)``; 0 at ``init``).
    """

    existence: Array
    labels: Array
    mask: Array
    density: GaussianMixture
    step: Array


class LMBUpdate(NamedTuple):
    """What :func:`update_tracks` returns.

    Attributes:
        tracks: the posterior :class:`LMBState`, ``T`` slots.
        existence: ``(N,)`` ``r'`` of the ``N`` predicted slots (before the track pruning).
        association: ``(N, M + 1)`` ``beta``: missed (column 0), detected by ``z_j`` (column ``j``).
        samples: ``(G, N)`` int32 the Gibbs rows (choices ``gamma``).
        distinct: ``(G,)`` bool, the rows kept (first occurrences).
        loglik: ``()`` the (truncated) log-likelihood of ``Z`` (module docstring).
        overflow: ``()`` bool, a track with ``r' >= existence_threshold`` did not fit in ``T`` slots.
        degenerate: ``()`` bool, every drawn hypothesis has weight 0 (every track is then dropped).
        repaired: ``()`` bool, a local update repaired a covariance.
    """

    tracks: LMBState
    existence: Array
    association: Array
    samples: Array
    distinct: Array
    loglik: Array
    overflow: Array
    degenerate: Array
    repaired: Array


class LabeledEstimates(NamedTuple):
    """Labelled state estimates of one scan.

    Attributes:
        states: ``(E, d)`` (0 where masked). labels: ``(E, 2)`` int32 (``-1`` where masked).
        mask: ``(E,)`` bool. n_estimates: ``()`` int32 ``n_hat`` (may exceed ``E``: ``overflow``).
        overflow: ``()`` bool.
    """

    states: Array
    labels: Array
    mask: Array
    n_estimates: Array
    overflow: Array


# ----------------------------------------------------------------------------- the track set


def empty_tracks(n_tracks: int, n_components: int, dim: int, dtype: Any = None) -> LMBState:
    """An LMB set with no track: ``n_tracks`` slots of ``n_components`` components in ``dim`` dims."""
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    eye = jnp.broadcast_to(jnp.eye(dim, dtype=dtype), (n_tracks, n_components, dim, dim))
    density = GaussianMixture(
        jnp.zeros((n_tracks, n_components), dtype),
        jnp.zeros((n_tracks, n_components, dim), dtype),
        eye,
        jnp.zeros((n_tracks, n_components), bool),
    )
    return LMBState(
        jnp.zeros(n_tracks, dtype),
        jnp.full((n_tracks, 2), -1, jnp.int32),
        jnp.zeros(n_tracks, bool),
        density,
        jnp.zeros((), jnp.int32),
    )


def _tracks_local(local: LocalFilter, density: GaussianMixture):
    return jax.vmap(jax.vmap(local.init))(density.means, density.covs)


def predict_tracks(local: LocalFilter, params: LMBParams, tracks: LMBState, t: Array) -> LMBState:
    """Survivors (``r <- P_S r``, components predicted) then the ``B`` births labelled ``(k, b)``,
    ``k = tracks.step + 1``: ``T + B`` slots (Reuter et al. 2014, Prop. 2)."""
    dtype = tracks.existence.dtype
    q_mean, q_cov = gaussian_moments(params.process_noise)
    states = _tracks_local(local, tracks.density)
    pred = jax.vmap(jax.vmap(lambda s: local.predict(s, t, q_mean, q_cov)))(states)
    means, covs = jax.vmap(jax.vmap(local.moments))(pred)
    cmask = tracks.density.mask
    d = means.shape[-1]
    means = jnp.where(cmask[..., None], means, 0.0)
    covs = jnp.where(cmask[..., None, None], covs, jnp.eye(d, dtype=covs.dtype))
    r = jnp.where(tracks.mask, tracks.existence * jnp.asarray(params.survival_prob, dtype), 0.0)

    step = tracks.step + 1
    birth = params.birth
    B, J = birth.capacity, cmask.shape[-1]
    first = jnp.arange(J) == 0
    b_cmask = birth.mask[:, None] & first[None, :]
    b_density = GaussianMixture(
        jnp.where(b_cmask, 1.0, 0.0).astype(dtype),
        jnp.where(b_cmask[..., None], birth.means[:, None, :], 0.0).astype(dtype),
        jnp.where(b_cmask[..., None, None], birth.covs[:, None], jnp.eye(d, dtype=dtype)).astype(dtype),
        b_cmask,
    )
    b_labels = jnp.stack([jnp.full(B, step, jnp.int32), jnp.arange(B, dtype=jnp.int32)], axis=1)
    density = jax.tree_util.tree_map(
        lambda a, b: jnp.concatenate([a, b]),
        GaussianMixture(tracks.density.weights, means, covs, cmask),
        b_density,
    )
    return LMBState(
        jnp.concatenate([r, jnp.where(birth.mask, birth.weights, 0.0).astype(dtype)]),
        jnp.concatenate([tracks.labels, jnp.where(birth.mask[:, None], b_labels, -1)]),
        jnp.concatenate([tracks.mask, birth.mask]),
        density,
        step,
    )


# ----------------------------------------------------------------------------- the update


def _pair_updates(local: LocalFilter, params: LMBParams, tracks: LMBState, zs: Array, t: Array):
    """Every component of every track updated with every measurement: means ``(N, J, M, d)``, covs
    ``(N, J, M, d, d)``, ``log q`` ``(N, J, M)`` (``-inf`` for an empty component or an absent ``z``)
    and whether a live pair was repaired."""
    r_mean, r_cov = gaussian_moments(params.measurement_noise)
    z_mask = measurement_mask(zs)
    zs_safe = jnp.where(z_mask[:, None], zs, 0.0)
    states = _tracks_local(local, tracks.density)

    def one(s):
        return jax.vmap(lambda z: local.update(s, z, t, r_mean, r_cov))(zs_safe)

    upd, info = jax.vmap(jax.vmap(one))(states)
    means, covs = jax.vmap(jax.vmap(jax.vmap(local.moments)))(upd)
    live = tracks.density.mask[:, :, None] & z_mask[None, None, :] & tracks.mask[:, None, None]
    log_q = jnp.where(live, info.loglik, -jnp.inf)
    return means, covs, log_q, jnp.any(live & info.repaired)


def joint_costs(params: LMBParams, tracks: LMBState, log_q: Array, z_mask: Array) -> Array:
    """``(N, M + 2)`` ``log eta_i(a)``: not existing, missed, detected by ``z_1 .. z_M`` (module
    docstring), from the components' ``log q`` ``(N, J, M)``; an empty slot is ``[0, -inf, ...]``, an
    absent ``z_j`` is ``-inf``."""
    dtype = tracks.existence.dtype
    r = tracks.existence
    p_d = jnp.asarray(params.detection_prob, dtype)
    log_kappa = jnp.log(jnp.asarray(params.clutter_rate, dtype) * jnp.asarray(params.clutter_density, dtype))
    w = jnp.where(tracks.density.mask, tracks.density.weights, 0.0)
    log_s = log_mixture_likelihood(w, log_q)
    valid = z_mask[None, :] & (log_s > -jnp.inf) & (r > 0)[:, None]
    detect = jnp.where(
        valid, _log(r)[:, None] + jnp.log(p_d) + jnp.where(valid, log_s, 0.0) - log_kappa, -jnp.inf
    )
    cost = jnp.concatenate([_log(1.0 - r)[:, None], _log(r * (1.0 - p_d))[:, None], detect], axis=1)
    empty = jnp.concatenate([jnp.zeros((1,), dtype), jnp.full((cost.shape[1] - 1,), -jnp.inf, dtype)])
    return jnp.where(tracks.mask[:, None], cost, empty[None, :])


def update_tracks(
    local: LocalFilter,
    params: LMBParams,
    tracks: LMBState,
    zs: Array,
    t: Array,
    uniforms: Array,
    *,
    n_tracks: int,
) -> LMBUpdate:
    """The GM-LMB update (module docstring) of the ``N`` predicted tracks with ``zs`` ``(M, m)``.

    Args:
        local: the component filter.
        params: :class:`LMBParams`.
        tracks: the predicted set (``N`` slots of ``J`` components).
        zs: ``(M, m)`` measurements; a row with a non-finite entry is absent.
        t: the step's time.
        uniforms: ``(G - 1, N)`` in ``[0, 1)``, the Gibbs sampler's draws.
        n_tracks: static ``T``, the posterior's track slots.
    """
    dtype = tracks.existence.dtype
    N, J = tracks.density.weights.shape
    z_mask = measurement_mask(zs)
    means, covs, log_q, repaired = _pair_updates(local, params, tracks, zs, t)
    log_eta = joint_costs(params, tracks, log_q, z_mask)
    samples = gibbs_sample(log_eta, tracks.mask, uniforms)
    distinct = distinct_rows(samples)

    _, r_post, beta, log_norm = hypothesis_marginals(log_eta, samples, distinct)
    feasible = log_norm > -jnp.inf

    density, reducer_overflow = posterior_density(params, tracks, r_post, beta, means, covs, log_q, z_mask, J)
    live = tracks.mask & (r_post > 0)
    cand = live & ~(r_post < jnp.asarray(params.existence_threshold, dtype))
    order = jnp.argsort(jnp.where(cand, -r_post, jnp.inf), stable=True)
    T = n_tracks
    if T < N:
        best = order[:T]
    else:
        best = jnp.concatenate([order, jnp.full((T - N,), N, order.dtype)])
    best_ok = (best < N) & cand[jnp.minimum(best, N - 1)]
    chosen = jnp.sort(jnp.where(best_ok, best, N))  # original order, empty slots last
    valid = chosen < N
    idx = jnp.minimum(chosen, N - 1)
    empty = empty_tracks(T, J, means.shape[-1], dtype)
    pick = lambda a, e: jnp.where(valid.reshape((-1,) + (1,) * (e.ndim - 1)), a[idx], e)  # noqa: E731
    post_density = jax.tree_util.tree_map(pick, density, empty.density)
    post = LMBState(
        pick(r_post, empty.existence),
        pick(tracks.labels, empty.labels),
        valid,
        post_density,
        tracks.step,
    )
    overflow = (jnp.sum(cand) > T) | reducer_overflow
    n_z = jnp.sum(z_mask).astype(dtype)
    lam = jnp.asarray(params.clutter_rate, dtype)
    log_kappa = jnp.log(lam * jnp.asarray(params.clutter_density, dtype))
    loglik = jnp.where(feasible, log_norm - lam + n_z * log_kappa, -jnp.inf)
    return LMBUpdate(post, r_post, beta, samples, distinct, loglik, overflow, ~feasible, repaired)


# ----------------------------------------------------------------------------- extraction


def cardinality_pmf(existence: Array, mask: Array) -> Array:
    """``(T + 1,)`` the cardinality pmf of an LMB set (Poisson binomial of the live ``r``'s)."""
    T = existence.shape[0]
    rho0 = jnp.zeros(T + 1, existence.dtype).at[0].set(1.0)

    def add(rho, r_live):
        r, live = r_live
        shifted = jnp.concatenate([jnp.zeros((1,), rho.dtype), rho[:-1]])
        return jnp.where(live, rho * (1.0 - r) + shifted * r, rho), None

    rho, _ = jax.lax.scan(add, rho0, (existence, mask))
    return rho


def extract_tracks(tracks: LMBState, *, max_estimates: int) -> LabeledEstimates:
    """Reuter et al. 2014, Sec. IV: the MAP cardinality ``n_hat`` (smallest on ties), then the
    ``n_hat`` most probable tracks (ties: lower slot first), each the mean of its heaviest component
    (slot 0) with its label, in decreasing ``r``."""
    rho = cardinality_pmf(tracks.existence, tracks.mask)
    n_hat = jnp.argmax(rho).astype(jnp.int32)
    order = jnp.argsort(jnp.where(tracks.mask, -tracks.existence, jnp.inf), stable=True)
    T = tracks.existence.shape[0]
    slot = jnp.arange(max_estimates)
    mask = slot < jnp.minimum(n_hat, jnp.sum(tracks.mask))
    idx = order[jnp.minimum(slot, T - 1)]
    states = jnp.where(mask[:, None], tracks.density.means[idx, 0], 0.0)
    labels = jnp.where(mask[:, None], tracks.labels[idx], -1)
    return LabeledEstimates(states, labels, mask, n_hat, n_hat > max_estimates)


# ----------------------------------------------------------------------------- the filter


def gm_lmb(
    model: StateSpaceModel,
    *,
    birth: GaussianMixture,
    survival_prob: float = 0.99,
    detection_prob: float = 0.98,
    clutter_rate: float = 10.0,
    clutter_density: float,
    capacity: int = 100,
    components_per_track: int = 10,
    n_samples: int = 1000,
    existence_threshold: float = 1e-3,
    component_threshold: float = 1e-5,
    max_estimates: int | None = None,
    local: str = "kf",
    local_kwargs: dict | None = None,
    reducer: Any = None,
) -> Filter:
    """Build a GM-LMB filter (Reuter, Vo, Vo & Dietmayer 2014) as a :class:`~gmjax.filters.Filter`.

    The arguments shared with :func:`gmjax.multitarget.gm_phd` mean the same (so
    ``gm_lmb(model, **scenario.filter_kwargs())`` works); the birth weights are the birth tracks'
    existence probabilities.

    Args:
        model: the single-target model (``f``, ``h``, noises; ``model.prior`` is not used).
        birth: the birth LMB, ``B`` slots with weights in ``[0, 1]``.
        survival_prob, detection_prob: ``P_S``, ``P_D`` in ``(0, 1]``.
        clutter_rate: ``lambda_c > 0``; clutter_density: ``c(z) > 0`` (``1 / V`` for uniform clutter).
        capacity: static ``T``, the track slots.
        components_per_track: static ``J``, each track's mixture slots.
        n_samples: static ``G >= 1``, the Gibbs sampler's rows per update (the hypothesis budget).
        existence_threshold, component_threshold: the pruning thresholds (module docstring).
        max_estimates: static ``E``, the capacity of the estimate set (default ``T``).
        local: the component filter (:data:`gmjax.filters.local.LOCAL_FILTERS`); local_kwargs: its
            options.
        reducer: ``None`` (default: each track keeps its ``J`` heaviest components above
            ``component_threshold``, as the reference does), or any Reducer config (e.g.
            ``reduction.Runnalls(num_out=J)``) applied per track to its ``(1 + M) J`` updated
            components first; its thresholds are traced leaves of ``params.reducer``.

    Returns:
        ``Filter(init, predict, update, params)`` with ``params`` an :class:`LMBParams` and states
        :class:`LMBState`. ``update`` needs a ``key`` (the sampler's draws: pass ``key=`` to
        :func:`gmjax.multitarget.run`) unless ``n_samples == 1``; it takes a padded measurement set
        ``(M, m)`` (NaN rows absent) and returns a :class:`StepInfo` with ``mean``/``cov`` the moments
        of the ``r``-weighted union of the track densities, ``loglik`` (:class:`LMBUpdate`),
        ``n_components`` (live components over all tracks), ``flags`` (``overflow``: a probable track
        cut by ``T``, a reducer that overflowed, or more estimates than ``E``; ``repaired``;
        ``degenerate``: no drawn hypothesis with positive weight; ``nonfinite_measurement``), and
        ``extra``: ``cardinality`` (``sum r``),
        ``cardinality_variance`` (``sum r (1 - r)``), ``cardinality_map``, ``n_tracks``,
        ``n_hypotheses`` (distinct drawn rows), ``n_estimates``, ``estimates`` ``(E, d)``,
        ``estimate_labels`` ``(E, 2)``, ``estimate_mask`` ``(E,)`` and ``n_measurements``.

    Raises:
        ValueError: a bad argument, naming it.
    """
    d, m = _check_model_and_birth(model, local, birth)
    if np.any(np.asarray(birth.weights)[np.asarray(birth.mask)] > 1):
        raise ValueError(
            "birth: weights are the birth tracks' existence probabilities; they must lie in [0, 1]"
        )
    _check_prob(survival_prob, "survival_prob", open_low=True)
    _check_prob(detection_prob, "detection_prob", open_low=True)
    if not float(clutter_rate) > 0 or not np.isfinite(float(clutter_rate)):
        raise ValueError(
            f"clutter_rate: must be finite and > 0 (the LMB update divides by kappa), got {clutter_rate!r}"
        )
    if not float(clutter_density) > 0 or not np.isfinite(float(clutter_density)):
        raise ValueError(f"clutter_density: must be finite and > 0, got {clutter_density!r}")
    for name, value in (
        ("existence_threshold", existence_threshold),
        ("component_threshold", component_threshold),
    ):
        if not 0 <= float(value) < 1:
            raise ValueError(f"{name}: must lie in [0, 1), got {value!r}")
    if reducer is not None and not (hasattr(reducer, "init") and hasattr(reducer, "reduce")):
        raise ValueError(f"reducer: expected None or a Reducer (init, reduce), got {type(reducer).__name__}")
    sizes = {}
    for name, value in (
        ("capacity", capacity),
        ("components_per_track", components_per_track),
        ("n_samples", n_samples),
        ("max_estimates", capacity if max_estimates is None else max_estimates),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < 1:
            raise ValueError(f"{name}: expected an int >= 1, got {value!r}")
        sizes[name] = int(value)
    T, J, G, E = sizes["capacity"], sizes["components_per_track"], sizes["n_samples"], sizes["max_estimates"]
    dtype = birth.weights.dtype
    lf = local_filter_for(model, local, **(local_kwargs or {}))
    process_noise, measurement_noise = _model_noises(model, dtype)
    params = LMBParams(
        birth=birth,
        survival_prob=jnp.asarray(survival_prob, dtype),
        detection_prob=jnp.asarray(detection_prob, dtype),
        clutter_rate=jnp.asarray(clutter_rate, dtype),
        clutter_density=jnp.asarray(clutter_density, dtype),
        process_noise=process_noise,
        measurement_noise=measurement_noise,
        existence_threshold=jnp.asarray(existence_threshold, dtype),
        component_threshold=jnp.asarray(component_threshold, dtype),
        reducer=reducer,
    )

    def init(params: LMBParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None):
        """``prior=None``: no track. A GaussianMixture prior: each live component a track with
        existence its weight (clipped to ``[0, 1]``) and label ``(0, slot)``."""
        del key
        dt = params.birth.weights.dtype
        tracks = empty_tracks(T, J, d, dt)
        if prior is None:
            return tracks
        gm, _ = _fit(prior, T)  # the T heaviest components, or padded to T slots
        first = (jnp.arange(J) == 0)[None, :] & gm.mask[:, None]
        density = GaussianMixture(
            jnp.where(first, 1.0, 0.0).astype(dt),
            jnp.where(first[..., None], gm.means[:, None, :], 0.0).astype(dt),
            jnp.where(first[..., None, None], gm.covs[:, None], jnp.eye(d, dtype=dt)).astype(dt),
            first,
        )
        labels = jnp.stack([jnp.zeros(T, jnp.int32), jnp.arange(T, dtype=jnp.int32)], axis=1)
        return LMBState(
            jnp.where(gm.mask, jnp.clip(gm.weights, 0.0, 1.0), 0.0).astype(dt),
            jnp.where(gm.mask[:, None], labels, -1),
            gm.mask,
            density,
            jnp.zeros((), jnp.int32),
        )

    def predict(params: LMBParams, state: LMBState, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        return predict_tracks(lf, params, state, inputs.t)

    def update(
        params: LMBParams, state: LMBState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ):
        zs = jnp.asarray(z)
        if zs.ndim != 2 or zs.shape[-1] != m:
            raise ValueError(f"z: expected a padded measurement set of shape (M, {m}), got {zs.shape}")
        N = state.existence.shape[0]
        dt = state.existence.dtype
        if key is None and G > 1:
            raise ValueError(
                "key: the GM-LMB's Gibbs sampler draws random numbers; pass key= to "
                "gmjax.multitarget.run (or to update), or build the filter with n_samples=1"
            )
        uniforms = jnp.zeros((0, N), dt) if key is None else gibbs_uniforms(key, G - 1, N, dt)
        upd = update_tracks(lf, params, state, zs.astype(dt), inputs.t, uniforms, n_tracks=T)
        post = upd.tracks
        est = extract_tracks(post, max_estimates=E)
        r = jnp.where(post.mask, post.existence, 0.0)
        flat = GaussianMixture(
            (r[:, None] * post.density.weights).reshape(-1),
            post.density.means.reshape(-1, d),
            post.density.covs.reshape(-1, d, d),
            post.density.mask.reshape(-1),
        )
        mean, cov = gmm.moments(flat)
        flags = StepFlags(upd.repaired, upd.overflow | est.overflow, upd.degenerate, jnp.any(jnp.isinf(zs)))
        extra = {
            "cardinality": jnp.sum(r),
            "cardinality_variance": jnp.sum(r * (1.0 - r)),
            "cardinality_map": est.n_estimates,
            "n_tracks": jnp.sum(post.mask).astype(jnp.int32),
            "n_hypotheses": jnp.sum(upd.distinct).astype(jnp.int32),
            "n_estimates": est.n_estimates,
            "estimates": est.states,
            "estimate_labels": est.labels,
            "estimate_mask": est.mask,
            "n_measurements": jnp.sum(measurement_mask(zs).astype(jnp.int32)),
        }
        n_comp = jnp.sum(post.density.mask).astype(jnp.int32)
        info = StepInfo(mean, cov, upd.loglik, n_comp, flags, None, extra)
        return post, info

    return Filter(init, predict, update, params)
