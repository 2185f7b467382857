"""Bootstrap (SIR) and regularised particle filters.

The filter state carries its own PRNG key, so a particle filter is a :class:`gmjax.filters.Filter`
like the Gaussian ones and runs under :func:`gmjax.filters.run`:

>>> pf = build_pf(model, 1000, resampling="systematic")
>>> states, infos = run(pf, zs, init_state=pf.init(key=key))

Step (Gordon, Salmond & Smith 1993): predict ``x_i <- f(x_i, t) + v_i`` with ``v_i`` drawn from the
process-noise sampler; update ``log w_i += log p_w(z - h(x_i, t))`` and normalise (log domain);
resample when the effective sample size ``ESS = 1 / sum w_i^2`` falls below
``ess_threshold * N`` (``ess_threshold = 1`` resamples every step; 0 never).

The regularised PF (Musso, Oudjane & Le Gland 2001; the "regularised SIR PF" peer of seed 001)
adds, after each resampling, a Gaussian kernel draw ``h_opt * D eps_i`` with ``D D^T`` the
weighted particle covariance before resampling and
``h_opt = bandwidth_scale * (4 / (d + 2))^{1/(d+4)} N^{-1/(d+4)}`` (the optimal Gaussian-kernel
bandwidth).

Noises: the process noise is a :class:`GaussianMixture` or any sampler ``(key, (N,)) -> (N, d)``
(e.g. a scenario's true-noise simulator); the measurement noise is a :class:`GaussianMixture` or a
log-density ``w (m,) -> ()``.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from gmjax import gaussian
from gmjax import mixture as gmm
from gmjax._types import Array, PRNGKey
from gmjax.filters._core import Filter, check_model, is_missing, loglik_from_chol, safe_chol
from gmjax.mixture import GaussianMixture
from gmjax.models._base import StateSpaceModel

__all__ = [
    "TimedSampler",
    "PFState",
    "PFInfo",
    "effective_sample_size",
    "multinomial",
    "systematic",
    "stratified",
    "residual",
    "RESAMPLERS",
    "build_pf",
    "pf_moments",
]


class TimedSampler(NamedTuple):
    """Wrap a per-draw, time-dependent noise simulator ``(key, t) -> (d,)`` for :func:`build_pf`.

    This is the signature of ``Scenario.sample_process_noise``; the particle filter draws one
    sample per particle with independent keys (``vmap`` over ``jax.random.split(key, N)``).
    """

    fn: Callable[[PRNGKey, Array], Array]


class PFState(NamedTuple):
    """Particles ``(N, d)``, normalised log-weights ``(N,)`` and the PRNG key for the next step."""

    particles: Array
    log_weights: Array
    key: PRNGKey


class PFInfo(NamedTuple):
    """What a particle-filter update reports.

    Attributes:
        loglik: ``()`` estimate of ``log p(z_k | z_{1:k-1})``, ``log sum_i w_i p(z | x_i)``
            (0 when ``z`` is missing; ``-inf`` when ``degenerate``).
        ess: ``()`` effective sample size after weighting, before resampling.
        resampled: ``()`` bool.
        degenerate: ``()`` bool, every particle had zero likelihood; the weights were kept
            unchanged instead of becoming NaN.
    """

    loglik: Array
    ess: Array
    resampled: Array
    degenerate: Array


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


def _gm_logpdf(gm: GaussianMixture) -> Callable[[Array], Array]:
    """Log-density of a (normalised) GM with factors precomputed; ``w (m,) -> ()``."""
    gm = gmm.normalize(gm)
    factors = jax.vmap(lambda P: safe_chol(P).factor)(gm.covs)
    logw = gmm.log_weights(gm)

    def one(w, mean, L):
        return loglik_from_chol(w - mean, L)

    def logpdf(w):
        return logsumexp(logw + jax.vmap(one, (None, 0, 0))(w, gm.means, factors))

    return logpdf


def _process_sampler(noise) -> Callable[[PRNGKey, tuple, Array], Array]:
    """A sampler ``(key, (N,), t) -> (N, d)`` from any supported process-noise description."""
    if isinstance(noise, GaussianMixture):
        sample = _gm_sampler(noise)
        return lambda key, shape, t: sample(key, shape)
    if isinstance(noise, TimedSampler):
        return lambda key, shape, t: jax.vmap(lambda k: noise.fn(k, t))(
            jax.random.split(key, shape[0])
        )
    if callable(noise):
        return lambda key, shape, t: noise(key, shape)
    raise ValueError(
        "process_noise: expected a GaussianMixture or a sampler (key, (N,)) -> (N, d), "
        f"got {type(noise).__name__}"
    )


def _measurement_logpdf(noise) -> Callable[[Array], Array]:
    if isinstance(noise, GaussianMixture):
        return _gm_logpdf(noise)
    if callable(noise):
        return noise
    raise ValueError(
        "measurement_noise: expected a GaussianMixture or a log-density w -> (), "
        f"got {type(noise).__name__}"
    )


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
        model: the state-space model (``f``, ``h``, prior; its noises are the defaults).
        n_particles: ``N`` (static).
        resampling: ``"multinomial"``, ``"systematic"``, ``"stratified"`` or ``"residual"``.
        ess_threshold: resample when ``ESS < ess_threshold * N``; ``1.0`` (default) resamples
            at every step (classic SIR), ``0`` never.
        process_noise: overrides ``model.process_noise``: a GM, a sampler
            ``(key, (N,)) -> (N, d)``, or a :class:`TimedSampler` around a per-draw simulator
            ``(key, t) -> (d,)`` such as ``Scenario.sample_process_noise``.
        measurement_noise: overrides ``model.measurement_noise``: a GM or a log-density
            ``w (m,) -> ()``.
        regularized: add the Gaussian kernel jitter after each resampling (regularised PF).
        bandwidth_scale: multiplies the optimal kernel bandwidth ``h_opt``.

    Returns:
        A :class:`Filter` whose ``init(prior=None, *, key)`` samples ``N`` particles from the
        prior (default ``model.prior``); ``update`` returns a :class:`PFInfo`.

    Raises:
        ValueError: unknown ``resampling``, ``n_particles < 1``, a threshold outside ``[0, 1]``,
            a non-positive bandwidth, or a bad model.
    """
    d, _ = check_model(model)
    if isinstance(n_particles, bool) or not isinstance(n_particles, int) or n_particles < 1:
        raise ValueError(f"n_particles: must be a positive integer, got {n_particles!r}")
    if resampling not in RESAMPLERS:
        raise ValueError(f"resampling: must be one of {sorted(RESAMPLERS)}, got {resampling!r}")
    if not 0.0 <= float(ess_threshold) <= 1.0:
        raise ValueError(f"ess_threshold: must lie in [0, 1], got {ess_threshold!r}")
    if not float(bandwidth_scale) > 0:
        raise ValueError(f"bandwidth_scale: must be > 0, got {bandwidth_scale!r}")
    N = n_particles
    resample = RESAMPLERS[resampling]
    sample_v = _process_sampler(model.process_noise if process_noise is None else process_noise)
    meas_lp = _measurement_logpdf(
        model.measurement_noise if measurement_noise is None else measurement_noise
    )
    fv = jax.vmap(model.f, in_axes=(0, None))
    hv = jax.vmap(model.h, in_axes=(0, None))
    h_opt = bandwidth_scale * (4.0 / (d + 2)) ** (1.0 / (d + 4)) * N ** (-1.0 / (d + 4))

    def init(prior: GaussianMixture | None = None, *, key: PRNGKey) -> PFState:
        prior = model.prior if prior is None else prior
        k_s, k_next = jax.random.split(key)
        x = _gm_sampler(prior)(k_s, (N,))
        return PFState(x, jnp.full((N,), -jnp.log(N), x.dtype), k_next)

    def predict(state: PFState, t) -> PFState:
        key, k_v = jax.random.split(state.key)
        v = sample_v(k_v, (N,), t).astype(state.particles.dtype)
        return PFState(fv(state.particles, t) + v, state.log_weights, key)

    def update(state: PFState, z, t) -> tuple[PFState, PFInfo]:
        z = jnp.asarray(z)
        missing = is_missing(z)
        x = state.particles
        pred = hv(x, t)
        z_safe = jnp.where(missing, pred[0], z)
        ll_i = jax.vmap(meas_lp)(z_safe - pred)
        ll_i = jnp.where(jnp.isnan(ll_i), -jnp.inf, ll_i)
        lw = state.log_weights + ll_i
        total = logsumexp(lw)
        ok = jnp.isfinite(total)
        lw = jnp.where(ok, lw - jnp.where(ok, total, 0.0), state.log_weights)
        lw = jnp.where(missing, state.log_weights, lw)
        ess = effective_sample_size(lw)
        do_rs = (ess < ess_threshold * N) & ~missing
        key, k_rs, k_reg = jax.random.split(state.key, 3)
        idx = resample(k_rs, lw)
        x_rs = x[idx]
        if regularized:
            _, cov = pf_moments(PFState(x, lw, key))
            D = safe_chol(cov).factor
            eps = jax.random.normal(k_reg, x.shape, x.dtype)
            x_rs = x_rs + h_opt * eps @ D.T
        uniform = jnp.full_like(lw, -jnp.log(N))
        new_x = jnp.where(do_rs, x_rs, x)
        new_lw = jnp.where(do_rs, uniform, lw)
        loglik = jnp.where(missing, 0.0, jnp.where(ok, total, -jnp.inf))
        return PFState(new_x, new_lw, key), PFInfo(loglik, ess, do_rs, ~ok & ~missing)

    return Filter(init, predict, update, pf_moments)

