"""The Gaussian-mixture probability hypothesis density (GM-PHD) filter (Vo & Ma 2006), batched.

The PHD ``v_k(x)`` of a multi-target state is a Gaussian mixture whose weights sum to the expected
number of targets (it is *not* normalised). One step of Vo & Ma 2006 (IEEE TSP 54(11), Table I):

* predict (eq 25 without spawning): every component goes through a local filter's prediction with
  its weight scaled by ``P_S``; the birth intensity ``gamma_k`` (a GM) is appended;
* update (eqs 26-29): the missed-detection terms ``(1 - P_D) w_j N(x; m_j, P_j)`` plus, for every
  measurement ``z`` of the set, the detection terms
  ``w_j(z) = P_D w_j q_j(z) / (kappa(z) + P_D sum_l w_l q_l(z))`` with the component updated by the
  local filter and ``q_j(z)`` its predicted measurement density; ``kappa(z) = lambda_c c(z)`` is the
  clutter intensity (Poisson clutter, uniform density ``c = 1 / V`` over the surveillance region);
* reduction (Table II): any gmjax reducer through the Reducer protocol, Vo–Ma pruning and merging
  (:class:`gmjax.reduction.VoMa`) by default;
* state extraction (Table III): every component with ``w > 0.5`` gives ``round(w)`` copies of its
  mean (round half down: the number of integers ``r >= 0`` with ``w > r + 1/2``), into a padded
  estimate set with a mask; the cardinality estimate is the sum of the weights.

Design choices (see also the builder :func:`gm_phd`):

* **The Filter contract** (docs/design.md §3) fits: ``init``, ``predict``, ``update`` are pure
  functions of ``params`` (:class:`PHDParams`, a pytree: birth intensity, ``P_S``, ``P_D``, clutter,
  noises, the reducer config, the extraction threshold), so ``jax.vmap`` over parameter sets and
  ``jax.grad`` w.r.t. thresholds go through :func:`run`. The measurement of a step is a padded set
  ``Z`` ``(M, m)``: **a row holding a NaN is an absent measurement** (the set's mask is
  ``isfinite(Z).all(-1)``), so a padded set needs no separate mask and a set of only NaN rows is an
  empty scan. A row with an infinite entry is ignored as well and raises the
  ``nonfinite_measurement`` flag (NaN padding does not: it is how a set is padded). ``filters.run`` wants ``(T, m)`` measurements, so this module has its own
  :func:`run` over ``(T, M, m)`` (the same ``lax.scan`` and key splitting).
* **Components** are predicted and updated by any local filter of :mod:`gmjax.filters.local`
  (``"kf"``, ``"ekf"``, ``"ukf"``, ``"ckf"``, ``"ghkf"``, ``"sgkf"``, ``"sckf"``) via the component-level
  :class:`~gmjax.filters.LocalFilter`: ``vmap`` over components × measurements of ``local.update``,
  whose log-likelihood is ``log q_j(z)``. Weights are combined in the log domain.
* **Unnormalised weights and the reducers.** The reducer sees the intensity as it is (weights sum
  to the expected number), which is what Vo–Ma's absolute thresholds mean (:class:`VoMa` compares raw
  weights with ``T``; its moment merge does not care about the total). Reducers return mixtures scaled
  to some total (VoMa: the input total; most others: 1), so the filter rescales the output to
  ``total - pruned_mass`` (the paper: pruned weight is lost) or, with ``keep_pruned_mass=True``, to
  ``total``. A reducer whose thresholds are meant for a *normalised* mixture is used with
  ``reducer_input="normalized"``: the filter divides by the total first and scales back.
* **Fixed capacities**: the posterior intensity has ``capacity`` slots ``J``; the predicted one
  ``J + J_b``; the updated one ``(J + J_b)(1 + M)``, of which the ``merge_capacity`` heaviest are handed
  to the reducer (Vo–Ma's merge is a loop over its input slots, so this bounds the cost). Whatever is
  dropped is reported; the overflow flag is raised when a dropped component weighed more than
  ``params.truncation_tolerance`` (default ``1e-5``, the paper's pruning threshold), so with Vo–Ma
  the truncation only removes what pruning would have removed anyway.
* Spawning (the ``beta`` term of eq 25) is not modelled; ``P_S`` and ``P_D`` are constants (traced
  leaves, so differentiable).
* Stateful reducers get a fresh state at every step (``reducer.init(merge_capacity)``): no memory
  across steps.

The cardinalised filter (GM-CPHD) is :mod:`gmjax.multitarget.cphd`, built from this module's pieces.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs, scan_steps
from gmjax.filters.local import LOCAL_FILTERS, LocalFilter, gaussian_moments, local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.models.base import StateSpaceModel
from gmjax.multitarget.extraction import Estimates, extract, soft_estimates
from gmjax.multitarget.scans import PaddedScans, measurement_mask, pad_scans
from gmjax.reduction import VoMa

__all__ = [
    "PHDParams",
    "PHDState",
    "Estimates",
    "gm_phd",
    "run",
    "empty_intensity",
    "extract",
    "soft_estimates",
    "predict_intensity",
    "update_intensity",
    "measurement_mask",
    "PaddedScans",
    "pad_scans",
]


class PHDParams(NamedTuple):
    """The numeric parameters of a GM-PHD filter (a pytree: vmap, differentiate or tune any leaf).

    Attributes:
        birth: the birth intensity ``gamma_k`` (Vo & Ma eq 21), a :class:`GaussianMixture` of
            ``J_b`` slots whose weights are expected numbers of births per step.
        survival_prob: ``()`` ``P_S``.
        detection_prob: ``()`` ``P_D``.
        clutter_rate: ``()`` ``lambda_c``, the mean number of clutter returns per scan.
        clutter_density: ``()`` ``c(z)``, the clutter's spatial density (``1 / V`` for clutter uniform
            over a region of volume ``V`` in measurement space); ``kappa = lambda_c c``.
        process_noise: ``(mean (d,), cov (d, d))`` or a :class:`GaussianMixture` (moment-matched).
        measurement_noise: ``(mean (m,), cov (m, m))`` or a :class:`GaussianMixture`.
        reducer: a Reducer config (``init(capacity)``, ``reduce(gm, state, key=)``).
        extract_threshold: ``()`` the weight above which a component is extracted (0.5 in Table III).
        truncation_tolerance: ``()`` the largest weight the pre-reduction truncation may drop without
            raising the overflow flag.
        initial: the intensity at time 0, a :class:`GaussianMixture` of ``capacity`` slots.
    """

    birth: GaussianMixture
    survival_prob: Array
    detection_prob: Array
    clutter_rate: Array
    clutter_density: Array
    process_noise: Any
    measurement_noise: Any
    reducer: Any
    extract_threshold: Array
    truncation_tolerance: Array
    initial: GaussianMixture


class PHDState(NamedTuple):
    """The filter state: the intensity (posterior: ``capacity`` slots; predicted: ``capacity + J_b``)."""

    intensity: GaussianMixture


def empty_intensity(capacity: int, dim: int, dtype: Any = None) -> GaussianMixture:
    """An intensity with no component (``capacity`` padded slots)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    return GaussianMixture(
        jnp.zeros(capacity, dtype),
        jnp.zeros((capacity, dim), dtype),
        jnp.broadcast_to(jnp.eye(dim, dtype=dtype), (capacity, dim, dim)),
        jnp.zeros(capacity, bool),
    )


