"""Splitting Gaussians into Gaussian mixtures: libraries, directions and refinement.

Two families of splits share one mechanism. A *1-D splitting library* approximates the standard
normal by ``M`` narrower components (seed 002 eq 12),

    N(x; 0, 1) ~= sum_i w_i N(x; mu_i, sigma^2),

and a Gaussian ``N(m, P)`` is split along a *split column* ``a`` (a ``(d,)`` vector with
``P - a a^T`` positive semi-definite) into

    sum_i w_i N(m + mu_i a, P - (1 - sigma^2) a a^T)                      (seed 002 eq 20)

which is eq 20 written for a square root ``L`` of ``P`` whose split column ``L e_d`` is ``a``.
Three choices of ``a`` are offered (``direction=``):

* ``None`` - the principal axis ``sqrt(lambda_max) e_max`` of ``P`` (seed 001 eq 32);
* an ``int`` ``i`` - coordinate ``i``: ``a = P e_i / sqrt(P_ii)``, which splits the marginal of
  ``x_i`` with the library and leaves the conditional law of the other coordinates given ``x_i``
  unchanged (for ``i = 0`` this is the first column of the lower Cholesky factor, eqs 17-20);
* a vector ``u`` - the same with ``a = P u / sqrt(u^T P u)``.

Libraries (built eagerly in NumPy, once):

* :func:`gauss_hermite_library` - Horwood-Poore's first library: ``w_i`` the normalised
  Gauss-Hermite weights, ``mu_i = k z_i`` with ``z_i`` the nodes for ``N(0, 1)`` (eq 36),
  ``sigma^2 = 1 - k^2``. Its moments agree with ``N(0, 1)`` up to order ``2M - 1``.
* :func:`uniform_library` - the second library: equally spaced means ``mu_i = -m + sigma (i-1)``,
  ``M = ceil(1 + 2m / sigma)``, ``m = 6`` if ``sigma < 1/2`` else ``4`` (eqs 14-16), with weights
  minimising the L2 distance of eq 13 subject to ``w >= 0`` and ``sum w = 1`` (eqs 10-11).
* :func:`principal_library` - seed 001's two-way split (eq 32): means ``+-l``, weights
  ``(omega, 1 - omega)``, ``sigma^2 = 1 - l^2``; along the principal axis this is exactly eq 32.

Functions that act on padded mixtures (:func:`split_mixture`, :func:`refine`) keep padded slots at
``(0, 0, I)`` and never produce NaN from them.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import gaussian
from gmjax._types import Array, ArrayLike, Vector
from gmjax.mixture import GaussianMixture, sanitize

__all__ = [
    "SplitLibrary",
    "RefineInfo",
    "gauss_hermite_library",
    "uniform_library",
    "principal_library",
    "library_l2_error",
    "library_moments",
    "split_axis",
    "split_gaussian",
    "split_mixture",
    "split_repeated",
    "split_principal",
    "refine",
    "split_count",
    "principal_axis",
    "split_gated",
]


class SplitLibrary(NamedTuple):
    """A 1-D splitting library ``N(0, 1) ~= sum_i w_i N(mu_i, sigma^2)`` (seed 002 eq 12).

    Attributes:
        weights: ``(M,)`` non-negative, summing to 1.
        means: ``(M,)`` component means ``mu_i``.
        sigma: ``()`` common component standard deviation ``0 < sigma < 1``.
    """

    weights: Array | np.ndarray
    means: Array | np.ndarray
    sigma: Array | np.ndarray

    @property
    def size(self) -> int:
        """``M``, the number of components (static)."""
        return int(np.shape(self.weights)[0])


class RefineInfo(NamedTuple):
    """What :func:`refine` did.

    Attributes:
        n_split: ``()`` int32, number of slots that were split.
        n_out: ``()`` int32, live components after refinement.
        overflow: ``()`` bool, True when some selected slots could not be split for lack of free
            slots (the heaviest selected slots were split first).
    """

    n_split: Array
    n_out: Array
    overflow: Array


# ----------------------------------------------------------------------------------------------
# Libraries (eager NumPy)
# ----------------------------------------------------------------------------------------------


def _check_sigma(sigma: float) -> float:
    sigma = float(sigma)
    if not (0.0 < sigma < 1.0) or not math.isfinite(sigma):
        raise ValueError(f"sigma: must satisfy 0 < sigma < 1, got {sigma}")
    return sigma


def _make_library(weights: np.ndarray, means: np.ndarray, sigma: float) -> SplitLibrary:
    return SplitLibrary(
        np.asarray(weights, np.float64), np.asarray(means, np.float64), np.asarray(sigma, np.float64)
    )


def gauss_hermite_library(num: int, sigma: float) -> SplitLibrary:
    """Horwood-Poore's Gauss-Hermite splitting library (seed 002 §III-A, first library).

    ``w_i`` are the Gauss-Hermite weights normalised to sum to 1 and ``mu_i = k z_i`` where ``z_i``
    are the nodes for ``N(0, 1)`` (``z_i = sqrt(2) eps_i`` with ``eps_i`` the roots of the physicists'
    Hermite polynomial, eq 36) and ``k = sqrt(1 - sigma^2)``, so that ``sigma^2 = 1 - k^2``. With the
    normalised nodes, the library's moments equal those of ``N(0, 1)`` up to order ``2 num - 1``.

    Args:
        num: ``M >= 1``, the number of components.
        sigma: component standard deviation, ``0 < sigma < 1``.

    Raises:
        ValueError: for ``num < 1`` or ``sigma`` outside ``(0, 1)``.
    """
    if int(num) != num or num < 1:
        raise ValueError(f"num: must be a positive integer, got {num}")
    sigma = _check_sigma(sigma)
    z, w = np.polynomial.hermite_e.hermegauss(int(num))
    w = w / w.sum()
    k = math.sqrt(1.0 - sigma * sigma)
    return _make_library(w, k * z, sigma)


def _l2_gram(means: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Quadratic form of eq 13: ``E(w) = c - 2 b^T w + w^T G w``."""
    diff = means[:, None] - means[None, :]
    s2 = 2.0 * sigma * sigma
    G = np.exp(-0.5 * diff**2 / s2) / math.sqrt(2.0 * math.pi * s2)
    v = 1.0 + sigma * sigma
    b = np.exp(-0.5 * means**2 / v) / math.sqrt(2.0 * math.pi * v)
    c = 1.0 / (2.0 * math.sqrt(math.pi))
    return G, b, c


