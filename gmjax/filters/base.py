"""The one filter contract (see ``docs/design.md`` §3).

Every filter of gmjax — the Gaussian local filters, the Gaussian sum filter, IMM, IMM-GSF, AGSSCKF,
the seed 004 bank and the particle filters — is a :class:`Filter`: a NamedTuple of three pure
functions and the default parameters they read.

* ``init(params, prior, *, key) -> state`` (``prior=None``: the prior held in ``params``);
* ``predict(params, state, inputs, *, key) -> state``;
* ``update(params, state, z, inputs, *, key) -> (state, StepInfo)``.

``params`` is a pytree (dynamax style): the model's noises and prior, a reducer config, thresholds.
Nothing numeric is baked into the functions, so ``jax.vmap`` over parameter sets and ``jax.grad``
with respect to a noise covariance or a pruning threshold go through :func:`run`. ``inputs`` is the
per-step :class:`StepInputs` pytree (the time ``t``; room for ``dt``, a control and filter-specific
``aux`` data such as the bank's true active cluster). The PRNG key is passed on every call (``None``
is accepted by filters that draw nothing); no key is hidden in a state. :class:`StepInfo` is the one
report every filter returns, with the fields every consumer reads and an ``extra`` dict for what is
filter-specific.

Time indexing of :func:`run`: the initial state describes ``x_0``; step ``k = 0 .. T-1`` predicts to
``inputs.t[k]`` and updates with ``zs[k]``, so ``states[k]`` is the posterior at ``inputs.t[k]``
given ``zs[:k+1]``. The default times are ``1, 2, ..., T``. A measurement with any non-finite
entry (NaN or ``±inf``) is a predict-only step (log-likelihood 0) and raises
``StepFlags.nonfinite_measurement``; every filter recovers at the next finite measurement.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._jitcache import IdentityCache
from gmjax._types import Array, PRNGKey
from gmjax._validate import is_concrete
from gmjax.inputs import StepInputs, step_inputs
from gmjax.mixture import GaussianMixture
from gmjax.models.base import LinearGaussianParams

__all__ = ["StepInputs", "StepFlags", "StepInfo", "Filter", "step_inputs", "no_flags", "run", "scan_steps"]


class StepFlags(NamedTuple):
    """What went wrong in a step (``()`` bools; inside ``jit`` failures are data, not exceptions).

    Attributes:
        repaired: a covariance was not numerically positive definite and was repaired.
        overflow: more components survived than the capacity holds (the heaviest were kept).
        degenerate: every likelihood underflowed (weights kept at their predicted values), or a
            particle cloud collapsed (its effective sample size fell below 1.5 particles).
        nonfinite_measurement: the measurement held a NaN or an infinite entry; the step was
            predict-only (state = prediction, log-likelihood 0). A NaN is also the way to mark a
            missing measurement on purpose; the flag then records that the step had no data, so
            :meth:`any` (what a Monte Carlo study counts) includes such steps.
    """

    repaired: Array
    overflow: Array
    degenerate: Array
    nonfinite_measurement: Array

    def any(self) -> Array:
        """``()`` bool: any flag raised."""
        return self.repaired | self.overflow | self.degenerate | self.nonfinite_measurement


def no_flags() -> StepFlags:
    """All flags down."""
    f = jnp.zeros((), bool)
    return StepFlags(f, f, f, f)


class StepInfo(NamedTuple):
    """The per-step report of every filter's ``update``.

    Attributes:
        mean: ``(d,)`` the point estimate (for Gaussian sum filters the moments of the updated
            mixture before reduction, seed 000 eq 17).
        cov: ``(d, d)`` its covariance (eq 18).
        loglik: ``()`` ``log p(z_k | z_{1:k-1})`` under the filter (0 on a predict-only step).
        n_components: ``()`` int32, live mixture components after the step (1 for filters that keep
            no mixture: single-Gaussian and particle filters).
        flags: :class:`StepFlags`.
        reduction: the reducer's :class:`~gmjax.reduction.ReductionInfo`, or ``None`` for filters
            that do not reduce.
        extra: a dict of filter-specific diagnostics (documented by each builder).
    """

    mean: Array
    cov: Array
    loglik: Array
    n_components: Array
    flags: StepFlags
    reduction: Any = None
    extra: dict[str, Any] = {}


class Filter(NamedTuple):
    """A filter: pure functions of ``(params, state, ...)`` and the default ``params``.

    Attributes:
        init: ``(params, prior: GaussianMixture | None, *, key) -> state``.
        predict: ``(params, state, inputs: StepInputs, *, key) -> state``.
        update: ``(params, state, z (m,), inputs: StepInputs, *, key) -> (state, StepInfo)``; a ``z``
            with a NaN or ``±inf`` entry is a predict-only step, flagged ``nonfinite_measurement``.
        params: the default parameter pytree (from the model and the configuration); replace it to
            vmap, differentiate or tune.
    """

    init: Callable[..., Any]
    predict: Callable[..., Any]
    update: Callable[..., tuple[Any, StepInfo]]
    params: Any = None


def measurement_dim(params: Any) -> int | None:
    """The measurement dimension ``m`` a filter's ``params`` imply, or ``None`` when they do not say.

    Read from the first model-level parameter set in the pytree (anything with a
    ``measurement_noise`` mixture: :class:`~gmjax.models.ModelParams`, also inside the IMM's tuple
    of models) or from the ``H`` matrix of :class:`~gmjax.models.LinearGaussianParams`.
    """

    def found(x):
        return isinstance(x, LinearGaussianParams) or isinstance(
            getattr(x, "measurement_noise", None), GaussianMixture
        )

    for node in jax.tree_util.tree_leaves(params, is_leaf=found):
        if isinstance(node, LinearGaussianParams):
            return int(jnp.shape(node.H)[0]) if jnp.ndim(node.H) == 2 else None
        if found(node):
            return int(node.measurement_noise.dim)
    return None


def check_measurements(zs: Array, m: int | None = None) -> Array:
    """``zs`` as an array of shape ``(T, m)`` (static shape checks; fine under ``jit``).

    Raises:
        ValueError: naming ``zs``: not 2-D, or ``m`` columns expected and not found.
    """
    zs = jnp.asarray(zs)
    if zs.ndim != 2:
        raise ValueError(f"zs: expected shape (T, m), got {zs.shape}")
    if m is not None and zs.shape[1] != m:
        raise ValueError(
            f"zs: the filter's model measures m={m} values per step, but zs has shape {zs.shape} "
            f"(expected (T, {m}))"
        )
    return zs


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
    """Run any :class:`Filter` over a measurement sequence with one ``lax.scan``.

    Args:
        filter: the filter.
        zs: ``(T, m)`` measurements; a row with a NaN or ``±inf`` entry is a predict-only step
            (flagged ``nonfinite_measurement``).
        inputs: per-step inputs: ``None`` (times ``1..T``), a ``(T,)`` array of times, or a
            :class:`StepInputs` with a leading ``T`` axis.
        key: PRNG key (required by filters that draw: particle filters, randomised reducers);
            ``init`` gets one split and step ``k`` the ``k``-th of ``jax.random.split(rest, T)``,
            split again between predict and update.
        params: parameters (default ``filter.params``).
        prior: the prior of ``x_0`` (default: the one in ``params``).
        init_state: a ready initial state; overrides ``prior``.

    Returns:
        ``(states, infos)`` with a leading ``T`` axis; ``infos`` is a :class:`StepInfo`.

    Raises:
        ValueError: ``zs`` not ``(T, m)`` with the model's ``m`` (see :func:`measurement_dim`),
            or inputs without the leading ``T`` axis.

    Called eagerly (no argument traced), ``init`` runs eagerly as always and the scan is a ``jax.jit``
    kept per filter object, so calling ``run`` again with new measurements, inputs, keys, priors or
    ``params`` of the same shapes does not compile again.
    """
    params = filter.params if params is None else params
    zs = check_measurements(zs, measurement_dim(params))
    if not is_concrete(zs, inputs, key, params, prior, init_state):
        return scan_steps(filter, params, zs, inputs, key=key, prior=prior, init_state=init_state)
    if init_state is None:
        k_init = None if key is None else jax.random.split(key)[0]  # as in scan_steps
        init_state = filter.init(params, prior, key=k_init)
    scan = _EAGER_SCANS.get((filter,), lambda: _compiled_scan(filter))
    return scan(params, zs, inputs, key, init_state)


_EAGER_SCANS = IdentityCache(maxsize=32)


def _compiled_scan(filter: Filter) -> Callable[..., tuple[Any, StepInfo]]:
    """``jit`` of :func:`scan_steps` for one filter, taking ``(params, zs, inputs, key, init_state)``
    (``params`` traced, as the contract allows)."""

    def scan(params, zs, inputs, key, init_state):
        return scan_steps(filter, params, zs, inputs, key=key, init_state=init_state)

    return jax.jit(scan)


def scan_steps(
    filter: Filter,
    params: Any,
    zs: Array,
    inputs: Any = None,
    *,
    key: PRNGKey | None = None,
    prior: GaussianMixture | None = None,
    init_state: Any = None,
) -> tuple[Any, StepInfo]:
    """The ``lax.scan`` behind :func:`run`, without checking ``zs`` (for filters whose per-step
    measurement is not a ``(m,)`` vector, e.g. the padded sets of :mod:`gmjax.multitarget`).

    The key splits as in :func:`run`: one key for ``init``, then one per step, split into predict
    and update keys.
    """
    n_steps = zs.shape[0]
    inputs = step_inputs(n_steps, inputs)
    if key is None:
        k_init, step_keys = None, None
    else:
        k_init, k_steps = jax.random.split(key)
        step_keys = jax.random.split(k_steps, n_steps)
    state0 = filter.init(params, prior, key=k_init) if init_state is None else init_state
    zs, inputs = _in_state_dtype(state0, zs, inputs)

    def step(state, xs):
        z, inp, k = xs
        k_pred, k_upd = (None, None) if k is None else jax.random.split(k)
        state = filter.predict(params, state, inp, key=k_pred)
        state, info = filter.update(params, state, z, inp, key=k_upd)
        return state, (state, info)

    _, (states, infos) = jax.lax.scan(step, state0, (zs, inputs, step_keys))
    return states, infos


def _in_state_dtype(state: Any, zs: Array, inputs: StepInputs) -> tuple[Array, StepInputs]:
    """``zs`` and the floating leaves of ``inputs`` cast to the floating dtype of the filter's state.

    A float32 model run on float64 measurements (or times) under x64 would otherwise promote the
    state to float64 in the first step and break the scan's carry; the model's dtype decides, as a
    float32 model asked for float32 arithmetic. A state with no floating leaf, or with several
    floating dtypes, leaves the arrays as they are.
    """
    dtypes = {leaf.dtype for leaf in jax.tree_util.tree_leaves(state) if _is_floating(leaf)}
    if len(dtypes) != 1:
        return zs, inputs
    (dtype,) = dtypes
    if jnp.issubdtype(zs.dtype, jnp.number) and zs.dtype != dtype:
        zs = zs.astype(dtype)
    inputs = jax.tree_util.tree_map(lambda x: x.astype(dtype) if _is_floating(x) else x, inputs)
    return zs, inputs


def _is_floating(leaf: Any) -> bool:
    """Whether ``leaf`` is an array of a real floating dtype."""
    return hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating)
