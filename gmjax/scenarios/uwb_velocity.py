"""Random-walk velocity models with GM measurement noise: the synthetic Models 1-3 and the UWB ranging noise
of Pishdad & Labeau (active-cluster reduction; seed 004 §V, Tables I-II)."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture as gmm
from gmjax._types import ArrayLike, DTypeLike
from gmjax.mixture import GaussianMixture
from gmjax.models import library as lib
from gmjax.models.base import Scenario, StateSpaceModel

__all__ = [
    "SYNTHETIC_MODELS",
    "UWB_NOISES",
    "DT",
    "ScalarGM",
    "LabeledRun",
    "synthetic",
    "uwb",
    "random_walk_velocity",
    "rwv_model",
    "synthetic_noise",
    "noise_gain",
    "simulate_labeled",
    "moment_matched",
    "kl_to_moment_matched",
    "kl_curve",
    "c_for_kl",
]

DT = 0.1080  # seconds, the UWB system's measurement interval (eq 18 footnote 4)


class ScalarGM(NamedTuple):
    """A univariate mixture ``(weights, means, variances)``."""

    weights: ArrayLike  # (C,): tuples in the tables, arrays once computed
    means: ArrayLike
    variances: ArrayLike


# Table I: weights and unscaled means (multiplied by c); every cluster has variance 1 (eqs 25-27).
SYNTHETIC_MODELS = {
    1: ScalarGM((0.2, 0.2, 0.2, 0.2, 0.2), (-50.0, -30.0, 0.0, 30.0, 50.0), (1.0,) * 5),
    2: ScalarGM((0.1, 0.1, 0.6, 0.1, 0.1), (-50.0, -30.0, 0.0, 30.0, 50.0), (1.0,) * 5),
    3: ScalarGM((0.5, 0.1, 0.1, 0.1, 0.2), (-50.0, 10.0, 30.0, 50.0, 80.0), (1.0,) * 5),
}

# Table II: process noise v (per axis) and measurement noise w.
UWB_NOISES = {
    "x": {
        "process": ScalarGM((0.13, 0.77, 0.099), (-41.44, 0.51, 49.79), (148.24, 48.38, 83.75)),
        "measurement": ScalarGM((0.07, 0.85, 0.08), (-300.01, -17.06, 207.37), (8163.20, 3611.99, 5677.21)),
    },
    "y": {
        "process": ScalarGM(
            (0.01, 0.06, 0.03, 0.03, 0.72, 0.04, 0.02, 0.06, 0.03),
            (-63.38, -48.73, -35.65, -17.40, -0.32, 9.52, 30.09, 44.24, 54.35),
            (24.34, 21.53, 18.18, 23.62, 3.13, 12.16, 18.81, 12.96, 15.44),
        ),
        "measurement": ScalarGM((0.98, 0.02), (-125.93, 147.25), (8500.19, 10809.10)),
    },
}


def _rwv_matrices(dt: float, dtype: DTypeLike) -> tuple[jax.Array, jax.Array]:
    """``F = [[1, dt], [0, 1]]`` and ``H = [1, 0]`` of eqs 18-19: the 1-D
    :func:`~gmjax.models.library.constant_velocity` transition and the
    :func:`~gmjax.models.library.cartesian_position` measurement of the position (exact entries)."""
    F_of_dt = lib.constant_velocity(1, 1.0).F
    assert F_of_dt is not None  # a linear motion model
    F = F_of_dt(jnp.asarray(dt, dtype))
    H = jnp.asarray(lib.cartesian_position((0,), 2).H, dtype)
    return F, H


def random_walk_velocity(
    process: ScalarGM,
    measurement: ScalarGM,
    *,
    dt: float = DT,
    prior_cov: ArrayLike = ((100.0, 0.0), (0.0, 100.0)),
    n_steps: int = 100,
    name: str = "rwv",
    description: str = "",
    jitter: float = 1e-9,
    dtype: DTypeLike | None = None,
) -> Scenario:
    """The linear model of seed 004 eqs 18–22 with GM process and measurement noise.

    ``x = (position, velocity)``, ``F = [[1, dt], [0, 1]]``, ``H = [1, 0]``; the process noise is
    ``v * (dt, 1)`` with ``v`` a scalar mixture, so component ``i`` has mean ``u_i (dt, 1)`` and
    covariance ``sigma_i [[dt^2, dt], [dt, 1]]`` (eqs 21–22). That covariance has rank 1; ``jitter``
    times the identity is added so that it is positive definite (the filters only ever add it to a
    positive definite prediction). The truth draws ``v`` and ``w`` from the same mixtures as the
    filters assume (the paper's synthetic setting). Not given by the paper, our choices: the prior
    ``N(0, prior_cov)`` (the truth starts from a draw of it) and the horizon ``n_steps``.
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    g = np.array([dt, 1.0])
    G = np.outer(g, g)
    q = GaussianMixture.create(
        process.weights,
        [u * g for u in process.means],
        [s * G + jitter * np.eye(2) for s in process.variances],
        dtype=dtype,
    )
    r = GaussianMixture.create(measurement.weights, measurement.means, measurement.variances, dtype=dtype)
    prior = GaussianMixture.create([1.0], [[0.0, 0.0]], [np.asarray(prior_cov, float)], dtype=dtype)
    F, H = _rwv_matrices(dt, dtype)
    pw = jnp.log(jnp.asarray(process.weights, dtype))
    pm = jnp.asarray(process.means, dtype)
    ps = jnp.sqrt(jnp.asarray(process.variances, dtype))
    gj = jnp.asarray(g, dtype)

    def sample_process_noise(key, t):
        k_c, k_n = jax.random.split(key)
        i = jax.random.categorical(k_c, pw)
        return (pm[i] + ps[i] * jax.random.normal(k_n, (), dtype)) * gj

    model = StateSpaceModel(
        f=lambda x, t: F @ x,
        h=lambda x, t: H @ x,
        process_noise=q,
        measurement_noise=r,
        prior=prior,
        f_jacobian=lambda x, t: F,
        h_jacobian=lambda x, t: H,
    )
    return Scenario(
        name=name,
        model=model,
        n_steps=n_steps,
        sample_initial=lambda key: gmm.sample(prior, key, 1)[0],
        sample_process_noise=sample_process_noise,
        sample_measurement_noise=lambda key, t: gmm.sample(r, key, 1)[0],
        position_dims=(0,),
        description=description,
    )


def synthetic(model: int, c: float, **kwargs: Any) -> Scenario:
    """Seed 004 Table I Model 1, 2 or 3 with mean scale ``c`` (the same GM for process and
    measurement noise, every cluster of variance 1, eqs 25–29)."""
    if model not in SYNTHETIC_MODELS:
        raise ValueError(f"model: expected 1, 2 or 3, got {model!r}")
    if not c >= 0:
        raise ValueError(f"c: must be >= 0, got {c!r}")
    base = SYNTHETIC_MODELS[model]
    gm = ScalarGM(base.weights, tuple(c * m for m in base.means), base.variances)
    return random_walk_velocity(
        gm,
        gm,
        name=f"seed004_model{model}",
        description=f"seed 004 Table I Model {model} with c = {c} (process and measurement noise)",
        **kwargs,
    )


def uwb(axis: str, **kwargs: Any) -> Scenario:
    """Seed 004 Table II noise models for the ``x`` or ``y`` axis (simulated data, not the paper's recordings)."""
    if axis not in UWB_NOISES:
        raise ValueError(f"axis: expected 'x' or 'y', got {axis!r}")
    noises = UWB_NOISES[axis]
    return random_walk_velocity(
        noises["process"],
        noises["measurement"],
        name=f"seed004_uwb_{axis}",
        description=f"seed 004 Table II UWB noise models, {axis} axis (simulated from the fitted mixtures)",
        **kwargs,
    )


# ---------------------------------------------------------------------------------------------
# Traceable model / simulator with the true active clusters (for the Matched filter), and the
# KL divergence between a scalar noise mixture and its moment-matched Gaussian (§V-A, footnote 5).


class LabeledRun(NamedTuple):
    """One simulated trajectory with the clusters that generated each noise draw.

    Attributes:
        xs: ``(T+1, 2)`` true states, ``xs[0] = x_0``.
        zs: ``(T, 1)`` measurements.
        active: ``(T, 2)`` int32: ``active[k] = (i, j)``, the process-noise cluster ``i`` and the
            measurement-noise cluster ``j`` that were active at step ``k + 1`` (the model
            ``M_k^{ij}`` of eq 5), which the Matched filter is given.
    """

    xs: jax.Array
    zs: jax.Array
    active: jax.Array


def _as_arrays(gm: ScalarGM, dtype) -> ScalarGM:
    return ScalarGM(*(jnp.asarray(a, dtype) for a in gm))


def noise_gain(dt: float = DT, dtype: DTypeLike | None = None) -> jax.Array:
    """``G = (dt, 1)^T`` of shape ``(2, 1)``: the process noise is ``v_k = G v_k`` with scalar ``v_k`` (eq 20)."""
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return jnp.asarray([[dt], [1.0]], dtype)


def synthetic_noise(model: int, c: ArrayLike) -> ScalarGM:
    """Table I Model ``model`` with mean scale ``c`` as arrays (``c`` may be traced, e.g. vmapped)."""
    if model not in SYNTHETIC_MODELS:
        raise ValueError(f"model: expected 1, 2 or 3, got {model!r}")
    base = SYNTHETIC_MODELS[model]
    c = jnp.asarray(c)
    dtype = c.dtype if jnp.issubdtype(c.dtype, jnp.floating) else jnp.zeros(()).dtype
    return ScalarGM(
        jnp.asarray(base.weights, dtype),
        c.astype(dtype) * jnp.asarray(base.means, dtype),
        jnp.asarray(base.variances, dtype),
    )


def rwv_model(
    process: ScalarGM,
    measurement: ScalarGM,
    *,
    dt: float = DT,
    prior_cov: ArrayLike = ((100.0, 0.0), (0.0, 100.0)),
    jitter: float = 1e-9,
    dtype: DTypeLike | None = None,
) -> StateSpaceModel:
    """The model of :func:`random_walk_velocity` (eqs 18–22) built with ``jnp`` only, so the noise
    parameters may be traced (one compiled kernel for a whole sweep over ``c``).

    Same conventions as :func:`random_walk_velocity`: component ``i`` of the process noise has mean
    ``u_i (dt, 1)`` and covariance ``sigma_i [[dt^2, dt], [dt, 1]] + jitter I`` (eqs 21–22), the
    prior is ``N(0, prior_cov)``. Clusters of weight 0 are padded slots (``mask`` False), so
    mixtures of different sizes can share one padded shape. No validation (use
    :func:`random_walk_velocity` for that).
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    p = _as_arrays(process, dtype)
    r = _as_arrays(measurement, dtype)
    g = jnp.asarray([dt, 1.0], dtype)
    G = jnp.outer(g, g)
    eye = jnp.eye(2, dtype=dtype)
    q = GaussianMixture.from_arrays(
        p.weights / jnp.sum(p.weights),
        p.means[:, None] * g,
        p.variances[:, None, None] * G + jitter * eye,
        p.weights > 0,
    )
    rm = GaussianMixture.from_arrays(
        r.weights / jnp.sum(r.weights), r.means[:, None], r.variances[:, None, None], r.weights > 0
    )
    prior = GaussianMixture.from_arrays(
        jnp.ones((1,), dtype), jnp.zeros((1, 2), dtype), jnp.asarray(prior_cov, dtype)[None]
    )
    F, H = _rwv_matrices(dt, dtype)
    return StateSpaceModel(
        f=lambda x, t: F @ x,
        h=lambda x, t: H @ x,
        process_noise=q,
        measurement_noise=rm,
        prior=prior,
        f_jacobian=lambda x, t: F,
        h_jacobian=lambda x, t: H,
    )


def simulate_labeled(
    process: ScalarGM,
    measurement: ScalarGM,
    key: jax.Array,
    *,
    n_steps: int = 100,
    dt: float = DT,
    prior_cov: ArrayLike = ((100.0, 0.0), (0.0, 100.0)),
    dtype: DTypeLike | None = None,
) -> LabeledRun:
    """Simulate eqs 18–22 and record the active noise clusters (traceable; ``vmap`` it over keys).

    ``x_0 ~ N(0, prior_cov)``; at step ``k = 1..T`` draw ``i ~ w``, ``v = u_i + sqrt(sigma_i) n``,
    ``x_k = F x_{k-1} + v (dt, 1)`` (exactly on the noise line of eq 20, no jitter), then
    ``j ~ p``, ``z_k = x_k[0] + b_j + sqrt(R_j) n'``. Same distribution as :func:`~gmjax.models.simulate` on
    :func:`random_walk_velocity`, but also returns ``(i, j)`` for the Matched filter.
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    p = _as_arrays(process, dtype)
    r = _as_arrays(measurement, dtype)
    F, _ = _rwv_matrices(dt, dtype)
    g = jnp.asarray([dt, 1.0], dtype)
    k0, ks = jax.random.split(key)
    L0 = jnp.linalg.cholesky(jnp.asarray(prior_cov, dtype))
    x0 = L0 @ jax.random.normal(k0, (2,), dtype)
    log_pw, log_rw = jnp.log(p.weights), jnp.log(r.weights)

    def step(x, k):
        ki, kv, kj, kw = jax.random.split(k, 4)
        i = jax.random.categorical(ki, log_pw)
        j = jax.random.categorical(kj, log_rw)
        v = p.means[i] + jnp.sqrt(p.variances[i]) * jax.random.normal(kv, (), dtype)
        x = F @ x + v * g
        z = x[:1] + r.means[j] + jnp.sqrt(r.variances[j]) * jax.random.normal(kw, (1,), dtype)
        return x, (x, z, jnp.stack([i, j]).astype(jnp.int32))

    _, (xs, zs, active) = jax.lax.scan(step, x0, jax.random.split(ks, n_steps))
    return LabeledRun(jnp.concatenate([x0[None], xs]), zs, active)


def _scalar_parts(gm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(weights, means, variances)`` float64 arrays of a :class:`ScalarGM` or 1-D GaussianMixture."""
    if isinstance(gm, GaussianMixture):
        if gm.dim != 1:
            raise ValueError(f"gm: expected a 1-D mixture, got dimension {gm.dim}")
        mask = np.asarray(gm.mask)
        w, m, v = (
            np.asarray(gm.weights, float)[mask],
            np.asarray(gm.means, float)[mask, 0],
            np.asarray(gm.covs, float)[mask, 0, 0],
        )
    elif isinstance(gm, ScalarGM):
        w, m, v = (np.asarray(a, float).reshape(-1) for a in gm)
    else:
        raise ValueError(f"gm: expected a ScalarGM or a 1-D GaussianMixture, got {type(gm).__name__}")
    if not (w.shape == m.shape == v.shape) or w.size == 0:
        raise ValueError(
            f"gm: weights, means, variances must have one equal, non-zero length; got "
            f"{w.shape}, {m.shape}, {v.shape}"
        )
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(m)) and np.all(np.isfinite(v))):
        raise ValueError("gm: contains NaN or inf")
    if np.any(w < 0) or w.sum() <= 0:
        raise ValueError("gm: weights must be >= 0 with a positive sum")
    if np.any(v <= 0):
        raise ValueError("gm: variances must be > 0")
    return w / w.sum(), m, v


def moment_matched(gm: ScalarGM | GaussianMixture) -> tuple[float, float]:
    """``(mean, variance)`` of the single Gaussian with the mixture's first two moments."""
    w, m, v = _scalar_parts(gm)
    mu = float(w @ m)
    return mu, float(w @ (v + (m - mu) ** 2))


def _log_gm(x: np.ndarray, w, m, v) -> np.ndarray:
    comp = -0.5 * (np.log(2 * np.pi * v) + (x[:, None] - m) ** 2 / v) + np.log(np.where(w > 0, w, 1.0))
    comp = np.where(w > 0, comp, -np.inf)
    top = comp.max(axis=1, keepdims=True)
    return top[:, 0] + np.log(np.exp(comp - top).sum(axis=1))


def kl_to_moment_matched(
    gm: ScalarGM | GaussianMixture,
    *,
    method: str = "quadrature",
    key: jax.Array | None = None,
    n_samples: int = 200_000,
    n_grid: int | None = None,
    return_stderr: bool = False,
) -> float | tuple[float, float]:
    """``KL(p || q)``, ``p`` a scalar Gaussian mixture and ``q`` its moment-matched Gaussian (§V-A).

    The paper measures multimodality by this divergence, estimated "using Monte-Carlo simulations
    with 2×10^5 samples" (footnote 5); it does not state the direction, we use ``KL(p || q) =
    E_p[log p - log q]`` (the direction that moment matching minimises).

    Args:
        gm: a :class:`ScalarGM` or a 1-D :class:`~gmjax.mixture.GaussianMixture`; the weights
            are normalised (Table II's rounded x process weights sum to 0.999).
        method: ``"quadrature"``: composite Simpson rule on ``n_grid`` points over
            ``[min(m_i - 12 s_i), max(m_i + 12 s_i)]`` (float64 NumPy; the tails beyond carry
            < 1e-30 of the mass); ``"mc"``: the mean of ``log p(x) - log q(x)`` over ``n_samples``
            draws ``x ~ p`` (as the paper), which needs ``key``.
        key: PRNG key (keyword-only), for ``method="mc"``.
        n_samples: Monte Carlo sample size (the paper's 2×10^5).
        n_grid: quadrature points (made odd); default: spacing ``min_i s_i / 40`` (at least 2001,
            at most 400001 points), for which the Simpson error is far below 1e-8.
        return_stderr: also return the standard error (0 for quadrature).

    Returns:
        The divergence (a float), or ``(kl, stderr)``.

    Raises:
        ValueError: an invalid mixture, unknown ``method``, or ``method="mc"`` without ``key``.
    """
    w, m, v = _scalar_parts(gm)
    mu, var = moment_matched(ScalarGM(w, m, v))
    if method == "quadrature":
        s = np.sqrt(v)
        lo, hi = np.min(m - 12 * s), np.max(m + 12 * s)
        if n_grid is None:
            n_grid = int(np.clip((hi - lo) / (s.min() / 40), 2001, 400_001))
        if n_grid < 3:
            raise ValueError(f"n_grid: must be >= 3, got {n_grid}")
        n_grid = n_grid + 1 - n_grid % 2
        x = np.linspace(lo, hi, n_grid)
        log_p = _log_gm(x, w, m, v)
        log_q = -0.5 * (np.log(2 * np.pi * var) + (x - mu) ** 2 / var)
        f = np.exp(log_p) * (log_p - log_q)
        h = x[1] - x[0]
        kl = float(h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum()))
        se = 0.0
    elif method == "mc":
        if key is None:
            raise ValueError("key: method='mc' needs a PRNG key")
        if n_samples < 2:
            raise ValueError(f"n_samples: must be >= 2, got {n_samples}")
        k_c, k_n = jax.random.split(key)
        idx = np.asarray(jax.random.choice(k_c, w.size, (n_samples,), p=jnp.asarray(w)))
        x = m[idx] + np.sqrt(v[idx]) * np.asarray(jax.random.normal(k_n, (n_samples,)), float)
        d = _log_gm(x, w, m, v) + 0.5 * (np.log(2 * np.pi * var) + (x - mu) ** 2 / var)
        kl = float(d.mean())
        se = float(d.std(ddof=1) / np.sqrt(n_samples))
    else:
        raise ValueError(f"method: expected 'quadrature' or 'mc', got {method!r}")
    return (kl, se) if return_stderr else kl


def kl_curve(model: int, cs: ArrayLike) -> np.ndarray:
    """Quadrature ``KL(p || q)`` of Table I Model ``model`` at each scale ``c`` in ``cs``."""
    if model not in SYNTHETIC_MODELS:
        raise ValueError(f"model: expected 1, 2 or 3, got {model!r}")
    base = SYNTHETIC_MODELS[model]
    return np.array(
        [
            kl_to_moment_matched(ScalarGM(base.weights, tuple(c * mm for mm in base.means), base.variances))
            for c in np.atleast_1d(np.asarray(cs, float))
        ]
    )


def c_for_kl(model: int, kl: float, *, c_max: float = 100.0, xtol: float = 1e-10) -> float:
    """The mean scale ``c`` at which Table I Model ``model`` has quadrature ``KL(p || q) = kl``.

    Brent's method on ``c -> KL(c) - kl`` over ``[0, c_max]`` (``KL(0) = 0``: at ``c = 0`` every
    cluster is ``N(0, 1)``). The smallest root is bracketed by scanning a grid first, so the answer
    is well defined even if ``KL(c)`` were not monotone.

    Raises:
        ValueError: unknown model, ``kl < 0``, or ``kl`` not reached on ``[0, c_max]``.
    """
    from scipy.optimize import brentq

    if model not in SYNTHETIC_MODELS:
        raise ValueError(f"model: expected 1, 2 or 3, got {model!r}")
    if not kl >= 0:
        raise ValueError(f"kl: must be >= 0, got {kl!r}")
    if kl == 0:
        return 0.0
    grid = np.concatenate([[0.0], np.geomspace(1e-3, c_max, 80)])
    vals = kl_curve(model, grid) - kl
    above = np.nonzero(vals > 0)[0]
    if above.size == 0:
        raise ValueError(f"kl: {kl} is not reached for c in [0, {c_max}] (max {vals.max() + kl:.3g})")
    hi = int(above[0])
    return float(brentq(lambda c: kl_curve(model, [c])[0] - kl, grid[hi - 1], grid[hi], xtol=xtol))
