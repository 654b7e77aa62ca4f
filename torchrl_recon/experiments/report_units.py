"""The units the experiments report prediction errors in."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torchrl_recon.modules import Normalizer


def state_scale(data: TensorDictBase) -> torch.Tensor:
    """Per-dimension standard deviation of the observations (1 where constant): the unit of
    reported MSEs.

    Examples:
        >>> from tensordict import TensorDict
        >>> obs = torch.tensor([[0.0, 5.0], [2.0, 5.0]])
        >>> state_scale(TensorDict({"observation": obs}, [2])).shape
        torch.Size([2])
    """
    norm = Normalizer(data["observation"].shape[-1])
    norm.fit(data["observation"].cpu())
    return norm.scale.clone()
