"""Posterior Cramér-Rao bounds (Zhang et al. 2021 = seed 002): Tichavsky's recursion, Monte Carlo and GMM-quadrature.

* :func:`pcrb_step` - one step of eq 4; :func:`pcrb_linear` - the linear Gaussian case (Kalman).
* :func:`pcrb_mc` - expectations of eqs 5-8 over simulated trajectories, chunked.
* :func:`pcrb_gmm` - Algorithms 1 and 2 with the nonlinearity switch (eqs 39-72).
* :func:`noise_information` - Fisher information of a Gaussian-mixture noise, which replaces
  ``Q^-1`` / ``R^-1`` when a noise is a mixture (``pcrb_linear``, ``pcrb_mc``, ``pcrb_gmm``).

One convention for every entry point: the model is a :class:`PCRBModel` or a
:class:`~gmjax.models.StateSpaceModel` (converted), and the result is a :class:`PCRBResult` whose
``information`` and ``bound`` are ``(T + 1, d, d)`` with index ``k`` the state ``x_k`` (index 0 the
prior), plus a method-specific ``info``.
"""

from gmjax.pcrb._gmm import GMMPCRBConfig as GMMPCRBConfig
from gmjax.pcrb._gmm import GMMPCRBInfo as GMMPCRBInfo
from gmjax.pcrb._gmm import build_pcrb_gmm as build_pcrb_gmm
from gmjax.pcrb._gmm import gmm_expectation as gmm_expectation
from gmjax.pcrb._gmm import nonlinearity_metric as nonlinearity_metric
from gmjax.pcrb._gmm import pcrb_gmm as pcrb_gmm
from gmjax.pcrb._mc import MCInfo as MCInfo
from gmjax.pcrb._mc import pcrb_from_expectations as pcrb_from_expectations
from gmjax.pcrb._mc import pcrb_mc as pcrb_mc
from gmjax.pcrb._model import PCRBModel as PCRBModel
from gmjax.pcrb._model import as_pcrb_model as as_pcrb_model
from gmjax.pcrb._model import from_state_space_model as from_state_space_model
from gmjax.pcrb._model import prior_information as prior_information
from gmjax.pcrb._noise import noise_information as noise_information
from gmjax.pcrb._recursion import PCRBResult as PCRBResult
from gmjax.pcrb._recursion import bounds_from_information as bounds_from_information
from gmjax.pcrb._recursion import pcrb_linear as pcrb_linear
from gmjax.pcrb._recursion import pcrb_step as pcrb_step

__all__ = [
    "PCRBModel",
    "PCRBResult",
    "MCInfo",
    "GMMPCRBConfig",
    "GMMPCRBInfo",
    "pcrb_step",
    "pcrb_linear",
    "pcrb_mc",
    "pcrb_gmm",
    "build_pcrb_gmm",
    "pcrb_from_expectations",
    "bounds_from_information",
    "gmm_expectation",
    "nonlinearity_metric",
    "prior_information",
    "from_state_space_model",
    "as_pcrb_model",
    "noise_information",
]
