"""Learnable modules: the LSTM world model, the learned reward and termination, and the helpers
they share (normalisation, checks, fitted-state checks).

The uncertainty estimators live in :mod:`torchrl_recon.estimators`; this package still exports
their names (``from torchrl_recon.modules import ReconstructionUncertainty``), and
``module_device`` / ``module_dtype`` from ``torchrl_recon.devices``.
"""

from __future__ import annotations

from torchrl_recon.devices import module_device, module_dtype
from torchrl_recon.estimators.ensemble import EnsembleUncertainty
from torchrl_recon.estimators.mc_dropout import MCDropoutUncertainty
from torchrl_recon.estimators.population import ReconstructionPopulation
from torchrl_recon.estimators.reconstruction import ReconstructionUncertainty
from torchrl_recon.estimators.registry import ESTIMATORS, get_estimator_class, make_estimator
from torchrl_recon.estimators.rnd import RNDUncertainty
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.estimators.world_model_ensemble import WorldModelEnsembleUncertainty
from torchrl_recon.modules.baselines import LinearDeltaModel
from torchrl_recon.modules.fitted import FittedCheck, check_fitted, unfitted_normalizers
from torchrl_recon.modules.normalization import Normalizer
from torchrl_recon.modules.reward_model import LearnedCost, LearnedTermination, RewardModel
from torchrl_recon.modules.world_model import LSTMWorldModel, WorldModelPopulation

__all__ = [
    "check_fitted",
    "EnsembleUncertainty",
    "ESTIMATORS",
    "FittedCheck",
    "LearnedCost",
    "LearnedTermination",
    "LinearDeltaModel",
    "LSTMWorldModel",
    "get_estimator_class",
    "make_estimator",
    "MCDropoutUncertainty",
    "module_device",
    "module_dtype",
    "Normalizer",
    "ReconstructionPopulation",
    "ReconstructionUncertainty",
    "RewardModel",
    "RNDUncertainty",
    "UncertaintyEstimator",
    "unfitted_normalizers",
    "WorldModelEnsembleUncertainty",
    "WorldModelPopulation",
]
