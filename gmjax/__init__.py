"""gmjax: Gaussian-mixture state estimation in JAX.

Fixed-capacity padded mixtures with masks, so reduction, Gaussian sum filtering and quadrature run as
compiled kernels, ``vmap``-ed over Monte Carlo runs and ``lax.scan``-ned over time. Importing gmjax
never changes ``jax.config``; enable float64 yourself with ``jax.config.update("jax_enable_x64", True)``.
"""

from gmjax import gaussian as gaussian
from gmjax import metrics as metrics
from gmjax import mixture as mixture
from gmjax.mixture import GaussianMixture as GaussianMixture

__version__ = "0.1.0"

__all__ = [
    "GaussianMixture",
    "gaussian",
    "metrics",
    "mixture",
    "__version__",
]
