"""The sigma-point Kalman core shared by the UKF, CKF, GHKF and sparse-grid filters (engine).

One core, :func:`local_sigma`, is parameterised by a :class:`gmjax.quadrature.SigmaPoints` rule
for ``N(0, I)``:

* predict: ``X_i = m + L z_i`` (``P = L L^T``), ``Y_i = f(X_i, t)``,
  ``m' = sum wm_i Y_i + q_mean``, ``P' = sum wc_i (Y_i - m'_0)(Y_i - m'_0)^T + Q``
  (seed 002 eqs 30–32; seed 001 eqs 8–10 for the cubature rule);
* update: points are **redrawn** from the predicted ``(m', P')`` (seed 001 eq 13),
  ``Z_i = h(X_i, t)``, ``z_hat = sum wm_i Z_i + r_mean``, ``S = sum wc_i dZ dZ^T + R``,
  ``Pxz = sum wc_i (X_i - m')(Z_i - z_hat_0)^T``, ``K = Pxz S^{-1}``, ``m+ = m' + K (z - z_hat)``,
  ``P+ = P' - K S K^T``.

Note: FilterPy's ``UnscentedKalmanFilter`` / ``CubatureKalmanFilter`` instead reuse the propagated
points ``f(X_i)`` in the update; with process noise the two differ. gmjax follows the papers
(redraw), which is also what makes the update depend on the predicted Gaussian only — a
requirement of Gaussian sum filters, whose components are re-created between predict and update.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from gmjax import gaussian, quadrature
from gmjax._types import StepFn
from gmjax.filters._core import (
    GaussianState,
    LocalFilter,
    check_model,
    circular_mean,
    finish_info,
    from_local,
    gaussian_state_init,
    gaussian_state_moments,
    kalman_gain,
    loglik_from_chol,
    repair_cov,
    safe_chol,
    safe_z,
    select_state,
    wrap_angles,
)
from gmjax.filters.base import Filter
from gmjax.models.base import StateSpaceModel, as_step_fn
from gmjax.quadrature import SigmaPoints

__all__ = ["check_rule", "rule_getter", "weighted_cov", "local_sigma", "build_sigma"]


def check_rule(rule) -> SigmaPoints:
    if not isinstance(rule, SigmaPoints):
        raise ValueError(f"rule: expected a quadrature.SigmaPoints, got {type(rule).__name__}")
    return rule


def rule_getter(rule):
    """``(d, dtype) -> SigmaPoints`` from a fixed rule or a constructor ``(d, dtype) -> rule``.

    The rule size is static, so constructors are called at trace time with the state's
    dimension and dtype; results are cached.
    """
    if isinstance(rule, SigmaPoints):

        def get(d, dtype):
            if rule.dim != d:
                raise ValueError(f"rule: dimension {rule.dim} does not match the state dimension {d}")
            return SigmaPoints(*(a.astype(dtype) for a in rule))

        return get
    if not callable(rule):
        raise ValueError(
            f"rule: expected a SigmaPoints or a callable (d, dtype) -> SigmaPoints, got {rule!r}"
        )
    cache = {}

    def get(d, dtype):
        key = (int(d), jnp.dtype(dtype).name)
        if key not in cache:
            # built eagerly even when first requested inside a trace, so the cache never
            # holds a tracer
            with jax.ensure_compile_time_eval():
                cache[key] = check_rule(rule(int(d), jnp.dtype(dtype)))
        return cache[key]

    return get


def weighted_cov(wc, A, B):
    """``sum_i wc_i A_i B_i^T`` for ``A (n, a)``, ``B (n, b)``."""
    return jnp.einsum("n,ni,nj->ij", wc, A, B)


def local_sigma(
    f: StepFn, h: StepFn, rule: SigmaPoints | Callable[..., SigmaPoints], angle_dims: tuple[int, ...] = ()
) -> LocalFilter:
    """Sigma-point Kalman filter with the quadrature ``rule`` (see the module docstring).

    Args:
        f: ``f(x (d,), t) -> (d,)``.
        h: ``h(x (d,), t) -> (m,)``.
        rule: a :class:`SigmaPoints` for ``N(0, I_d)``, or a constructor
            ``(d, dtype) -> SigmaPoints`` called at trace time with the state's size.
        angle_dims: measurement components that are angles: the predicted measurement averages
            them on the circle (:func:`~gmjax.filters._core.circular_mean`) and the deviations and
            the innovation are wrapped into ``[-pi, pi)``.

    Returns:
        A :class:`LocalFilter` over :class:`GaussianState`. The update's ``repaired`` flag is set
        when the predicted covariance, ``S`` or the posterior covariance needed jitter.
    """
    get_rule = rule_getter(rule)
    angle_dims = tuple(angle_dims)
    fv = jax.vmap(as_step_fn(f), in_axes=(0, None))
    hv = jax.vmap(as_step_fn(h), in_axes=(0, None))

    def predict(state: GaussianState, t, noise_mean, noise_cov) -> GaussianState:
        rule = get_rule(state.mean.shape[-1], state.mean.dtype)
        wm, wc = rule.wm, rule.wc
        X = quadrature.transform(rule, state.mean, safe_chol(state.cov).factor, is_chol=True)
        Y = fv(X, t)
        mean0 = wm @ Y
        dY = Y - mean0
        cov = gaussian.symmetrize(weighted_cov(wc, dY, dY) + noise_cov)
        return GaussianState(mean0 + noise_mean, cov)

    def update(state: GaussianState, z, t, noise_mean, noise_cov):
        m, P = state
        rule = get_rule(m.shape[-1], m.dtype)
        wm, wc = rule.wm, rule.wc
        chol_P = safe_chol(P)
        X = quadrature.transform(rule, m, chol_P.factor, is_chol=True)
        Z = hv(X, t)
        z0 = circular_mean(Z, wm, angle_dims)
        z_hat = z0 + noise_mean
        missing, z = safe_z(z, z_hat)
        dZ = wrap_angles(Z - z0, angle_dims)
        S = gaussian.symmetrize(weighted_cov(wc, dZ, dZ) + noise_cov)
        Pxz = weighted_cov(wc, X - m, dZ)
        chol_S = safe_chol(S)
        K = kalman_gain(Pxz, chol_S.factor)
        y = wrap_angles(z - z_hat, angle_dims)
        mean = m + K @ y
        cov, rep_post = repair_cov(P - K @ S @ K.T)
        ll = loglik_from_chol(y, chol_S.factor)
        info = finish_info(missing, ll, y, S, chol_P.repaired | chol_S.repaired | rep_post)
        return select_state(missing, state, GaussianState(mean, cov)), info

    return LocalFilter(gaussian_state_init, predict, update, gaussian_state_moments)


def build_sigma(model: StateSpaceModel, rule: SigmaPoints) -> Filter:
    """Model-level sigma-point filter with any rule (GM noises/prior moment-matched)."""
    d, _ = check_model(model)
    rule = check_rule(rule)
    if rule.dim != d:
        raise ValueError(f"rule: dimension {rule.dim} does not match the state dimension {d}")
    f, h, _, _ = model.step_fns()
    return from_local(model, local_sigma(f, h, rule, model.angle_dims))
