"""The fixed-capacity padded Gaussian mixture and its operations.

A :class:`GaussianMixture` has capacity ``K`` slots; ``mask`` says which hold a component. Padded
slots carry weight 0, mean 0 and identity covariance, so Cholesky factors, log-determinants and
gradients never see NaN. ``K`` never depends on data: a mixture can be a ``lax.scan`` carry, and
no function here recompiles when the number of live components changes.

Boundary functions (:meth:`GaussianMixture.create`, :func:`check`) validate eagerly and raise
``ValueError`` naming the bad field and index. Everything else is traceable (jit/vmap/grad).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, Covs, DTypeLike, Mask, Matrix, Means, PRNGKey, Vector, Weights

_LOG_2PI = gaussian._LOG_2PI  # log(2 pi): one definition

__all__ = [
    "GaussianMixture",
    "check",
    "check_points",
    "check_same_dim",
    "sanitize",
    "log_weights",
    "logpdf",
    "pdf",
    "component_logpdfs",
    "mean",
    "cov",
    "moments",
    "normalize",
    "total_weight",
    "n_active",
    "compact",
    "pad",
    "sample",
    "marginal",
    "affine",
    "concat",
    "top_k",
    "heaviest_slots",
    "descending_ranks",
    "from_gaussian",
]


class GaussianMixture(NamedTuple):
    """A Gaussian mixture with fixed capacity ``K`` (a pytree; no batch dims inside).

    Attributes:
        weights: ``(K,)`` non-negative; exactly 0 where ``mask`` is False.
        means: ``(K, d)``; 0 where ``mask`` is False.
        covs: ``(K, d, d)`` symmetric positive definite; identity where ``mask`` is False.
        mask: ``(K,)`` bool, which slots hold a component.
    """

    weights: Weights
    means: Means
    covs: Covs
    mask: Mask

    @property
    def capacity(self) -> int:
        """``K``, the number of slots (static)."""
        return self.weights.shape[-1]

    @property
    def dim(self) -> int:
        """``d``, the state dimension (static)."""
        return self.means.shape[-1]

    @property
    def dtype(self):
        return self.means.dtype

    @classmethod
    def create(
        cls,
        weights: ArrayLike,
        means: ArrayLike,
        covs: ArrayLike,
        capacity: int | None = None,
        *,
        normalize: bool = True,
        dtype: DTypeLike | None = None,
    ) -> GaussianMixture:
        """Validate concrete arrays and build a padded mixture (the API boundary).

        Args:
            weights: ``(n,)`` non-negative, not all zero.
            means: ``(n, d)`` (or ``(n,)`` for ``d = 1``).
            covs: ``(n, d, d)`` symmetric positive definite; ``(n,)`` variances for ``d = 1``
                and ``(n, d)`` diagonals are accepted.
            capacity: number of slots ``K >= n`` (default ``n``).
            normalize: divide the weights by their sum.
            dtype: floating dtype (default: the JAX default float).

        The values are validated twice: as given (in float64), and after the cast to ``dtype``,
        so a dtype that cannot hold them is refused instead of silently producing inf, 0 or a
        singular covariance.

        Raises:
            ValueError: naming the field and offending index on NaN/inf, negative or all-zero
                weights, non-symmetric or non-PD covariances, mismatched shapes, complex or
                non-numeric arrays, a state dimension ``d = 0``, a ``capacity`` that is not an int
                (e.g. 2.5) or is ``< n``, a non-floating ``dtype``, or values that ``dtype`` cannot hold
                (a mean or weight that overflows, a positive weight that underflows to 0, a
                covariance that is no longer positive definite after the cast), e.g.
                ``"covs: component 0 is not positive definite in float32"``.
        """
        dtype = _float_dtype(dtype)
        w, m, P = (
            _real_array(name, x) for name, x in (("weights", weights), ("means", means), ("covs", covs))
        )
        if w.ndim != 1:
            raise ValueError(f"weights: expected shape (n,), got {w.shape}")
        n = w.shape[0]
        if n == 0:
            raise ValueError("weights: a mixture needs at least one component")
        if m.ndim == 1 and m.shape[0] == n:
            m = m[:, None]
        if m.ndim != 2 or m.shape[0] != n:
            raise ValueError(f"means: expected shape ({n}, d) to match weights ({n},), got {m.shape}")
        d = m.shape[1]
        if d == 0:
            raise ValueError(f"means: the state dimension d is 0 (shape {m.shape}); a mixture needs d >= 1")
        if P.ndim == 1 and d == 1 and P.shape[0] == n:
            P = P[:, None, None]
        elif P.ndim == 2 and P.shape == (n, d):
            P = np.einsum("ki,ij->kij", P, np.eye(d))
        if P.shape != (n, d, d):
            raise ValueError(f"covs: expected shape ({n}, {d}, {d}), got {P.shape}")
        K = n if capacity is None else _capacity(capacity)
        if K < n:
            raise ValueError(f"capacity: {K} is smaller than the number of components {n}")
        _validate_components(w, m, P, np.ones(n, bool))
        if normalize:  # scaled first, so huge weights ([1e308, 1e308]) do not overflow the sum
            w = w / w.max()
            w = w / w.sum()
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        w, m, P = _cast_checked(w, m, P, dtype)
        mask = np.zeros(K, bool)
        mask[:n] = True
        W = np.zeros(K, dtype)
        W[:n] = w
        M = np.zeros((K, d), dtype)
        M[:n] = m
        C = np.broadcast_to(np.eye(d, dtype=dtype), (K, d, d)).copy()
        C[:n] = P
        return cls(jnp.asarray(W, dtype), jnp.asarray(M, dtype), jnp.asarray(C, dtype), jnp.asarray(mask))

    @classmethod
    def from_arrays(
        cls,
        weights: ArrayLike,
        means: ArrayLike,
        covs: ArrayLike,
        mask: ArrayLike | None = None,
    ) -> GaussianMixture:
        """Build a mixture inside traced code (no validation); padded slots are sanitised."""
        weights = jnp.asarray(weights)
        mask = jnp.ones(weights.shape, bool) if mask is None else jnp.asarray(mask, bool)
        return sanitize(cls(weights, jnp.asarray(means), jnp.asarray(covs), mask))


def from_gaussian(mean: ArrayLike, cov: ArrayLike, capacity: int = 1) -> GaussianMixture:
    """A one-component mixture ``N(mean, cov)`` padded to ``capacity`` slots (traceable)."""
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov)
    d = mean.shape[-1]
    mask = jnp.arange(capacity) == 0
    means = jnp.zeros((capacity, d), mean.dtype).at[0].set(mean)
    covs = jnp.broadcast_to(jnp.eye(d, dtype=cov.dtype), (capacity, d, d)).at[0].set(cov)
    weights = mask.astype(mean.dtype)
    return GaussianMixture(weights, means, covs, mask)


def _real_array(name: str, x: ArrayLike) -> np.ndarray:
    """``x`` as a float64 NumPy array; complex, boolean, string or object input is refused by name."""
    a = np.asarray(x)
    if a.dtype.kind not in "fiu":
        kind = {"c": "complex", "b": "boolean"}.get(a.dtype.kind, "non-numeric")
        raise ValueError(f"{name}: expected real numbers, got a {kind} array (dtype {a.dtype})")
    return a.astype(np.float64)


def _capacity(capacity: Any) -> int:
    """``capacity`` as a Python int; a float such as 2.5, a bool or a non-scalar is refused."""
    if isinstance(capacity, (bool, np.bool_)) or not isinstance(capacity, (int, np.integer)):
        raise ValueError(f"capacity: expected a whole number of slots (an int), got {capacity!r}")
    return int(capacity)


def _float_dtype(dtype) -> np.dtype:
    """The floating dtype a mixture will hold (``None``: JAX's default float), as JAX stores it."""
    if dtype is None:
        return np.dtype(jnp.zeros(()).dtype)
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"dtype: {dtype!r} is not a dtype") from None
    if not jnp.issubdtype(dt, jnp.floating):
        raise ValueError(f"dtype: a mixture needs a floating dtype (float32 or float64), got {dt}")
    return np.dtype(jax.dtypes.canonicalize_dtype(dt))  # float64 is float32 unless x64 is enabled


