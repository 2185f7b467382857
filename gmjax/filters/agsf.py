"""Adaptive Gaussian-sum square-root cubature Kalman filter with split-merge (AGSSCKF; Liu et al. 2014 = seed 001).

One time step of Table 1 is split over the two halves of a :class:`~gmjax.filters.Filter`
(``params`` is an :class:`AGSFParams`; ``inputs.t`` is the time passed to ``f`` and ``h``):

* ``predict(params, state, inputs)`` is **Step 7** (eqs 40–41): every posterior component ``j'`` is
  paired with every process-noise component ``l`` (``q`` of them) and propagated by a square-root
  cubature predict (eqs 8–12) with noise ``N(w_l, Q_l)`` (the shared kernel
  :func:`gmjax.filters.gsf.gs_predict`); weight ``alpha_j' beta_l``; slot ``j = l N + j'``
  (noise-major, as eq 41 numbers them).
* ``update(params, state, z, inputs)`` is **Steps 2–6**:

  - *Step 2–3, adaptive splitting.* While ``N < N_max``: the degree of nonlinearity (DON, eqs 26–29,
    :func:`degree_of_nonlinearity`) of every predicted component is computed from its cubature
    points through ``h(., t)``; the component with the largest DON is split by the split-decision
    model (eq 31, levels below) along the principal eigenvector of its covariance (eq 32,
    :func:`gmjax.split.split_gated`); the loop stops at the first component that is not split.
  - *Step 4*, square-root cubature update of every component (eqs 13–22, 33) and the weights of
    eqs 34–35: ``alpha^{m,f} ∝ p(z | m, f) alpha^m alpha^{m,f}``, i.e. a child's prior weight is its
    parent's weight times its split fraction; normalised in the log domain (the shared kernel
    :func:`gmjax.filters.gsf.gs_update` with the one measurement-noise component).
  - *Step 5*, the global estimate (eqs 36–38): the moments of the updated mixture (reported in
    ``StepInfo.mean`` / ``cov``, before Step 6, like :func:`gmjax.filters.gsf.build_gsf`).
  - *Step 6*, pruning and the three merge rules (eq 39): the stateful reducer :class:`Step6Merge`.

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
renormalised and ``StepInfo.flags.overflow`` says so (a designed cap, not a failure).

**Step 6, our reading.** The paper gives the three rules in words. "Before and after a time step"
is read as *at the previous time step's Step 6 and now*: every working slot remembers its ancestor
(the posterior slot it descends from through prediction and splitting). This history is the
:class:`Step6State` of the reducer, one entry per slot (the ancestor's slot, weight and DON, and
its row of the previous posterior's pair-cost matrix), carried in :class:`AGSFState` and given to
each child by prediction and splitting (see :class:`Step6Merge` for the rules): predicted slot
``l N + j'`` gets the entries of posterior slot ``j'`` (the contract's
:func:`~gmjax.filters.gsf.inherit`, reordered to eq 41's numbering), a split child those of the
split component, and the filter writes each working component's DON into the state before Step 6.

**GSCKF and GSUKF peers.** The paper's GSCKF (Pei et al. 2013) is a Gaussian-sum CKF with its own,
non-adaptive split-merge. We take GSCKF = this engine *without splitting* (``psi_th = inf``): same
sub-filters, same pruning and merging (:func:`build_gsckf`), so the comparison isolates adaptive
splitting and AGSSCKF with ``psi_th = inf`` equals GSCKF exactly. GSUKF is the same engine with UKF
sub-filters (``kappa = 3 - n``, :func:`build_gsukf`).

The measurement noise must be a single Gaussian (as in both examples of §4).

**Loops.** The split loop (at most ``min(N_max, capacity)`` splits) and the merge loop (at most
``capacity - 1`` merges) have static bounds. They are ``lax.while_loop`` s that exit at the first
step with nothing to do; their derivatives come from a custom JVP rule that differentiates the same
loops run with the static trip count (same values), so ``jax.grad`` and ``jax.jvp`` through
:func:`~gmjax.filters.run` reach the noises in ``params.model`` and the thresholds (with the hard
gate the split and merge decisions are piecewise constant; a smooth ``split_gate`` makes the output
differentiable in ``psi_th``, ``r``), and an undifferentiated run pays for the early exit only.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import _validate
from gmjax import mixture as gmm
from gmjax._loops import bounded_loop
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.filters._core import LocalFilter, check_model, is_missing, safe_chol
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs
from gmjax.filters.gsf import gs_predict, gs_update, inherit
from gmjax.filters.local import local_filter_for
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams, StateSpaceModel
from gmjax.reduction.step6 import Step6Merge, Step6State
from gmjax.split import split_gated

__all__ = [
    "AGSFConfig",
    "AGSFParams",
    "AGSFState",
    "Step6Merge",
    "Step6State",
    "degree_of_nonlinearity",
    "hard_gate",
    "build_agsf",
    "build_gsckf",
    "build_gsukf",
]


@pytree_dataclass
class AGSFConfig:
    """Configuration of :func:`build_agsf` (defaults: seed 001 §4).

    Static fields change the compiled code (changing them recompiles). Traced fields are thresholds:
    differentiable, no recompilation; the filter reads them from ``params.config`` at every call.

    Static fields:
        n_max: ``N_max``, the largest number of sub-filters (15).
        capacity: working slots of Steps 2–6 (default ``None`` = ``n_max``); the posterior keeps
            ``capacity // q`` slots (``q`` process-noise components). See the module docstring.
        max_level: the largest ``n`` of eq 31 (``N_F <= 2^max_level``); 0 disables splitting.
        split_gate: ``(psi, threshold) -> gate in [0, 1]``; ``None`` is the hard step
            ``psi >= threshold`` (the paper).

    Traced fields:
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


