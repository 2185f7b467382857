"""Differentiate w.r.t. the differentiable leaves of a params pytree (equinox-style filtering).

A filter's ``params`` (and a model's, a reducer's) is a pytree that mixes leaves ``jax.grad`` can take
with leaves it refuses: every :class:`~gmjax.mixture.GaussianMixture` in it carries a boolean ``mask``
``(K,)``, and configs may hold integer arrays or keys. ``jax.grad(f)(gsf.params)`` therefore raises
``TypeError: grad requires real- or complex-valued inputs``. The functions here split such a tree in
two, in the style of equinox's ``partition`` / ``combine`` / ``filter_grad``:

- :func:`is_differentiable`: the leaves to differentiate: floating or complex arrays and Python
  floats; masks, integer arrays, Python ints and bools, PRNG keys and other objects are not.
- :func:`partition` ``tree -> (diff, static)``: two trees of the structure of ``tree``, each with
  ``None`` where a leaf belongs to the other; :func:`combine` ``(diff, static) -> tree`` undoes it.
- :func:`grad` / :func:`value_and_grad`: ``jax.grad`` / ``jax.value_and_grad`` of ``fun`` w.r.t. the
  differentiable leaves of its first argument; the gradient has that argument's structure with
  ``None`` at every other leaf (the masks).

Example::

    g = gmjax.grad(lambda p: montecarlo.study_loss(gsf, scenario, 16, key, params=p))(gsf.params)
    g.model.process_noise.covs      # (K, d, d) d loss / d covs;  g.model.process_noise.mask is None

    diff, static = gmjax.partition(gsf.params)            # optax sees only the differentiable half
    opt = optax.adam(1e-2); state = opt.init(diff)
    updates, state = opt.update(g, state, diff)
    params = gmjax.combine(optax.apply_updates(diff, updates), static)

A gradient step can leave a mixture invalid (a negative weight, a covariance that is not positive
definite); map constrained leaves through an unconstrained parametrisation, as :mod:`gmjax.tune` does.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["is_differentiable", "partition", "combine", "grad", "value_and_grad"]


def is_differentiable(leaf: Any) -> bool:
    """Whether ``jax.grad`` can differentiate w.r.t. ``leaf``.

    Args:
        leaf: one pytree leaf.

    Returns:
        ``True`` for a JAX or NumPy array (or NumPy scalar) of floating or complex dtype, of any shape,
        traced or not, and for a Python ``float`` or ``complex``; ``False`` for boolean arrays (the
        masks of :class:`~gmjax.mixture.GaussianMixture`), integer arrays, PRNG key arrays, Python
        ``int`` and ``bool``, and every other object.
    """
    if isinstance(leaf, (jax.Array, np.ndarray, np.generic)):
        return bool(jnp.issubdtype(leaf.dtype, jnp.inexact))
    return isinstance(leaf, (float, complex))


def partition(tree: Any, *, predicate: Callable[[Any], bool] = is_differentiable) -> tuple[Any, Any]:
    """Split ``tree`` into its differentiable leaves and the rest.

    Args:
        tree: any pytree, e.g. a filter's ``params`` (NamedTuples, pytree dataclasses, mixtures).
        predicate: ``leaf -> bool``, the leaves that go to ``diff`` (default :func:`is_differentiable`).

    Returns:
        ``(diff, static)``: two pytrees of the structure of ``tree``. ``diff`` holds the leaves for
        which ``predicate`` is true and ``None`` elsewhere, ``static`` the other leaves and ``None``
        where ``diff`` has one; e.g. a mixture ``(weights (K,), means (K, d), covs (K, d, d), mask (K,))``
        becomes ``(weights, means, covs, None)`` and ``(None, None, None, mask)``. ``diff`` is a valid
        input of ``jax.grad`` and of an optax optimiser (``None`` is an empty subtree).
    """
    flags = jax.tree_util.tree_map(predicate, tree)
    diff = jax.tree_util.tree_map(lambda keep, x: x if keep else None, flags, tree)
    static = jax.tree_util.tree_map(lambda keep, x: None if keep else x, flags, tree)
    return diff, static


def _first_not_none(*leaves: Any) -> Any:
    return next((x for x in leaves if x is not None), None)


def combine(*trees: Any) -> Any:
    """Undo :func:`partition`: merge trees of one structure, leaf by leaf.

    Args:
        *trees: pytrees of the same structure with ``None`` at the leaves they do not hold, e.g.
            ``(diff, static)`` from :func:`partition` (or a gradient-updated ``diff`` and ``static``).

    Returns:
        The tree whose every leaf is the first non-``None`` leaf of ``trees`` at that position:
        ``combine(*partition(tree))`` is ``tree``.
    """
    if not trees:
        raise TypeError("combine: need at least one pytree")
    return jax.tree_util.tree_map(_first_not_none, *trees, is_leaf=lambda x: x is None)


def _split_first(name: str, args: tuple[Any, ...]) -> tuple[Any, tuple[Any, ...]]:
    if not args:
        raise TypeError(
            f"gmjax.{name}: the function must be called with its first argument (the pytree to "
            "differentiate) by position"
        )
    return args[0], args[1:]


def value_and_grad(fun: Callable[..., Any], *, has_aux: bool = False) -> Callable[..., Any]:
    """``jax.value_and_grad`` of ``fun`` w.r.t. the differentiable leaves of its first argument.

    The first argument is split by :func:`partition`; ``fun`` is called on the recombined tree, so it
    sees the masks and other static leaves unchanged. The other arguments are not differentiated.
    Works under ``jax.jit`` and ``jax.vmap``.

    Args:
        fun: ``(tree, *args, **kwargs) -> ()`` a real scalar (or ``(scalar, aux)`` with ``has_aux``).
        has_aux: as in ``jax.value_and_grad``.

    Returns:
        A function of the same arguments returning ``(value, grads)`` (``((value, aux), grads)`` with
        ``has_aux``); ``grads`` has the structure of the first argument, the gradient at each
        differentiable leaf (same shape and dtype) and ``None`` at every other leaf, e.g. at every
        mixture's ``mask``.
    """

    @functools.wraps(fun)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        tree, rest = _split_first("value_and_grad", args)
        diff, static = partition(tree)

        def of_diff(d: Any) -> Any:
            return fun(combine(d, static), *rest, **kwargs)

        return jax.value_and_grad(of_diff, has_aux=has_aux)(diff)

    return wrapper


def grad(fun: Callable[..., Any], *, has_aux: bool = False) -> Callable[..., Any]:
    """``jax.grad`` of ``fun`` w.r.t. the differentiable leaves of its first argument.

    ``gmjax.grad(lambda p: montecarlo.study_loss(gsf, scenario, 16, key, params=p))(gsf.params)`` is
    the gradient of the study's loss w.r.t. every floating leaf of the filter's params (its noises'
    weights, means and covariances, the reducer's thresholds), where ``jax.grad`` refuses the
    boolean masks. See :func:`value_and_grad`.

    Args:
        fun: ``(tree, *args, **kwargs) -> ()`` a real scalar (or ``(scalar, aux)`` with ``has_aux``).
        has_aux: as in ``jax.grad``.

    Returns:
        A function of the same arguments returning ``grads`` (``(grads, aux)`` with ``has_aux``):
        the structure of the first argument with the gradient at each differentiable leaf and
        ``None`` at the others (the masks).
    """
    value_and_grad_fun = value_and_grad(fun, has_aux=has_aux)

    @functools.wraps(fun)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        value, grads = value_and_grad_fun(*args, **kwargs)
        return (grads, value[1]) if has_aux else grads

    return wrapper