def library_l2_error(library: SplitLibrary) -> float:
    """L2 distance of eq 13 between ``N(0, 1)`` and the library, ``E`` (not its root).

    Integrated on a fine uniform grid (the trapezoid rule is spectrally accurate for these smooth,
    fast-decaying integrands), which avoids the cancellation of the closed form ``c - 2 b^T w +
    w^T G w`` when ``E`` is near machine precision.
    """
    w = np.asarray(library.weights, np.float64)
    mu = np.asarray(library.means, np.float64)
    s = float(library.sigma)
    lo = min(-10.0, float(mu.min()) - 12.0 * s)
    hi = max(10.0, float(mu.max()) + 12.0 * s)
    n = int(min(200_001, max(20_001, 40 * (hi - lo) / s)))
    x = np.linspace(lo, hi, n)
    ref = np.exp(-0.5 * x**2) / math.sqrt(2.0 * math.pi)
    mix = np.zeros_like(x)
    for wi, mi in zip(w, mu):
        mix += wi * np.exp(-0.5 * ((x - mi) / s) ** 2) / (s * math.sqrt(2.0 * math.pi))
    return float(np.trapezoid((ref - mix) ** 2, x))


def library_moments(library: SplitLibrary, orders: Sequence[int]) -> np.ndarray:
    """Raw moments ``E[x^p]`` of the library mixture for each ``p`` in ``orders`` (closed form)."""
    w = np.asarray(library.weights, np.float64)
    mu = np.asarray(library.means, np.float64)
    s = float(library.sigma)
    out = []
    for p in orders:
        # E[(mu + s e)^p] = sum_j C(p, j) mu^(p-j) s^j E[e^j], E[e^j] = (j-1)!! for even j.
        tot = np.zeros_like(mu)
        for j in range(0, p + 1, 2):
            dfact = float(np.prod(np.arange(j - 1, 0, -2))) if j > 0 else 1.0
            tot = tot + math.comb(p, j) * mu ** (p - j) * s**j * dfact
        out.append(float(w @ tot))
    return np.asarray(out)


