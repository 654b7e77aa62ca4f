"""torchrl_recon: TorchRL components for reconstruction-uncertainty model-based control.

Importing the package registers the gymnasium environments
``torchrl_recon/IndustrialBenchmark-v0``, ``torchrl_recon/Drone-v0`` and
``torchrl_recon/Minitaur-v0``.
"""

from __future__ import annotations

from torchrl_recon.envs.registry import register_envs

__version__ = "0.1.0"

register_envs()

__all__ = ["__version__", "register_envs"]
