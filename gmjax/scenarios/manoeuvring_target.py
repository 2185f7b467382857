"""A manoeuvring target (circular motion, step manoeuvre) with a GM initial state and GM measurement noise,
tracked by an IMM of CS and CT models: Xu et al. 2019 (GMRCM; seed 003 §4.2).

The paper (Xu, Fang, Wu, Zhang, J. NUDT 2019, in Chinese) gives, for §4.2:

* state ``x = [x, ẋ, ẍ]^T`` (position, velocity, acceleration of one axis);
* GM initial state ``p(x_0) = 0.6 N(x_1, P_1) + 0.4 N(x_2, P_2)``, ``x_1 = [30, 20, 10]``,
  ``P_1 = diag[300, 100, 50]``, ``x_2 = [20, 10, 5]``, ``P_2 = diag[350, 200, 40]``;
* GM measurement noise ``p(v) = 0.5 N(v_1, R_1) + 0.5 N(v_2, R_2)``, ``v_1 = [10, 5, 2]``,
  ``R_1 = diag[100, 25, 4]``, ``v_2 = [-10, 3, 1]``, ``R_2 = diag[100, 9, 1]``;
* "system state noise" ``Q = diag[10, 4, 2]``; ``t_s = 1`` s, ``T_o = 200`` s, 100 Monte Carlo runs;
* an IMM of a "current statistic" (CS) model and a constant-turn (CT) model with known turn rate
  ``0.02π`` rad/s, manoeuvre frequency ``α = 0.01`` Hz, ``a_max = 50`` m/s² ("other CS parameters
  see ref [22]"), ``P_IMM = [[0.95, 0.05], [0.05, 0.95]]``;
* §4.2.1: the target moves on a circle at ``0.02π`` rad/s; §4.2.2: step manoeuvre with
  ``ẍ = 10`` (``0 < t < 50``), ``20`` (``50 ≤ t < 100``), ``-10`` m/s² (``100 ≤ t ≤ 200``).

**Our reading** of what the paper leaves out (every choice is a parameter):

* *Measurement model.* The noise mixture is 3-D, so every state component is measured:
  ``z = x + v`` (``H = I_3``). The glint density of eqs 19–21 (``ε = 0.01``) is the paper's
  motivation for GM noise; the stated measurement noise is the two-component mixture above, and
  that is both the simulator's and the filters' noise (the prior is the true initial density too).
* *CS model* (Zhou's current-statistic model, the paper's ref [22]). Its transition is the Singer
  matrix ``F(α)`` plus the input ``U(α) ā`` with the "current" mean acceleration ``ā`` equal to the
  one-step prediction of the acceleration; substituting ``ā = ẍ`` gives the linear transition
  ``F_CS = F(α) + U(α) e_3^T``, which is exactly the constant-acceleration matrix
  (:func:`cs_transition` builds it from ``α`` and the test checks the identity). Ref [22]'s
  adaptive variance ``σ_a² = (4-π)/π (a_max - |ā|)²`` makes the process noise depend on the
  state estimate, which is not an additive GM noise; we use the paper's explicit ``Q`` for both
  models, so ``a_max`` only appears in the description.
* *CT model.* For one axis of a planar turn at rate ``ω`` the acceleration obeys ``d ẍ/dt = -ω² ẋ``
  (independent of the turn centre), so the CT transition on ``[x, ẋ, ẍ]`` is
  ``expm(A t_s)`` with ``A = [[0, 1, 0], [0, 0, 1], [0, -ω², 0]]`` (:func:`ct_transition`).
* *Truth.* ``x_0`` is drawn from the GM prior. Circular motion (§4.2.1) is the CT transition
  without process noise (the one-axis projection of a uniform circular motion at ``0.02π`` rad/s);
  the step manoeuvre (§4.2.2) keeps the prior's position and velocity draw, sets the acceleration
  to the schedule (``ẍ_0 = 10``) and integrates it exactly (constant acceleration over each
  sampling interval, the acceleration of step ``t`` being the schedule at ``t``). The paper's ``Q``
  is what the filters assume; ``truth_process_noise=True`` also adds ``N(0, Q)`` to the truth.
* *Tracker.* :func:`imm_models` returns the CS and CT :class:`StateSpaceModel` s for
  :func:`gmjax.filters.imm.build_imm_gsf` (IMM with Gaussian-sum model-conditioned filters, the
  reduction applied in each model's filter after its update) with :data:`TRANSITION` and the
  regulariser ``α = 0.3`` of GMRCM (:data:`REGULARIZER`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array, DTypeLike
from gmjax.mixture import GaussianMixture
from gmjax.models.base import Scenario, StateSpaceModel
from gmjax.models.noise import mixture_sampler

__all__ = [
    "cs_transition",
    "ct_transition",
    "step_acceleration",
    "imm_models",
    "tracking",
    "circular_motion",
    "step_maneuver",
    "TRANSITION",
    "REGULARIZER",
    "PAPER",
]

TRANSITION = np.array([[0.95, 0.05], [0.05, 0.95]])
"""``P_IMM`` of §4.2 (``[i, j] = P(model j | model i)``; model 0 = CS, model 1 = CT)."""

REGULARIZER = 0.3
"""The regularisation constant of §4.2 (GMRCM's ``α`` of eq 10)."""

PAPER = {
    "circular": {
        "armse": {"GMRC": 8.96, "Runnalls": 9.29, "GMRCM": 9.32, "GMRP": 9.78},
        "time_s": {"GMRC": 0.52, "Runnalls": 0.48, "GMRCM": 0.38, "GMRP": 0.44},
    },
    "step": {
        "armse": {"GMRC": 9.32, "Runnalls": 9.58, "GMRCM": 10.2, "GMRP": 12.17},
        "time_s": {"GMRC": 0.67, "Runnalls": 0.57, "GMRCM": 0.45, "GMRP": 0.62},
    },
}
"""The paper's average position RMSE (m) and run time (s) per reducer (§4.2.1, §4.2.2)."""

_Q = np.diag([10.0, 4.0, 2.0])
_PRIOR = (
    [0.6, 0.4],
    [[30.0, 20.0, 10.0], [20.0, 10.0, 5.0]],
    [np.diag([300.0, 100.0, 50.0]), np.diag([350.0, 200.0, 40.0])],
)
_NOISE = (
    [0.5, 0.5],
    [[10.0, 5.0, 2.0], [-10.0, 3.0, 1.0]],
    [np.diag([100.0, 25.0, 4.0]), np.diag([100.0, 9.0, 1.0])],
)


def cs_transition(alpha: float = 0.01, dt: float = 1.0) -> np.ndarray:
    """Current-statistic transition with the mean acceleration set to the predicted one (ref [22]).

    ``F(α) = [[1, T, (αT - 1 + e^{-αT})/α²], [0, 1, (1 - e^{-αT})/α], [0, 0, e^{-αT}]]`` and
    ``U(α) = [(-T + αT²/2 + (1 - e^{-αT})/α)/α, T - (1 - e^{-αT})/α, 1 - e^{-αT}]``; returns
    ``F(α) + U(α) e_3^T`` (``(3, 3)``), which equals the constant-acceleration matrix.
    """
    if not alpha > 0 or not dt > 0:
        raise ValueError(f"alpha, dt: must be positive, got alpha={alpha!r}, dt={dt!r}")
    a, T = float(alpha), float(dt)
    e = np.exp(-a * T)
    F = np.array([[1.0, T, (a * T - 1 + e) / a**2], [0.0, 1.0, (1 - e) / a], [0.0, 0.0, e]])
    U = np.array([(-T + a * T**2 / 2 + (1 - e) / a) / a, T - (1 - e) / a, 1 - e])
    return F + np.outer(U, [0.0, 0.0, 1.0])


def ct_transition(omega: float = 0.02 * np.pi, dt: float = 1.0) -> np.ndarray:
    """``expm(A dt)`` for ``A = [[0, 1, 0], [0, 0, 1], [0, -ω², 0]]`` (one axis of a turn at rate ``ω``).

    ``[[1, sin(ωT)/ω, (1 - cos ωT)/ω²], [0, cos ωT, sin(ωT)/ω], [0, -ω sin ωT, cos ωT]]``.
    """
    if not omega > 0 or not dt > 0:
        raise ValueError(f"omega, dt: must be positive, got omega={omega!r}, dt={dt!r}")
    w, T = float(omega), float(dt)
    s, c = np.sin(w * T), np.cos(w * T)
    return np.array([[1.0, s / w, (1 - c) / w**2], [0.0, c, s / w], [0.0, -w * s, c]])


def step_acceleration(t: Array) -> Array:
    """The §4.2.2 schedule ``ẍ(t)``: 10 for ``t < 50``, 20 for ``50 <= t < 100``, -10 after (m/s²)."""
    t = jnp.asarray(t)
    return jnp.where(t < 50, 10.0, jnp.where(t < 100, 20.0, -10.0))


def _mixtures(dtype):
    q = GaussianMixture.create([1.0], [np.zeros(3)], [_Q], dtype=dtype)
    r = GaussianMixture.create(*_NOISE, dtype=dtype)
    prior = GaussianMixture.create(*_PRIOR, dtype=dtype)
    return q, r, prior


def imm_models(
    *, alpha: float = 0.01, omega: float = 0.02 * np.pi, dt: float = 1.0, dtype: DTypeLike | None = None
) -> tuple[StateSpaceModel, StateSpaceModel]:
    """The CS and CT models of the §4.2 IMM (GM prior, ``Q``, GM measurement noise, ``H = I_3``)."""
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    q, r, prior = _mixtures(dtype)
    eye = jnp.eye(3, dtype=dtype)

    def model(Fm):
        Fj = jnp.asarray(Fm, dtype)
        return StateSpaceModel(
            f=lambda x, t: Fj @ x,
            h=lambda x, t: x,
            process_noise=q,
            measurement_noise=r,
            prior=prior,
            f_jacobian=lambda x, t: Fj,
            h_jacobian=lambda x, t: eye,
        )

    return model(cs_transition(alpha, dt)), model(ct_transition(omega, dt))


def tracking(
    motion: str = "circular",
    *,
    alpha: float = 0.01,
    omega: float = 0.02 * np.pi,
    dt: float = 1.0,
    duration: float = 200.0,
    truth_process_noise: bool = False,
    dtype: DTypeLike | None = None,
) -> Scenario:
    """The §4.2 scenario ``motion`` (``"circular"`` or ``"step"``); see the module docstring.

    ``Scenario.model`` is the CS model (the filters' models are :func:`imm_models`).
    """
    if motion not in ("circular", "step"):
        raise ValueError(f"motion: expected 'circular' or 'step', got {motion!r}")
    if not duration > 0:
        raise ValueError(f"duration: must be positive, got {duration!r}")
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    cs, ct = imm_models(alpha=alpha, omega=omega, dt=dt, dtype=dtype)
    q, r, prior = _mixtures(dtype)
    draw_prior = mixture_sampler(prior)
    draw_r = mixture_sampler(r)
    Lq = jnp.asarray(np.linalg.cholesky(_Q), dtype)
    n_steps = int(round(duration / dt))
    if motion == "circular":
        Fct = jnp.asarray(ct_transition(omega, dt), dtype)
        truth_f = lambda x, t: Fct @ x  # noqa: E731
        sample_initial = draw_prior
        what = f"uniform circular motion at {omega:.4g} rad/s (CT transition, no process noise)"
    else:

        def truth_f(x, t):
            a = x[2]
            return jnp.stack(
                [x[0] + x[1] * dt + a * dt**2 / 2, x[1] + a * dt, step_acceleration(t * dt).astype(x.dtype)]
            )

        def sample_initial(key):
            x0 = draw_prior(key)
            return x0.at[2].set(step_acceleration(0.0).astype(x0.dtype))

        what = "step manoeuvre (acceleration 10 / 20 / -10 m/s^2 switching at 50 s and 100 s)"

    if truth_process_noise:
        sample_q = lambda key, t: Lq @ jax.random.normal(key, (3,), dtype)  # noqa: E731
    else:
        sample_q = lambda key, t: jnp.zeros(3, dtype)  # noqa: E731
    return Scenario(
        name=f"seed003_{motion}",
        model=cs,
        n_steps=n_steps,
        sample_initial=sample_initial,
        sample_process_noise=sample_q,
        sample_measurement_noise=lambda key, t: draw_r(key),
        truth_f=truth_f,
        truth_h=lambda x, t: x,
        position_dims=(0,),
        description=(
            f"seed 003 §4.2: {what}; state [x, v, a], z = x + v with the paper's 2-component GM "
            f"noise, GM prior, Q = diag[10, 4, 2] assumed by the filters"
            f"{' and added to the truth' if truth_process_noise else ''}; IMM of CS (alpha={alpha}, "
            f"a_max = 50 m/s^2 not used: fixed Q) and CT (omega={omega:.4g}) models; {n_steps} steps "
            f"of {dt} s."
        ),
    )


def circular_motion(**kwargs: Any) -> Scenario:
    """§4.2.1: :func:`tracking` with ``motion="circular"``."""
    return tracking("circular", **kwargs)


def step_maneuver(**kwargs: Any) -> Scenario:
    """§4.2.2: :func:`tracking` with ``motion="step"``."""
    return tracking("step", **kwargs)