def _nnls_simplex(G: np.ndarray, b: np.ndarray, rho: float = 1e3) -> np.ndarray:
    """``argmin w^T G w - 2 b^T w`` s.t. ``w >= 0, sum w = 1`` (NNLS on a square root of ``G``).

    ``G`` is written as ``A^T A`` with ``A = diag(sqrt(lam)) V^T`` from its eigendecomposition (``G``
    is a Gram matrix of Gaussians, positive semi-definite but badly conditioned). The linear term
    becomes ``A^T c = b`` on the numerically non-null eigenspace, and the sum constraint is an extra
    row weighted by ``rho``. The solution is refined by a few active-set Newton steps and finally
    rescaled to sum to 1 exactly.
    """
    from scipy.optimize import nnls

    lam, V = np.linalg.eigh(G)
    keep = lam > lam.max() * 1e-15
    A = np.sqrt(lam[keep])[:, None] * V[:, keep].T
    c = (V[:, keep].T @ b) / np.sqrt(lam[keep])
    n = G.shape[0]
    A_aug = np.vstack([A, rho * np.ones((1, n))])
    c_aug = np.concatenate([c, [rho]])
    w, _ = nnls(A_aug, c_aug, maxiter=50 * n)
    # Polish: on the active set solve the equality-constrained QP exactly (KKT system).
    for _ in range(5):
        act = w > 0
        k = int(act.sum())
        K = np.zeros((k + 1, k + 1))
        K[:k, :k] = G[np.ix_(act, act)]
        K[:k, k] = 1.0
        K[k, :k] = 1.0
        rhs = np.concatenate([b[act], [1.0]])
        try:
            sol = np.linalg.lstsq(K, rhs, rcond=None)[0]
        except np.linalg.LinAlgError:  # pragma: no cover
            break
        if np.all(sol[:k] >= 0):
            w = np.zeros(n)
            w[act] = sol[:k]
            break
        # step towards the KKT point while staying feasible
        wa = np.zeros(n)
        wa[act] = sol[:k]
        d = wa - w
        neg = d < 0
        t = min(1.0, float(np.min(-w[neg] / d[neg]))) if neg.any() else 1.0
        w = np.maximum(w + t * d, 0.0)
        w[w < 1e-300] = 0.0
    return w / w.sum()


def uniform_library(sigma: float) -> SplitLibrary:
    """Horwood-Poore's uniform-spacing library with L2-optimal weights (seed 002 eqs 13-16).

    ``sigma_i = sigma`` (eq 14), ``mu_i = -m + sigma (i - 1)`` (eq 15), ``M = ceil(1 + 2 m / sigma)``
    (eq 16) with ``m = 6`` if ``sigma < 1/2`` else ``m = 4``. The weights minimise the closed-form
    L2 distance of eq 13 - a quadratic ``c - 2 b^T w + w^T G w`` with ``G_ij = N(mu_i; mu_j, 2 sigma^2)``
    and ``b_i = N(mu_i; 0, 1 + sigma^2)`` - subject to ``w >= 0`` and ``sum w = 1`` (eqs 10-11; the
    paper says only "a quadratic optimisation problem"; we keep the weights a valid mixture).
    Solved once with SciPy's NNLS on a square root of ``G`` plus an exact KKT polish.

    Args:
        sigma: component standard deviation, ``0 < sigma < 1`` (e.g. 1/4 gives ``M = 49``).

    Raises:
        ValueError: for ``sigma`` outside ``(0, 1)``.
    """
    sigma = _check_sigma(sigma)
    m = 6.0 if sigma < 0.5 else 4.0
    num = int(math.ceil(1.0 + 2.0 * m / sigma - 1e-9))
    means = -m + sigma * np.arange(num, dtype=np.float64)
    G, b, _ = _l2_gram(means, sigma)
    w = _nnls_simplex(G, b)
    return _make_library(w, means, sigma)


