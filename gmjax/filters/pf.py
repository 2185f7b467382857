"""Bootstrap (SIR) and regularised particle filters.

A particle filter is a :class:`gmjax.filters.Filter` like the Gaussian ones and runs under
:func:`gmjax.filters.run`; its PRNG key is passed on every call (never kept in the state):

>>> pf = build_pf(model, 1000, resampling="systematic")
>>> states, infos = run(pf, zs, key=key)

Step (Gordon, Salmond & Smith 1993): predict ``x_i <- f(x_i, t) + v_i`` with ``v_i`` drawn from the
process-noise sampler; update ``log w_i += log p_w(z - h(x_i, t))`` and normalise (log domain);
resample when the effective sample size ``ESS = 1 / sum w_i^2`` falls below
``ess_threshold * N`` (``ess_threshold = 1`` resamples every step; 0 never).

The regularised PF (Musso, Oudjane & Le Gland 2001; the "regularised SIR PF" peer of seed 001)
adds, after each resampling, a Gaussian kernel draw ``h_opt * D eps_i`` with ``D D^T`` the
weighted particle covariance before resampling and
``h_opt = bandwidth_scale * (4 / (d + 2))^{1/(d+4)} N^{-1/(d+4)}`` (the optimal Gaussian-kernel
bandwidth).

Noises: the process noise is a :class:`GaussianMixture` (read from ``params`` at every call) or any
sampler ``(key, (N,)) -> (N, d)`` (e.g. a scenario's true-noise simulator, static code); the
measurement noise is a :class:`GaussianMixture` (in ``params``) or a log-density ``w (m,) -> ()``.

Angles (``model.angle_dims``): the residual ``z - h(x_i)`` is wrapped into ``[-pi, pi)``; with a GM
measurement noise each component's residual ``z - h(x_i) - r_j`` is wrapped again, so component
means that are angles act on the circle (a custom log-density receives the wrapped ``z - h(x_i)``).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters._core import check_model, is_missing, loglik_from_chol, safe_chol
from gmjax.filters.base import Filter, StepFlags, StepInfo, StepInputs
from gmjax.mixture import GaussianMixture
from gmjax.models.base import ModelParams, StateSpaceModel, wrap_angles

__all__ = [
    "TimedSampler",
    "PFState",
    "PFParams",
    "effective_sample_size",
    "multinomial",
    "systematic",
    "stratified",
    "residual",
    "RESAMPLERS",
    "build_pf",
    "pf_moments",
    "kernel_bandwidth",
]


class TimedSampler(NamedTuple):
    """Wrap a per-draw, time-dependent noise simulator ``(key, t) -> (d,)`` for :func:`build_pf`.

    This is the signature of ``Scenario.sample_process_noise``; the particle filter draws one
    sample per particle with independent keys (``vmap`` over ``jax.random.split(key, N)``) and
    passes ``inputs.t`` as ``t``.
    """

    fn: Callable[[PRNGKey, Array], Array]


class PFState(NamedTuple):
    """Particles ``(N, d)`` and normalised log-weights ``(N,)`` (no PRNG key: it is passed per call)."""

    particles: Array
    log_weights: Array


class PFParams(NamedTuple):
    """Parameters of :func:`build_pf` (a pytree; replace leaves to vmap or tune).

    Attributes:
        model: the model's prior and GM noises (:class:`~gmjax.models.ModelParams`). A GM noise
            override given to :func:`build_pf` is stored here; a noise given as a sampler or a
            log-density is code, stays in the filter's closure, and the corresponding entry here is
            then unused.
        ess_threshold: ``()`` resample when ``ESS < ess_threshold * N``.
        bandwidth_scale: ``()`` multiplies the optimal kernel bandwidth ``h_opt`` (regularised PF
            only).
    """

    model: ModelParams
    ess_threshold: Array
    bandwidth_scale: Array


def _normalize_log(log_w: Array) -> Array:
    return log_w - logsumexp(log_w)


def effective_sample_size(log_weights: Array) -> Array:
    """``1 / sum w_i^2`` for (possibly unnormalised) log-weights ``(N,)``."""
    lw = _normalize_log(log_weights)
    return jnp.exp(-logsumexp(2.0 * lw))


def _weights(log_weights):
    return jnp.exp(_normalize_log(log_weights))


def _inverse_cdf(w: Array, u: Array) -> Array:
    """Indices ``i`` with ``cumsum(w)[i-1] <= u < cumsum(w)[i]`` (clipped against rounding)."""
    cdf = jnp.cumsum(w)
    cdf = cdf / cdf[-1]  # exactly 1 at the end, so u < 1 never falls past the last live particle
    idx = jnp.searchsorted(cdf, u, side="right")
    return jnp.clip(idx, 0, w.shape[0] - 1)


def multinomial(key: PRNGKey, log_weights: Array) -> Array:
    """Multinomial resampling: ``N`` i.i.d. draws from the weights. Returns indices ``(N,)``.

    Inverse-CDF lookup of ``N`` uniforms, ``O(N log N)`` (``jax.random.categorical`` with
    ``N`` draws over ``N`` classes would cost ``O(N^2)`` Gumbel variates).
    """
    n = log_weights.shape[0]
    w = _weights(log_weights)
    return _inverse_cdf(w, jax.random.uniform(key, (n,), w.dtype))


def stratified(key: PRNGKey, log_weights: Array) -> Array:
    """Stratified resampling: one uniform in each stratum ``[i/N, (i+1)/N)``. Indices ``(N,)``."""
    n = log_weights.shape[0]
    w = _weights(log_weights)
    u = (jnp.arange(n, dtype=w.dtype) + jax.random.uniform(key, (n,), w.dtype)) / n
    return _inverse_cdf(w, u)


def systematic(key: PRNGKey, log_weights: Array) -> Array:
    """Systematic resampling: one shared uniform offset, ``u_i = (i + U) / N``. Indices ``(N,)``.

    Each particle is copied ``floor(N w_i)`` or ``ceil(N w_i)`` times.
    """
    n = log_weights.shape[0]
    w = _weights(log_weights)
    u = (jnp.arange(n, dtype=w.dtype) + jax.random.uniform(key, (), w.dtype)) / n
    return _inverse_cdf(w, u)


def residual(key: PRNGKey, log_weights: Array) -> Array:
    """Residual resampling with a fixed-size output.

    Particle ``i`` is first copied ``floor(N w_i)`` times (deterministic part, filled in slot
    order); the remaining ``R = N - sum floor(N w_i)`` slots are multinomial draws from the
    residual weights ``N w_i - floor(N w_i)``. Both parts are computed for all ``N`` slots and
    selected by slot position, so the shape never depends on data. Indices ``(N,)``.
    """
    n = log_weights.shape[0]
    w = _weights(log_weights)
    nw = n * w
    counts = jnp.floor(nw)
    det_cum = jnp.cumsum(counts).astype(jnp.int32)
    n_det = det_cum[-1]
    slots = jnp.arange(n)
    det_idx = jnp.clip(jnp.searchsorted(det_cum, slots, side="right"), 0, n - 1)
    res = jnp.maximum(nw - counts, 0.0)
    total = jnp.sum(res)
    # If every residual is 0 (all N w_i integral) no slot reads the draws; avoid 0 / 0.
    ok = total > 0
    res_w = jnp.where(ok, res / jnp.where(ok, total, 1.0), 1.0 / n)
    draws = _inverse_cdf(res_w, jax.random.uniform(key, (n,), w.dtype))
    return jnp.where(slots < n_det, det_idx, draws)


RESAMPLERS: dict[str, Callable[[PRNGKey, Array], Array]] = {
    "multinomial": multinomial,
    "systematic": systematic,
    "stratified": stratified,
    "residual": residual,
}


def pf_moments(state: PFState) -> tuple[Array, Array]:
    """Weighted particle mean ``(d,)`` and covariance ``(d, d)``."""
    w = _weights(state.log_weights)
    mean = w @ state.particles
    dev = state.particles - mean
    return mean, gaussian.symmetrize(jnp.einsum("n,ni,nj->ij", w, dev, dev))


def kernel_bandwidth(bandwidth_scale: Array, d: int, n_particles: int) -> Array:
    """Optimal Gaussian-kernel bandwidth ``bandwidth_scale * (4/(d+2))^{1/(d+4)} N^{-1/(d+4)}``
    (Musso, Oudjane & Le Gland 2001); ``d`` and ``N`` are static, ``bandwidth_scale`` may be traced."""
    return bandwidth_scale * (4.0 / (d + 2)) ** (1.0 / (d + 4)) * n_particles ** (-1.0 / (d + 4))


def _gm_sampler(gm: GaussianMixture) -> Callable[[PRNGKey, tuple], Array]:
    """Sampler of a GM with its Cholesky factors computed once (not once per particle)."""
    factors = jax.vmap(lambda P: safe_chol(P).factor)(gm.covs)
    logw = gmm.log_weights(gm)

    def sample(key, shape):
        k_c, k_n = jax.random.split(key)
        idx = jax.random.categorical(k_c, logw, shape=shape)
        eps = jax.random.normal(k_n, shape + (gm.dim,), gm.means.dtype)
        return gm.means[idx] + jnp.einsum("...ij,...j->...i", factors[idx], eps)

    return sample


def _gm_logpdf(gm: GaussianMixture, angle_dims: tuple[int, ...] = ()) -> Callable[[Array], Array]:
    """Log-density of a (normalised) GM with factors precomputed; ``w (m,) -> ()``.

    ``angle_dims``: components that are angles. Each component's residual ``w - r_j`` is wrapped
    into ``[-pi, pi)`` before its Gaussian is evaluated (as the Gaussian-sum filter's components
    do), so a component whose mean is an angle (e.g. a front/back ambiguity at ``pi``) sees its
    residual on the circle.
    """
    gm = gmm.normalize(gm)
    factors = jax.vmap(lambda P: safe_chol(P).factor)(gm.covs)
    logw = gmm.log_weights(gm)

    def one(w, mean, L):
        return loglik_from_chol(wrap_angles(w - mean, angle_dims), L)

    def logpdf(w):
        return logsumexp(logw + jax.vmap(one, (None, 0, 0))(w, gm.means, factors))

    return logpdf


_ProcessSampler = Callable[[GaussianMixture, PRNGKey, tuple, Array], Array]


def _process_sampler(noise: Any) -> _ProcessSampler:
    """A sampler ``(params_noise, key, (N,), t) -> (N, d)`` from a process-noise description.

    ``None`` or a GM: draw from the GM held in ``params`` (read at each call). A
    :class:`TimedSampler` or a callable ``(key, (N,)) -> (N, d)``: static code; ``params_noise``
    is ignored.
    """
    if noise is None or isinstance(noise, GaussianMixture):
        return lambda gm, key, shape, t: _gm_sampler(gm)(key, shape)
    if isinstance(noise, TimedSampler):
        return lambda gm, key, shape, t: jax.vmap(lambda k: noise.fn(k, t))(jax.random.split(key, shape[0]))
    if callable(noise):
        return lambda gm, key, shape, t: noise(key, shape)
    raise ValueError(
        "process_noise: expected a GaussianMixture or a sampler (key, (N,)) -> (N, d), "
        f"got {type(noise).__name__}"
    )


def _measurement_logpdf(
    noise: Any, angle_dims: tuple[int, ...] = ()
) -> Callable[[GaussianMixture], Callable[[Array], Array]]:
    """``params_noise -> (w (m,) -> ())``: the GM in ``params`` (``None`` or a GM override; each
    component's residual wrapped on ``angle_dims``) or a static log-density (``params_noise``
    ignored)."""
    if noise is None or isinstance(noise, GaussianMixture):
        return lambda gm: _gm_logpdf(gm, angle_dims)
    if callable(noise):
        return lambda gm: noise
    raise ValueError(
        f"measurement_noise: expected a GaussianMixture or a log-density w -> (), got {type(noise).__name__}"
    )


def _check_noise_dim(name: str, noise: Any, dim: int) -> None:
    if isinstance(noise, GaussianMixture) and noise.dim != dim:
        raise ValueError(f"{name}: dimension {noise.dim} does not match the expected {dim}")


def _require_key(key: PRNGKey | None, call: str) -> PRNGKey:
    if key is None:
        raise ValueError(
            f"key: the particle filter needs a PRNG key in {call} (pass key=jax.random.key(...), "
            "or run(filter, zs, key=...))"
        )
    return key


# below this effective sample size (after weighting) one particle carries essentially all the weight:
# the cloud has collapsed and its covariance says nothing (flagged ``degenerate``)
_COLLAPSED_ESS = 1.5


def _reweight(log_weights: Array, ll_i: Array, missing: Array) -> tuple[Array, Array, Array]:
    """Bayes step in the log domain: ``log w_i + log p(z | x_i)``, normalised.

    Returns:
        ``(log_weights (N,), loglik (), degenerate ())``: ``loglik = log sum_i w_i p(z | x_i)``
        (0 when ``missing``, ``-inf`` when every likelihood underflowed); on a degenerate or
        missing step the weights are kept unchanged.
    """
    ll_i = jnp.where(jnp.isnan(ll_i), -jnp.inf, ll_i)
    lw = log_weights + ll_i
    total = logsumexp(lw)
    ok = jnp.isfinite(total)
    lw = jnp.where(ok, lw - jnp.where(ok, total, 0.0), log_weights)
    lw = jnp.where(missing, log_weights, lw)
    loglik = jnp.where(missing, 0.0, jnp.where(ok, total, -jnp.inf))
    return lw, loglik, ~ok & ~missing


def _regularize(key: PRNGKey, x_rs: Array, x: Array, lw: Array, h_opt: Array) -> Array:
    """Musso et al. kernel jitter: ``x_rs + h_opt * D eps``, ``D D^T`` the weighted covariance of
    the particles ``x`` with log-weights ``lw`` before resampling; ``eps ~ N(0, I)``."""
    _, cov = pf_moments(PFState(x, lw))
    D = safe_chol(cov).factor
    eps = jax.random.normal(key, x.shape, x.dtype)
    return x_rs + h_opt * eps @ D.T


def _check_build_args(n_particles, resampling, ess_threshold, bandwidth_scale) -> None:
    if isinstance(n_particles, bool) or not isinstance(n_particles, int) or n_particles < 1:
        raise ValueError(f"n_particles: must be a positive integer, got {n_particles!r}")
    if resampling not in RESAMPLERS:
        raise ValueError(f"resampling: must be one of {sorted(RESAMPLERS)}, got {resampling!r}")
    if not 0.0 <= float(ess_threshold) <= 1.0:
        raise ValueError(f"ess_threshold: must lie in [0, 1], got {ess_threshold!r}")
    if not float(bandwidth_scale) > 0:
        raise ValueError(f"bandwidth_scale: must be > 0, got {bandwidth_scale!r}")


def _default_params(
    model: StateSpaceModel,
    process_noise: Any,
    measurement_noise: Any,
    ess_threshold: float,
    bandwidth_scale: float,
) -> PFParams:
    """``filter.params``: the model's parameters with any GM noise override in place."""
    base = model.params
    if isinstance(process_noise, GaussianMixture):
        base = base._replace(process_noise=process_noise)
    if isinstance(measurement_noise, GaussianMixture):
        base = base._replace(measurement_noise=measurement_noise)
    return PFParams(base, jnp.asarray(float(ess_threshold)), jnp.asarray(float(bandwidth_scale)))


