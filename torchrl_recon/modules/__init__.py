"""Learnable modules: the LSTM world model and the uncertainty estimators."""

from __future__ import annotations

from torchrl_recon.modules.baselines import LinearDeltaModel
from torchrl_recon.modules.device import module_device, module_dtype
from torchrl_recon.modules.ensemble import EnsembleUncertainty
from torchrl_recon.modules.estimators import ESTIMATORS, get_estimator_class, make_estimator
from torchrl_recon.modules.fitted import FittedCheck, check_fitted, unfitted_normalizers
from torchrl_recon.modules.mc_dropout import MCDropoutUncertainty
from torchrl_recon.modules.normalization import Normalizer
from torchrl_recon.modules.population import ReconstructionPopulation, WorldModelPopulation
from torchrl_recon.modules.reconstruction import ReconstructionUncertainty
from torchrl_recon.modules.reward_model import LearnedCost, LearnedTermination, RewardModel
from torchrl_recon.modules.rnd import RNDUncertainty
from torchrl_recon.modules.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.modules.world_model_ensemble import WorldModelEnsembleUncertainty

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