def principal_library(l: float = 0.5, w: float = 0.5) -> SplitLibrary:  # noqa: E741
    """Seed 001's two-way split (eq 32) as a library: means ``(+l, -l)``, weights ``(w, 1 - w)``.

    Applied along the principal axis ``sqrt(lambda) e_v`` it gives exactly eq 32:
    ``mu_{1,2} = mu +- l sqrt(lambda) e_v`` and ``Sigma_{1,2} = Sigma - l^2 lambda e_v e_v^T``
    (so ``sigma^2 = 1 - l^2``). For ``w != 1/2`` the split does not preserve the mean (as written in
    the paper).

    Raises:
        ValueError: unless ``0 < l < 1`` and ``0 < w < 1``.
    """
    if not (0.0 < float(l) < 1.0):
        raise ValueError(f"l: must satisfy 0 < l < 1, got {l}")
    if not (0.0 < float(w) < 1.0):
        raise ValueError(f"w: must satisfy 0 < w < 1, got {w}")
    return _make_library(np.array([w, 1.0 - w]), np.array([l, -l]), math.sqrt(1.0 - float(l) ** 2))


# ----------------------------------------------------------------------------------------------
# Splitting (traceable)
# ----------------------------------------------------------------------------------------------


def split_axis(cov: ArrayLike, direction: int | ArrayLike | None = None) -> Vector:
    """The split column ``a`` (``(d,)``) of a covariance for a direction choice.

    Args:
        cov: ``(d, d)`` covariance.
        direction: ``None`` for the principal axis ``sqrt(lambda_max) e_max``; an ``int`` ``i`` for
            ``P e_i / sqrt(P_ii)``; a ``(d,)`` vector ``u`` for ``P u / sqrt(u^T P u)``.

    Returns:
        ``a`` with ``P - a a^T`` positive semi-definite.
    """
    cov = gaussian.symmetrize(jnp.asarray(cov))
    d = cov.shape[-1]
    if direction is None:
        lam, vecs = jnp.linalg.eigh(cov)
        lam_max = jnp.maximum(lam[-1], 0.0)
        return jnp.sqrt(lam_max) * vecs[:, -1]
    if isinstance(direction, (int, np.integer)):
        if not 0 <= int(direction) < d:
            raise ValueError(f"direction: axis {direction} out of range for dimension {d}")
        u = jnp.zeros(d, cov.dtype).at[int(direction)].set(1.0)
    else:
        u = jnp.asarray(direction, cov.dtype)
        if u.shape != (d,):
            raise ValueError(f"direction: expected a ({d},) vector, got shape {u.shape}")
    Pu = cov @ u
    s2 = u @ Pu
    ok = s2 > 0
    return jnp.where(ok, Pu / jnp.sqrt(jnp.where(ok, s2, 1.0)), 0.0)


def _lib_arrays(library: SplitLibrary, dtype) -> tuple[Array, Array, Array]:
    return (
        jnp.asarray(library.weights, dtype),
        jnp.asarray(library.means, dtype),
        jnp.asarray(library.sigma, dtype),
    )


def _split_one(weight, mean, cov, library: SplitLibrary, direction):
    dtype = jnp.result_type(mean, cov)
    lw, lm, ls = _lib_arrays(library, dtype)
    a = split_axis(cov, direction)
    means = mean[None, :] + lm[:, None] * a[None, :]
    child_cov = gaussian.symmetrize(cov - (1.0 - ls * ls) * jnp.outer(a, a))
    covs = jnp.broadcast_to(child_cov, (lw.shape[0],) + cov.shape)
    return weight * lw, means, covs


