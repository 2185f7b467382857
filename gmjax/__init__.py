"""gmjax: Gaussian-mixture state estimation in JAX.

Fixed-capacity padded mixtures with masks, so reduction, Gaussian sum filtering and quadrature run as
compiled kernels, ``vmap``-ed over Monte Carlo runs and ``lax.scan``-ned over time. Importing gmjax
never changes ``jax.config``; enable float64 yourself with ``jax.config.update("jax_enable_x64", True)``.

Modules: :mod:`mixture` (the core type), :mod:`gaussian`, :mod:`metrics`, :mod:`quadrature`,
:mod:`split`, :mod:`reduction`, :mod:`filters`, :mod:`models`, :mod:`scenarios` (the papers' systems),
:mod:`montecarlo`, :mod:`pcrb`,
:mod:`fitting` (``fit``: learn any leaf of a filter's params by maximum likelihood or a study loss,
re-exported here), :mod:`tune` (differentiable threshold tuning), :mod:`studies`, :mod:`params` (``grad``,
``value_and_grad``, ``partition``, ``combine`` over the differentiable leaves of a params pytree,
re-exported here: ``gmjax.grad(loss)(gsf.params)`` skips the mixtures' boolean masks).

Docstrings cite the five papers gmjax implements by equation number under the labels "seed 000" to
"seed 004": seed 000 is Xu et al., PCM (IEEE Access); seed 001 Liu et al. 2014, AGSSCKF; seed 002
Zhang et al. 2021, PCRBs from Gaussian mixtures; seed 003 Xu et al. 2019, GMRCM; seed 004 Pishdad &
Labeau 2014, the active-cluster reduction. Full references: ``docs/references.md``.
"""

from gmjax import filters as filters
from gmjax import fitting as fitting
from gmjax import gaussian as gaussian
from gmjax import metrics as metrics
from gmjax import mixture as mixture
from gmjax import models as models
from gmjax import montecarlo as montecarlo
from gmjax import multitarget as multitarget
from gmjax import params as params
from gmjax import pcrb as pcrb
from gmjax import quadrature as quadrature
from gmjax import reduction as reduction
from gmjax import scenarios as scenarios
from gmjax import split as split
from gmjax import tune as tune
from gmjax._version import __version__ as __version__
from gmjax.fitting import fit as fit
from gmjax.mixture import GaussianMixture as GaussianMixture
from gmjax.montecarlo import monte_carlo as monte_carlo
from gmjax.params import combine as combine
from gmjax.params import grad as grad
from gmjax.params import partition as partition
from gmjax.params import value_and_grad as value_and_grad

__all__ = [
    "GaussianMixture",
    "monte_carlo",
    "fit",
    "grad",
    "value_and_grad",
    "partition",
    "combine",
    "gaussian",
    "metrics",
    "mixture",
    "quadrature",
    "split",
    "reduction",
    "filters",
    "models",
    "montecarlo",
    "pcrb",
    "scenarios",
    "tune",
    "fitting",
    "multitarget",
    "params",
    "__version__",
]
