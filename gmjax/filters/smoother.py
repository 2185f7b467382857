"""Fixed-interval smoothers over what :func:`gmjax.filters.run` returns.

* :func:`rts_smoother` — Rauch–Tung–Striebel smoothing of Gaussian filtered moments (Rauch, Tung &
  Striebel 1965). The backward pass re-predicts every filtered ``(m_k, P_k)`` through the model and
  needs the predicted moments and the cross-covariance ``C_{k+1} = Cov(x_k, x_{k+1} | z_{1:k})``:

  * ``"kf"`` / ``"ekf"``: ``F = df/dx`` at ``m_k``, ``m^- = f(m_k) + q``, ``P^- = F P_k F^T + Q``,
    ``C = P_k F^T`` (FilterPy's ``KalmanFilter.rts_smoother`` for a linear model);
  * ``"ukf"``, ``"ckf"``, ``"ghkf"`` or any :class:`~gmjax.quadrature.SigmaPoints` rule: the
    sigma-point (unscented) RTS smoother of Särkkä (2008), ``C = sum_i wc_i (X_i - m_k)(f(X_i) - m^-)^T``;

  then ``G = C (P^-)^{-1}``, ``m^s_k = m_k + G (m^s_{k+1} - m^-)``,
  ``P^s_k = P_k + G (P^s_{k+1} - P^-) G^T`` (Särkkä, *Bayesian Filtering and Smoothing*, Thm 8.2 /
  Alg 9.3). :func:`rts_linear` is the same recursion from matrices ``F``, ``Q``.
* :func:`gaussian_sum_smoother` — a forward–backward Gaussian-sum RTS smoother with a reducer in the
  loop (see its docstring for the method and its one approximation).

Time indexing follows :func:`gmjax.filters.run`: entry ``k`` is the posterior at ``inputs.t[k]``,
and the transition from entry ``k`` to ``k + 1`` is the model's step with ``inputs[k + 1]``
(``f(x, t[k+1])``, ``Q(dt[k+1])``).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from gmjax import gaussian, quadrature
from gmjax import mixture as gmm
from gmjax._types import Array
from gmjax.filters._core import check_model, gaussian_moments, safe_chol
from gmjax.filters._sigma import rule_getter, weighted_cov
from gmjax.filters.base import StepInputs, step_inputs
from gmjax.mixture import GaussianMixture
from gmjax.models.base import StateSpaceModel

__all__ = [
    "SmootherResult",
    "GSSmootherResult",
    "rts_smoother",
    "rts_linear",
    "gaussian_sum_smoother",
    "predict_with_cross",
]


class SmootherResult(NamedTuple):
    """Smoothed moments.

    Attributes:
        mean: ``(T, d)`` ``E[x_k | z_{1:T}]``.
        cov: ``(T, d, d)`` ``Cov[x_k | z_{1:T}]``.
        gain: ``(T, d, d)`` smoother gains ``G_k`` (the last is 0).
        predicted_cov: ``(T, d, d)`` ``P^-_{k+1}`` re-predicted from entry ``k`` (the last is 0).
    """

    mean: Array
    cov: Array
    gain: Array
    predicted_cov: Array


def _sigma_rule(method: Any):
    """A ``(d, dtype) -> SigmaPoints`` getter for a sigma-point method name or rule."""
    if isinstance(method, str):
        if method == "ukf":
            return rule_getter(lambda d, dtype: quadrature.unscented(d, 1.0, 0.0, None, dtype=dtype))
        if method == "ckf":
            return rule_getter(lambda d, dtype: quadrature.cubature(d, dtype=dtype))
        if method == "ghkf":
            return rule_getter(lambda d, dtype: quadrature.gauss_hermite(d, 3, dtype=dtype))
        raise ValueError(
            f"method: expected 'kf', 'ekf', 'ukf', 'ckf', 'ghkf' or a quadrature.SigmaPoints rule, "
            f"got {method!r}"
        )
    return rule_getter(method)


def predict_with_cross(
    f: Callable[[Array, Any], Array], f_jacobian: Callable[[Array, Any], Array] | None, method: Any
) -> Callable[..., tuple[Array, Array, Array]]:
    """``(m (d,), P (d, d), inputs, q_mean, Q) -> (m^-, P^-, C)`` with ``C = Cov(x_k, x_{k+1})``.

    Args:
        f: ``f(x, inputs)``; f_jacobian: ``(x, inputs) -> (d, d)`` or ``None`` (``jax.jacfwd``).
        method: ``"kf"``, ``"ekf"``, ``"ukf"``, ``"ckf"``, ``"ghkf"``, a
            :class:`~gmjax.quadrature.SigmaPoints` rule or a constructor ``(d, dtype) -> rule``.
    """
    if isinstance(method, str) and method in ("kf", "ekf"):
        jac = jax.jacfwd(f) if f_jacobian is None else f_jacobian

        def lin(m, P, inp, q_mean, Q):
            F = jac(m, inp)
            C = P @ F.T
            return f(m, inp) + q_mean, gaussian.symmetrize(F @ C + Q), C

        return lin
    get_rule = _sigma_rule(method)
    fv = jax.vmap(f, in_axes=(0, None))

    def sigma(m, P, inp, q_mean, Q):
        rule = get_rule(m.shape[-1], m.dtype)
        X = quadrature.transform(rule, m, safe_chol(P).factor, is_chol=True)
        Y = fv(X, inp)
        y0 = rule.wm @ Y
        dY = Y - y0
        P_pred = gaussian.symmetrize(weighted_cov(rule.wc, dY, dY) + Q)
        return y0 + q_mean, P_pred, weighted_cov(rule.wc, X - m, dY)

    return sigma


def _gain(C: Array, P_pred: Array) -> Array:
    """``G = C (P^-)^{-1}`` with a (repaired) Cholesky factor of ``P^-``."""
    L = safe_chol(P_pred).factor
    return gaussian.cho_solve_small(L, C.T).T


def _rts_scan(backward, means: Array, covs: Array, xs_next) -> SmootherResult:
    """The backward pass for ``k = T-2 .. 0``; ``backward(m_k, P_k, next_k) -> (m^-, P^-, C)``."""
    (_, _), (ms, Ps, G, Pp) = jax.lax.scan(
        lambda c, x: _rts_body(backward, c, x),
        (means[-1], covs[-1]),
        (means[:-1], covs[:-1], xs_next),
        reverse=True,
    )
    zeros = jnp.zeros_like(covs[:1])
    return SmootherResult(
        jnp.concatenate([ms, means[-1:]]),
        jnp.concatenate([Ps, covs[-1:]]),
        jnp.concatenate([G, zeros]),
        jnp.concatenate([Pp, zeros]),
    )


def _rts_body(backward, carry, xs):
    ms_next, Ps_next = carry
    m, P, nxt = xs
    m_pred, P_pred, C = backward(m, P, nxt)
    G = _gain(C, P_pred)
    ms = m + G @ (ms_next - m_pred)
    Ps = gaussian.symmetrize(P + G @ (Ps_next - P_pred) @ G.T)
    return (ms, Ps), (ms, Ps, G, P_pred)


def _check_moments(means, covs) -> tuple[Array, Array]:
    means, covs = jnp.asarray(means), jnp.asarray(covs)
    if means.ndim != 2 or covs.shape != means.shape + means.shape[-1:]:
        raise ValueError(
            f"means, covs: expected shapes (T, d) and (T, d, d), got {means.shape} and {covs.shape}"
        )
    if means.shape[0] < 1:
        raise ValueError("means: need at least one step")
    return means, covs


def rts_linear(F: Array, Q: Array, means: Array, covs: Array) -> SmootherResult:
    """RTS smoother of a linear model, FilterPy's ``KalmanFilter.rts_smoother(Xs, Ps, Fs, Qs)``.

    Args:
        F: ``(d, d)`` or ``(T, d, d)``; ``F[k + 1]`` maps entry ``k`` to ``k + 1`` (``F[0]`` unused).
        Q: ``(d, d)`` or ``(T, d, d)``, likewise.
        means, covs: ``(T, d)``, ``(T, d, d)`` filtered moments.
    """
    means, covs = _check_moments(means, covs)
    T, d = means.shape
    F = jnp.broadcast_to(jnp.asarray(F, means.dtype), (T, d, d))
    Q = jnp.broadcast_to(jnp.asarray(Q, means.dtype), (T, d, d))

    def backward(m, P, nxt):
        Fk, Qk = nxt
        C = P @ Fk.T
        return Fk @ m, gaussian.symmetrize(Fk @ C + Qk), C

    if T == 1:
        return SmootherResult(means, covs, jnp.zeros_like(covs), jnp.zeros_like(covs))
    return _rts_scan(backward, means, covs, (F[1:], Q[1:]))


def _step_inputs(inputs, T):
    return step_inputs(T, inputs)


def _slice_inputs(inputs: StepInputs, start: int) -> StepInputs:
    return jax.tree_util.tree_map(lambda a: a[start:], inputs)


def rts_smoother(
    model: StateSpaceModel,
    means: Array,
    covs: Array,
    inputs: Any = None,
    *,
    method: Any = "ekf",
    params: Any = None,
) -> SmootherResult:
    """Rauch–Tung–Striebel smoother of a Gaussian filter's output (module docstring).

    Args:
        model: the model the filter ran on (its ``f``, Jacobian, process noise, ``process_noise_at``).
        means, covs: ``(T, d)``, ``(T, d, d)`` filtered moments, e.g. ``infos.mean``, ``infos.cov``
            of :func:`gmjax.filters.run` with a KF, EKF, UKF, CKF or GHKF.
        inputs: the same inputs given to :func:`~gmjax.filters.run` (``None``: times ``1..T``).
        method: how to re-predict: ``"kf"``/``"ekf"`` (Jacobian) or ``"ukf"``/``"ckf"``/``"ghkf"``/a
            sigma-point rule (Särkkä's URTS); use the filter's own.
        params: a :class:`~gmjax.models.ModelParams` (default ``model.params``); a GM process noise
            is moment-matched, as the single-Gaussian filters do.

    Returns:
        :class:`SmootherResult`.
    """
    check_model(model)
    means, covs = _check_moments(means, covs)
    T = means.shape[0]
    inputs = _step_inputs(inputs, T)
    params = model.params if params is None else params
    f, _, fj, _ = model.step_fns()
    pred = predict_with_cross(f, fj, method)
    if T == 1:
        return SmootherResult(means, covs, jnp.zeros_like(covs), jnp.zeros_like(covs))

    def backward(m, P, inp):
        x = m if model.state_dependent_noise else None  # Q(x) at the filtered mean, as the filter
        q_mean, Q = gaussian_moments(model.noise_at(params.process_noise, inp, x))
        return pred(m, P, inp, q_mean.astype(m.dtype), Q.astype(m.dtype))

    return _rts_scan(backward, means, covs, _slice_inputs(inputs, 1))


# ---------------------------------------------------------------------------------------------
# Gaussian-sum smoother


class GSSmootherResult(NamedTuple):
    """Output of :func:`gaussian_sum_smoother`.

    Attributes:
        mixture: smoothed mixtures with a leading ``T`` axis (capacity ``capacity``).
        mean: ``(T, d)`` their means. cov: ``(T, d, d)`` their covariances.
        reduction: the reducer's :class:`~gmjax.reduction.ReductionInfo` per backward step
            (leading ``T - 1`` axis; entry ``k`` reduced the smoothed mixture of entry ``k``). Its
            ``overflow`` is also True where the reducer's output held more live components than
            ``capacity`` (the heaviest were kept).
    """

    mixture: GaussianMixture
    mean: Array
    cov: Array
    reduction: Any


def _gs_backward_step(
    pred, filtered: GaussianMixture, smoothed: GaussianMixture, inp, noise: GaussianMixture
) -> GaussianMixture:
    """The ``K·L·S`` smoothed components of entry ``k`` (see :func:`gaussian_sum_smoother`)."""

    def pair(m, P, qm, qP):
        m_pred, P_pred, C = pred(m, P, inp, qm, qP)
        return m_pred, P_pred, _gain(C, P_pred)

    over_l = jax.vmap(pair, (None, None, 0, 0))
    m_pred, P_pred, G = jax.vmap(over_l, (0, 0, None, None))(
        filtered.means, filtered.covs, noise.means, noise.covs
    )  # (K, L, d), (K, L, d, d)
    log_pair = (
        gmm.log_weights(filtered)[:, None]
        + gmm.log_weights(noise)[None, :]
        - logsumexp(gmm.log_weights(noise))
    )  # (K, L)
    pair_mask = filtered.mask[:, None] & noise.mask[None, :]

    def one_s(mu, Sig):
        # log N(mu_s; m^-_il, P^-_il + Sigma_s): the (i, l) pair's responsibility under component s
        def loglik(a, B):
            return gaussian.logpdf(mu, a, gaussian.symmetrize(B + Sig))

        ll = jax.vmap(jax.vmap(loglik))(m_pred, P_pred)
        logw = jnp.where(pair_mask, log_pair + ll, -jnp.inf)
        logw = logw - logsumexp(logw)
        mean = filtered.means[:, None, :] + jnp.einsum("klij,klj->kli", G, mu - m_pred)
        cov = filtered.covs[:, None] + jnp.einsum("klij,kljm,klnm->klin", G, Sig - P_pred, G)
        return logw, mean, gaussian.symmetrize(cov)

    logw, means, covs = jax.vmap(one_s)(smoothed.means, smoothed.covs)  # (S, K, L, ...)
    logw = logw + gmm.log_weights(smoothed)[:, None, None]
    mask = smoothed.mask[:, None, None] & pair_mask[None]
    d = filtered.dim
    w = jnp.where(mask, jnp.exp(logw - logsumexp(jnp.where(mask, logw, -jnp.inf))), 0.0)
    return gmm.sanitize(
        GaussianMixture(w.reshape(-1), means.reshape(-1, d), covs.reshape(-1, d, d), mask.reshape(-1))
    )


def gaussian_sum_smoother(
    model: StateSpaceModel,
    mixtures: GaussianMixture,
    inputs: Any = None,
    *,
    reducer: Any = None,
    capacity: int | None = None,
    method: Any = "ekf",
    params: Any = None,
) -> GSSmootherResult:
    """Forward–backward Gaussian-sum RTS smoother with a reducer in the backward loop.

    Method. The forward pass is any Gaussian sum filter (:func:`gmjax.filters.build_gsf`), whose
    posteriors ``p(x_k | z_{1:k}) = sum_i w_i N(m_i, P_i)`` are ``mixtures``. With a GM process noise
    ``sum_l g_l N(q_l, Q_l)``, the backward kernel is a mixture over pairs ``(i, l)``:
    ``p(x_k | x_{k+1}, z_{1:k}) = sum_il omega_il(x_{k+1}) N(x_k; m_i + G_il (x_{k+1} - m^-_il),
    P_i - G_il P^-_il G_il^T)`` with the RTS gain ``G_il`` of the pair (its moments re-predicted by
    ``method``, as in :func:`rts_smoother`) and ``omega_il(x) ∝ w_i g_l N(x; m^-_il, P^-_il)``. Given
    the smoothed ``p(x_{k+1} | z_{1:T}) = sum_s v_s N(mu_s, Sigma_s)``, every ``(s, i, l)`` gives the
    RTS component ``N(m_i + G_il (mu_s - m^-_il), P_i + G_il (Sigma_s - P^-_il) G_il^T)`` with weight
    ``v_s omega_il|s``, where the one approximation of the method replaces the weight function
    ``omega_il(x)`` by the ratio of its numerator's and denominator's expectations under component
    ``s``: ``omega_il|s ∝ w_i g_l N(mu_s; m^-_il, P^-_il + Sigma_s)`` (exact when ``Sigma_s -> 0``,
    and for a single pair, where the recursion is the RTS smoother). The ``S·K·L`` components are
    reduced back to ``capacity`` by ``reducer`` at every step. It is the mixture form of the RTS
    backward pass (Rauch, Tung & Striebel 1965) with a reducer in the loop, as the Gaussian sum filter
    has in its forward pass; Kitagawa's (1994) Gaussian-sum smoother instead uses the two-filter
    formula. Checked against a dense-grid forward-backward smoother in ``tests/filters/test_smoother.py``.

    Args:
        model: the model of the forward pass (``f``, its Jacobian, the GM process noise).
        mixtures: the filtered posteriors with a leading ``T`` axis (``states.mixture`` of
            :func:`gmjax.filters.run` with a GSF).
        inputs: the forward pass's inputs (``None``: times ``1..T``).
        reducer: a :mod:`gmjax.reduction` config (stateless; e.g. ``Runnalls(num_out=capacity)``);
            ``None`` keeps the ``capacity`` heaviest components (:class:`~gmjax.reduction.PruneTop`).
        capacity: slots of the smoothed mixtures (default: the filtered mixtures' capacity). The
            last filtered mixture (the last smoothed one) must fit: ``ValueError`` when it is
            concrete and has more live components; a traced one (under ``jit``) keeps its heaviest.
        method: how each pair is re-predicted: ``"ekf"`` (``"kf"``) or a sigma-point method.
        params: a :class:`~gmjax.models.ModelParams` (default ``model.params``).

    Returns:
        :class:`GSSmootherResult`.
    """
    from gmjax.filters.gsf import check_reducer, concrete_n_active, fit_capacity
    from gmjax.reduction import PruneTop

    check_model(model)
    if not isinstance(mixtures, GaussianMixture) or mixtures.means.ndim != 3:
        raise ValueError(
            "mixtures: expected a GaussianMixture with a leading T axis (states.mixture of a GSF run)"
        )
    T, K, d = mixtures.means.shape
    capacity = K if capacity is None else capacity
    if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
        raise ValueError(f"capacity: must be a positive int, got {capacity!r}")
    reducer = PruneTop(num_out=capacity, capacity=capacity) if check_reducer(reducer) is None else reducer
    inputs = _step_inputs(inputs, T)
    params = model.params if params is None else params
    f, _, fj, _ = model.step_fns()
    pred = predict_with_cross(f, fj, method)
    last = jax.tree_util.tree_map(lambda a: a[-1], mixtures)
    n_last = concrete_n_active(last)
    if n_last is not None and n_last > capacity:
        raise ValueError(
            f"capacity: the last filtered mixture has {n_last} live components, more than "
            f"capacity={capacity} slots hold (the smoothed mixture of the last step is the filtered one)"
        )
    last = fit_capacity(gmm.normalize(last), capacity)[0]

    def body(smoothed, xs):
        filtered, inp = xs
        noise = model.noise_at(params.process_noise, inp)
        full = _gs_backward_step(pred, filtered, smoothed, inp, noise)
        out, _, rinfo = reducer.reduce(full, reducer.init(full.capacity), key=None)
        out, overflow = fit_capacity(out, capacity)
        return out, (out, rinfo._replace(overflow=rinfo.overflow | overflow))

    filtered = jax.tree_util.tree_map(lambda a: a[:-1], mixtures)
    if T == 1:
        smoothed = jax.tree_util.tree_map(lambda a: a[None], last)
        rinfo = None
    else:
        _, (smoothed, rinfo) = jax.lax.scan(body, last, (filtered, _slice_inputs(inputs, 1)), reverse=True)
        smoothed = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), smoothed, last)
    mean, cov = jax.vmap(gmm.moments)(smoothed)
    return GSSmootherResult(smoothed, mean, cov, rinfo)
