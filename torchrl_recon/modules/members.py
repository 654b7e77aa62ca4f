"""A member dim: R modules of one kind held as one, their weights stacked ``[R, ...]`` by tensordict.

:class:`StackedMembers` is the plumbing a module with a ``num_members`` option shares: the
members' parameters and buffers are stacked by :meth:`tensordict.TensorDict.from_modules` and
keep the member's names (a world model's ``lstm.weight_ih_l0`` becomes ``[R, 4·hid, N + M]``),
so a member goes in and out with :meth:`~tensordict.TensorDictBase.update_` on
:meth:`~tensordict.TensorDict.from_module`. Members are independent: each one's outputs and
gradients depend on its own weights and inputs only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from torchrl_recon.devices import module_device


def _holder(params: TensorDictBase) -> nn.Module:
    """A plain module holding ``params``' leaves as its parameters and buffers, nested as the keys.

    Stacked weights are held, not run: their first dim is the members', so the member's own
    layers (``nn.LSTM``, ``nn.Linear``) would misread them.
    """
    holder = nn.Module()
    for key, value in params.items():
        if isinstance(value, TensorDictBase):
            holder.add_module(key, _holder(value))
        elif isinstance(value, nn.Parameter):
            holder.register_parameter(key, value)
        else:
            holder.register_buffer(key, value)
    return holder


def _renamed_member_keys(module: nn.Module, state_dict: dict, prefix: str, *_) -> None:
    """``load_state_dict`` pre-hook: stacked weights saved before the member dim was part of the
    member's own class are named ``lstm_weight_ih_l0``; they load as ``lstm.weight_ih_l0``."""
    if module.num_members is None:
        return
    for key, _ in (*module.named_parameters(), *module.named_buffers()):
        old = prefix + key.replace(".", "_")
        if prefix + key not in state_dict and old in state_dict:
            state_dict[prefix + key] = state_dict.pop(old)


class StackedMembers:
    """Mixin for a module whose weights may carry a leading member dim R (``num_members``).

    ``num_members`` is None for one model, else R: every parameter and buffer is the members'
    stacked ``[R, ...]``, and every input and output carries the member dim first. A subclass
    defines ``config()`` (with ``num_members`` when it is set) and calls :meth:`_hold` with its
    members; ``member_type`` is the class of one member (None: the class itself).
    """

    num_members: int | None
    member_type: ClassVar[type[nn.Module] | None] = None

    @classmethod
    def _member_class(cls) -> type[nn.Module]:
        return cls.member_type or cls

    def _register_member_hooks(self) -> None:
        """Let checkpoints with the former stacked names (``lstm_weight_ih_l0``) load."""
        self.register_load_state_dict_pre_hook(_renamed_member_keys)

    def _hold(self, members: Sequence[nn.Module]) -> None:
        """Stack ``members``' weights (``TensorDict.from_modules``) and hold them as this module's."""
        params = TensorDict.from_modules(*members)
        for name, part in params.items():
            setattr(self, name, _holder(part))
        self.num_members = len(members)
        self.in_keys, self.out_keys = list(members[0].in_keys), list(members[0].out_keys)

    def _member_config(self) -> dict:
        return {k: v for k, v in self.config().items() if k != "num_members"}

    @classmethod
    def from_members(cls, members: Sequence[nn.Module]):
        """One module holding copies of ``members``' weights (all of one config and device).

        Examples:
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> models = LSTMWorldModel.from_members([LSTMWorldModel(6, 3) for _ in range(4)])
            >>> models.num_members, models.lstm.weight_hh_l0.shape
            (4, torch.Size([4, 128, 32]))
        """
        members = list(members)
        kind = cls._member_class()
        if not members or not all(
            type(m) is kind and getattr(m, "num_members", None) is None for m in members
        ):
            raise ValueError(
                f"{cls.__name__}.from_members needs at least one single {kind.__name__}, "
                f"got {[type(m).__name__ for m in members]}."
            )
        configs = [m.config() for m in members]
        if any(c != configs[0] for c in configs):
            raise ValueError(f"All members must share one config; got {configs}.")
        with torch.device("meta"):  # no weights drawn: _hold replaces them
            stacked = cls(**configs[0], num_members=1)
        stacked._hold(members)
        return stacked

    def _stacked(self) -> TensorDictBase:
        """The stacked weights as a ``[R]`` TensorDict of this module's own tensors (no copies)."""
        if self.num_members is None:
            raise ValueError(f"This {type(self).__name__} is one model (num_members=None).")
        params = TensorDict.from_module(self)
        params.batch_size = torch.Size([self.num_members])
        return params

    def member(self, index: int) -> nn.Module:
        """A standalone copy of member ``index`` (one model, on this module's device)."""
        stacked = self._stacked()
        with torch.device("meta"):
            model = self._member_class()(**self._member_config())
        model = model.to_empty(device=module_device(self))
        with torch.no_grad():
            TensorDict.from_module(model).update_(stacked[index])
        model.in_keys, model.out_keys = list(self.in_keys), list(self.out_keys)
        return model

    def split(self) -> list[nn.Module]:
        """Every member as a standalone model; ``from_members(m.split())`` gives ``m`` back.

        Examples:
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> [m.num_members for m in LSTMWorldModel(6, 3, num_members=2).split()]
            [None, None]
        """
        return [self.member(i) for i in range(len(self._stacked()))]

    @torch.no_grad()
    def load_member(self, index: int, model: nn.Module) -> None:
        """Copy ``model``'s weights (one model of the members' config) into member ``index``."""
        stacked = self._stacked()
        if model.config() != self._member_config():
            raise ValueError(
                f"model config {model.config()} differs from the members' {self._member_config()}."
            )
        stacked[index].update_(TensorDict.from_module(model))

    def _members_first(self, name: str, x: torch.Tensor, min_ndim: int) -> None:
        """Raise unless ``x`` has the member dim first and at least ``min_ndim`` dims in all
        (nothing to check for one model)."""
        if self.num_members is None:
            return
        if x.dim() < min_ndim or x.shape[0] != self.num_members:
            raise ValueError(
                f"{name} has shape {tuple(x.shape)}; a population of {self.num_members} expects "
                f"the member dim first, [{self.num_members}, ...] with at least {min_ndim} dims."
            )

    def _bcast(self, stat: torch.Tensor, ndim: int) -> torch.Tensor:
        """A per-member ``[R, D]`` statistic viewed to broadcast against ``[R, ..., D]`` of ``ndim`` dims."""
        return stat.reshape(stat.shape[0], *([1] * (ndim - 2)), stat.shape[-1])