def build_pf(
    model: StateSpaceModel,
    n_particles: int,
    *,
    resampling: str = "systematic",
    ess_threshold: float = 1.0,
    process_noise: GaussianMixture | Callable | None = None,
    measurement_noise: GaussianMixture | Callable | None = None,
    regularized: bool = False,
    bandwidth_scale: float = 1.0,
) -> Filter:
    """A bootstrap (SIR) or regularised particle filter as a :class:`Filter`.

    Args:
        model: the state-space model (``f``, ``h`` stay in the closure; its prior and noises are
            the defaults of ``params.model``).
        n_particles: ``N`` (static).
        resampling: ``"multinomial"``, ``"systematic"``, ``"stratified"`` or ``"residual"``
            (static).
        ess_threshold: resample when ``ESS < ess_threshold * N``; ``1.0`` (default) resamples
            at every step (classic SIR), ``0`` never. Stored in ``params.ess_threshold``.
        process_noise: overrides ``model.process_noise``: a GM (stored in
            ``params.model.process_noise``), or code kept static in the closure: a sampler
            ``(key, (N,)) -> (N, d)`` or a :class:`TimedSampler` around a per-draw simulator
            ``(key, t) -> (d,)`` such as ``Scenario.sample_process_noise`` (a sampler is the
            noise as given: ``model.process_noise_at`` is not applied to it). A GM goes through
            ``model.process_noise_at`` at every step (``Q(dt)``); a state-dependent one,
            ``process_noise_at(noise, inputs, x)``, is evaluated at every particle and each
            particle draws from its own noise.
        measurement_noise: overrides ``model.measurement_noise``: a GM (stored in
            ``params.model.measurement_noise``) or a static log-density ``w (m,) -> ()``.
        regularized: add the Gaussian kernel jitter after each resampling (regularised PF; static).
        bandwidth_scale: multiplies the optimal kernel bandwidth ``h_opt``
            (:func:`kernel_bandwidth`); stored in ``params.bandwidth_scale``.

    Returns:
        A :class:`Filter` over :class:`PFState` with :class:`PFParams`. ``init(params, prior=None,
        *, key)`` samples ``N`` particles from the prior (default ``params.model.prior``);
        ``predict`` draws the process noise with its ``key``; ``update`` uses its ``key`` for the
        resampling and the regularisation jitter. Every call needs a key. ``update``'s
        :class:`StepInfo` reports the weighted particle moments after the update
        (:func:`pf_moments`), ``loglik = log sum_i w_i p(z | x_i)`` (``-inf`` when degenerate),
        ``n_components = 1`` (a particle cloud is no mixture; the count is static, ``N``),
        ``flags.degenerate`` (every likelihood underflowed, the weights were kept; or the cloud
        collapsed: ESS after weighting below 1.5, one particle carries essentially all the
        weight), ``flags.nonfinite_measurement`` (a NaN or ``±inf`` in ``z``: predict-only), and ``extra = {"ess": () ESS after weighting, before resampling,
        "resampled": () bool}``.

    Raises:
        ValueError: unknown ``resampling``, ``n_particles < 1``, a threshold outside ``[0, 1]``,
            a non-positive bandwidth, a bad noise override or a bad model; at call time, a missing
            ``key`` or a prior that is not a :class:`GaussianMixture`.
    """
    d, m = check_model(model)
    _check_build_args(n_particles, resampling, ess_threshold, bandwidth_scale)
    _check_noise_dim("process_noise", process_noise, d)
    _check_noise_dim("measurement_noise", measurement_noise, m)
    N = n_particles
    resample = RESAMPLERS[resampling]
    sample_v = _process_sampler(process_noise)
    gm_noise = process_noise is None or isinstance(process_noise, GaussianMixture)
    per_particle_noise = gm_noise and model.state_dependent_noise
    angle_dims = tuple(model.angle_dims)
    meas_lp = _measurement_logpdf(measurement_noise, angle_dims)
    f_step, h_step, _, _ = model.step_fns()
    fv = jax.vmap(f_step, in_axes=(0, None))
    hv = jax.vmap(h_step, in_axes=(0, None))

    def init(
        params: PFParams, prior: GaussianMixture | None = None, *, key: PRNGKey | None = None
    ) -> PFState:
        key = _require_key(key, "init")
        prior = params.model.prior if prior is None else prior
        if not isinstance(prior, GaussianMixture):
            raise ValueError(f"prior: expected a GaussianMixture, got {type(prior).__name__}")
        x = _gm_sampler(prior)(key, (N,))
        return PFState(x, jnp.full((N,), -jnp.log(N), x.dtype))

    def predict(
        params: PFParams, state: PFState, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> PFState:
        key = _require_key(key, "predict")
        x = state.particles
        if per_particle_noise:  # v_i ~ process_noise_at(noise, inputs, x_i): one draw per particle

            def draw(xi, ki):
                return _gm_sampler(model.noise_at(params.model.process_noise, inputs, xi))(ki, ())

            v = jax.vmap(draw)(x, jax.random.split(key, N))
        elif gm_noise:
            v = sample_v(model.noise_at(params.model.process_noise, inputs), key, (N,), inputs.t)  # Q(dt)
        else:  # a sampler given to build_pf: it is the noise (params and process_noise_at unused)
            v = sample_v(params.model.process_noise, key, (N,), inputs.t)
        return PFState(fv(x, inputs) + v.astype(x.dtype), state.log_weights)

    def update(
        params: PFParams, state: PFState, z: Array, inputs: StepInputs, *, key: PRNGKey | None = None
    ) -> tuple[PFState, StepInfo]:
        key = _require_key(key, "update")
        z = jnp.asarray(z)
        missing = is_missing(z)
        x = state.particles
        pred = hv(x, inputs)
        z_safe = jnp.where(missing, pred[0], z)
        # angles: the residual on the circle; a GM noise wraps each component's z - h(x) - r_j again
        residual = wrap_angles(z_safe - pred, angle_dims)
        ll_i = jax.vmap(meas_lp(params.model.measurement_noise))(residual)
        lw, loglik, degenerate = _reweight(state.log_weights, ll_i, missing)
        ess = effective_sample_size(lw)
        do_rs = (ess < jnp.asarray(params.ess_threshold, ess.dtype) * N) & ~missing
        k_rs, k_reg = jax.random.split(key)
        x_rs = x[resample(k_rs, lw)]
        if regularized:
            h_opt = kernel_bandwidth(jnp.asarray(params.bandwidth_scale, x.dtype), d, N)
            x_rs = _regularize(k_reg, x_rs, x, lw, h_opt)
        new = PFState(jnp.where(do_rs, x_rs, x), jnp.where(do_rs, jnp.full_like(lw, -jnp.log(N)), lw))
        mean, cov = pf_moments(new)
        no = jnp.zeros((), bool)
        collapsed = (ess < _COLLAPSED_ESS) & ~missing if N > 1 else no
        flags = StepFlags(no, no, degenerate | collapsed, missing)
        info = StepInfo(
            mean, cov, loglik, jnp.ones((), jnp.int32), flags, None, {"ess": ess, "resampled": do_rs}
        )
        return new, info

    params = _default_params(model, process_noise, measurement_noise, ess_threshold, bandwidth_scale)
    return Filter(init, predict, update, params)