# ----------------------------------------------------------------------------- the recursion


def _local_states(local: LocalFilter, gm: GaussianMixture):
    return jax.vmap(local.init)(gm.means, gm.covs)


def predict_intensity(
    local: LocalFilter, params: PHDParams, intensity: GaussianMixture, t: Array
) -> GaussianMixture:
    """Vo & Ma Table I, step 2 (eqs 25, without spawning): survivors predicted, births appended.

    Returns:
        The predicted intensity, capacity ``J + J_b`` (survivors first).
    """
    q_mean, q_cov = gaussian_moments(params.process_noise)
    states = _local_states(local, intensity)
    pred = jax.vmap(lambda s: local.predict(s, t, q_mean, q_cov))(states)
    means, covs = jax.vmap(local.moments)(pred)
    p_s = jnp.asarray(params.survival_prob, intensity.weights.dtype)
    survivors = gmm.sanitize(GaussianMixture(intensity.weights * p_s, means, covs, intensity.mask))
    birth = jax.tree_util.tree_map(
        lambda a: a.astype(intensity.means.dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a,
        params.birth,
    )
    return gmm.concat(survivors, birth)


class _Update(NamedTuple):
    intensity: GaussianMixture  # (K (1 + M),) missed-detection terms, then detection terms by measurement
    loglik: Array  # () log of the Poisson approximation of p(Z_k | Z_{1:k-1})
    repaired: Array  # () bool


def update_intensity(
    local: LocalFilter, params: PHDParams, predicted: GaussianMixture, zs: Array, t: Array
) -> _Update:
    """Vo & Ma Table I, steps 3-4 (eqs 26-29) over a padded measurement set ``zs`` ``(M, m)``.

    The log-likelihood reported is ``-(lambda_c + P_D sum_j w_j) + sum_z log(kappa + P_D sum_j w_j
    q_j(z))``: the density of the measurement set when it is Poisson with the predicted PHD's
    intensity (the Poisson assumption behind the PHD recursion).
    """
    dtype = predicted.weights.dtype
    r_mean, r_cov = gaussian_moments(params.measurement_noise)
    z_mask = measurement_mask(zs)
    p_d = jnp.asarray(params.detection_prob, dtype)
    kappa = jnp.asarray(params.clutter_rate, dtype) * jnp.asarray(params.clutter_density, dtype)
    states = _local_states(local, predicted)

    def one(state, z):
        return local.update(state, z, t, r_mean, r_cov)

    upd, info = jax.vmap(lambda s: jax.vmap(lambda z: one(s, z))(zs))(states)  # leaves (K, M, ...)
    means, covs = jax.vmap(jax.vmap(local.moments))(upd)
    w = jnp.where(predicted.mask, predicted.weights, 0.0)
    live = predicted.mask[:, None] & z_mask[None, :] & (w[:, None] > 0)
    safe_w = jnp.where(w > 0, w, 1.0)
    log_num = jnp.where(live, jnp.log(p_d) + jnp.log(safe_w)[:, None] + info.loglik, -jnp.inf)
    # log-sum-exps guarded so that empty columns (padded rows, or no live component) and kappa = 0
    # give neither NaN values nor NaN gradients
    any_live = jnp.any(live, axis=0)  # (M,)
    lse = jax.nn.logsumexp(jnp.where(any_live[None, :], log_num, 0.0), axis=0)
    lse = jnp.where(any_live, lse, -jnp.inf)
    log_kappa = jnp.log(kappa)
    ok = any_live | (kappa > 0)
    log_den = jnp.where(ok, jnp.logaddexp(jnp.where(ok, log_kappa, 0.0), jnp.where(ok, lse, 0.0)), -jnp.inf)
    log_den = jnp.where(ok & ~any_live, log_kappa, log_den)  # (M,)
    w_det = jnp.where(live, jnp.exp(jnp.where(live, log_num - log_den[None, :], -jnp.inf)), 0.0)  # (K, M)
    K, M = w_det.shape
    d = predicted.dim
    missed = GaussianMixture((1.0 - p_d) * w, predicted.means, predicted.covs, predicted.mask)
    det_mask = predicted.mask[:, None] & z_mask[None, :]
    detected = GaussianMixture(
        w_det.T.reshape(K * M),
        jnp.swapaxes(means, 0, 1).reshape(K * M, d),
        jnp.swapaxes(covs, 0, 1).reshape(K * M, d, d),
        det_mask.T.reshape(K * M),
    )
    out = gmm.sanitize(gmm.concat(missed, detected))
    loglik = -(jnp.asarray(params.clutter_rate, dtype) + p_d * jnp.sum(w)) + jnp.sum(
        jnp.where(z_mask, log_den, 0.0)
    )
    repaired = jnp.any(jnp.where(det_mask, info.repaired, False))
    return _Update(out, loglik, repaired)


def _truncate(gm: GaussianMixture, capacity: int) -> tuple[GaussianMixture, Array, Array]:
    """The ``capacity`` heaviest components; ``(gm, dropped_mass, heaviest_dropped_weight)``."""
    if capacity >= gm.capacity:
        zero = jnp.zeros((), gm.weights.dtype)
        return gmm.pad(gm, capacity) if capacity > gm.capacity else gm, zero, zero
    idx, _ = gmm.heaviest_slots(gm.weights, gm.mask, capacity)
    kept = jnp.zeros(gm.capacity, bool).at[idx].set(True)
    dropped = gm.mask & ~kept
    w0 = jnp.where(gm.mask, gm.weights, 0.0)
    out = gmm.sanitize(jax.tree_util.tree_map(lambda a: a[idx], gm))
    return out, jnp.sum(jnp.where(dropped, w0, 0.0)), jnp.max(jnp.where(dropped, w0, 0.0))


def _reduce(reducer, gm: GaussianMixture, *, normalized: bool, keep_pruned_mass: bool, key):
    """Run ``reducer`` on an unnormalised intensity and restore the intensity's scale (module doc)."""
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    ok = total > 0
    safe_total = jnp.where(ok, total, 1.0)
    gm_in = gm._replace(weights=w / safe_total) if normalized else gm
    out, _, info = reducer.reduce(gm_in, reducer.init(gm.capacity), key=key)
    pruned = info.pruned_mass * safe_total if normalized else info.pruned_mass
    target = total if keep_pruned_mass else jnp.maximum(total - pruned, 0.0)
    w_out = jnp.where(out.mask, out.weights, 0.0)
    s = jnp.sum(w_out)
    s_ok = s > 0
    scale = jnp.where(s_ok, target / jnp.where(s_ok, s, 1.0), 0.0)
    return gmm.sanitize(out._replace(weights=w_out * scale)), info


def _fit(gm: GaussianMixture, capacity: int) -> tuple[GaussianMixture, Array]:
    """``gm`` in exactly ``capacity`` slots (the heaviest if it holds more); ``(gm, overflow)``."""
    if gm.capacity == capacity:
        return gm, jnp.zeros((), bool)
    if gm.capacity < capacity:
        return gmm.pad(gm, capacity), jnp.zeros((), bool)
    return gmm.top_k(gm, capacity), gmm.n_active(gm) > capacity


# ----------------------------------------------------------------------------- the filter


def _as_noise(noise, dim: int, name: str, dtype):
    if isinstance(noise, GaussianMixture):
        noise = gaussian_moments(noise)
    if isinstance(noise, (tuple, list)) and len(noise) == 2:
        mean, cov = np.asarray(noise[0], float), np.asarray(noise[1], float)
    else:
        cov = np.asarray(noise, float)
        mean = np.zeros(cov.shape[:1])
    if mean.shape != (dim,) or cov.shape != (dim, dim):
        raise ValueError(
            f"{name}: expected a ({dim},) mean and a ({dim}, {dim}) covariance, got "
            f"{mean.shape} and {cov.shape}"
        )
    if not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T):
        raise ValueError(f"{name}: covariance must be finite and symmetric")
    eig = np.linalg.eigvalsh(cov)
    if np.any(eig < -1e-10 * max(1.0, float(np.max(np.abs(eig))))):
        raise ValueError(f"{name}: covariance must be positive semi-definite (eigenvalues {eig})")
    return jnp.asarray(mean, dtype), jnp.asarray(cov, dtype)


