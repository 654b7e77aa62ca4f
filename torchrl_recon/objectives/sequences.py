"""Turn replay-buffer samples into ``[B, L]`` sequences."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torchrl_recon.data.buffers import MASK_KEY
from torchrl_recon.modules.checks import check_int, check_type, in_graph


def as_sequences(tensordict: TensorDictBase, slice_len: int | None) -> TensorDictBase:
    """Return ``tensordict`` shaped ``[B, L]``.

    A 2-D batch is returned as it is; a flat ``[B * L]`` batch from a ``SliceSampler`` is
    reshaped with ``slice_len``.

    Examples:
        >>> from tensordict import TensorDict
        >>> as_sequences(TensorDict({"x": torch.arange(12)}, [12]), 4).batch_size
        torch.Size([3, 4])
    """
    if not in_graph():  # (a compiled or captured fit's graph: checked when eager)
        check_type("tensordict", tensordict, TensorDictBase, "a TensorDict of transitions")
        if slice_len is not None:
            check_int("slice_len", slice_len)
    if tensordict.batch_dims >= 2:
        return tensordict
    if slice_len is None:
        raise ValueError(
            f"Got a flat batch of shape {tuple(tensordict.batch_size)}; pass slice_len= to the loss "
            "(the SliceSampler's slice_len) or give a [B, L] tensordict."
        )
    if tensordict.batch_dims != 1 or tensordict.batch_size[0] % slice_len:
        raise ValueError(
            f"Batch of shape {tuple(tensordict.batch_size)} cannot be split into slices of {slice_len} steps."
        )
    return tensordict.reshape(-1, slice_len)


def sequence_mask(sequences: TensorDictBase) -> torch.Tensor | None:
    """The ``[B, L]`` mask of real steps of padded ``[B, L]`` sequences (``("collector", "mask")``,
    written by ``make_sequence_buffer(pad_short=True)``'s sampler), or None when they have none.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({("collector", "mask"): torch.tensor([True, True, True, False])}, [4])
        >>> sequence_mask(as_sequences(td, 2)).tolist()
        [[True, True], [True, False]]
    """
    mask = sequences.get(MASK_KEY, None)
    return None if mask is None else mask.reshape(sequences.batch_size)


def marked_slice_len(tensordict: TensorDictBase) -> int | None:
    """The slice length of a flat ``[B * L]`` batch from TorchRL's ``SliceSampler``, read from the
    marks it writes: ``("next", "truncated")`` at each slice's last step, else ``"is_init"`` at
    its first. None when the batch has neither, or its slices differ in length (then pass
    ``slice_len=``).

    Examples:
        >>> from tensordict import TensorDict
        >>> ends = torch.tensor([0, 0, 1, 0, 0, 1], dtype=torch.bool)[:, None]
        >>> marked_slice_len(TensorDict({("next", "truncated"): ends}, [6]))
        3
        >>> marked_slice_len(TensorDict({"x": torch.zeros(6)}, [6])) is None
        True
    """
    if tensordict.batch_dims != 1 or tensordict.numel() == 0:
        return None
    n = tensordict.batch_size[0]
    for key, at_end in ((("next", "truncated"), True), ("is_init", False)):
        marks = tensordict.get(key, None)
        if marks is None or marks.numel() != n:
            continue
        where = marks.reshape(n).nonzero().flatten()
        if where.numel() == 0:
            continue
        length = int(where[0]) + 1 if at_end else (int(where[1]) if where.numel() > 1 else n)
        if length > 0 and n % length == 0:
            expected = torch.arange(n // length, device=where.device) * length
            expected = expected + (length - 1 if at_end else 0)
            if where.numel() == n // length and bool((where == expected).all()):
                return length
    return None