def split_gaussian(
    weight: ArrayLike,
    mean: ArrayLike,
    cov: ArrayLike,
    library: SplitLibrary,
    direction: int | ArrayLike | None = 0,
) -> GaussianMixture:
    """Split one weighted Gaussian with a 1-D library along a direction (seed 002 eq 20).

    Args:
        weight: ``()`` weight of the component (children get ``weight * w_i``).
        mean: ``(d,)``. cov: ``(d, d)``.
        library: a :class:`SplitLibrary` with ``M`` components.
        direction: see :func:`split_axis` (default: coordinate 0).

    Returns:
        A ``M``-component mixture ``sum_i weight w_i N(mean + mu_i a, cov - (1 - sigma^2) a a^T)``.
    """
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov, mean.dtype)
    spec, u = _direction_spec(direction, mean.shape[-1])
    one = GaussianMixture(jnp.asarray(weight, mean.dtype)[None], mean[None], cov[None], jnp.ones(1, bool))
    return _split_mixture_jit(one, library, u, spec)


def _direction_spec(direction, d: int):
    """Split a direction into a static part (kind, axis) and a dynamic vector (for jit)."""
    if direction is None:
        return ("principal", 0), None
    if isinstance(direction, (int, np.integer)):
        if not 0 <= int(direction) < d:
            raise ValueError(f"direction: axis {direction} out of range for dimension {d}")
        return ("axis", int(direction)), None
    u = jnp.asarray(direction)
    if u.shape != (d,):
        raise ValueError(f"direction: expected a ({d},) vector, got shape {u.shape}")
    return ("vector", 0), u


def _resolve(spec, u):
    kind, axis = spec
    if kind == "principal":
        return None
    if kind == "axis":
        return axis
    return u


@partial(jax.jit, static_argnames=("spec",))
def _split_mixture_jit(gm: GaussianMixture, library: SplitLibrary, u, spec) -> GaussianMixture:
    M = library.weights.shape[0]
    K, d = gm.capacity, gm.dim
    direction = _resolve(spec, u)
    # Padded slots: replace the (degenerate, identity) covariance by diag(1..d) before eigh so that
    # gradients stay finite; their children are sanitised afterwards.
    safe_cov = jnp.where(gm.mask[:, None, None], gm.covs, jnp.diag(jnp.arange(1, d + 1, dtype=gm.covs.dtype)))
    w, m, P = jax.vmap(lambda a, b, c: _split_one(a, b, c, library, direction))(
        gm.weights, gm.means, safe_cov
    )
    mask = jnp.repeat(gm.mask, M)
    out = GaussianMixture(w.reshape(K * M), m.reshape(K * M, d), P.reshape(K * M, d, d), mask)
    return sanitize(out)


def split_mixture(
    gm: GaussianMixture, library: SplitLibrary, direction: int | ArrayLike | None = 0
) -> GaussianMixture:
    """Split every slot of a mixture with a library: capacity ``K -> K M`` (children parent-major).

    Padded parents give padded children; live weights are multiplied by the library weights, so the
    total weight is unchanged. Compiled once per shape and direction kind.
    """
    spec, u = _direction_spec(direction, gm.dim)
    return _split_mixture_jit(gm, library, u, spec)


def split_repeated(
    gm: GaussianMixture,
    library: SplitLibrary,
    directions: Sequence[int | ArrayLike | None],
) -> GaussianMixture:
    """Apply :func:`split_mixture` once per entry of ``directions`` (capacity ``K M^len``).

    Repeated splitting gives the multidirectional GMM of seed 002 §III-A; e.g. the 1-D benchmark
    splits ``N(0, 1)`` four times along axis 0 with the ``sigma = 1/2, M = 8`` library (4096 terms).
    """
    for direction in directions:
        gm = split_mixture(gm, library, direction)
    return gm


