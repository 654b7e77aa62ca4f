"""What a fit trains, as R members (one model: R = 1): the module, its losses ``[R]``, the
members' buffers and their sampling streams (:class:`FitData`)."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.objectives import LossModule

from torchrl_recon.data.buffers import MASK_KEY
from torchrl_recon.estimators.population import ReconstructionPopulation
from torchrl_recon.estimators.reconstruction import ReconstructionUncertainty
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss, as_sequences

Batches = list[TensorDictBase] | TensorDictBase
"""R members' batches: a list of R flat batches, or one ``[R, B·L]`` batch (shared sampling)."""


def loss_value(loss_module: LossModule, batch: TensorDictBase) -> torch.Tensor:
    """The sum of ``loss_module``'s ``loss*`` entries on ``batch``."""
    out = loss_module(batch)
    return sum(v for k, v in out.items() if k.startswith("loss"))


def one_member(loss_module: LossModule) -> Callable[[Batches], torch.Tensor]:
    """``losses(batches) -> [1]``: one model's loss as the losses of R = 1 members.

    Examples:
        >>> from tensordict import TensorDict
        >>> class Half(torch.nn.Module):
        ...     def forward(self, td):
        ...         return TensorDict(loss_x=td["x"].mean() / 2)
        >>> one_member(Half())([TensorDict(x=torch.ones(4), batch_size=[4])])
        tensor([0.5000])
    """
    return lambda batches: loss_value(loss_module, batches[0]).reshape(1)


class ProcessRNG:
    """One model's sampling: ``torch.manual_seed(seed)`` now, then every batch drawn from the
    process's own RNG (what :func:`~torchrl_recon.fitting.train_loss_module` has always done:
    the process's RNG after a fit is where its draws left it)."""

    def __init__(self, seed: int) -> None:
        torch.manual_seed(seed)

    def sample(self, r: int, buffer: TensorDictReplayBuffer, device: torch.device):
        return buffer.sample().to(device)


class MemberRNG:
    """One global-RNG stream per member: member r samples as if ``torch.manual_seed(seeds[r])`` ran first."""

    def __init__(self, seeds: list[int]) -> None:
        self.states = [torch.Generator().manual_seed(int(s)).get_state() for s in seeds]

    def sample(self, r: int, buffer: TensorDictReplayBuffer, device: torch.device):
        with torch.random.fork_rng(devices=[]):
            torch.set_rng_state(self.states[r])
            batch = buffer.sample()
            self.states[r] = torch.get_rng_state()
        return batch.to(device)


@dataclass
class FitData:
    """What a fit trains: ``module`` (whose parameters Adam updates), ``losses_of(batches)``
    (the members' losses ``[R]``), one training buffer and one validation source per member,
    their sampling (``rng``), and ``data_keys``, the entries the losses read (None: every one),
    checked for NaN when a step fails. ``shared_sampling``: see
    :func:`~torchrl_recon.fitting.fit_population`."""

    module: nn.Module
    losses_of: Callable[[Batches], torch.Tensor]
    buffers: list[TensorDictReplayBuffer]
    val_sources: list[TensorDictReplayBuffer]
    rng: ProcessRNG | MemberRNG
    data_keys: Sequence | None = None
    shared_sampling: bool = False
    batches: list = field(default_factory=list)

    @property
    def count(self) -> int:
        """R, the number of members (1: one model, without a member dim)."""
        return len(self.buffers)

    def validation(self, batches: int, device: torch.device) -> list[list[TensorDictBase]]:
        """``batches`` validation batches per member, drawn once (before any training batch)."""
        return [
            [self.rng.sample(r, self.val_sources[r], device) for _ in range(batches)]
            for r in range(self.count)
        ]

    def sample(self, active: list[bool], device: torch.device) -> Batches:
        """The active members' next training batches; a stopped member's batch stays (it is
        frozen anyway)."""
        if self.shared_sampling and self.count > 1:
            return sample_shared(self.rng, self.buffers, active, device)
        if not self.batches:
            self.batches = [None] * self.count
        for r in range(self.count):
            if active[r]:
                self.batches[r] = self.rng.sample(r, self.buffers[r], device)
        return self.batches