def _cast_checked(w: np.ndarray, m: np.ndarray, P: np.ndarray, dtype: np.dtype):
    """Cast the validated float64 arrays to ``dtype`` and validate what ``dtype`` holds.

    Raises:
        ValueError: naming the field, index and dtype when a value overflows, a positive weight
            underflows to 0, the weights' sum overflows, or a covariance stops being PD.
    """
    name = np.dtype(dtype).name
    with np.errstate(over="ignore", under="ignore"):
        wc, mc, Pc = (np.asarray(a, dtype) for a in (w, m, P))
    held = [np.asarray(a, np.float64) for a in (wc, mc, Pc)]  # exactly the values dtype holds
    for field, arr in zip(("weights", "means", "covs"), held):
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = int(np.argwhere(bad.reshape(arr.shape[0], -1).any(axis=1))[0, 0])
            raise ValueError(f"{field}: component {idx} overflows {name} (its values do not fit)")
    lost = np.flatnonzero((w > 0) & (held[0] == 0))
    if lost.size:
        raise ValueError(f"weights: weight {w[lost[0]]:g} at index {int(lost[0])} underflows to 0 in {name}")
    with np.errstate(over="ignore"):
        total = np.sum(wc)
    if not np.isfinite(total):
        raise ValueError(f"weights: their sum overflows {name} (normalize them or use a wider dtype)")
    _validate_components(held[0], held[1], held[2], np.ones(w.shape[0], bool), where=f" in {name}")
    return wc, mc, Pc


