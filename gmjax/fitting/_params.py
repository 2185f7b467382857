"""The fitted leaves of a params pytree: names, constraints and the unconstrained parametrisation.

:func:`gmjax.fitting.fit` optimises unconstrained values ``u``; this module names the floating leaves of a
filter's params by their dotted paths (:func:`~gmjax.fitting.leaf_names`), chooses each fitted leaf's
constraint (:data:`~gmjax.fitting.CONSTRAINTS`: simplex, SPD by log-Cholesky, positive by softplus, ...),
maps between natural and unconstrained values, and refuses a starting value outside its constraint
(:class:`~gmjax.fitting.ParamView`, :func:`~gmjax.fitting.param_view`).
"""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array

CONSTRAINTS = ("real", "positive", "unit", "simplex", "stochastic", "spd")


# ----------------------------------------------------------------------------- leaves by name


def _name(path: tuple) -> str:
    parts = []
    for k in path:
        for attr in ("name", "key", "idx"):
            if hasattr(k, attr):
                parts.append(str(getattr(k, attr)))
                break
        else:  # pragma: no cover - other key types
            parts.append(str(k))
    return ".".join(parts)


def _is_float_leaf(leaf: Any) -> bool:
    if isinstance(leaf, (jax.Array, np.ndarray, np.generic)):
        return bool(jnp.issubdtype(leaf.dtype, jnp.floating))
    return isinstance(leaf, float)


def leaf_names(params: Any) -> list[str]:
    """The names :func:`fit` accepts for ``params``: every floating leaf's dotted path, in tree order."""
    return [_name(p) for p, leaf in jax.tree_util.tree_flatten_with_path(params)[0] if _is_float_leaf(leaf)]


def with_leaves(params: Any, values: Mapping[str, Any]) -> Any:
    """``params`` with the floating leaves named in ``values`` (dotted paths, :func:`leaf_names`)
    replaced, each in the leaf's dtype (a Python float leaf takes the value as given); traceable.

    Raises:
        ValueError: a name that is not a floating leaf of ``params`` (the message lists the names),
            or a value whose shape differs from the leaf's.
    """
    flat, treedef = jax.tree_util.tree_flatten_with_path(params)
    index = {_name(p): i for i, (p, leaf) in enumerate(flat) if _is_float_leaf(leaf)}
    leaves = [leaf for _, leaf in flat]
    for name, value in values.items():
        if name not in index:
            raise ValueError(f"{name!r} names no floating leaf of the params; the leaves are {list(index)}")
        old = leaves[index[name]]
        if jnp.shape(value) != jnp.shape(old):
            raise ValueError(
                f"{name!r}: a value of shape {jnp.shape(value)} for a leaf of shape {jnp.shape(old)}"
            )
        leaves[index[name]] = value if isinstance(old, float) else jnp.asarray(value, jnp.result_type(old))
    return jax.tree_util.tree_unflatten(treedef, leaves)


# ----------------------------------------------------------------------------- constraints


def _softplus_inv(x: Array) -> Array:
    return x + jnp.log(-jnp.expm1(-x))


def _to_natural(kind: Any, u: Array, mask: Array | None) -> Array:
    if kind == "real":
        return u
    if kind == "positive":
        return jax.nn.softplus(u)
    if kind == "unit":
        return jax.nn.sigmoid(u)
    if isinstance(kind, tuple):
        lo, hi = kind
        return lo + (hi - lo) * jax.nn.sigmoid(u)
    if kind == "simplex":
        live = jnp.ones(u.shape, bool) if mask is None else mask
        logits = jnp.where(live, u, -jnp.inf)
        return jnp.where(live, jax.nn.softmax(logits), 0.0)
    if kind == "stochastic":  # each row on the simplex (a Markov matrix)
        return jax.nn.softmax(u, axis=-1)
    # spd: u is the log-Cholesky factor (..., d, d): strict lower triangle, log of the diagonal
    d = u.shape[-1]
    eye = jnp.eye(d, dtype=u.dtype)
    L = jnp.tril(u, -1) + eye * jnp.exp(jnp.diagonal(u, axis1=-2, axis2=-1))[..., None, :]
    return L @ jnp.swapaxes(L, -1, -2)


