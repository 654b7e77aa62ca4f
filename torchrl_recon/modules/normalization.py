"""Per-feature affine normalisation whose statistics live in the module's buffers."""

from __future__ import annotations

import torch
from torch import nn


class Normalizer(nn.Module):
    """Standardise features with a fitted mean and standard deviation.

    The statistics are buffers, so they are saved in ``state_dict`` with the model that
    owns them (a checkpoint is self-contained). Features whose standard deviation is
    below ``min_scale`` (e.g. a constant setpoint) get a scale of 1.

    Args:
        num_features: size of the last dimension.

    Keyword Args:
        min_scale: standard deviations below this are replaced by 1.

    Examples:
        >>> norm = Normalizer(2)
        >>> norm.fit(torch.tensor([[0.0, 5.0], [2.0, 5.0], [4.0, 5.0]]))
        >>> norm.normalize(torch.tensor([[4.0, 5.0]]))
        tensor([[1., 0.]])
    """

    loc: torch.Tensor
    scale: torch.Tensor
    fitted: torch.Tensor

    def __init__(self, num_features: int, *, min_scale: float = 1e-6) -> None:
        super().__init__()
        self.num_features = num_features
        self.min_scale = min_scale
        self.register_buffer("loc", torch.zeros(num_features))
        self.register_buffer("scale", torch.ones(num_features))
        self.register_buffer("fitted", torch.tensor(False))

    @torch.no_grad()
    def fit(self, data: torch.Tensor) -> None:
        """Fit the statistics on ``data`` of shape ``[..., num_features]``."""
        if data.shape[-1] != self.num_features:
            raise ValueError(
                f"Normalizer expects last dim {self.num_features}, got data of shape {tuple(data.shape)}."
            )
        flat = data.reshape(-1, self.num_features).to(torch.float64)
        if flat.shape[0] < 2:
            raise ValueError(f"Normalizer needs at least 2 samples to fit, got {flat.shape[0]}.")
        if not torch.isfinite(flat).all():
            raise ValueError("Normalizer.fit got NaN or inf values; clean the data first.")
        std = flat.std(0)
        self.loc.copy_(flat.mean(0))
        self.scale.copy_(torch.where(std < self.min_scale, torch.ones_like(std), std))
        self.fitted.fill_(True)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Map raw values to standardised ones."""
        return (x - self.loc) / self.scale

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Map standardised values back to raw units."""
        return x * self.scale + self.loc