def sample_shared(
    rng: MemberRNG, buffers: list, active: list[bool], device: torch.device
) -> TensorDictBase:
    """One sample per buffer for all its active members (``fit_population(shared_sampling=True)``),
    as one ``[R, batch_size]`` batch: member r's rows are its slice of its buffer's sample. A
    stopped member (frozen, its loss unused) gets the first active member's rows."""
    groups: dict[int, list[int]] = {}
    for r, buffer in enumerate(buffers):
        if active[r]:
            groups.setdefault(id(buffer), []).append(r)
    parts, order = [], []
    for members in groups.values():
        first, buffer = members[0], buffers[members[0]]
        size = buffer.batch_size
        with torch.random.fork_rng(devices=[]), warnings.catch_warnings():
            # TorchRL warns that the size differs from the buffer's: it is meant to.
            warnings.filterwarnings("ignore", message="Got conflicting batch_sizes")
            torch.set_rng_state(rng.states[first])
            batch = buffer.sample(size * len(members))
            rng.states[first] = torch.get_rng_state()
        parts.append(batch.reshape(len(members), size))
        order += members
    fill_masks(parts)
    rows = torch.cat(parts, 0) if len(parts) > 1 else parts[0]
    if order != list(range(len(buffers))):  # members out of order, or stopped ones
        block = dict(zip(order, range(len(order)), strict=True))
        rows = rows[torch.tensor([block.get(r, 0) for r in range(len(buffers))])]
    return rows.to(device)


def fill_masks(batches: list[TensorDictBase]) -> None:
    """Give the batches without a mask of real steps an all-True one when another has one (a
    padded buffer's samples carry :data:`MASK_KEY`, a plain buffer's do not), so they stack."""
    if len(batches) < 2 or all(b.get(MASK_KEY, None) is None for b in batches):
        return
    for b in batches:
        if b.get(MASK_KEY, None) is None:
            b.set(MASK_KEY, torch.ones(b.shape, dtype=torch.bool, device=b.device))


GRAPH_KEYS = ("observation", "action", ("next", "observation"), MASK_KEY)
"""What a population's training loss reads from a batch (a captured step's static inputs)."""


def graph_inputs(batches: Batches) -> TensorDictBase:
    """The members' batches as one ``[R, B·L]`` tensordict of :data:`GRAPH_KEYS` (the layout of
    a shared sample, which the population losses read alike): a captured step's inputs."""
    if isinstance(batches, TensorDictBase):
        return batches.select(*GRAPH_KEYS, strict=False)
    fill_masks(batches)
    return torch.stack([b.select(*GRAPH_KEYS, strict=False) for b in batches])


def member_sequences(batches: Batches, slice_len: int, keys: tuple) -> list[torch.Tensor]:
    """``keys`` of R members' batches as ``[R, B, L, ...]``: from a list of R flat batches, or
    one ``[R, B·L]`` batch (shared sampling)."""
    if isinstance(batches, TensorDictBase):
        members = batches.shape[0]
        seqs = as_sequences(batches.reshape(-1), slice_len)
        return [seqs.get(k).reshape(members, -1, *seqs.get(k).shape[1:]) for k in keys]
    seqs = [as_sequences(b, slice_len) for b in batches]
    return [torch.stack([s.get(k) for s in seqs]) for k in keys]


def member_mask(batches: Batches, slice_len: int) -> torch.Tensor | None:
    """The members' masks of real steps ``[R, B, L]`` (padded buffers' samples), None when no
    batch carries one; a member's batch without one is all real steps."""
    if isinstance(batches, TensorDictBase):
        mask = batches.get(MASK_KEY, None)
        return None if mask is None else mask.reshape(batches.shape[0], -1, slice_len)
    if all(b.get(MASK_KEY, None) is None for b in batches):
        return None
    batches = [b.clone(False) for b in batches]
    fill_masks(batches)
    return member_sequences(batches, slice_len, (MASK_KEY,))[0]


def population_loss(
    models: list[nn.Module], mode: str, slice_len: int
) -> tuple[nn.Module, Callable[[Batches], torch.Tensor]]:
    """``(module, losses(batches) -> [R])`` for R models: the model's own loss for one, else a population's."""
    first = models[0]
    if len(models) == 1:
        if isinstance(first, LSTMWorldModel):
            loss_module = WorldModelPredictionLoss(first, mode=mode, slice_len=slice_len)
        else:
            loss_module = UncertaintyLoss(first, slice_len=slice_len)
        return loss_module, one_member(loss_module)
    if isinstance(first, LSTMWorldModel):
        pop = LSTMWorldModel.from_members(models)
        keys = ("observation", "action", ("next", "observation"))

        def losses(batches: Batches) -> torch.Tensor:
            obs, action, next_obs = member_sequences(batches, slice_len, keys)
            mask = member_mask(batches, slice_len)
            return pop.prediction_loss(obs, action, next_obs, mode, mask=mask)

        return pop, losses
    if isinstance(first, ReconstructionUncertainty):
        pop = ReconstructionPopulation.from_members(models)

        def losses(batches: Batches) -> torch.Tensor:
            obs, action = member_sequences(batches, slice_len, ("observation", "action"))
            return pop.loss(obs, action, mask=member_mask(batches, slice_len))

        return pop, losses
    raise TypeError(
        f"fit_population runs populations of LSTMWorldModel or ReconstructionUncertainty; got "
        f"{type(first).__name__} (fit those one at a time with fit_uncertainty)."
    )