def split_principal(
    weight: ArrayLike,
    mean: ArrayLike,
    cov: ArrayLike,
    n_split: int,
    l: float = 0.5,  # noqa: E741
    w: float = 0.5,
) -> GaussianMixture:
    """Seed 001 eq 32 repeated ``n_split`` times: ``N_F = 2^n_split`` components.

    Each pass splits every current component in two along the eigenvector of its own largest
    eigenvalue: ``mu +- l sqrt(lambda) e_v``, covariance ``Sigma - l^2 lambda e_v e_v^T``, weights
    ``w`` and ``1 - w`` (seed 001 §3.3, Step 3).

    Args:
        weight: ``()`` weight of the component being split.
        mean: ``(d,)``. cov: ``(d, d)``.
        n_split: ``n >= 0`` (static); ``0`` returns the component itself.
        l: displacement, ``0 < l < 1`` (paper: 0.5). w: weight ``omega`` (paper: 0.5).

    Returns:
        A mixture of ``2^n_split`` components whose weights sum to ``weight``.
    """
    if int(n_split) != n_split or n_split < 0:
        raise ValueError(f"n_split: must be a non-negative integer, got {n_split}")
    lib = principal_library(l, w)
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov, mean.dtype)
    gm = GaussianMixture(jnp.asarray(weight, mean.dtype)[None], mean[None], cov[None], jnp.ones(1, bool))
    return split_repeated(gm, lib, [None] * int(n_split))


def refine(
    gm: GaussianMixture,
    mask_to_split: ArrayLike,
    library: SplitLibrary,
    capacity: int | None = None,
    *,
    direction: int | ArrayLike | None = None,
) -> tuple[GaussianMixture, RefineInfo]:
    """Split the selected slots of a mixture inside a fixed capacity.

    Each selected live slot is replaced by its ``M`` children. The output lists the live slots in
    their original order, compacted to the front, with every split slot expanded in place into its
    children (so the slots after it shift); padded slots follow. When free slots run short, the
    heaviest selected slots are split first and ``info.overflow`` is set; nothing is ever dropped.

    Args:
        gm: mixture of capacity ``K``.
        mask_to_split: ``(K,)`` bool, which slots to split (padded slots are ignored).
        library: the splitting library (e.g. :func:`principal_library` for seed 001).
        capacity: output capacity ``C >= K`` (static; default ``K``).
        direction: see :func:`split_axis` (default: principal axis).

    Returns:
        ``(mixture of capacity C, RefineInfo)``.
    """
    K, d = gm.capacity, gm.dim
    C = K if capacity is None else int(capacity)
    if C < K:
        raise ValueError(f"capacity: {C} is smaller than the mixture capacity {K}")
    sel_in = jnp.asarray(mask_to_split, bool)
    if sel_in.shape != (K,):
        raise ValueError(f"mask_to_split: expected shape ({K},), got {sel_in.shape}")
    spec, u = _direction_spec(direction, d)
    return _refine_jit(gm, sel_in, library, u, spec=spec, capacity=C)


