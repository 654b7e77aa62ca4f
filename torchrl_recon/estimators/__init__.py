"""Uncertainty estimators: score how unfamiliar T-step windows of (s, a) are (paper eq. 2).

The interface (:class:`UncertaintyEstimator`), the paper's autoencoder
(:class:`ReconstructionUncertainty`) and its population, the baselines it is compared with
(ensembles, MC dropout, RND, an ensemble of world models), and the registry a recipe's
``estimator.kind`` is looked up in (:data:`ESTIMATORS`, :func:`make_estimator`).
``torchrl_recon.modules`` exports the same names.
"""

from __future__ import annotations

# torchrl_recon.modules first: it re-exports the estimators, so its __init__ imports this
# package's modules; loaded from here, it finds them not yet half-imported.
import torchrl_recon.modules  # noqa: F401  isort: skip
from torchrl_recon.estimators.ensemble import EnsembleUncertainty
from torchrl_recon.estimators.mc_dropout import MCDropoutUncertainty
from torchrl_recon.estimators.population import ReconstructionPopulation
from torchrl_recon.estimators.reconstruction import ReconstructionUncertainty
from torchrl_recon.estimators.registry import ESTIMATORS, get_estimator_class, make_estimator
from torchrl_recon.estimators.rnd import RNDUncertainty
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.estimators.world_model_ensemble import WorldModelEnsembleUncertainty

__all__ = [
    "EnsembleUncertainty",
    "ESTIMATORS",
    "get_estimator_class",
    "make_estimator",
    "MCDropoutUncertainty",
    "ReconstructionPopulation",
    "ReconstructionUncertainty",
    "RNDUncertainty",
    "UncertaintyEstimator",
    "WorldModelEnsembleUncertainty",
]