def _validate_components(
    w: np.ndarray, m: np.ndarray, P: np.ndarray, mask: np.ndarray, where: str = ""
) -> None:
    for name, arr in (("weights", w), ("means", m), ("covs", P)):
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = int(np.argwhere(bad.reshape(arr.shape[0], -1).any(axis=1))[0, 0])
            raise ValueError(f"{name}: non-finite value (NaN or inf) in component {idx}{where}")
    neg = np.flatnonzero(w < 0)
    if neg.size:
        raise ValueError(f"weights: negative weight {w[neg[0]]:g} at index {int(neg[0])}")
    if not mask.any():
        raise ValueError("mask: no live component (all-False mask)")
    if not (w[mask] > 0).any():
        raise ValueError(f"weights: all live weights are zero{where}")
    d = m.shape[-1]
    for k in np.flatnonzero(mask):
        Pk = P[k]
        scale = max(np.abs(Pk).max(), 1e-300)
        if not np.allclose(Pk, Pk.T, rtol=1e-8, atol=1e-10 * scale):
            raise ValueError(f"covs: component {int(k)} is not symmetric{where}")
        try:
            np.linalg.cholesky(Pk)
        except np.linalg.LinAlgError:
            raise ValueError(f"covs: component {int(k)} is not positive definite{where}") from None
        if d and np.linalg.eigvalsh(Pk)[0] <= 0:
            raise ValueError(f"covs: component {int(k)} is not positive definite{where}")