@partial(jax.jit, static_argnames=("spec", "capacity"))
def _refine_jit(gm, sel_in, library, u, *, spec, capacity):
    K, d = gm.capacity, gm.dim
    C = capacity
    M = library.weights.shape[0]
    sel = sel_in & gm.mask
    free = C - jnp.sum(gm.mask.astype(jnp.int32))
    # rank the selected slots by weight (heaviest first); the r-th needs (r + 1)(M - 1) free slots
    prio = jnp.where(sel, gm.weights, -jnp.inf)
    order = jnp.argsort(-prio, stable=True)
    rank = jnp.zeros(K, jnp.int32).at[order].set(jnp.arange(K, dtype=jnp.int32))
    allowed = sel & ((rank + 1) * (M - 1) <= free)
    children = _split_mixture_jit(gm, library, u, spec)
    cw = children.weights.reshape(K, M)
    cm = children.means.reshape(K, M, d)
    cP = children.covs.reshape(K, M, d, d)
    keep_w = jnp.zeros((K, M), gm.weights.dtype).at[:, 0].set(gm.weights)
    keep_m = jnp.zeros((K, M, d), gm.means.dtype).at[:, 0].set(gm.means)
    keep_P = jnp.broadcast_to(jnp.eye(d, dtype=gm.covs.dtype), (K, M, d, d)).at[:, 0].set(gm.covs)
    first_only = jnp.arange(M) == 0
    w = jnp.where(allowed[:, None], cw, keep_w)
    m = jnp.where(allowed[:, None, None], cm, keep_m)
    P = jnp.where(allowed[:, None, None, None], cP, keep_P)
    live = gm.mask[:, None] & (allowed[:, None] | first_only[None, :])
    flat_live = live.reshape(K * M)
    pos = jnp.cumsum(flat_live.astype(jnp.int32)) - 1
    dest = jnp.where(flat_live, pos, C)  # dead entries go out of bounds and are dropped
    eye = jnp.eye(d, dtype=gm.covs.dtype)
    out = GaussianMixture(
        jnp.zeros(C, gm.weights.dtype).at[dest].set(w.reshape(K * M), mode="drop"),
        jnp.zeros((C, d), gm.means.dtype).at[dest].set(m.reshape(K * M, d), mode="drop"),
        jnp.broadcast_to(eye, (C, d, d)).at[dest].set(P.reshape(K * M, d, d), mode="drop"),
        jnp.zeros(C, bool).at[dest].set(True, mode="drop"),
    )
    info = RefineInfo(
        n_split=jnp.sum(allowed.astype(jnp.int32)),
        n_out=jnp.sum(out.mask.astype(jnp.int32)),
        overflow=jnp.any(sel & ~allowed),
    )
    return sanitize(out), info


# ----------------------------------------------------------------------------------------------
# Seed 001: split-decision model (eq 31) and gated principal-axis splitting (eq 32, traceable)
# ----------------------------------------------------------------------------------------------


def split_count(psi: ArrayLike, psi_th: ArrayLike, r: ArrayLike, max_level: int) -> Array:
    """Seed 001 eq 31: the split level ``n`` (``N_F = 2^n``) of a component with DON ``psi``.

    ``n`` is the largest ``1 <= n <= max_level`` with ``psi >= psi_th r^(n-1)`` (so
    ``psi_th r^(n-1) <= psi < psi_th r^n`` gives ``N_F = 2^n``), and ``0`` (no split,
    ``N_F = 1``) when ``psi < psi_th``. The paper's ``n`` is unbounded; ``max_level`` (static)
    caps it. Traceable and broadcasting over ``psi``; ``psi_th = inf`` gives 0.

    Returns:
        int32 array of the broadcast shape of ``psi``.
    """
    if int(max_level) != max_level or max_level < 0:
        raise ValueError(f"max_level: must be a non-negative integer, got {max_level!r}")
    psi = jnp.asarray(psi)
    levels = jnp.arange(1, int(max_level) + 1, dtype=psi.dtype)
    thresholds = jnp.asarray(psi_th, psi.dtype) * jnp.asarray(r, psi.dtype) ** (levels - 1)
    hit = psi[..., None] >= thresholds
    # thresholds increase with n (r >= 1), so the hits are a prefix: count them
    return jnp.sum(jnp.cumprod(hit.astype(jnp.int32), axis=-1), axis=-1).astype(jnp.int32)


def principal_axis(cov: ArrayLike) -> tuple[Array, Array]:
    """``(lambda_max, e_v)`` of a covariance with a deterministic eigenvector sign.

    The sign of ``e_v`` is fixed so that its entry of largest magnitude is positive (the first
    such entry on ties), so that NumPy and JAX references split in the same direction.
    """
    cov = gaussian.symmetrize(jnp.asarray(cov))
    lam, vecs = jnp.linalg.eigh(cov)
    e = vecs[:, -1]
    i = jnp.argmax(jnp.abs(e))
    e = jnp.where(e[i] < 0, -e, e)
    return jnp.maximum(lam[-1], 0.0), e


