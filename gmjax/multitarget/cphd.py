"""The Gaussian-mixture cardinalised PHD (GM-CPHD) filter (Vo, Vo & Cantoni 2007), batched.

The CPHD filter (Mahler 2007) propagates, beside the intensity ``v_k(x)`` of the GM-PHD filter, the
distribution ``p_k(n)`` of the number of targets, ``n = 0 .. N_max``; the multi-target density is
approximated by an i.i.d. cluster process (cardinality ``p_k``, spatial density ``v_k / <1, v_k>``)
instead of the PHD's Poisson process. The closed form for linear Gaussian models is that of
B.-T. Vo, B.-N. Vo & A. Cantoni, "Analytic implementations of the cardinalized probability
hypothesis density filter", IEEE TSP 55(7), 2007 (the CPHD recursion, then its Gaussian-mixture
form; the symbols below are the paper's). With constant ``P_S``, ``P_D``, no spawning:

* **predict.** The intensity as the GM-PHD's (survivors' weights times ``P_S``, births appended:
  :func:`gmjax.multitarget.phd.predict_intensity`); the cardinality

  ``p_{k|k-1}(n) = sum_{j=0}^{n} p_Gamma(n - j) Pi(j)``,
  ``Pi(j) = sum_{l=j}^{N_max} C(l, j) P_S^j (1 - P_S)^{l-j} p_{k-1}(l)``

  (survivors: binomial thinning, then the birth cardinality convolved in). The birth cardinality
  ``p_Gamma`` is **Poisson with mean** ``sum`` of the birth weights (the GM-CPHD with a Poisson birth
  RFS). The mass the births push beyond ``N_max`` is cut and the rest renormalised; the cut mass is
  kept in the state (``tail_mass``) and raises the ``overflow`` flag above
  ``params.cardinality_tolerance``.
* **update** with the measurement set ``Z`` (``|Z| = m_z`` valid rows):

  ``Upsilon^u[w, Z](n) = sum_{j=0}^{min(m_z, n)} (m_z - j)! p_K(m_z - j) P^n_{j+u}
  (1 - P_D)^{n - (j+u)} e_j(Lambda(w, Z)) / (1^T w)^{j+u}``, ``u = 0, 1``,

  with ``P^n_i = n! / (n - i)!``, ``e_j`` the elementary symmetric function of order ``j`` and
  ``Lambda(w, Z) = {<1, kappa> / kappa(z) P_D w^T q(z) : z in Z}``, ``q_i(z)`` component ``i``'s
  predicted measurement density. The clutter is a Poisson RFS: ``p_K`` **is Poisson with mean**
  ``lambda_c`` and ``kappa(z) = lambda_c c(z)``, so ``<1, kappa> / kappa(z) = 1 / c(z)`` and
  ``(m_z - j)! p_K(m_z - j) = exp(-lambda_c) lambda_c^{m_z - j}``. Then

  ``p_k(n) = Upsilon^0[w, Z](n) p_{k|k-1}(n) / <Upsilon^0[w, Z], p_{k|k-1}>``,

  and the intensity keeps the GM-PHD's components with new weights: missed detections
  ``(1 - P_D) w_i <Upsilon^1[w, Z], p> / <Upsilon^0[w, Z], p>`` and, for every ``z``, detections
  ``P_D w_i q_i(z) / c(z) * <Upsilon^1[w, Z \\ {z}], p> / <Upsilon^0[w, Z], p>`` (means and
  covariances from the local filter's update with ``z``).
* **reduction** (pruning and merging, Vo & Ma Table II by default) as in the GM-PHD filter; it acts on
  the intensity only (the cardinality distribution is kept as updated).
* **state extraction**: the MAP cardinality ``n_hat = argmax_n p_k(n)``, then the means of the
  ``n_hat`` heaviest components of the reduced intensity (:func:`extract_map`).

Numerics (all fixed shapes, so ``jit``, ``vmap`` and ``grad`` go through):

* ``Upsilon`` is computed in the log domain. The factor ``(1^T w)^{-j}`` is folded into the ESF's
  arguments: ``e_j(Lambda) / W^j = e_j(Lambda / W)``, so only the normalised weights ``w_i / W``
  enter (a step with no predicted component is not a division by zero). ``e_j`` comes from Vieta's
  recursion ``e_j <- e_j + x e_{j-1}`` run in the log domain over the ``M`` slots of the padded set
  (:func:`log_esf`; a padded slot is the factor ``(1 + 0 t)``, i.e. skipped), and the ``M`` sets
  ``Z \\ {z}`` by one such recursion per ``z`` with that entry left out (:func:`log_esf_leave_one_out`,
  ``O(M^2)`` each). Every ``logsumexp`` is guarded, so all ``-inf`` rows give ``-inf`` with zero
  gradients (no ``NaN``), and ``P_D = 1``, ``P_S = 1``, ``lambda_c = 0`` and no births are exact
  (``0^0 = 1``).
* The cardinality distribution is kept as ``log p(n)`` (``(N_max + 1,)``) in :class:`CPHDState`.
* A measurement set impossible under the model (``<Upsilon^0, p> = 0``: measurements with no clutter
  and no target that can explain them, or ``N_max`` too small) raises the ``degenerate`` flag; the
  step then keeps the predicted intensity and cardinality and reports ``loglik = -inf``.

Everything else (the Filter contract, padded measurement sets with NaN rows, capacities, truncation
before the reducer, the reducers' scaling, local filters) is that of :mod:`gmjax.multitarget.phd`, whose
building blocks this module imports. Run the filter with :func:`gmjax.multitarget.run` (the same driver
as the GM-PHD's).
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
from gmjax.multitarget.cardinality import (
    _lse,
    _normalize_log,
    cardinality_moments,
    log_esf,
    log_esf_leave_one_out,
    log_upsilon,
    poisson_log_pmf,
    predict_cardinality,
)
from gmjax.multitarget.phd import (
    Estimates,
    PHDParams,
    _check_model_and_birth,
    _check_prob,
    _check_sizes_and_reducer,
    _fit,
    _initial_intensity,
    _local_states,
    _model_noises,
    _reduce,
    _truncate,
    measurement_mask,
    predict_intensity,
)

__all__ = [
    "CPHDParams",
    "CPHDState",
    "CPHDUpdate",
    "gm_cphd",
    "log_esf",
    "log_esf_leave_one_out",
    "log_upsilon",
    "predict_cardinality",
    "poisson_log_pmf",
    "update_cphd",
    "extract_map",
    "cardinality_moments",
]


class CPHDParams(NamedTuple):
    """The numeric parameters of a GM-CPHD filter (a pytree: vmap, differentiate or tune any leaf).

    The fields shared with :class:`~gmjax.multitarget.phd.PHDParams` mean the same.

    Attributes:
        birth: the birth intensity ``gamma_k``, ``J_b`` slots; its total is the Poisson birth
            cardinality's mean.
        survival_prob: ``()`` ``P_S``.
        detection_prob: ``()`` ``P_D``.
        clutter_rate: ``()`` ``lambda_c``, the Poisson clutter cardinality's mean.
        clutter_density: ``()`` ``c(z)`` (``1 / V`` for uniform clutter).
        process_noise: ``(mean (d,), cov (d, d))``.
        measurement_noise: ``(mean (m,), cov (m, m))``.
        reducer: a Reducer config.
        truncation_tolerance: ``()`` the largest weight the pre-reduction truncation may drop without
            raising the overflow flag.
        cardinality_tolerance: ``()`` the largest cardinality mass beyond ``N_max`` a prediction may
            cut without raising the overflow flag.
        initial: the intensity at time 0, ``capacity`` slots.
        initial_cardinality: ``(N_max + 1,)`` the cardinality distribution at time 0 (a pmf).
    """

    birth: GaussianMixture
    survival_prob: Array
    detection_prob: Array
    clutter_rate: Array
    clutter_density: Array
    process_noise: Any
    measurement_noise: Any
    reducer: Any
    truncation_tolerance: Array
    cardinality_tolerance: Array
    initial: GaussianMixture
    initial_cardinality: Array

    def as_phd(self) -> PHDParams:
        """The same numbers as :class:`PHDParams` (for the GM-PHD's intensity building blocks)."""
        dtype = self.birth.weights.dtype
        return PHDParams(
            birth=self.birth,
            survival_prob=self.survival_prob,
            detection_prob=self.detection_prob,
            clutter_rate=self.clutter_rate,
            clutter_density=self.clutter_density,
            process_noise=self.process_noise,
            measurement_noise=self.measurement_noise,
            reducer=self.reducer,
            extract_threshold=jnp.asarray(0.5, dtype),
            truncation_tolerance=self.truncation_tolerance,
            initial=self.initial,
        )


class CPHDState(NamedTuple):
    """The filter state.

    Attributes:
        intensity: the intensity (posterior: ``capacity`` slots; predicted: ``capacity + J_b``).
        log_cardinality: ``(N_max + 1,)`` ``log p(n)``, ``n = 0 .. N_max`` (``-inf`` where ``p(n) = 0``).
        tail_mass: ``()`` the cardinality mass the last prediction cut beyond ``N_max``.
    """

    intensity: GaussianMixture
    log_cardinality: Array
    tail_mass: Array

    @property
    def cardinality(self) -> Array:
        """``(..., N_max + 1)`` the cardinality distribution ``p(n)``."""
        return jnp.exp(self.log_cardinality)


# ----------------------------------------------------------------------------- the update


class CPHDUpdate(NamedTuple):
    """What :func:`update_cphd` returns.

    Attributes:
        intensity: ``(K (1 + M),)`` slots: missed-detection terms, then detection terms by measurement
            (the layout of :func:`gmjax.multitarget.phd.update_intensity`).
        log_cardinality: ``(N_max + 1,)`` the updated ``log p_k(n)``.
        loglik: ``()`` ``log p(Z_k | Z_{1:k-1})`` under the i.i.d. cluster prediction:
            ``log <Upsilon^0, p_{k|k-1}> + m_z log c`` (``-inf`` when degenerate).
        repaired: ``()`` bool, a local update repaired a covariance.
        degenerate: ``()`` bool, ``<Upsilon^0, p> = 0`` (or not finite): the step kept the prediction.
    """

    intensity: GaussianMixture
    log_cardinality: Array
    loglik: Array
    repaired: Array
    degenerate: Array


def _pair_updates(local: LocalFilter, params: CPHDParams, predicted: GaussianMixture, zs: Array, t: Array):
    """Every component updated with every measurement: moments ``(K, M, d)``, ``(K, M, d, d)`` and
    ``log q_i(z)`` ``(K, M)`` from ``local.update`` (absent rows are fed as zeros and masked later)."""
    r_mean, r_cov = gaussian_moments(params.measurement_noise)
    zs_safe = jnp.where(measurement_mask(zs)[:, None], zs, 0.0)
    states = _local_states(local, predicted)
    upd, info = jax.vmap(lambda s: jax.vmap(lambda z: local.update(s, z, t, r_mean, r_cov))(zs_safe))(states)
    means, covs = jax.vmap(jax.vmap(local.moments))(upd)
    return means, covs, info.loglik, info.repaired


def update_cphd(
    local: LocalFilter,
    params: CPHDParams,
    predicted: GaussianMixture,
    log_cardinality: Array,
    zs: Array,
    t: Array,
) -> CPHDUpdate:
    """The GM-CPHD update (module docstring) over a padded measurement set ``zs`` ``(M, m)``.

    Args:
        local: the component filter.
        params: :class:`CPHDParams`.
        predicted: the predicted intensity, ``K`` slots.
        log_cardinality: ``(N_max + 1,)`` ``log p_{k|k-1}(n)``.
        zs: ``(M, m)`` measurements, a row with a non-finite entry is absent.
        t: the step's time.

    Returns:
        A :class:`CPHDUpdate`.
    """
    dtype = predicted.weights.dtype
    log_p = jnp.asarray(log_cardinality, dtype)
    n_max = log_p.shape[-1] - 1
    z_mask = measurement_mask(zs)
    n_z = jnp.sum(z_mask.astype(jnp.int32))
    p_d = jnp.asarray(params.detection_prob, dtype)
    lam = jnp.asarray(params.clutter_rate, dtype)
    log_c = jnp.log(jnp.asarray(params.clutter_density, dtype))
    means, covs, loglik_q, repaired = _pair_updates(local, params, predicted, zs, t)

    # normalised weights s_i = w_i / W (the spatial density of the i.i.d. cluster process)
    w = jnp.where(predicted.mask, predicted.weights, 0.0)
    total = jnp.sum(w)
    live = predicted.mask & (w > 0)
    log_s = jnp.where(
        live, jnp.log(jnp.where(live, w, 1.0)) - jnp.log(jnp.where(total > 0, total, 1.0)), -jnp.inf
    )
    pair = live[:, None] & z_mask[None, :]
    # log(P_D s_i q_i(z) <1, kappa> / kappa(z)) = log(P_D s_i q_i(z) / c(z))       (K, M)
    log_det = jnp.where(
        pair, jnp.log(p_d) + log_s[:, None] + jnp.where(pair, loglik_q, 0.0) - log_c, -jnp.inf
    )
    log_lambda = _lse(log_det, axis=0)  # (M,) log of Lambda(w, Z) / W

    log_e = log_esf(log_lambda, z_mask)
    log_e_wo = log_esf_leave_one_out(log_lambda, z_mask)
    ups0 = log_upsilon(log_e, n_z, 0, lam, p_d, n_max)
    ups1 = log_upsilon(log_e, n_z, 1, lam, p_d, n_max)
    ups1_wo = jax.vmap(lambda e: log_upsilon(e, n_z - 1, 1, lam, p_d, n_max))(log_e_wo)  # (M, N+1)

    norm = _lse(ups0 + log_p)
    ok = jnp.isfinite(norm)
    safe_norm = jnp.where(ok, norm, 0.0)
    ratio_missed = _lse(ups1 + log_p) - safe_norm  # log <Upsilon^1[Z], p> / <Upsilon^0[Z], p>  (times W)
    ratio_det = _lse(ups1_wo + log_p[None, :], axis=1) - safe_norm  # (M,) ... [Z \ {z}] ...
    log_post = jnp.where(ok, ups0 + log_p - safe_norm, log_p)

    missed_w = jnp.where(ok, (1.0 - p_d) * jnp.exp(log_s + ratio_missed), w)
    det_w = jnp.where(pair & ok, jnp.exp(jnp.where(pair, log_det + ratio_det[None, :], -jnp.inf)), 0.0)
    K, M = det_w.shape
    d = predicted.dim
    missed = GaussianMixture(missed_w, predicted.means, predicted.covs, predicted.mask)
    det_mask = predicted.mask[:, None] & z_mask[None, :]
    detected = GaussianMixture(
        det_w.T.reshape(K * M),
        jnp.swapaxes(means, 0, 1).reshape(K * M, d),
        jnp.swapaxes(covs, 0, 1).reshape(K * M, d, d),
        det_mask.T.reshape(K * M),
    )
    out = gmm.sanitize(gmm.concat(missed, detected))
    loglik = jnp.where(ok, norm + n_z.astype(dtype) * log_c, -jnp.inf)
    any_repaired = jnp.any(jnp.where(det_mask, repaired, False))
    return CPHDUpdate(out, log_post, loglik, any_repaired, ~ok)


# ----------------------------------------------------------------------------- extraction


def extract_map(intensity: GaussianMixture, log_cardinality: Array, *, max_estimates: int) -> Estimates:
    """State extraction of the GM-CPHD: the MAP cardinality, then the heaviest components' means.

    ``n_hat = argmax_n p(n)`` (the smallest ``n`` on ties); the estimates are the means of the
    ``min(n_hat, live components)`` heaviest components (heaviest first).

    Args:
        intensity: the (reduced) posterior intensity, ``J`` slots.
        log_cardinality: ``(N_max + 1,)`` ``log p(n)``.
        max_estimates: static ``E``, the capacity of the estimate set.

    Returns:
        An :class:`~gmjax.multitarget.phd.Estimates` (``overflow`` when more than ``E`` are extracted).
    """
    n_hat = jnp.argmax(log_cardinality).astype(jnp.int32)
    w = jnp.where(intensity.mask, intensity.weights, -jnp.inf)
    order = jnp.argsort(-w, stable=True)
    count = jnp.minimum(n_hat, gmm.n_active(intensity).astype(jnp.int32))
    slot = jnp.arange(max_estimates)
    mask = slot < count
    comp = order[jnp.minimum(slot, intensity.capacity - 1)]
    states = jnp.where(mask[:, None], intensity.means[comp], 0.0)
    return Estimates(states, mask, count, count > max_estimates)


# ----------------------------------------------------------------------------- the filter


def _check_n_max(n_max: Any) -> int:
    if isinstance(n_max, bool) or not isinstance(n_max, (int, np.integer)) or int(n_max) < 1:
        raise ValueError(f"n_max: expected an int >= 1 (the largest cardinality kept), got {n_max!r}")
    return int(n_max)


def _check_pmf(pmf: Any, n_max: int, dtype) -> Array:
    p = np.asarray(pmf, np.float64)
    if p.shape != (n_max + 1,):
        raise ValueError(f"initial_cardinality: expected a pmf of shape ({n_max + 1},), got {p.shape}")
    if not np.all(np.isfinite(p)) or np.any(p < 0) or abs(p.sum() - 1.0) > 1e-6:
        raise ValueError("initial_cardinality: must be finite, non-negative and sum to 1")
    return jnp.asarray(p / p.sum(), dtype)


def gm_cphd(
    model: StateSpaceModel,
    *,
    birth: GaussianMixture,
    survival_prob: float = 0.99,
    detection_prob: float = 0.98,
    clutter_rate: float = 10.0,
    clutter_density: float,
    n_max: int = 100,
    reducer: Any = None,
    capacity: int = 100,
    merge_capacity: int | None = None,
    max_estimates: int | None = None,
    local: str = "kf",
    truncation_tolerance: float = 1e-5,
    cardinality_tolerance: float = 1e-5,
    initial: GaussianMixture | None = None,
    initial_cardinality: Any = None,
    reducer_input: str = "intensity",
    keep_pruned_mass: bool = False,
    local_kwargs: dict | None = None,
) -> Filter:
    """Build a GM-CPHD filter (Vo, Vo & Cantoni 2007) as a :class:`~gmjax.filters.Filter`.

    The arguments shared with :func:`gmjax.multitarget.gm_phd` mean the same (so
    ``gm_cphd(model, **scenario.filter_kwargs(), n_max=...)`` works). The birth cardinality is Poisson
    with mean ``sum(birth.weights)``; the clutter cardinality is Poisson with mean ``clutter_rate``.

    Args:
        model: the single-target model (``f``, ``h``, noises; ``model.prior`` is not used).
        birth: the birth intensity, ``J_b`` slots.
        survival_prob, detection_prob: ``P_S``, ``P_D`` in ``(0, 1]``.
        clutter_rate: ``lambda_c >= 0``; clutter_density: ``c(z) > 0`` (``1 / V`` for uniform clutter).
        n_max: static ``N_max >= 1``, the largest cardinality kept (distributions over ``0 .. N_max``).
        reducer: any Reducer config (default ``VoMa(1e-5, 4.0, max_components=capacity)``).
        capacity: static ``J``, the posterior intensity's slots.
        merge_capacity: static, how many of the heaviest updated components the reducer receives
            (default ``4 J``).
        max_estimates: static ``E``, the capacity of the estimate set (default ``J``).
        local: the component filter (:data:`gmjax.filters.local.LOCAL_FILTERS`).
        truncation_tolerance: see :mod:`gmjax.multitarget.phd`.
        cardinality_tolerance: the cardinality mass beyond ``N_max`` a prediction may cut silently.
        initial: the intensity at time 0 (default: empty).
        initial_cardinality: ``(N_max + 1,)`` pmf at time 0 (default: Poisson with the mean
            ``initial``'s total weight, truncated at ``N_max``; a point mass at 0 for an empty one).
        reducer_input, keep_pruned_mass, local_kwargs: as in :func:`gmjax.multitarget.gm_phd`.

    Returns:
        ``Filter(init, predict, update, params)`` with ``params`` a :class:`CPHDParams` and states
        :class:`CPHDState`. ``update`` takes a padded measurement set ``(M, m)`` (NaN rows absent) and
        returns a :class:`StepInfo` with ``mean``/``cov`` the moments of the normalised intensity,
        ``loglik`` (:class:`CPHDUpdate`), ``n_components``, ``flags`` (``overflow``: truncation above
        tolerance, cardinality mass beyond ``N_max`` above ``cardinality_tolerance``, reducer or
        capacity overflow, or more estimates than ``E``; ``repaired``; ``degenerate``: an impossible
        measurement set or a non-finite cardinality; ``nonfinite_measurement``: a row with an infinite
        entry, ignored), ``reduction`` and ``extra``: ``cardinality`` (the mean of ``p_k``),
        ``cardinality_variance``, ``cardinality_map`` (``n_hat``), ``intensity_mass`` (sum of the
        updated weights before reduction: the same mean, to rounding), ``cardinality_reduced``
        (after), ``cardinality_tail`` (mass cut at ``N_max`` by this step's prediction),
        ``n_estimates``, ``estimates`` ``(E, d)``, ``estimate_mask`` ``(E,)``, ``truncated_mass`` and
        ``n_measurements``.

    Raises:
        ValueError: a bad argument, naming it.
    """
    d, m = _check_model_and_birth(model, local, birth)
    n_max = _check_n_max(n_max)
    _check_prob(survival_prob, "survival_prob", open_low=True)
    _check_prob(detection_prob, "detection_prob", open_low=True)
    if not float(clutter_rate) >= 0 or not np.isfinite(float(clutter_rate)):
        raise ValueError(f"clutter_rate: must be finite and >= 0, got {clutter_rate!r}")
    if not float(clutter_density) > 0 or not np.isfinite(float(clutter_density)):
        raise ValueError(f"clutter_density: must be finite and > 0, got {clutter_density!r}")
    for name, tol in (
        ("truncation_tolerance", truncation_tolerance),
        ("cardinality_tolerance", cardinality_tolerance),
    ):
        if not float(tol) >= 0:
            raise ValueError(f"{name}: must be >= 0, got {tol!r}")
    capacity, merge_capacity, max_estimates, reducer = _check_sizes_and_reducer(
        capacity, merge_capacity, max_estimates, reducer_input, reducer
    )
    dtype = birth.weights.dtype
    initial = _initial_intensity(initial, capacity, d, birth.means.dtype)
    if initial_cardinality is None:
        pmf0 = np.exp(np.asarray(poisson_log_pmf(n_max, float(gmm.total_weight(initial))), np.float64))
        initial_cardinality = pmf0 / pmf0.sum()
    initial_pmf = _check_pmf(initial_cardinality, n_max, dtype)
    lf = local_filter_for(model, local, **(local_kwargs or {}))
    process_noise, measurement_noise = _model_noises(model, dtype)
    params = CPHDParams(
        birth=birth,
        survival_prob=jnp.asarray(survival_prob, dtype),
        detection_prob=jnp.asarray(detection_prob, dtype),
        clutter_rate=jnp.asarray(clutter_rate, dtype),
        clutter_density=jnp.asarray(clutter_density, dtype),
        process_noise=process_noise,
        measurement_noise=measurement_noise,
        reducer=reducer,
        truncation_tolerance=jnp.asarray(truncation_tolerance, dtype),
        cardinality_tolerance=jnp.asarray(cardinality_tolerance, dtype),
        initial=initial,
        initial_cardinality=initial_pmf,
    )
    normalized = reducer_input == "normalized"

    def init(params: CPHDParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None):
        """``prior=None``: ``params.initial`` and ``params.initial_cardinality``; a GaussianMixture
        prior gets the Poisson cardinality of its total weight, truncated at ``N_max``."""
        del key
        if prior is None:
            gm, _ = _fit(params.initial, capacity)
            pmf = jnp.asarray(params.initial_cardinality)
            log_p = jnp.where(pmf > 0, jnp.log(jnp.where(pmf > 0, pmf, 1.0)), -jnp.inf)
        else:
            gm, _ = _fit(prior, capacity)
            log_p, _ = _normalize_log(poisson_log_pmf(n_max, gmm.total_weight(gm)))
        log_p = log_p.astype(gm.weights.dtype)
        return CPHDState(gm, log_p, jnp.zeros((), gm.weights.dtype))

    def predict(params: CPHDParams, state: CPHDState, inputs: StepInputs, *, key: PRNGKey | None = None):
        del key
        intensity = predict_intensity(lf, params.as_phd(), state.intensity, inputs.t)
        birth_mean = gmm.total_weight(params.birth).astype(intensity.weights.dtype)
        log_p, tail = predict_cardinality(state.log_cardinality, params.survival_prob, birth_mean)
        return CPHDState(intensity, log_p, tail)

    def update(
        params: CPHDParams, state: CPHDState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ):
        zs = jnp.asarray(z)
        if zs.ndim != 2 or zs.shape[-1] != m:
            raise ValueError(f"z: expected a padded measurement set of shape (M, {m}), got {zs.shape}")
        predicted = state.intensity
        upd = update_cphd(
            lf, params, predicted, state.log_cardinality, zs.astype(predicted.means.dtype), inputs.t
        )
        work, truncated, heaviest_dropped = _truncate(upd.intensity, merge_capacity)
        reduced, rinfo = _reduce(
            params.reducer, work, normalized=normalized, keep_pruned_mass=keep_pruned_mass, key=key
        )
        post, cap_overflow = _fit(reduced, capacity)
        est = extract_map(post, upd.log_cardinality, max_estimates=max_estimates)
        card_mean, card_var = cardinality_moments(upd.log_cardinality)
        mean, cov = gmm.moments(post)
        overflow = (heaviest_dropped > params.truncation_tolerance) | rinfo.overflow | cap_overflow
        overflow = overflow | est.overflow | (state.tail_mass > params.cardinality_tolerance)
        degenerate = upd.degenerate | ~jnp.isfinite(card_mean) | ~jnp.isfinite(gmm.total_weight(post))
        flags = StepFlags(upd.repaired, overflow, degenerate, jnp.any(jnp.isinf(zs)))
        extra = {
            "cardinality": card_mean,
            "cardinality_variance": card_var,
            "cardinality_map": jnp.argmax(upd.log_cardinality).astype(jnp.int32),
            "intensity_mass": gmm.total_weight(upd.intensity),
            "cardinality_reduced": gmm.total_weight(post),
            "cardinality_tail": state.tail_mass,
            "n_estimates": est.n_estimates,
            "estimates": est.states,
            "estimate_mask": est.mask,
            "truncated_mass": truncated,
            "n_measurements": jnp.sum(measurement_mask(zs).astype(jnp.int32)),
        }
        info = StepInfo(mean, cov, upd.loglik, gmm.n_active(post), flags, rinfo, extra)
        return CPHDState(post, upd.log_cardinality, state.tail_mass), info

    return Filter(init, predict, update, params)
