"""Padded training sequences: episodes shorter than a slice, started at rest, their padding masked."""

from __future__ import annotations

import inspect
from typing import Any

import torch

from torchrl_recon.modules.checks import in_graph


def check_prefix_mask(mask: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """``mask`` ``[*B, L]`` as bool, checked: the sequences' shape ``[*B, L]`` and each row a run of
    real steps (True) then padding (False), as TorchRL's ``SliceSampler(pad_output=True)`` writes.

    Examples:
        >>> check_prefix_mask(torch.tensor([[1, 1, 0]]), torch.Size([1, 3])).tolist()
        [[True, True, False]]
    """
    if mask.shape != shape:
        raise ValueError(
            f"mask has shape {tuple(mask.shape)}; expected {tuple(shape)}, the sequences' "
            "batch and time dims."
        )
    mask = mask.bool()
    if in_graph():  # a host read would cut the graph or fail the capture: eager steps check it
        return mask
    if bool((mask[..., 1:] & ~mask[..., :-1]).any()):
        raise ValueError(
            "mask has a real step after a padded one; expected each row's real steps first, "
            "then its padding (SliceSampler(pad_output=True)'s layout)."
        )
    if not bool(mask[..., 0].all()):
        raise ValueError("mask has a row without a real step; each sampled slice holds one.")
    return mask


def start_at_rest(
    mask: torch.Tensor,
    steps: int,
    *sequences: torch.Tensor,
    rest: dict[int, torch.Tensor | float] | None = None,
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Shift each row with fewer than ``steps`` real steps right, so that ``steps`` slots end at
    its last real step; the slots before the episode's start hold its first step (at rest).

    A row of ``mask`` ``[*B, L]`` (real steps first, then padding) with n < ``steps`` real
    steps is a whole episode from its start (a ``SliceSampler`` slice of an episode shorter
    than the slice), so ``steps − n`` slots are put before it, each a copy of its first step:
    the convention :class:`~torchrl_recon.policies.MPCPolicy` (``warmup="plan"``) plans an
    episode's start with. The padding at the row's end is dropped first (a row keeps its length
    L, so ``steps <= L``). ``rest`` replaces those slots of some sequences by a value: index in
    ``sequences`` → value (e.g. ``{1: 0.0}``: the rest action). Rows with ``steps`` real steps
    or more are left as they are.

    Args:
        mask: ``[*B, L]`` bool, True at real steps.
        steps: the slots each row needs up to its last real step (a context and one target).
        sequences: tensors ``[*B, L, D]`` to shift alike.

    Keyword Args:
        rest: the value of the slots before the start, per sequence (default: its first step).

    Returns:
        The shifted mask (False before the start and at the padding) and the shifted sequences.

    Examples:
        >>> x = torch.arange(1.0, 6.0).view(1, 5, 1)
        >>> mask = torch.tensor([[True, True, False, False, False]])
        >>> new_mask, (y, a) = start_at_rest(mask, 4, x, x, rest={1: 0.0})
        >>> y.flatten().tolist(), a.flatten().tolist(), new_mask.int().tolist()
        ([1.0, 1.0, 1.0, 2.0, 3.0], [0.0, 0.0, 1.0, 2.0, 3.0], [[0, 0, 1, 1, 0]])
    """
    length = mask.shape[-1]
    if not 1 <= steps <= length:
        raise ValueError(f"steps must be in [1, {length}] (the sequence length), got {steps}.")
    shift = (steps - mask.sum(-1, keepdim=True)).clamp(min=0)  # [*B, 1]
    t = torch.arange(length, device=mask.device)
    source = (t - shift).clamp(min=0)  # [*B, L]: the step each slot shows
    before = t < shift
    shifted_mask = mask.gather(-1, source) & ~before
    out = []
    for i, x in enumerate(sequences):
        y = x.gather(-2, source[..., None].expand(*source.shape, x.shape[-1]))
        if rest is not None and i in rest:
            value = rest[i]  # a number stays on the host: no copy to y's device
            y = torch.where(before[..., None], value.to(y) if torch.is_tensor(value) else value, y)
        out.append(y)
    return shifted_mask, out


def masked_mean(values: torch.Tensor, mask: torch.Tensor, dims: int) -> torch.Tensor:
    """The mean of ``values`` where ``mask`` is True over the last ``dims`` dims; values
    elsewhere count in neither the sum nor the count (not even a NaN); 0 where nothing is True.

    ``mask`` broadcasts against ``values`` (e.g. ``[B, L, 1]`` against ``[B, L, N]``).

    Examples:
        >>> masked_mean(torch.tensor([[1.0, 3.0, float("nan")]]), torch.tensor([[1, 1, 0]]).bool(), 2)
        tensor(2.)
    """
    mask = mask.expand_as(values)
    kept = torch.where(mask, values, values.new_zeros(()))
    lead = values.shape[: values.dim() - dims]
    count = mask.reshape(*lead, -1).sum(-1).clamp(min=1)
    return kept.reshape(*lead, -1).sum(-1) / count


def windows_at_rest(
    obs: torch.Tensor, action: torch.Tensor, mask: torch.Tensor, window: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Padded sequences ``[*B, L, N]``, ``[*B, L, M]`` (``mask`` ``[*B, L]``) made ready for an
    estimator's windows: each row with fewer than ``window`` real steps started at rest (its
    first observation and the zero action, see :func:`start_at_rest`), and the mask
    ``[*B, L - window + 1]`` of the windows that end at a real step (the only ones to count).

    Examples:
        >>> obs, action = torch.randn(2, 6, 3), torch.randn(2, 6, 1)
        >>> mask = torch.tensor([[True] * 6, [True] * 2 + [False] * 4])
        >>> obs, action, valid = windows_at_rest(obs, action, mask, 4)
        >>> valid.int().tolist()
        [[1, 1, 1], [1, 0, 0]]
    """
    mask = check_prefix_mask(mask, obs.shape[:-1])
    mask, (obs, action) = start_at_rest(mask, window, obs, action, rest={1: 0.0})
    return obs, action, mask[..., window - 1 :]


def loss_takes_mask(estimator: Any) -> bool:
    """Whether an estimator (an instance or its class) trains on padded slices: its ``loss``
    takes a ``mask`` of real steps.

    Examples:
        >>> from torchrl_recon.modules import EnsembleUncertainty, ReconstructionUncertainty
        >>> loss_takes_mask(ReconstructionUncertainty), loss_takes_mask(EnsembleUncertainty)
        (True, False)
    """
    return "mask" in inspect.signature(estimator.loss).parameters
