"""Array aliases whose names document the dimensions used throughout gmjax.

K: mixture components (capacity), d: state dimension, m: measurement dimension,
T: time steps, N: Monte Carlo runs, n: samples / sigma points.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.typing

Array = jax.Array
ArrayLike = Any  # anything jnp.asarray accepts
PRNGKey = jax.Array

Scalar = Array  # ()
Weights = Array  # (K,)
Means = Array  # (K, d)
Covs = Array  # (K, d, d)
Mask = Array  # (K,) bool
Vector = Array  # (d,)
Matrix = Array  # (d, d)

DTypeLike = jax.typing.DTypeLike  # a dtype or anything jnp.dtype accepts
StepFn = Callable[[Array, Array], Array]  # (x (d,), t) -> (d,) or (m,): a model's f or h
