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

from gmjax.split._gated import principal_axis as principal_axis
from gmjax.split._gated import split_count as split_count
from gmjax.split._gated import split_gated as split_gated
from gmjax.split._libraries import SplitLibrary as SplitLibrary
from gmjax.split._libraries import gauss_hermite_library as gauss_hermite_library
from gmjax.split._libraries import library_l2_error as library_l2_error
from gmjax.split._libraries import library_moments as library_moments
from gmjax.split._libraries import principal_library as principal_library
from gmjax.split._libraries import uniform_library as uniform_library
from gmjax.split._splitting import RefineInfo as RefineInfo
from gmjax.split._splitting import refine as refine
from gmjax.split._splitting import split_axis as split_axis
from gmjax.split._splitting import split_gaussian as split_gaussian
from gmjax.split._splitting import split_mixture as split_mixture
from gmjax.split._splitting import split_principal as split_principal
from gmjax.split._splitting import split_repeated as split_repeated

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
