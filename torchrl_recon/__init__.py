"""torchrl_recon: TorchRL components for reconstruction-uncertainty model-based control.

Importing the package registers the gymnasium environments
``torchrl_recon/IndustrialBenchmark-v0``, ``torchrl_recon/Drone-v0`` and
``torchrl_recon/Minitaur-v0``. The old paths of the modules that moved
(``torchrl_recon.timing`` to ``torchrl_recon.runs``, ``torchrl_recon.modules.reconstruction``
to ``torchrl_recon.estimators``, ``torchrl_recon.configs`` to ``torchrl_recon.trainers``, ...)
still import, with a ``DeprecationWarning``, for one release (``torchrl_recon.runs._moved``).
"""

from __future__ import annotations

from torchrl_recon.envs.registry import register_envs
from torchrl_recon.runs._moved import install as _install_moved

__version__ = "0.1.0"

register_envs()
_install_moved()

__all__ = ["__version__", "register_envs"]