def check(gm: GaussianMixture) -> GaussianMixture:
    """Validate a concrete mixture eagerly; return it unchanged.

    Raises:
        ValueError: naming the field and index: a non-floating dtype, shapes that disagree, a
            non-boolean or all-False mask, NaN/inf, negative or all-zero live weights, non-symmetric or non-PD live
            covariances, or padded slots that are not (0, 0, I).
    """
    if not isinstance(gm, GaussianMixture):
        raise ValueError(f"gm: expected a GaussianMixture, got {type(gm).__name__}")
    w, m, P, mask = (np.asarray(a) for a in gm)
    for name, arr in (("weights", w), ("means", m), ("covs", P)):
        if not jnp.issubdtype(arr.dtype, jnp.floating):
            raise ValueError(
                f"{name}: a mixture needs a floating dtype (float32 or float64), got {arr.dtype}"
            )
    if w.ndim != 1:
        raise ValueError(f"weights: expected shape (K,), got {w.shape} (batch with vmap, not inside)")
    K = w.shape[0]
    if m.ndim != 2 or m.shape[0] != K:
        raise ValueError(f"means: expected shape ({K}, d), got {m.shape}")
    d = m.shape[1]
    if P.shape != (K, d, d):
        raise ValueError(f"covs: expected shape ({K}, {d}, {d}), got {P.shape}")
    if mask.shape != (K,) or mask.dtype != np.bool_:
        raise ValueError(f"mask: expected a bool array of shape ({K},), got {mask.dtype} {mask.shape}")
    _validate_components(w, m, P, mask)
    pad_idx = np.flatnonzero(~mask)
    for k in pad_idx:
        if w[k] != 0 or np.any(m[k] != 0) or np.any(P[k] != np.eye(d)):
            raise ValueError(f"mask: padded slot {int(k)} must hold weight 0, mean 0 and identity covariance")
    return gm


def sanitize(gm: GaussianMixture) -> GaussianMixture:
    """Reset padded slots to (0, 0, I) (traceable). Call after any operation that may dirty them."""
    w, m, P, mask = gm
    d = m.shape[-1]
    eye = jnp.eye(d, dtype=P.dtype)
    return GaussianMixture(
        jnp.where(mask, w, 0.0),
        jnp.where(mask[:, None], m, 0.0),
        jnp.where(mask[:, None, None], P, eye),
        mask,
    )


def total_weight(gm: GaussianMixture) -> Array:
    """Sum of the live weights ``()``."""
    return jnp.sum(jnp.where(gm.mask, gm.weights, 0.0))


def log_weights(gm: GaussianMixture) -> Weights:
    """``log w`` for live slots, ``-inf`` for padded or zero-weight ones (gradient-safe)."""
    live = gm.mask & (gm.weights > 0)
    return jnp.where(live, jnp.log(jnp.where(live, gm.weights, 1.0)), -jnp.inf)


def check_points(gm: GaussianMixture, x: ArrayLike, name: str = "x") -> Array:
    """``x`` as one point ``(d,)`` or ``n`` points ``(n, d)`` of ``gm``'s dimension (static check).

    For a 1-D mixture a vector ``(n,)`` with ``n > 1`` is refused as ambiguous (``n`` points or
    one point of the wrong dimension?): pass ``x[:, None]`` for ``n`` points.

    Raises:
        ValueError: naming ``name``, when the shape is neither ``(d,)`` nor ``(n, d)``.
    """
    x = jnp.asarray(x)
    d = gm.dim
    if x.ndim not in (1, 2) or x.shape[-1] != d:
        hint = (
            f"; for {x.shape[0]} points of a 1-D mixture pass shape ({x.shape[0]}, 1)"
            if (d == 1 and x.ndim == 1)
            else ""
        )
        raise ValueError(
            f"{name}: expected one point ({d},) or points (n, {d}) of the {d}-D mixture, got shape "
            f"{x.shape}{hint}"
        )
    return x


def check_same_dim(a: GaussianMixture, b: GaussianMixture, names: tuple[str, str] = ("a", "b")) -> None:
    """Raise ``ValueError`` naming both arguments when two mixtures live in different dimensions."""
    if a.dim != b.dim:
        raise ValueError(
            f"{names[0]}, {names[1]}: mixtures of different dimensions ({names[0]} is {a.dim}-D, "
            f"{names[1]} is {b.dim}-D)"
        )


