"""Polish a reduced mixture by minimising its ISE to the original over weights, means and
Cholesky factors with optax (a ``lax.scan`` of optimiser steps)."""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from gmjax import _validate
from gmjax._pytree import pytree_dataclass, static_field
from gmjax._types import Array
from gmjax.metrics import ise
from gmjax.mixture import GaussianMixture, sanitize
from gmjax.reduction import _util
from gmjax.reduction.base import ReductionInfo, Stateless, make_info

__all__ = ["ise_refine", "Refined"]


class _Params(NamedTuple):
    logits: jax.Array  # (K,) log weights of live slots
    means: jax.Array  # (K, d)
    chol: jax.Array  # (K, d, d) lower factors with log-diagonal


def _to_params(gm: GaussianMixture) -> _Params:
    d = gm.dim
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    covs = jnp.where(gm.mask[:, None, None], gm.covs, eye)
    L = jnp.linalg.cholesky(covs)
    diag = jnp.diagonal(L, axis1=-2, axis2=-1)
    Lp = L - jax.vmap(jnp.diag)(diag) + jax.vmap(jnp.diag)(jnp.log(diag))
    live = gm.mask & (gm.weights > 0)
    logits = jnp.where(live, jnp.log(jnp.where(live, gm.weights, 1.0)), 0.0)
    return _Params(logits, gm.means, Lp)


def _from_params(p: _Params, mask: jax.Array, total: jax.Array) -> GaussianMixture:
    tril = jnp.tril(p.chol, -1)
    L = tril + jax.vmap(jnp.diag)(jnp.exp(jnp.diagonal(p.chol, axis1=-2, axis2=-1)))
    covs = L @ jnp.swapaxes(L, -1, -2)
    logits = jnp.where(mask, p.logits, -jnp.inf)
    w = total * jax.nn.softmax(logits)
    w = jnp.where(mask, w, 0.0)
    return sanitize(GaussianMixture(w, p.means, covs, mask))


_EPS_ROOT = 1e-16


@partial(jax.jit, static_argnames=("n_steps", "optimize_weights"))
def _refine(gm, target, n_steps, learning_rate, optimize_weights):
    mask = gm.mask & (gm.weights > 0)
    total = jnp.sum(jnp.where(gm.mask, gm.weights, 0.0))
    p0 = _to_params(gm._replace(mask=mask))
    # eps_root keeps d sqrt(nu)/d nu finite where a gradient entry is exactly 0 (padded slots, fixed
    # weights): without it the derivative w.r.t. the learning rate is 0 * inf = NaN
    opt = optax.adam(learning_rate, eps_root=_EPS_ROOT)

    def loss(p):
        return ise(target, _from_params(p, mask, total))

    def step(carry, _):
        p, state, best_p, best_v = carry
        v, g = jax.value_and_grad(loss)(p)
        g = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)
        if not optimize_weights:
            g = g._replace(logits=jnp.zeros_like(g.logits))
        better = v < best_v
        best_p = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), p, best_p)
        best_v = jnp.where(better, v, best_v)
        upd, state = opt.update(g, state, p)
        return (optax.apply_updates(p, upd), state, best_p, best_v), v

    v0 = loss(p0)
    carry = (p0, opt.init(p0), p0, v0)
    (p, _, best_p, best_v), trace = jax.lax.scan(step, carry, None, length=n_steps)
    v_last = loss(p)
    better = v_last < best_v
    best_p = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), p, best_p)
    best_v = jnp.where(better, v_last, best_v)
    out = _from_params(best_p, mask, total)
    out = out._replace(mask=gm.mask)
    out = sanitize(out)
    labels = _util.identity_labels(gm)
    return out, make_info(gm, out, labels, cost=best_v, aux={"initial_ise": v0, "trace": trace})


def ise_refine(
    gm: GaussianMixture,
    target: GaussianMixture,
    *,
    n_steps: int = 200,
    learning_rate: Any = 1e-2,
    optimize_weights: bool = True,
    key: jax.Array | None = None,
) -> tuple[GaussianMixture, ReductionInfo]:
    """Minimise ``ISE(target, gm)`` over the live weights (softmax logits, total weight fixed),
    means and Cholesky factors (log-diagonal) of ``gm`` with ``n_steps`` Adam steps (optax).

    The returned parameters are the best visited, so ``info.cost <= ISE(target, gm)`` always
    (``info.aux["initial_ise"]``). Capacity, mask and slot order of ``gm`` are kept;
    ``info.labels`` is the identity of ``gm``'s slots (not of ``target``'s).

    Args:
        gm: the reduction to polish (any reducer's output).
        target: the original mixture.
        n_steps: static number of optimiser steps.
        learning_rate: Adam step size (may be traced).
        optimize_weights: static; False keeps the weights fixed.
        key: unused.
    """
    del key
    (learning_rate,), bad = _util.replace_nans((learning_rate, 1e-2))
    _validate.validate_mixture(gm, "gm")
    _validate.validate_mixture(target, "target")
    if gm.dim != target.dim:
        raise ValueError(f"target: dimension {target.dim} differs from gm's {gm.dim}")
    n_steps = _validate.validate_count(n_steps, "n_steps", 0, 2**31 - 1)
    _validate.validate_nonneg(learning_rate, "learning_rate", allow_inf=False)
    lr = jnp.asarray(learning_rate, gm.weights.dtype)
    return _util.unchanged_if_nan(bad, gm, _refine(gm, target, n_steps, lr, bool(optimize_weights)))


@pytree_dataclass
class Refined(Stateless):
    """A reducer followed by :func:`ise_refine` against the reducer's input.

    A traced NaN ``learning_rate`` skips the refinement (the base reduction is returned unrefined)
    and sets ``info.invalid_threshold``; a NaN threshold of ``base`` is flagged by ``base``.

    Attributes:
        base: any Reducer config (a pytree; its thresholds stay dynamic).
        n_steps: static optimiser steps. learning_rate: dynamic Adam step size.
    """

    base: Any
    n_steps: int = static_field(200)
    learning_rate: Any = 1e-2

    def __call__(
        self, gm: GaussianMixture, *, key: Array | None = None
    ) -> tuple[GaussianMixture, ReductionInfo]:
        red, info = self.base(gm, key=key)
        out, rinfo = ise_refine(red, gm, n_steps=self.n_steps, learning_rate=self.learning_rate)
        return out, info._replace(
            n_out=rinfo.n_out,
            cost=rinfo.cost,
            aux={**info.aux, "initial_ise": rinfo.aux["initial_ise"]},
            invalid_threshold=info.invalid_threshold | rinfo.invalid_threshold,
        )
