"""Scenarios of seed 004 (Pishdad & Labeau, *A New Reduction Scheme for Gaussian Sum Filters*), §V."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import mixture as gmm
from gmjax.mixture import GaussianMixture
from gmjax.models._base import Scenario, StateSpaceModel

__all__ = ["SYNTHETIC_MODELS", "UWB_NOISES", "ScalarGM", "synthetic", "uwb", "random_walk_velocity"]

DT = 0.1080  # seconds, the UWB system's measurement interval (eq 18 footnote 4)


class ScalarGM(NamedTuple):
    """A univariate mixture ``(weights, means, variances)``."""

    weights: tuple[float, ...]
    means: tuple[float, ...]
    variances: tuple[float, ...]


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


def random_walk_velocity(
    process: ScalarGM,
    measurement: ScalarGM,
    *,
    dt: float = DT,
    prior_cov=((100.0, 0.0), (0.0, 100.0)),
    n_steps: int = 100,
    name: str = "rwv",
    description: str = "",
    jitter: float = 1e-9,
    dtype=None,
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
    F = jnp.asarray([[1.0, dt], [0.0, 1.0]], dtype)
    H = jnp.asarray([[1.0, 0.0]], dtype)
    pw = jnp.log(jnp.asarray(process.weights, dtype))
    pm = jnp.asarray(process.means, dtype)
    ps = jnp.sqrt(jnp.asarray(process.variances, dtype))
    gj = jnp.asarray(g, dtype)

    def sample_process_noise(key, t):
        k_c, k_n = jax.random.split(key)
        i = jax.random.categorical(k_c, pw)
        return (pm[i] + ps[i] * jax.random.normal(k_n, (), dtype)) * gj

    model = StateSpaceModel(
        f=lambda x, t: F @ x, h=lambda x, t: H @ x, process_noise=q, measurement_noise=r, prior=prior,
        f_jacobian=lambda x, t: F, h_jacobian=lambda x, t: H,
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


def synthetic(model: int, c: float, **kwargs) -> Scenario:
    """Seed 004 Table I Model 1, 2 or 3 with mean scale ``c`` (the same GM for process and
    measurement noise, every cluster of variance 1, eqs 25–29)."""
    if model not in SYNTHETIC_MODELS:
        raise ValueError(f"model: expected 1, 2 or 3, got {model!r}")
    if not c >= 0:
        raise ValueError(f"c: must be >= 0, got {c!r}")
    base = SYNTHETIC_MODELS[model]
    gm = ScalarGM(base.weights, tuple(c * m for m in base.means), base.variances)
    return random_walk_velocity(
        gm, gm, name=f"seed004_model{model}",
        description=f"seed 004 Table I Model {model} with c = {c} (process and measurement noise)", **kwargs,
    )


def uwb(axis: str, **kwargs) -> Scenario:
    """Seed 004 Table II noise models for the ``x`` or ``y`` axis (simulated data, not the paper's recordings)."""
    if axis not in UWB_NOISES:
        raise ValueError(f"axis: expected 'x' or 'y', got {axis!r}")
    noises = UWB_NOISES[axis]
    return random_walk_velocity(
        noises["process"], noises["measurement"], name=f"seed004_uwb_{axis}",
        description=f"seed 004 Table II UWB noise models, {axis} axis (simulated from the fitted mixtures)",
        **kwargs,
    )