def component_logpdfs(gm: GaussianMixture, x: ArrayLike) -> Array:
    """``log N(x; m_k, P_k)`` for every slot: ``(K,)`` for ``x`` of shape ``(d,)``, ``(n, K)`` for ``(n, d)``.

    Raises:
        ValueError: ``x`` of another shape (see :func:`check_points`).
    """
    x = check_points(gm, x)
    factors = jax.vmap(lambda P: gaussian.safe_cholesky(P).factor)(gm.covs)  # once per component
    half_logdet = jnp.sum(jnp.log(jnp.diagonal(factors, axis1=-2, axis2=-1)), axis=-1)
    d = gm.dim

    def one(xi):
        r = jax.vmap(gaussian.solve_lower)(factors, xi - gm.means)  # (K, d)
        return -0.5 * (d * _LOG_2PI + jnp.sum(r * r, axis=-1)) - half_logdet

    return one(x) if x.ndim == 1 else jax.vmap(one)(x)


def logpdf(gm: GaussianMixture, x: ArrayLike) -> Array:
    """Mixture log-density (weights used as stored): ``()`` for ``x`` ``(d,)``, ``(n,)`` for ``(n, d)``.

    For a 1-D mixture ``x`` of shape ``(n,)``, ``n > 1``, is refused (pass ``(n, 1)``); any other
    shape raises ``ValueError`` naming ``x``.
    """
    return logsumexp(component_logpdfs(gm, x) + log_weights(gm), axis=-1)


def pdf(gm: GaussianMixture, x: ArrayLike) -> Array:
    """Mixture density: ``()`` for ``x`` ``(d,)``, ``(n,)`` for ``(n, d)`` (shapes as :func:`logpdf`)."""
    return jnp.exp(logpdf(gm, x))


def _safe_normalized_weights(gm: GaussianMixture) -> Weights:
    w = jnp.where(gm.mask, gm.weights, 0.0)
    total = jnp.sum(w)
    ok = total > 0
    return jnp.where(ok, w / jnp.where(ok, total, 1.0), 0.0)


def moments(gm: GaussianMixture) -> tuple[Vector, Matrix]:
    """Mean ``(d,)`` and covariance ``(d, d)`` of the (normalised) mixture."""
    w = _safe_normalized_weights(gm)
    mu = w @ gm.means
    dev = gm.means - mu
    spread = jnp.einsum("k,ki,kj->ij", w, dev, dev)
    within = jnp.einsum("k,kij->ij", w, gm.covs)
    return mu, gaussian.symmetrize(within + spread)


def mean(gm: GaussianMixture) -> Vector:
    """Mixture mean ``sum_k w_k m_k / sum_k w_k`` ``(d,)``."""
    return moments(gm)[0]


def cov(gm: GaussianMixture) -> Matrix:
    """Mixture covariance ``sum_k w_k (P_k + (m_k - m)(m_k - m)^T)`` (normalised weights) ``(d, d)``."""
    return moments(gm)[1]


def normalize(gm: GaussianMixture) -> GaussianMixture:
    """Scale the live weights to sum to 1 (a mixture with zero total weight is left at 0)."""
    return gm._replace(weights=_safe_normalized_weights(gm))


def n_active(gm: GaussianMixture) -> Array:
    """Number of live slots ``()`` int32."""
    return jnp.sum(gm.mask, dtype=jnp.int32)


def compact(gm: GaussianMixture) -> GaussianMixture:
    """Move live slots to the front, keeping their relative order (a stable partition)."""
    order = jnp.argsort(~gm.mask, stable=True)
    return jax.tree_util.tree_map(lambda a: a[order], gm)


def pad(gm: GaussianMixture, capacity: int) -> GaussianMixture:
    """Append padded slots up to ``capacity`` (static, ``>= gm.capacity``)."""
    K = gm.capacity
    if capacity < K:
        raise ValueError(f"capacity: {capacity} is smaller than the current capacity {K}; use top_k")
    extra = capacity - K
    d = gm.dim
    return GaussianMixture(
        jnp.concatenate([gm.weights, jnp.zeros(extra, gm.weights.dtype)]),
        jnp.concatenate([gm.means, jnp.zeros((extra, d), gm.means.dtype)]),
        jnp.concatenate([gm.covs, jnp.broadcast_to(jnp.eye(d, dtype=gm.covs.dtype), (extra, d, d))]),
        jnp.concatenate([gm.mask, jnp.zeros(extra, bool)]),
    )


