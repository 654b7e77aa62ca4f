"""Simple action sources for data collection and validation sets."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase


class OffsetNoisePolicy(TensorDictModuleBase):
    """Actions = clip(offset + noise · U(−1, 1)) with a fixed per-episode ``offset``.

    A larger offset makes a trajectory less like uniform-random data; drawing a new offset per
    episode gives validation sets that cover more of the state-action space.

    Args:
        offset: ``[M]`` action offset, or ``[B, M]``: one per row of a batch of ``B`` envs.

    Keyword Args:
        noise: half-width of the uniform noise.
        low, high: action bounds.
        generator: torch generator for the noise.

    Examples:
        >>> policy = OffsetNoisePolicy(torch.full((3,), 0.5), noise=0.1)
        >>> from tensordict import TensorDict
        >>> bool((policy(TensorDict({}, []))["action"] >= 0.4).all())
        True
    """

    out_keys = ["action"]

    def __init__(
        self,
        offset: torch.Tensor,
        *,
        noise: float = 0.5,
        low: float = -1.0,
        high: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.in_keys = []
        self.offset, self.noise, self.low, self.high, self.generator = (
            offset,
            noise,
            low,
            high,
            generator,
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = (*tensordict.batch_size, self.offset.shape[-1])
        noise = torch.rand(shape, generator=self.generator) * 2 - 1
        return tensordict.set(
            "action", (self.offset + self.noise * noise).clamp(self.low, self.high)
        )
