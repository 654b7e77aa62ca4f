"""Evaluation of world models and uncertainty estimates on real trajectories."""

from __future__ import annotations

from torchrl_recon.evaluation.prediction import multi_step_errors

__all__ = ["multi_step_errors"]