def _to_unconstrained(kind: Any, x: Array, mask: Array | None) -> Array:
    if kind == "real":
        return x
    if kind == "positive":
        return _softplus_inv(x)
    if kind == "unit":
        return jnp.log(x) - jnp.log1p(-x)
    if isinstance(kind, tuple):
        lo, hi = kind
        p = (x - lo) / (hi - lo)
        return jnp.log(p) - jnp.log1p(-p)
    if kind == "simplex":
        live = jnp.ones(x.shape, bool) if mask is None else mask
        return jnp.where(live, jnp.log(jnp.where(live, x, 1.0)), 0.0)
    if kind == "stochastic":
        return jnp.log(x)
    L = jnp.linalg.cholesky(x)
    d = x.shape[-1]
    eye = jnp.eye(d, dtype=x.dtype)
    return jnp.tril(L, -1) + eye * jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1))[..., None, :]


def _check_natural(kind: Any, name: str, x: np.ndarray, mask: np.ndarray | None) -> None:
    """Refuse a starting value outside the leaf's constraint (its unconstrained value would be NaN)."""
    live = np.ones(x.shape[:1], bool) if mask is None else np.asarray(mask)
    bad = None
    if kind == "positive" and not np.all(x > 0):
        bad = "must be > 0"
    elif kind == "unit" and not np.all((x > 0) & (x < 1)):
        bad = "must lie in (0, 1)"
    elif isinstance(kind, tuple) and not np.all((x > kind[0]) & (x < kind[1])):
        bad = f"must lie in ({kind[0]}, {kind[1]})"
    elif kind == "simplex" and not (np.all(x[live] > 0) and abs(x[live].sum() - 1) < 1e-6):
        bad = "must be > 0 on the live components and sum to 1"
    elif kind == "stochastic" and not (
        x.ndim >= 1 and np.all(x > 0) and np.allclose(x.sum(-1), 1.0, rtol=0.0, atol=1e-6)
    ):
        bad = "must be > 0 with every row summing to 1"
    elif kind == "spd" and not (
        x.ndim >= 2
        and x.shape[-1] == x.shape[-2]
        and np.allclose(x, np.swapaxes(x, -1, -2))
        and np.all(np.linalg.eigvalsh(x[live] if x.ndim == 3 else x) > 0)
    ):
        bad = "must be symmetric positive definite"
    if bad is not None:
        raise ValueError(f"fit: {name!r} starts at {x.tolist()!r:.120}, which {bad} (constraint {kind!r})")


_COVARIANCE_NAMES = ("covs", "cov", "Q", "R", "P0", "prior_cov")


def _default_constraint(name: str, value: np.ndarray, mask: np.ndarray | None) -> str:
    """``weights`` (and ``*probs``) that sum to 1: simplex; a mixture's weights that do not (an intensity,
    such as a PHD's birth: expected numbers): positive; a ``transition`` matrix whose rows sum to 1:
    stochastic; covariances (``covs``, ``cov``, ``Q``, ``R``, ``P0``, ``prior_cov``): SPD; ``means``:
    real; anything else: positive."""
    last = name.rsplit(".", 1)[-1]
    if last == "weights" or last.endswith("probs"):
        live = np.ones(value.shape, bool) if mask is None else np.asarray(mask, bool)
        return "simplex" if value.ndim == 1 and abs(float(np.sum(value[live])) - 1.0) < 1e-6 else "positive"
    if last == "transition" and value.ndim == 2 and np.allclose(value.sum(-1), 1.0, rtol=0.0, atol=1e-6):
        return "stochastic"
    if last in _COVARIANCE_NAMES and value.ndim >= 2:
        return "spd"
    return "real" if last == "means" else "positive"


def _as_constraint(c: Any, name: str) -> Any:
    if isinstance(c, str) and c in CONSTRAINTS:
        return c
    if isinstance(c, (tuple, list)) and len(c) == 2 and all(isinstance(v, (int, float)) for v in c):
        lo, hi = float(c[0]), float(c[1])
        if not lo < hi:
            raise ValueError(f"constraints[{name!r}]: need low < high, got {c!r}")
        return (lo, hi)
    raise ValueError(f"constraints[{name!r}]: expected one of {CONSTRAINTS} or (low, high), got {c!r}")


