"""Learn a filter's model from data: maximum likelihood or a study loss, any parameter, in one call.

:func:`fit` takes a filter, the data (measurement sequences, or a :class:`~gmjax.models.Scenario` to
simulate), an objective and the names of the leaves of ``filter.params`` to fit, and runs an optax
optimiser in a compiled step until the loss stops moving. Everything else in ``params`` is held fixed;
masks and integer leaves never reach ``jax.grad``.

**Which leaves.** ``fit=["model.measurement_noise", "reducer.threshold"]`` names leaves by their path in
``filter.params`` (attribute names joined by dots, sequence indices as numbers); a name selects every
differentiable leaf below it (a mixture's ``weights``, ``means`` and ``covs``, not its ``mask``).
:func:`leaf_names` lists the names a filter has.

**Constraints.** The optimiser works on unconstrained values ``u``; each fitted leaf is mapped into its
valid set (:data:`CONSTRAINTS`): a mixture's ``weights`` onto the simplex of its live components
(softmax of log-weights; the weights of an intensity that does not sum to 1, such as a GM-PHD's
birth, stay positive instead), its ``covs`` onto SPD matrices (log-Cholesky: ``C = L L^T`` with ``L``'s
diagonal ``exp(u_ii)``), ``means`` unconstrained, every other leaf positive (softplus) unless
``constraints={name: "real" | "positive" | "unit" | "simplex" | "stochastic" | "spd" | (low, high)}``
says otherwise; an IMM's ``transition`` matrix keeps its rows on the simplex (``"stochastic"``), a
Kalman filter's ``Q``, ``R`` and ``prior_cov`` stay SPD.
Results are returned in natural units.

**Objectives.** :func:`nll` (the default with measurements): the negative log-likelihood per step,
``-(1 / (B T)) Σ_b Σ_t StepInfo.loglik``, of one ``(T, m)`` or a batch ``(B, T, m)`` of sequences, for
every filter that reports ``loglik`` (KF/EKF/UKF/CKF, GSF, IMM, PF, ...; the multi-target GM-PHD, GM-CPHD
and GM-LMB on padded sets ``(B, T, M, m)``, the LMB with ``key``'s draws, the same every step).
:func:`study` (the default with
a scenario): any loss of :mod:`gmjax.montecarlo` (``armse_loss``, ``anees_loss``, ...) on ``n_runs``
simulated runs, the same runs every step (common random numbers) unless ``resample``; for a GM-PHD
filter on a :class:`~gmjax.multitarget.MultiTargetScenario`, a per-run loss of
:mod:`gmjax.multitarget.study` such as the mean relaxed GOSPA ``gospa_loss(c=...)``.

**Convergence.** The default optimiser is ``optax.lbfgs()`` for a deterministic objective and
``optax.adam(0.05)`` with ``resample``. A fit has converged when the unconstrained gradient's largest
entry is below ``gtol`` or the loss changed by less than ``ftol`` (relative) in each of the last 3
steps; it then stops early. A step with a non-finite loss or gradient is skipped and counted.

**Resume.** With ``checkpoint=path`` the unconstrained values, the optimiser state and the history are
written atomically (with a checksum) every ``checkpoint_every`` seconds, at the end and on an
interruption; the same call resumes and continues bit for bit. :func:`gmjax.tune.tune` names the
leaves it tunes the same way (``{"reducer.rho": 0.95}``, :func:`with_leaves`); it is the lighter loop
(scalars in box bounds, a plot of each step), ``fit`` the general one.
"""

from gmjax.fitting._loop import FitHistory as FitHistory
from gmjax.fitting._loop import FitResult as FitResult
from gmjax.fitting._loop import fit as fit
from gmjax.fitting._loop import plot_history as plot_history
from gmjax.fitting._objectives import Objective as Objective
from gmjax.fitting._objectives import loss_fn as loss_fn
from gmjax.fitting._objectives import nll as nll
from gmjax.fitting._objectives import study as study
from gmjax.fitting._params import CONSTRAINTS as CONSTRAINTS
from gmjax.fitting._params import ParamView as ParamView
from gmjax.fitting._params import leaf_names as leaf_names
from gmjax.fitting._params import param_view as param_view
from gmjax.fitting._params import with_leaves as with_leaves

__all__ = [
    "CONSTRAINTS",
    "Objective",
    "ParamView",
    "FitHistory",
    "FitResult",
    "nll",
    "study",
    "leaf_names",
    "param_view",
    "with_leaves",
    "loss_fn",
    "fit",
    "plot_history",
]