def _check_model_and_birth(model: Any, local: Any, birth: Any) -> tuple[int, int]:
    """The multi-target builders' checks of the model, the local filter's name and the birth mixture
    (``ValueError`` naming the argument); returns ``(d, m)``."""
    if not isinstance(model, StateSpaceModel):
        raise ValueError(f"model: expected a StateSpaceModel, got {type(model).__name__}")
    if local not in LOCAL_FILTERS:
        raise ValueError(f"local: unknown local filter {local!r}; expected one of {sorted(LOCAL_FILTERS)}")
    d, m = model.state_dim, model.measurement_dim
    if not isinstance(birth, GaussianMixture) or birth.dim != d:
        raise ValueError(f"birth: expected a GaussianMixture of dimension {d}")
    if np.any(np.asarray(birth.weights) < 0) or not np.all(np.isfinite(np.asarray(birth.weights))):
        raise ValueError("birth: weights must be finite and non-negative")
    return d, m


def _model_noises(model: StateSpaceModel, dtype: Any) -> tuple[Any, Any]:
    """The model's process and measurement noises as checked ``(mean, cov)`` pairs of ``dtype``."""
    d, m = model.state_dim, model.measurement_dim
    return (
        _as_noise(gaussian_moments(model.process_noise), d, "model.process_noise", dtype),
        _as_noise(gaussian_moments(model.measurement_noise), m, "model.measurement_noise", dtype),
    )