def sample(gm: GaussianMixture, key: PRNGKey, n: int) -> Array:
    """Draw ``n`` samples ``(n, d)`` from the (normalised) mixture."""
    k_comp, k_norm = jax.random.split(key)
    idx = jax.random.categorical(k_comp, log_weights(gm), shape=(n,))
    factors = jax.vmap(lambda P: gaussian.safe_cholesky(P).factor)(gm.covs)
    z = jax.random.normal(k_norm, (n, gm.dim), gm.means.dtype)
    return gm.means[idx] + jnp.einsum("nij,nj->ni", factors[idx], z)


def marginal(gm: GaussianMixture, dims: Sequence[int]) -> GaussianMixture:
    """Marginal mixture over the state dimensions ``dims`` (static, distinct, in ``[-d, d)``).

    Raises:
        ValueError: naming ``dims``: empty, out of range, repeated or not integers.
    """
    d = gm.dim
    try:
        idx = np.asarray(dims)
    except Exception:  # a traced array: dims must be static
        raise ValueError("dims: must be static integers (a list or tuple), not a traced array") from None
    idx = idx.reshape(-1) if idx.ndim == 0 else idx
    if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"dims: expected a non-empty sequence of integers, got {dims!r}")
    if np.any((idx < -d) | (idx >= d)):
        raise ValueError(f"dims: {list(idx.tolist())} out of range for a {d}-D mixture (valid: 0..{d - 1})")
    if np.unique(idx % d).size != idx.size:
        raise ValueError(
            f"dims: repeated dimension in {list(idx.tolist())} (the covariance would be singular)"
        )
    sel = jnp.asarray(idx % d)
    return GaussianMixture(gm.weights, gm.means[:, sel], gm.covs[:, sel][:, :, sel], gm.mask)


def affine(gm: GaussianMixture, A: ArrayLike, b: ArrayLike | None = None) -> GaussianMixture:
    """Distribution of ``A x + b`` for ``x ~ gm``: means ``A m_k + b``, covariances ``A P_k A^T``.

    ``A`` is ``(e, d)``, ``b`` is ``(e,)``; ``A`` must have full row rank for the result to be a proper
    mixture.

    Raises:
        ValueError: ``A`` not ``(e, d)`` or ``b`` not ``(e,)``, naming the argument.
    """
    A = jnp.asarray(A)
    if A.ndim != 2 or A.shape[1] != gm.dim:
        raise ValueError(f"A: expected shape (e, {gm.dim}) for a {gm.dim}-D mixture, got {A.shape}")
    means = gm.means @ A.T
    if b is not None:
        b = jnp.asarray(b)
        if b.shape != (A.shape[0],):
            raise ValueError(f"b: expected shape ({A.shape[0]},) to match A {A.shape}, got {b.shape}")
        means = means + b
    covs = gaussian.symmetrize(jnp.einsum("ij,kjl,ml->kim", A, gm.covs, A))
    return sanitize(GaussianMixture(gm.weights, means, covs, gm.mask))


def concat(a: GaussianMixture, b: GaussianMixture) -> GaussianMixture:
    """Slots of ``a`` then slots of ``b`` (capacity ``K_a + K_b``); weights kept as they are.

    Raises:
        ValueError: mixtures of different dimensions.
    """
    check_same_dim(a, b)
    return jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x, y]), a, b)


_RANK_BY_COMPARISON_MAX = 64  # capacities up to this rank by K^2 comparisons, above by lax.top_k


def _total_order_key(x: Array) -> Array:
    """Signed integers in the total order of the floats ``x`` (``-NaN < -inf < … < -0 < +0 < … <
    inf < NaN``), the order of ``lax.top_k``: the sign bit flips every other bit of a negative."""
    x = jax.lax.stop_gradient(x)
    itype = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[jnp.dtype(x.dtype).itemsize]
    bits = jax.lax.bitcast_convert_type(x, itype)
    return jnp.where(bits < 0, bits ^ jnp.iinfo(itype).max, bits)


