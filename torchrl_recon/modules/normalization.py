"""Per-feature affine normalisation whose statistics live in the module's buffers."""

from __future__ import annotations

import torch
from torch import nn

from torchrl_recon.modules.checks import check_int, check_real


class Normalizer(nn.Module):
    """Standardise features with a fitted mean and standard deviation.

    The statistics are buffers, so they are saved in ``state_dict`` with the model that
    owns them (a checkpoint is self-contained). Features whose standard deviation is
    below ``min_scale`` (e.g. a constant setpoint) get a scale of 1.

    Args:
        num_features: size of the last dimension (an int >= 1).

    Keyword Args:
        min_scale: standard deviations below this are replaced by 1 (a finite number > 0).

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
        check_int("num_features", num_features)
        check_real("min_scale", min_scale, minimum=0, exclusive=True)
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

    @torch.no_grad()
    def statistics(self, data: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``(loc, scale)`` :meth:`fit` would set from ``data``, without setting them (on
        this normaliser's device and dtype).

        Examples:
            >>> Normalizer(1).statistics(torch.tensor([[1.0], [3.0]]))
            (tensor([2.]), tensor([1.4142]))
        """
        probe = Normalizer(self.num_features, min_scale=self.min_scale)
        probe.fit(data)
        return probe.loc.to(self.loc), probe.scale.to(self.scale)


def refit_inputs(
    weight: torch.Tensor,
    bias: torch.Tensor,
    old: tuple[torch.Tensor, torch.Tensor],
    new: tuple[torch.Tensor, torch.Tensor],
) -> None:
    """Rewrite in place a layer that reads standardised inputs (``weight`` ``[*R, out, F]``,
    ``bias`` ``[*R, out]``) so that, fed with the ``new`` statistics ``(loc, scale)``
    ``[*R, F]`` instead of the ``old``, it computes the same outputs from the same raw inputs.
    A feature the old statistics saw constant (scale exactly 1 and the new one not: a
    :class:`Normalizer` gives 1 where the data did not vary) gets zero weight instead: its
    weights were never trained, and scaled up by its new spread they would swamp the layer the
    moment the feature moves; the outputs on the data so far stay the same either way.

    Examples:
        >>> layer = torch.nn.Linear(2, 1)
        >>> old = (torch.tensor([1.0, 0.0]), torch.tensor([2.0, 1.0]))
        >>> new = (torch.tensor([0.0, 5.0]), torch.tensor([4.0, 3.0]))
        >>> x = torch.tensor([[3.0, 0.0]])  # feature 1 was constant (0) so far
        >>> before = layer((x - old[0]) / old[1])
        >>> refit_inputs(layer.weight.data, layer.bias.data, old, new)
        >>> torch.allclose(layer((x - new[0]) / new[1]), before), layer.weight[0, 1].item()
        (True, 0.0)
    """
    (old_loc, old_scale), (new_loc, new_scale) = old, new
    constant = ((old_scale == 1) & (new_scale != 1)).unsqueeze(-2)
    weight.masked_fill_(constant, 0.0)
    bias.add_((weight * ((new_loc - old_loc) / old_scale).unsqueeze(-2)).sum(-1))
    weight.mul_((new_scale / old_scale).unsqueeze(-2))


def refit_outputs(
    weight: torch.Tensor,
    bias: torch.Tensor,
    old: tuple[torch.Tensor, torch.Tensor],
    new: tuple[torch.Tensor, torch.Tensor],
) -> None:
    """Rewrite in place a layer whose outputs are standardised targets (``weight``
    ``[*R, D, in]``, ``bias`` ``[*R, D]``) so that, read back with the ``new`` statistics
    ``(loc, scale)`` ``[*R, D]`` instead of the ``old``, it gives the same targets in raw units.

    Examples:
        >>> layer = torch.nn.Linear(3, 2)
        >>> old = (torch.tensor([1.0, 0.0]), torch.tensor([2.0, 1.0]))
        >>> new = (torch.tensor([0.0, 5.0]), torch.tensor([4.0, 3.0]))
        >>> z = torch.randn(4, 3)
        >>> before = layer(z) * old[1] + old[0]
        >>> refit_outputs(layer.weight.data, layer.bias.data, old, new)
        >>> torch.allclose(layer(z) * new[1] + new[0], before, atol=1e-6)
        True
    """
    (old_loc, old_scale), (new_loc, new_scale) = old, new
    weight.mul_((old_scale / new_scale).unsqueeze(-1))
    bias.mul_(old_scale).add_(old_loc - new_loc).div_(new_scale)
