"""Filters: Gaussian local filters (KF, EKF, UKF, CKF, GHKF, sparse-grid, SCKF), particle filters, IMM.

Component level (one Gaussian, noise ``(mean, cov)`` passed per call, for Gaussian sum filters):
``local_kf``, ``local_ekf``, ``local_ukf``, ``local_ckf``, ``local_ghkf``, ``local_sgkf``,
``local_sckf``, ``local_sigma`` → :class:`LocalFilter`.

Model level: every filter is one :class:`Filter` ``(init, predict, update, params)`` (the contract of
:mod:`gmjax.filters.base`, docs/design.md §3) and :func:`run` scans any of them over measurements:
``build_kf``, ``build_ekf``, ``build_ukf``, ``build_ckf``, ``build_ghkf``, ``build_sgkf``,
``build_sckf``, ``build_sigma`` and ``kalman_filter`` (from arrays); particle filters
(:mod:`gmjax.filters.pf`), IMM and the IMM of Gaussian sum filters (:mod:`gmjax.filters.imm`), the
Gaussian sum filter (GM prior and noises, any local filter, any reducer; :mod:`gmjax.filters.gsf`),
seed 001's adaptive split-merge AGSSCKF (:mod:`gmjax.filters.agsf`), and seed 004's linear bank with
the active-cluster reduction (:mod:`gmjax.filters.bank`).

Smoothers (:mod:`gmjax.filters.smoother`): ``rts_smoother`` (KF/EKF and the sigma-point URTS),
``rts_linear`` and the Gaussian-sum ``gaussian_sum_smoother``.
"""

from gmjax.filters import agsf as agsf  # noqa: E402
from gmjax.filters import bank as bank  # noqa: E402
from gmjax.filters import gsf as gsf  # noqa: E402
from gmjax.filters import imm as imm  # noqa: E402
from gmjax.filters import pf as pf  # noqa: E402
from gmjax.filters import smoother as smoother  # noqa: E402
from gmjax.filters._core import GaussianState as GaussianState
from gmjax.filters._core import LocalFilter as LocalFilter
from gmjax.filters._core import SqrtState as SqrtState
from gmjax.filters._core import UpdateInfo as UpdateInfo
from gmjax.filters._core import from_local as from_local
from gmjax.filters._sigma import build_sigma as build_sigma
from gmjax.filters._sigma import local_sigma as local_sigma
from gmjax.filters.agsf import AGSFConfig as AGSFConfig
from gmjax.filters.agsf import AGSFParams as AGSFParams
from gmjax.filters.agsf import AGSFState as AGSFState
from gmjax.filters.agsf import Step6Merge as Step6Merge
from gmjax.filters.agsf import Step6State as Step6State
from gmjax.filters.agsf import build_agsf as build_agsf
from gmjax.filters.agsf import build_gsckf as build_gsckf
from gmjax.filters.agsf import build_gsukf as build_gsukf
from gmjax.filters.agsf import degree_of_nonlinearity as degree_of_nonlinearity
from gmjax.filters.bank import BANK_METHODS as BANK_METHODS
from gmjax.filters.bank import BankParams as BankParams
from gmjax.filters.bank import BankState as BankState
from gmjax.filters.bank import build_bank as build_bank
from gmjax.filters.base import Filter as Filter
from gmjax.filters.base import StepFlags as StepFlags
from gmjax.filters.base import StepInfo as StepInfo
from gmjax.filters.base import StepInputs as StepInputs
from gmjax.filters.base import run as run
from gmjax.filters.base import step_inputs as step_inputs
from gmjax.filters.ckf import build_ckf as build_ckf
from gmjax.filters.ckf import local_ckf as local_ckf
from gmjax.filters.ekf import build_ekf as build_ekf
from gmjax.filters.ekf import local_ekf as local_ekf
from gmjax.filters.ghkf import build_ghkf as build_ghkf
from gmjax.filters.ghkf import local_ghkf as local_ghkf
from gmjax.filters.gsf import GSFParams as GSFParams
from gmjax.filters.gsf import GSFState as GSFState
from gmjax.filters.gsf import build_gsf as build_gsf
from gmjax.filters.imm import IMMGSFParams as IMMGSFParams
from gmjax.filters.imm import IMMGSFState as IMMGSFState
from gmjax.filters.imm import IMMParams as IMMParams
from gmjax.filters.imm import IMMState as IMMState
from gmjax.filters.imm import build_imm as build_imm
from gmjax.filters.imm import build_imm_gsf as build_imm_gsf
from gmjax.filters.kf import LinearGaussianParams as LinearGaussianParams
from gmjax.filters.kf import build_kf as build_kf
from gmjax.filters.kf import kalman_filter as kalman_filter
from gmjax.filters.kf import local_kf as local_kf
from gmjax.filters.pf import PFParams as PFParams
from gmjax.filters.pf import PFState as PFState
from gmjax.filters.pf import build_pf as build_pf
from gmjax.filters.sckf import build_sckf as build_sckf
from gmjax.filters.sckf import local_sckf as local_sckf
from gmjax.filters.sckf import tria as tria
from gmjax.filters.sgkf import build_sgkf as build_sgkf
from gmjax.filters.sgkf import local_sgkf as local_sgkf
from gmjax.filters.smoother import gaussian_sum_smoother as gaussian_sum_smoother
from gmjax.filters.smoother import rts_linear as rts_linear
from gmjax.filters.smoother import rts_smoother as rts_smoother
from gmjax.filters.ukf import build_ukf as build_ukf
from gmjax.filters.ukf import local_ukf as local_ukf

__all__ = [
    "Filter",
    "StepFlags",
    "StepInfo",
    "StepInputs",
    "step_inputs",
    "LinearGaussianParams",
    "kalman_filter",
    "GaussianState",
    "LocalFilter",
    "SqrtState",
    "UpdateInfo",
    "from_local",
    "run",
    "local_kf",
    "local_ekf",
    "local_sigma",
    "local_ukf",
    "local_ckf",
    "local_ghkf",
    "local_sgkf",
    "local_sckf",
    "build_kf",
    "build_ekf",
    "build_sigma",
    "build_ukf",
    "build_ckf",
    "build_ghkf",
    "build_sgkf",
    "build_sckf",
    "tria",
    "imm",
    "pf",
    "IMMParams",
    "IMMState",
    "build_imm",
    "PFParams",
    "PFState",
    "build_pf",
    "gsf",
    "GSFParams",
    "GSFState",
    "build_gsf",
    "IMMGSFParams",
    "IMMGSFState",
    "build_imm_gsf",
    "bank",
    "BANK_METHODS",
    "BankParams",
    "BankState",
    "build_bank",
    "agsf",
    "AGSFConfig",
    "AGSFParams",
    "AGSFState",
    "Step6Merge",
    "Step6State",
    "build_agsf",
    "build_gsckf",
    "build_gsukf",
    "degree_of_nonlinearity",
    "smoother",
    "rts_smoother",
    "rts_linear",
    "gaussian_sum_smoother",
]