class ParamView(NamedTuple):
    """The fitted leaves of a params pytree and their constraints (see :func:`param_view`).

    Attributes:
        names: the fitted leaves' names, in tree order.
        constraints: name -> constraint (one of :data:`CONSTRAINTS` or ``(low, high)``).
        params: the params pytree the view was made from (everything not fitted is taken from it).
    """

    names: tuple[str, ...]
    constraints: dict[str, Any]
    params: Any

    def _leaves(self) -> tuple[list, Any, dict[str, int], dict[str, Any]]:
        flat, treedef = jax.tree_util.tree_flatten_with_path(self.params)
        index = {_name(p): i for i, (p, _) in enumerate(flat)}
        leaves = [leaf for _, leaf in flat]
        masks = {}
        for n in self.names:  # a mixture's weights are constrained on its live components
            parent = n.rsplit(".", 1)[0] + ".mask" if "." in n else "mask"
            masks[n] = leaves[index[parent]] if parent in index and n.endswith("weights") else None
        return leaves, treedef, index, masks

    def unconstrained(self, params: Any = None) -> dict[str, Array]:
        """``{name: u}``: the unconstrained values of the fitted leaves of ``params`` (default: the view's)."""
        view = self if params is None else self._replace(params=params)
        leaves, _, index, masks = view._leaves()
        return {
            n: _to_unconstrained(self.constraints[n], jnp.asarray(leaves[index[n]]), masks[n])
            for n in self.names
        }

    def natural(self, u: Mapping[str, Array]) -> dict[str, Array]:
        """``{name: value}`` in natural units for unconstrained ``u``."""
        _, _, _, masks = self._leaves()
        return {n: _to_natural(self.constraints[n], u[n], masks[n]) for n in self.names}

    def params_at(self, u: Mapping[str, Array]) -> Any:
        """The full params pytree with the fitted leaves at ``u`` (traceable)."""
        leaves, treedef, index, _ = self._leaves()
        leaves = list(leaves)
        for n, v in self.natural(u).items():  # in the leaf's dtype (an optimiser may promote u)
            leaves[index[n]] = v.astype(jnp.result_type(leaves[index[n]]))
        return jax.tree_util.tree_unflatten(treedef, leaves)


def param_view(
    params: Any, fit: Sequence[str] | str, constraints: Mapping[str, Any] | None = None
) -> ParamView:
    """Select the leaves of ``params`` named by ``fit`` (each a leaf's dotted path or a prefix of it).

    Raises:
        ValueError: a name that selects no floating leaf (the message lists the names there are), a bad
            constraint, or a starting value outside its constraint.
    """
    if isinstance(fit, str):
        fit = [fit]
    fit = list(fit)
    if not fit:
        raise ValueError("fit: name at least one leaf of filter.params to fit")
    available = leaf_names(params)
    names: list[str] = []
    for sel in fit:
        if not isinstance(sel, str):
            raise ValueError(f"fit: expected leaf names (str), got {sel!r}")
        hit = [n for n in available if n == sel or n.startswith(sel + ".")]
        if not hit:
            raise ValueError(
                f"fit: {sel!r} names no floating leaf of filter.params; the leaves are {available}"
            )
        names += [n for n in hit if n not in names]
    names = [n for n in available if n in names]  # tree order
    constraints = dict(constraints or {})
    unknown = [sel for sel in constraints if not any(n == sel or n.startswith(sel + ".") for n in names)]
    if unknown:
        raise ValueError(f"constraints: {unknown} name no fitted leaf (fitted: {names})")
    leaves, _, index, masks = ParamView(tuple(names), {}, params)._leaves()
    start = {n: np.asarray(leaves[index[n]], np.float64) for n in names}
    mask = {n: None if masks[n] is None else np.asarray(masks[n]) for n in names}
    chosen: dict[str, Any] = {}
    for n in names:
        rule = next((c for sel, c in constraints.items() if n == sel or n.startswith(sel + ".")), None)
        chosen[n] = _default_constraint(n, start[n], mask[n]) if rule is None else _as_constraint(rule, n)
        _check_natural(chosen[n], n, start[n], mask[n])
    return ParamView(tuple(names), chosen, params)