def _check_prob(value, name, *, open_low=False):
    v = float(value)
    if not (0.0 < v <= 1.0 if open_low else 0.0 <= v <= 1.0):
        raise ValueError(f"{name}: must lie in {'(0, 1]' if open_low else '[0, 1]'}, got {value!r}")


def _check_sizes_and_reducer(
    capacity: Any, merge_capacity: Any, max_estimates: Any, reducer_input: str, reducer: Any
) -> tuple[int, int, int, Any]:
    """The builders' capacities (``merge_capacity`` default ``4 capacity``, ``max_estimates`` default
    ``capacity``) and reducer (default Vo–Ma, ``T = 1e-5``, ``U = 4``), checked (``ValueError`` naming
    the argument)."""
    capacity = int(capacity)
    if capacity < 1:
        raise ValueError(f"capacity: must be >= 1, got {capacity}")
    merge_capacity = 4 * capacity if merge_capacity is None else int(merge_capacity)
    if merge_capacity < 1:
        raise ValueError(f"merge_capacity: must be >= 1, got {merge_capacity}")
    max_estimates = capacity if max_estimates is None else int(max_estimates)
    if max_estimates < 1:
        raise ValueError(f"max_estimates: must be >= 1, got {max_estimates}")
    if reducer_input not in ("intensity", "normalized"):
        raise ValueError(f"reducer_input: expected 'intensity' or 'normalized', got {reducer_input!r}")
    if reducer is None:
        reducer = VoMa(1e-5, 4.0, max_components=min(capacity, merge_capacity))
    if not (hasattr(reducer, "init") and hasattr(reducer, "reduce")):
        raise ValueError(f"reducer: expected a Reducer (init, reduce), got {type(reducer).__name__}")
    return capacity, merge_capacity, max_estimates, reducer


