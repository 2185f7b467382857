"""Monte Carlo PCRB: the expectations of eqs 5-8 over simulated trajectories.

Trajectories ``x_0 ~ prior``, ``x_{n+1} = f(x_n, n) + w_n`` are simulated in chunks of a fixed size
(one compiled kernel: ``vmap`` over the chunk, ``lax.scan`` over time), and only the per-step sums
of ``F^T Q^{-1} F``, ``F`` and ``H^T R^{-1} H`` leave the kernel, so ``10^7`` samples need the memory
of one chunk. The per-chunk estimates also give a batch-means standard error of the bound.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._progress import Progress
from gmjax._types import Array, ArrayLike, PRNGKey
from gmjax.mixture import GaussianMixture
from gmjax.mixture import sample as sample_mixture
from gmjax.pcrb._model import PCRBModel, as_pcrb_model, prior_information
from gmjax.pcrb._noise import noise_information
from gmjax.pcrb._recursion import PCRBResult, bounds_from_information, pcrb_step

__all__ = ["MCInfo", "pcrb_mc", "mc_expectations", "pcrb_from_expectations"]


class MCInfo(NamedTuple):
    """Diagnostics of :func:`pcrb_mc`.

    Attributes:
        n_samples: number of simulated trajectories.
        n_chunks: number of chunks.
        bound_stderr: ``(T + 1, d, d)`` batch-means standard error of the bound over chunks
            (NaN when there is a single chunk).
        D11, D12, D22: ``(T, d, d)`` the estimated expectations (eqs 5, 6, 8).
    """

    n_samples: int
    n_chunks: int
    bound_stderr: Array
    D11: Array
    D12: Array
    D22: Array


def _chunk_sums(model: PCRBModel, key: PRNGKey, n_valid: Array, *, n_steps: int, chunk_size: int):
    """Per-step sums over one chunk: ``(T, d, d)`` of ``F^T Q^-1 F``, ``F``, ``H^T R^-1 H``."""
    dtype = model.prior.means.dtype
    Qi = model.process_information(dtype)  # Q^-1, or the Fisher information of a GM noise
    Ri = model.measurement_information(dtype)
    k0, kw = jax.random.split(key)
    x0 = sample_mixture(model.prior, k0, chunk_size)
    valid = (jnp.arange(chunk_size) < n_valid).astype(dtype)

    def step(x, inp):
        n, k = inp
        F = jax.vmap(model.jac_f, (0, None))(x, n)  # (N, d, d)
        s11 = jnp.einsum("s,sji,jk,skl->il", valid, F, Qi, F)
        sF = jnp.einsum("s,sij->ij", valid, F)
        w = model.sample_process_noise(k, chunk_size, dtype)
        x1 = jax.vmap(model.f, (0, None))(x, n) + w
        H = jax.vmap(model.jac_h, (0, None))(x1, n + 1)  # (N, m, d)
        s22 = jnp.einsum("s,sji,jk,skl->il", valid, H, Ri, H)
        return x1, (s11, sF, s22)

    ns = jnp.arange(n_steps)
    keys = jax.random.split(kw, n_steps)
    _, sums = jax.lax.scan(step, x0, (ns, keys))
    return sums


def pcrb_from_expectations(
    J0: ArrayLike, D11: ArrayLike, EF: ArrayLike, EHRH: ArrayLike, Q: ArrayLike | GaussianMixture
) -> Array:
    """Run eq 4 from ``J_0`` given ``E[F^T I_Q F]``, ``E[F]`` and ``E[H^T I_R H]`` per step.

    ``Q`` is the process-noise covariance or a :class:`~gmjax.mixture.GaussianMixture`; ``I_Q`` is
    ``Q^-1`` or the mixture's Fisher information (:func:`gmjax.pcrb.noise_information`).

    Returns ``(T + 1, d, d)`` FIMs ``J_0..J_T``.
    """
    J0 = jnp.asarray(J0)
    return _from_expectations(J0, D11, EF, EHRH, noise_information(Q, dtype=J0.dtype))


@jax.jit
def _from_expectations(J0, D11, EF, EHRH, Qi) -> Array:

    def step(J, inp):
        d11, ef, ehrh = inp
        D12 = -ef.T @ Qi  # eq 6: -E{dF^T/dx} Q^-1
        D22 = Qi + ehrh  # eq 8
        Jn = pcrb_step(J, d11, D12, D22)
        return Jn, Jn

    _, Js = jax.lax.scan(step, J0, (jnp.asarray(D11), jnp.asarray(EF), jnp.asarray(EHRH)))
    return jnp.concatenate([J0[None], Js])


def mc_expectations(
    model: PCRBModel,
    n_steps: int,
    n_samples: int,
    *,
    key: PRNGKey,
    chunk_size: int = 100_000,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-chunk Monte Carlo averages of ``F^T Q^-1 F``, ``F``, ``H^T R^-1 H`` and chunk sizes.

    Returns:
        ``(D11c, EFc, EHc, counts)`` with shapes ``(C, T, d, d)`` x3 and ``(C,)``, C chunks.
    """
    chunk = int(min(chunk_size, n_samples))
    n_chunks = -(-int(n_samples) // chunk)
    out11, outF, out22, counts = [], [], [], []
    kernel = _kernel(model, int(n_steps), chunk)
    bar = Progress(n_chunks, desc="pcrb_mc", unit="chunks", enabled=progress)
    for c in range(n_chunks):
        n_valid = min(chunk, n_samples - c * chunk)
        s11, sF, s22 = kernel(jax.random.fold_in(key, c), jnp.asarray(n_valid))
        out11.append(np.asarray(s11, np.float64) / n_valid)
        outF.append(np.asarray(sF, np.float64) / n_valid)
        out22.append(np.asarray(s22, np.float64) / n_valid)
        counts.append(n_valid)
        bar.update(1)
    return np.stack(out11), np.stack(outF), np.stack(out22), np.asarray(counts, np.float64)


_KERNELS: dict = {}


def _kernel(model: PCRBModel, n_steps: int, chunk: int):
    """The compiled chunk kernel for a model (cached on the model object, last 8 models).

    The model holds Python callables, so it is closed over rather than passed to ``jit``; the cache
    keeps repeated calls with the same model object from recompiling.
    """
    key = (id(model), n_steps, chunk)
    hit = _KERNELS.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    kernel = jax.jit(partial(_chunk_sums, model, n_steps=n_steps, chunk_size=chunk))
    if len(_KERNELS) >= 8:
        _KERNELS.pop(next(iter(_KERNELS)))
    _KERNELS[key] = (model, kernel)
    return kernel


def pcrb_mc(
    model: PCRBModel,
    n_steps: int,
    n_samples: int,
    *,
    key: PRNGKey,
    J0: ArrayLike | None = None,
    chunk_size: int = 100_000,
    progress: bool = True,
) -> PCRBResult:
    """Monte Carlo PCRB (seed 002 eqs 4-8 with sample averages, eq 73).

    ``D11 = E[F^T Q^-1 F]`` and ``D12 = -E[F]^T Q^-1`` average over ``x_n``; ``D22 = Q^-1 +
    E[H^T R^-1 H]`` over ``x_{n+1}``, all on the same simulated trajectories. With Gaussian-mixture
    noises ``Q^-1`` and ``R^-1`` are the noises' Fisher informations (by quadrature,
    :func:`gmjax.pcrb.noise_information`) and the trajectories sample the mixture. Chunks are
    compiled once (fixed size; the last one is masked), the loop over chunks runs in Python and
    prints a progress bar to stderr.

    Args:
        model: a :class:`PCRBModel`, or a :class:`~gmjax.models.StateSpaceModel` (converted by
            :func:`gmjax.pcrb.from_state_space_model`).
        n_steps: ``T`` (static).
        n_samples: number of trajectories ``N``.
        key: PRNG key (keyword-only).
        J0: initial FIM; default ``Sigma_0^{-1}`` of a one-component prior.
        chunk_size: trajectories per compiled chunk (memory ``~ chunk_size * d^2``).
        progress: print a progress bar over chunks to stderr.

    Returns:
        :class:`PCRBResult` with an :class:`MCInfo` (including a batch-means standard error of the
        bound over chunks).
    """
    model = as_pcrb_model(model)
    if int(n_samples) < 1:
        raise ValueError(f"n_samples: must be >= 1, got {n_samples}")
    if int(n_steps) < 1:
        raise ValueError(f"n_steps: must be >= 1, got {n_steps}")
    if int(chunk_size) < 1:
        raise ValueError(f"chunk_size: must be >= 1, got {chunk_size}")
    J0 = prior_information(model.prior, J0)
    D11c, EFc, EHc, counts = mc_expectations(
        model, int(n_steps), int(n_samples), key=key, chunk_size=chunk_size, progress=progress
    )
    wts = counts / counts.sum()
    D11 = np.einsum("c,ctij->tij", wts, D11c)
    EF = np.einsum("c,ctij->tij", wts, EFc)
    EH = np.einsum("c,ctij->tij", wts, EHc)
    dtype = model.prior.means.dtype
    Qi = model.process_information(dtype)
    Js = _from_expectations(J0, jnp.asarray(D11, dtype), jnp.asarray(EF, dtype), jnp.asarray(EH, dtype), Qi)
    bound = bounds_from_information(Js)
    n_chunks = len(counts)
    if n_chunks >= 2:
        per = jax.vmap(lambda a, b, c: bounds_from_information(_from_expectations(J0, a, b, c, Qi)))(
            jnp.asarray(D11c, dtype), jnp.asarray(EFc, dtype), jnp.asarray(EHc, dtype)
        )
        per = np.asarray(per, np.float64)
        mean = np.einsum("c,ctij->tij", wts, per)
        var = np.einsum("c,ctij->tij", wts, (per - mean) ** 2) * n_chunks / (n_chunks - 1)
        stderr = np.sqrt(var / n_chunks)
    else:
        stderr = np.full(np.shape(bound), np.nan)
    Qi_np = np.asarray(Qi, np.float64)
    info = MCInfo(
        n_samples=int(n_samples),
        n_chunks=n_chunks,
        bound_stderr=jnp.asarray(stderr),
        D11=jnp.asarray(D11),
        D12=jnp.asarray(-np.swapaxes(EF, -1, -2) @ Qi_np),
        D22=jnp.asarray(Qi_np + EH),
    )
    return PCRBResult(Js, bound, info)