def descending_ranks(x: Array) -> Array:
    """``(K,)`` int32: the position of each entry of ``x`` ``(K,)`` in descending order, ties to the
    lower slot first (the inverse of the permutation ``lax.top_k(x, K)`` gives, NaN and signed
    zeros included).

    Up to ``K = 64`` counted by ``K^2`` comparisons of :func:`_total_order_key`: under ``vmap``
    over 1000 rows of 60 about 0.7–1.2 µs per row, against 4.6 for a full ``top_k`` and 5.0 for a
    stable ``argsort`` (XLA:CPU sorts each row apart); at 128 slots the comparisons cost 19 µs
    against 11, so larger capacities sort.
    """
    K = x.shape[-1]
    if K > _RANK_BY_COMPARISON_MAX:
        order = jax.lax.top_k(jax.lax.stop_gradient(x), K)[1]
        return jnp.zeros(K, jnp.int32).at[order].set(jnp.arange(K, dtype=jnp.int32))
    key = _total_order_key(x)
    slot = jnp.arange(K)
    ahead = (key[None, :] > key[:, None]) | ((key[None, :] == key[:, None]) & (slot[None, :] < slot[:, None]))
    return jnp.sum(ahead, axis=-1, dtype=jnp.int32)


def heaviest_slots(weights: Array, keep: Array, k: int) -> tuple[Array, Array]:
    """The slots of the ``k`` heaviest kept components, heaviest first (ties: the lower slot first).

    The one keep-the-heaviest primitive of the library (``lax.top_k``'s selection over the weights
    with the slots not kept at ``-inf``): the reducers' output fitting, top-``K`` pruning, the gated
    pruning and the GM-PHD's truncation all select through it. Float64 weights in at most 64 slots
    are ranked by :func:`descending_ranks` (the same slots; 0.7 against 4.7 µs per mixture for 20 of
    60 under ``vmap``); float32 weights go to ``lax.top_k``, which XLA:CPU runs on a fast path of its
    own for float32 (1.3 µs; the ranks made the 1-D float32 NL-GSF 1.9x slower).

    Args:
        weights: ``(K,)`` weights. keep: ``(K,)`` bool, the slots that may be selected.
        k: static number of slots to select; may exceed ``K`` (the extra entries are slot 0, invalid).

    Returns:
        ``(idx (k,), valid (k,))``: the selected slots and whether each holds a kept component
        (fewer than ``k`` kept: the rest of ``idx`` are slots that were not kept, marked invalid).
    """
    K = weights.shape[-1]
    ranked = jnp.where(keep, weights, -jnp.inf)
    if K <= _RANK_BY_COMPARISON_MAX and ranked.dtype != jnp.float32:
        rank = descending_ranks(ranked)
        idx = jnp.zeros(K, jnp.int32).at[rank].set(jnp.arange(K, dtype=jnp.int32))[: min(k, K)]
    else:
        idx = jax.lax.top_k(jax.lax.stop_gradient(ranked), min(k, K))[1]
    valid = keep[idx]
    if k > K:
        idx = jnp.concatenate([idx, jnp.zeros(k - K, idx.dtype)])
        valid = jnp.concatenate([valid, jnp.zeros(k - K, bool)])
    return idx, valid


def top_k(gm: GaussianMixture, k: int, *, renormalize: bool = False) -> GaussianMixture:
    """The ``k`` heaviest live components in a mixture of capacity ``k`` (static), heaviest first.

    Ties keep the lower slot index first. Slots beyond the number of live components are padded.
    With ``renormalize`` the kept weights are scaled to sum to 1.
    """
    if k < 1:
        raise ValueError(f"k: must be >= 1, got {k}")
    if k <= gm.capacity:
        idx, _ = heaviest_slots(gm.weights, gm.mask, k)
        out = jax.tree_util.tree_map(lambda a: a[idx], gm)
    else:
        out = top_k(pad(gm, k), k)
        return normalize(out) if renormalize else out
    out = sanitize(out)
    return normalize(out) if renormalize else out