def _initial_intensity(initial: GaussianMixture | None, capacity: int, d: int, dtype: Any) -> GaussianMixture:
    """The intensity at time 0 in ``capacity`` slots (default: empty)."""
    if initial is None:
        initial = empty_intensity(capacity, d, dtype)
    elif not isinstance(initial, GaussianMixture) or initial.dim != d:
        raise ValueError(f"initial: expected a GaussianMixture of dimension {d}")
    else:
        initial, _ = _fit(initial, capacity)
    return initial


def gm_phd(
    model: StateSpaceModel,
    *,
    birth: GaussianMixture,
    survival_prob: float = 0.99,
    detection_prob: float = 0.98,
    clutter_rate: float = 10.0,
    clutter_density: float,
    reducer: Any = None,
    capacity: int = 100,
    merge_capacity: int | None = None,
    max_estimates: int | None = None,
    local: str = "kf",
    extract_threshold: float = 0.5,
    truncation_tolerance: float = 1e-5,
    initial: GaussianMixture | None = None,
    reducer_input: str = "intensity",
    keep_pruned_mass: bool = False,
    local_kwargs: dict | None = None,
) -> Filter:
    """Build a GM-PHD filter (Vo & Ma 2006) as a :class:`~gmjax.filters.Filter`.

    Args:
        model: the single-target model: ``f``, ``h`` (traceable) and the process and measurement noises
            (GM noises are moment-matched; ``model.prior`` is not used: see ``initial``).
        birth: the birth intensity (weights: expected births per step), ``J_b`` slots.
        survival_prob, detection_prob: ``P_S``, ``P_D`` in ``[0, 1]`` (``P_D < 1`` for the missed terms).
        clutter_rate: ``lambda_c >= 0`` returns per scan; clutter_density: ``c(z) > 0``
            (``1 / V`` for uniform clutter).
        reducer: any Reducer config (default ``VoMa(1e-5, 4.0, max_components=capacity)``, Table II with
            ``T = 1e-5``, ``U = 4``, ``J_max = capacity``).
        capacity: static ``J``, the posterior intensity's slots.
        merge_capacity: static, how many of the heaviest updated components the reducer receives
            (default ``4 J``).
        max_estimates: static ``E``, the capacity of the estimate set (default ``J``).
        local: the component filter (:data:`gmjax.filters.local.LOCAL_FILTERS`), ``"kf"`` by default.
        extract_threshold: Table III's 0.5.
        truncation_tolerance: see the module docstring.
        initial: the intensity at time 0 (default: empty); padded or truncated to ``capacity``.
        reducer_input: ``"intensity"`` (default: the reducer sees the unnormalised intensity) or
            ``"normalized"`` (divided by its total and scaled back).
        keep_pruned_mass: rescale the reduced intensity to the updated total instead of dropping the
            pruned weight (the paper drops it).
        local_kwargs: keyword arguments of the local filter (e.g. the UKF's ``alpha``).

    Returns:
        ``Filter(init, predict, update, params)`` with ``params`` a :class:`PHDParams`. ``update``
        takes a padded measurement set ``(M, m)`` (NaN rows absent) and returns a :class:`StepInfo`
        with ``mean``/``cov`` the moments of the normalised intensity (not a target estimate),
        ``loglik`` the Poisson approximation of ``log p(Z_k | Z_{1:k-1})``, ``n_components``,
        ``flags`` (``overflow``: truncation above tolerance, reducer or capacity overflow, or more
        estimates than ``E``; ``repaired``; ``degenerate``: a non-finite total weight;
        ``nonfinite_measurement``: a row with an infinite entry, ignored), ``reduction``
        (the reducer's info) and ``extra``: ``cardinality`` (sum of the updated weights, before
        reduction, eq 29's ``N_k``), ``cardinality_reduced`` (after), ``n_estimates``, ``estimates``
        ``(E, d)``, ``estimate_mask`` ``(E,)``, ``truncated_mass`` and ``n_measurements``.

    Raises:
        ValueError: a bad argument, naming it.
    """
    d, m = _check_model_and_birth(model, local, birth)
    _check_prob(survival_prob, "survival_prob")
    _check_prob(detection_prob, "detection_prob")
    if not float(clutter_rate) >= 0:
        raise ValueError(f"clutter_rate: must be >= 0, got {clutter_rate!r}")
    if not float(clutter_density) > 0:
        raise ValueError(f"clutter_density: must be > 0, got {clutter_density!r}")
    if float(clutter_rate) == 0 and float(detection_prob) == 1:
        pass  # allowed: kappa = 0, every measurement is a detection (log-domain update handles it)
    capacity, merge_capacity, max_estimates, reducer = _check_sizes_and_reducer(
        capacity, merge_capacity, max_estimates, reducer_input, reducer
    )
    if float(extract_threshold) < 0:
        raise ValueError(f"extract_threshold: must be >= 0, got {extract_threshold!r}")
    initial = _initial_intensity(initial, capacity, d, birth.means.dtype)
    lf = local_filter_for(model, local, **(local_kwargs or {}))
    dtype = birth.weights.dtype
    process_noise, measurement_noise = _model_noises(model, dtype)
    params = PHDParams(
        birth=birth,
        survival_prob=jnp.asarray(survival_prob, dtype),
        detection_prob=jnp.asarray(detection_prob, dtype),
        clutter_rate=jnp.asarray(clutter_rate, dtype),
        clutter_density=jnp.asarray(clutter_density, dtype),
        process_noise=process_noise,
        measurement_noise=measurement_noise,
        reducer=reducer,
        extract_threshold=jnp.asarray(extract_threshold, dtype),
        truncation_tolerance=jnp.asarray(truncation_tolerance, dtype),
        initial=initial,
    )
    normalized = reducer_input == "normalized"

    def init(params: PHDParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None):
        del key
        gm = params.initial if prior is None else prior
        gm, _ = _fit(gm, capacity)
        return PHDState(gm)

    def predict(params: PHDParams, state: PHDState, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        return PHDState(predict_intensity(lf, params, state.intensity, inputs.t))

    def update(
        params: PHDParams, state: PHDState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ):
        zs = jnp.asarray(z)
        if zs.ndim != 2 or zs.shape[-1] != m:
            raise ValueError(f"z: expected a padded measurement set of shape (M, {m}), got {zs.shape}")
        predicted = state.intensity
        upd = update_intensity(lf, params, predicted, zs.astype(predicted.means.dtype), inputs.t)
        cardinality = gmm.total_weight(upd.intensity)
        work, truncated, heaviest_dropped = _truncate(upd.intensity, merge_capacity)
        reduced, rinfo = _reduce(
            params.reducer, work, normalized=normalized, keep_pruned_mass=keep_pruned_mass, key=key
        )
        post, cap_overflow = _fit(reduced, capacity)
        est = extract(post, params.extract_threshold, max_estimates=max_estimates)
        mean, cov = gmm.moments(post)
        overflow = (heaviest_dropped > params.truncation_tolerance) | rinfo.overflow | cap_overflow
        overflow = overflow | est.overflow
        flags = StepFlags(upd.repaired, overflow, ~jnp.isfinite(cardinality), jnp.any(jnp.isinf(zs)))
        extra = {
            "cardinality": cardinality,
            "cardinality_reduced": gmm.total_weight(post),
            "n_estimates": est.n_estimates,
            "estimates": est.states,
            "estimate_mask": est.mask,
            "truncated_mass": truncated,
            "n_measurements": jnp.sum(measurement_mask(zs).astype(jnp.int32)),
        }
        info = StepInfo(mean, cov, upd.loglik, gmm.n_active(post), flags, rinfo, extra)
        return PHDState(post), info

    return Filter(init, predict, update, params)


def run(
    filter: Filter,
    zs: Array,
    inputs: Any = None,
    *,
    key: PRNGKey | None = None,
    params: Any = None,
    prior: GaussianMixture | None = None,
    init_state: Any = None,
) -> tuple[Any, StepInfo]:
    """Run a multi-target filter over padded measurement sets with one ``lax.scan``.

    The same driver as :func:`gmjax.filters.run` (time indexing, key splitting), for measurements
    ``zs`` of shape ``(T, M, m)`` whose NaN rows are absent measurements. The filter cannot see rows
    that were cut before it: a scan of more than ``M`` returns padded by hand to ``M`` rows reads as a
    full scan. Build ``zs`` with :func:`pad_scans` (or :func:`~gmjax.multitarget.simulate`), whose
    ``overflow`` flags every cut scan.

    Returns:
        ``(states, infos)`` with a leading ``T`` axis.
    """
    zs = jnp.asarray(zs)
    if zs.ndim != 3:
        raise ValueError(f"zs: expected padded measurement sets of shape (T, M, m), got {zs.shape}")
    params = filter.params if params is None else params
    return scan_steps(filter, params, zs, inputs, key=key, prior=prior, init_state=init_state)