class AGSFParams(NamedTuple):
    """Parameters of :func:`build_agsf` (a pytree: vmap, differentiate or tune them).

    Attributes:
        model: the prior, GM process noise and single-Gaussian measurement noise.
        config: the :class:`AGSFConfig` (its thresholds are leaves; its static fields must be the
            ones the filter was built with).
    """

    model: ModelParams
    config: AGSFConfig


class AGSFState(NamedTuple):
    """State of the AGSSCKF (the ``lax.scan`` carry is the posterior).

    Attributes:
        mixture: after ``update``: the posterior after Step 6, ``capacity // q`` slots; after
            ``predict``: the predicted mixture in the ``capacity`` working slots.
        step6: the :class:`Step6State` aligned with ``mixture``'s slots (after ``update`` each
            posterior component is its own ancestor, with the DON recorded at its Step 2;
            ``inf`` for the prior).
    """

    mixture: GaussianMixture
    step6: Step6State


# ---------------------------------------------------------------------------------------------
# Degree of nonlinearity (eqs 26–29)


def degree_of_nonlinearity(
    h: Callable[[Array, Array], Array],
    mean: Array,
    cov: Array,
    t: ArrayLike = 0,
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


def _step6(config: AGSFConfig, capacity: int) -> Step6Merge:
    """The Step 6 reducer with the thresholds of ``config`` (read at each call)."""
    return Step6Merge(
        prune_threshold=config.prune_threshold,
        low_weight=config.low_weight,
        merge_threshold=config.merge_threshold,
        merge_don=config.merge_don,
        capacity=capacity,
    )


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
    if config.capacity is not None and (not isinstance(config.capacity, int) or config.capacity < 1):
        raise ValueError(f"config.capacity: must be a positive int or None, got {config.capacity!r}")
    if config.split_gate is not None and not callable(config.split_gate):
        raise ValueError("config.split_gate: must be a callable (psi, threshold) -> gate or None")
    concrete = _validate.is_concrete(config.psi_th, config.r, config.l, config.w)
    if concrete:
        if not float(config.psi_th) >= 0:
            raise ValueError(f"config.psi_th: must be >= 0 (inf allowed), got {config.psi_th!r}")
        if not float(config.r) >= 1:
            raise ValueError(f"config.r: eq 31 needs r >= 1, got {config.r!r}")
        if not 0 < float(config.l) < 1:
            raise ValueError(f"config.l: eq 32 needs 0 < l < 1, got {config.l!r}")
        if not 0 < float(config.w) < 1:
            raise ValueError(f"config.w: eq 32 needs 0 < omega < 1, got {config.w!r}")
    for name in ("prune_threshold", "low_weight", "merge_threshold", "merge_don"):
        _validate.validate_nonneg(getattr(config, name), f"config.{name}")


def _static_part(config: AGSFConfig) -> tuple:
    return (config.n_max, config.capacity, config.max_level, config.split_gate)


def _single_noise(noise: GaussianMixture) -> GaussianMixture:
    """The one-component mixture ``N(mean, cov)`` of a single-Gaussian measurement noise."""
    mean, cov = gmm.moments(noise)
    return GaussianMixture(jnp.ones((1,), mean.dtype), mean[None], cov[None], jnp.ones((1,), bool))


def _noise_major(tree: Any, n_post: int, n_q: int) -> Any:
    """Reorder parent-major children ``j' q + l`` (``gs_predict``, ``inherit``) to eq 41's ``l N + j'``."""

    def one(a):
        return jnp.swapaxes(a.reshape((n_post, n_q) + a.shape[1:]), 0, 1).reshape(a.shape)

    return jax.tree_util.tree_map(one, tree)


def _pad_slots(tree: Any, capacity: int) -> Any:
    """Zero-pad every leaf's leading slot axis to ``capacity`` (padded slots hold no component)."""

    def one(a):
        extra = capacity - a.shape[0]
        return jnp.pad(a, [(0, extra)] + [(0, 0)] * (a.ndim - 1))

    return jax.tree_util.tree_map(one, tree)


class _Sizes(NamedTuple):
    C: int  # working slots
    Q: int  # process-noise components
    K_post: int  # posterior slots, C // Q
    N_lim: int  # min(N_max, C)
    L: int  # max_level


def _dons(h: Callable, gm: GaussianMixture, t: Any) -> Array:
    """``(K,)`` DON of every live component (0 in padded slots)."""
    eye = jnp.eye(gm.dim, dtype=gm.covs.dtype)
    covs = jnp.where(gm.mask[:, None, None], gm.covs, eye)
    means = jnp.where(gm.mask[:, None], gm.means, 0.0)
    psi = jax.vmap(lambda mu, P: degree_of_nonlinearity(h, mu, P, t))(means, covs)
    return jnp.where(gm.mask, psi, 0.0)


def _check_params(params: AGSFParams, static: tuple, n_q: int) -> AGSFConfig:
    """Validate ``params`` against the build (static fields, process-noise slots); its config."""
    if not isinstance(params, AGSFParams):
        raise ValueError(f"params: expected an AGSFParams, got {type(params).__name__}")
    if _static_part(params.config) != static:
        raise ValueError(
            "params.config: its static fields (n_max, capacity, max_level, "
            "split_gate) differ from the ones the filter was built with"
        )
    if params.model.process_noise.capacity != n_q:
        raise ValueError(
            f"params.model.process_noise: the filter was built for {n_q} slots, "
            f"got {params.model.process_noise.capacity}"
        )
    return params.config


def _init_state(cfg: AGSFConfig, sz: _Sizes, prior: Any) -> AGSFState:
    """The prior (eq 23) in the posterior slots, named as the previous posterior of Step 6 (DON
    unknown)."""
    if not isinstance(prior, GaussianMixture):
        raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
    n_live = gmm.n_active(prior)
    if _validate.is_concrete(n_live) and int(n_live) > sz.K_post:
        raise ValueError(
            f"prior: {int(n_live)} live components exceed the posterior capacity {sz.K_post} "
            f"(= capacity {sz.C} // {sz.Q} process-noise components); raise config.capacity"
        )
    fitted = gmm.pad(gmm.normalize(gmm.compact(prior)), max(sz.K_post, prior.capacity))
    fitted = jax.tree_util.tree_map(lambda a: a[: sz.K_post], fitted)
    return AGSFState(fitted, _step6(cfg, sz.K_post).history(fitted))


def _split_stage(
    h: Callable, gate: Callable, cfg: AGSFConfig, sz: _Sizes, gm: GaussianMixture, t: Any, enabled: Array
) -> tuple[GaussianMixture, Array, Array]:
    """Steps 2–3: split the most nonlinear component while ``N < N_max`` (eqs 26–32).

    Returns:
        ``(split mixture, origin (C,) int32, n_split ())``: ``origin[j]`` is the slot of the
        predicted mixture whose entries slot ``j`` inherits (itself when not a split child).
    """
    C, L = sz.C, sz.L
    origin0 = jnp.arange(C, dtype=jnp.int32)
    n_split0 = jnp.zeros((), jnp.int32)
    if L == 0:
        return gm, origin0, n_split0
    dtype = gm.means.dtype
    levels = jnp.arange(1, L + 1)
    sizes = 2**levels

    def body(carry):
        gm, origin, n_split = carry
        psi_all = jnp.where(gm.mask, _dons(h, gm, t), -jnp.inf)
        m = jnp.argmax(psi_all)
        psi = psi_all[m]
        N = gmm.n_active(gm)
        thresholds = jnp.asarray(cfg.psi_th, dtype) * jnp.asarray(cfg.r, dtype) ** (levels - 1).astype(dtype)
        psi_safe = jnp.where(jnp.isfinite(psi), psi, 0.0)
        g = gate(psi_safe, thresholds)
        fits = N - 1 + sizes <= sz.N_lim
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
        origin = origin.at[dest].set(origin[m], mode="drop")
        return (new, origin, n_split + do.astype(jnp.int32)), do

    return bounded_loop(sz.N_lim, body, (gm, origin0, n_split0))


def build_agsf(
    model: StateSpaceModel,
    config: AGSFConfig = AGSFConfig(),
    *,
    local: LocalFilter | str = "sckf",
) -> Filter:
    """Build the AGSSCKF of seed 001 (Table 1) as a :class:`~gmjax.filters.Filter`.

    Args:
        model: GM prior (eq 23) and GM process noise (eq 24); a single-Gaussian measurement noise.
            Their values are the defaults of ``params.model``; ``f`` and ``h`` stay in the filter.
        config: an :class:`AGSFConfig`; ``params.config``. Its static fields (``n_max``,
            ``capacity``, ``max_level``, ``split_gate``) and the number ``q`` of process-noise
            components fix the slot counts at build time; its thresholds are read from
            ``params.config`` at every call.
        local: the sub-filter (default ``"sckf"``, eqs 8–22); ``"ukf"`` / ``"ckf"`` or any
            :class:`LocalFilter` give the GSUKF / GSCKF variants. The DON always uses the cubature
            points of eq 26.

    Returns:
        ``Filter(init, predict, update, params)`` over :class:`AGSFState` with
        ``params = AGSFParams(model.params, config)``. ``predict`` (Step 7) gives the
        ``capacity`` working slots, ``update`` (Steps 2–6) the ``capacity // q`` posterior slots
        (an ``update`` without a preceding ``predict`` pads the posterior to the working slots).
        The :class:`~gmjax.filters.StepInfo` has ``mean`` / ``cov`` = eqs 36–38 of the updated
        mixture before Step 6, ``n_components`` after Step 6, ``flags.overflow`` = more than
        ``capacity // q`` components survived Step 6, ``reduction`` = Step 6's
        :class:`~gmjax.reduction.ReductionInfo` (:class:`Step6Merge`), and ``extra`` =
        ``{"n_predicted": live components after Step 7, "n_split": components split in Step 3,
        "n_updated": live components after splitting (the sub-filters of Step 4), "don_max": the
        largest DON of the predicted components}``.

    Raises:
        ValueError: bad model or config, a multi-component measurement noise, or a capacity that
            cannot hold one posterior component per process-noise component; at call time,
            params whose static part differs from the build.

    The builder is long only because it closes the three functions of the contract over ``f``,
    ``h``, the local filter and the static sizes; the steps themselves are module-level helpers.
    """
    check_model(model)
    _check_config(config)
    local = _resolve_local(model, local)
    rn = model.measurement_noise
    if _validate.is_concrete(rn.mask) and int(np.sum(np.asarray(rn.mask))) != 1:
        raise ValueError(
            f"model.measurement_noise: AGSSCKF (seed 001) assumes one Gaussian measurement noise, "
            f"got {int(np.sum(np.asarray(rn.mask)))} components"
        )
    Q = model.process_noise.capacity
    C = config.n_max if config.capacity is None else config.capacity
    if C < Q:
        raise ValueError(
            f"config.capacity: {C} working slots cannot hold the {Q} children of one component "
            f"(process noise has {Q} components)"
        )
    sz = _Sizes(C=C, Q=Q, K_post=C // Q, N_lim=min(config.n_max, C), L=config.max_level)
    gate = hard_gate if config.split_gate is None else config.split_gate
    h = model.step_fns()[1]  # h(x, inputs): the whole StepInputs reaches the model
    static = _static_part(config)

    def check_params(params: AGSFParams) -> AGSFConfig:
        return _check_params(params, static, Q)

    def init(
        params: AGSFParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None
    ) -> AGSFState:
        del key
        cfg = check_params(params)
        return _init_state(cfg, sz, params.model.prior if prior is None else prior)

    def predict(
        params: AGSFParams, state: AGSFState, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> AGSFState:
        """Step 7 (eqs 40–41): ``capacity // q`` posterior slots -> ``capacity`` working slots."""
        del key
        check_params(params)
        K = state.mixture.capacity
        noise = model.noise_at(params.model.process_noise, inputs)  # e.g. Q(dt)
        predicted = gs_predict(local, state.mixture, inputs, noise)
        predicted, step6 = _noise_major((predicted, inherit(state.step6, Q)), K, Q)
        return AGSFState(gmm.pad(predicted, C), _pad_slots(step6, C))

    def update(
        params: AGSFParams, state: AGSFState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> tuple[AGSFState, StepInfo]:
        """Steps 2–6 (eqs 26–39) on the ``capacity`` working slots."""
        cfg = check_params(params)
        t = inputs
        gm, step6 = state
        if gm.capacity < C:  # no prediction before this update
            gm, step6 = gmm.pad(gm, C), _pad_slots(step6, C)
        missing = is_missing(jnp.asarray(z))
        n_predicted = gmm.n_active(gm)
        don_max = jnp.max(jnp.where(gm.mask, _dons(h, gm, t), 0.0))

        # Steps 2-3; every split child inherits its parent's Step 6 history
        gm, origin, n_split = _split_stage(h, gate, cfg, sz, gm, t, ~missing)
        step6 = jax.tree_util.tree_map(lambda a: a[origin], step6)._replace(don=_dons(h, gm, t))

        # Step 4 (eqs 13-22, 33-35); one measurement-noise component: child i of slot i
        up = gs_update(local, gm, z, t, _single_noise(params.model.measurement_noise))

        # Step 5 (eqs 36-38)
        mean, cov = gmm.moments(up.mixture)

        # Step 6: pruning, then rules 1-3 (eq 39)
        merge = _step6(cfg, sz.K_post)
        post, step6, rinfo = merge.reduce(up.mixture, step6, key=key)
        info = StepInfo(
            mean=mean,
            cov=cov,
            loglik=up.loglik,
            n_components=gmm.n_active(post),
            flags=StepFlags(
                repaired=up.repaired,
                overflow=rinfo.overflow,
                degenerate=up.degenerate,
                nonfinite_measurement=missing,
            ),
            reduction=rinfo,
            extra={
                "n_predicted": n_predicted,
                "n_split": n_split,
                "n_updated": gmm.n_active(gm),
                "don_max": don_max,
            },
        )
        return AGSFState(post, step6), info

    return Filter(init, predict, update, AGSFParams(model.params, config))


def build_gsckf(model: StateSpaceModel, config: AGSFConfig = AGSFConfig()) -> Filter:
    """GSCKF peer of seed 001 Tables 2–3: :func:`build_agsf` with ``psi_th = inf`` (no splitting).

    Same square-root cubature sub-filters, pruning and merge rules as the AGSSCKF (see the module
    docstring for why this reading of the paper's GSCKF); ``params.config.psi_th`` is ``inf``.
    """
    return build_agsf(model, dataclasses.replace(config, psi_th=math.inf), local="sckf")


def build_gsukf(model: StateSpaceModel, config: AGSFConfig = AGSFConfig()) -> Filter:
    """GSUKF peer of seed 001 Tables 2–3: the GSCKF engine with UKF sub-filters (``kappa = 3 - n``)."""
    return build_agsf(model, dataclasses.replace(config, psi_th=math.inf), local="ukf")
