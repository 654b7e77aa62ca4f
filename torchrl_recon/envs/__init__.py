"""Environments of the paper (gymnasium) and the factory that wraps them for TorchRL."""

from __future__ import annotations

from torchrl_recon.envs.dmc import DMCEntry
from torchrl_recon.envs.entry_checks import entry_errors
from torchrl_recon.envs.factory import make_env
from torchrl_recon.envs.registry import (
    ENVS,
    LEARNED,
    EnvEntry,
    GymEntry,
    get_entry,
    gym_entry,
    import_cost,
    register_env,
    register_envs,
)
from torchrl_recon.envs.threads import close_env, closing_env, keep_num_threads

__all__ = [
    "ENVS",
    "LEARNED",
    "DMCEntry",
    "EnvEntry",
    "GymEntry",
    "get_entry",
    "gym_entry",
    "close_env",
    "closing_env",
    "entry_errors",
    "import_cost",
    "keep_num_threads",
    "make_env",
    "register_env",
    "register_envs",
]