def split_gated(
    weight: ArrayLike,
    mean: ArrayLike,
    cov: ArrayLike,
    displacements: ArrayLike,
    active: ArrayLike,
    w: ArrayLike = 0.5,
) -> GaussianMixture:
    """Seed 001 eq 32 applied level by level with per-level displacements (traceable).

    Level ``n`` (``n = 1 .. L``, ``L = len(displacements)`` static) splits every current child
    ``N(mu, Sigma)`` that is live into ``omega N(mu + l_n sqrt(lambda) e_v, Sigma - l_n^2 lambda e_v
    e_v^T) + (1 - omega) N(mu - l_n sqrt(lambda) e_v, same)`` along the principal eigenvector of its
    own covariance (:func:`principal_axis`), when ``active[n-1]``; an inactive level leaves the
    children unchanged. With ``l_n = l`` for the first ``n`` levels this is exactly
    :func:`split_principal` with ``n_split = n`` (``N_F = 2^n``, eq 31); a smaller ``l_n`` (e.g.
    ``l`` times a soft gate) gives a partial, differentiable split.

    Args:
        weight: ``()``. mean: ``(d,)``. cov: ``(d, d)``.
        displacements: ``(L,)`` displacement ``l_n`` of each level (``0 <= l_n < 1``).
        active: ``(L,)`` bool, which levels split.
        w: the weight ``omega`` of the ``+`` child (paper: 0.5).

    Returns:
        A mixture of capacity ``2^L``: the children in tree order (child ``c`` of level ``n`` has
        children ``2c`` and ``2c + 1`` at level ``n + 1``; an inactive level keeps ``2c`` and pads
        ``2c + 1``). The live weights sum to ``weight``.
    """
    mean = jnp.asarray(mean)
    dtype = mean.dtype
    cov = jnp.asarray(cov, dtype)
    disp = jnp.asarray(displacements, dtype)
    active = jnp.asarray(active, bool)
    if disp.ndim != 1 or active.shape != disp.shape:
        raise ValueError(
            f"displacements/active: expected two (L,) arrays, got {disp.shape} and {active.shape}"
        )
    d = mean.shape[-1]
    w = jnp.asarray(w, dtype)
    ws = jnp.asarray(weight, dtype)[None]
    ms = mean[None]
    Ps = cov[None]
    live = jnp.ones(1, bool)
    eye = jnp.eye(d, dtype=dtype)
    for n in range(disp.shape[0]):
        ln = disp[n]
        on = active[n]
        safe_P = jnp.where(live[:, None, None], Ps, eye)
        lam, e = jax.vmap(principal_axis)(safe_P)
        a = jnp.sqrt(lam)[:, None] * e  # (c, d): sqrt(lambda) e_v
        child_P = gaussian.symmetrize(Ps - (ln * ln) * jnp.einsum("ci,cj->cij", a, a))
        plus_m = ms + ln * a
        minus_m = ms - ln * a
        # interleave: child 2c is the "+" child (or the parent), 2c + 1 the "-" child (or padding)
        m_new = jnp.stack([jnp.where(on, plus_m, ms), jnp.where(on, minus_m, 0.0)], 1).reshape(-1, d)
        P_new = jnp.stack(
            [jnp.where(on, child_P, Ps), jnp.where(on, child_P, jnp.broadcast_to(eye, Ps.shape))], 1
        ).reshape(-1, d, d)
        w_new = jnp.stack([jnp.where(on, w * ws, ws), jnp.where(on, (1.0 - w) * ws, 0.0)], 1).reshape(-1)
        live = jnp.stack([live, live & on], 1).reshape(-1)
        ws, ms, Ps = w_new, m_new, P_new
    return sanitize(GaussianMixture(jnp.where(live, ws, 0.0), ms, Ps, live))
