"""The per-step inputs every model function and every filter step reads (below models and filters).

:class:`StepInputs` carries the time ``t``, the step length ``dt``, a control input and filter-specific
``aux`` data; :func:`step_inputs` normalises what :func:`gmjax.filters.run` and
:func:`gmjax.models.simulate` accept into one with a leading ``T`` axis. Both are re-exported by
:mod:`gmjax.filters` (``gmjax.filters.StepInputs``), where they were defined before version 0.2.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmjax._types import Array

__all__ = ["StepInputs", "step_inputs"]


class StepInputs(NamedTuple):
    """Per-step inputs of a filter (a pytree; :func:`gmjax.filters.run` scans over a leading ``T`` axis).

    Attributes:
        t: ``()`` the time passed to the model's ``f(x, t)`` and ``h(x, t)`` (an int step index by
            default).
        dt: ``()`` the step length, or ``None``.
        control: a control input ``u_k``, or ``None``.
        aux: filter-specific per-step data, or ``None`` (the ``matched`` bank filter reads the true
            active cluster pair ``(2,)`` int here).
    """

    t: Array
    dt: Array | None = None
    control: Any = None
    aux: Any = None


def step_inputs(n_steps: int, inputs: Any = None) -> StepInputs:
    """Normalise what :func:`gmjax.filters.run` accepts as inputs into a :class:`StepInputs` with a ``T`` axis.

    Args:
        n_steps: ``T``.
        inputs: ``None`` (times ``1..T``), an array ``(T,)`` of times, or a :class:`StepInputs`
            whose leaves have a leading ``T`` axis.

    Raises:
        ValueError: a leaf without the leading ``T`` axis, naming the field.
    """
    if inputs is None:
        return StepInputs(t=jnp.arange(1, n_steps + 1, dtype=jnp.int32))
    if not isinstance(inputs, StepInputs):
        inputs = StepInputs(t=jnp.asarray(inputs))
    for name, value in zip(StepInputs._fields, inputs):
        for leaf in jax.tree_util.tree_leaves(value):
            shape = jnp.shape(leaf)
            if not shape or shape[0] != n_steps:
                raise ValueError(
                    f"inputs.{name}: expected a leading axis of length T={n_steps} (one entry per "
                    f"measurement), got shape {shape}"
                )
    return inputs
