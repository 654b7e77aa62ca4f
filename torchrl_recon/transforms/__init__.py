"""TorchRL transforms: the paper's uncertainty on any TorchRL env, a model-based one above all."""

from __future__ import annotations

from torchrl_recon.transforms.uncertainty_penalty import UncertaintyPenalty

__all__ = ["UncertaintyPenalty"]
