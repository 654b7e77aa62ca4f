"""A fit's training step, one interface for its three forms: eager, compiled and captured.

A step is two calls: ``losses(batches)``, the members' losses ``[R]``, which the fit checks,
then ``apply(losses)``: backward, each member's gradient clip, Adam, the stopped members'
restore and the learning-rate schedule. :class:`FitStep` runs the losses eagerly or under
``torch.compile`` and applies the update after the check; :class:`GraphStep` runs the whole
update inside its ``losses`` call, as one captured CUDA graph
(:class:`~torchrl_recon.fitting.CapturedStep`), so its update is applied before the check
(:attr:`~FitStep.applies_early`: a failed check restores the best weights first).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from torchrl_recon.fitting.early_stopping import EarlyStopping
from torchrl_recon.fitting.fit_data import Batches, graph_inputs

COMPILING = "torch.compile: the first step compiles"
"""What a compiled fit's progress bar says until its first step is done (on a CPU a cold
compile takes tens of seconds, with the bar at 0)."""


def clip_per_member(grads: list[torch.Tensor], members: int, max_norm: float) -> None:
    """``clip_grad_norm_`` applied to each member's slice ``[r]`` of every gradient on its own.

    Examples:
        >>> g = torch.tensor([[3.0, 4.0], [0.3, 0.4]])
        >>> clip_per_member([g], 2, 1.0)
        >>> torch.linalg.vector_norm(g, dim=1).round(decimals=4).tolist()
        [1.0, 0.5]
    """
    norms = torch.stack([torch.linalg.vector_norm(g.reshape(members, -1), dim=1) for g in grads])
    coef = (max_norm / (torch.linalg.vector_norm(norms, dim=0) + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.reshape(members, *([1] * (g.dim() - 1))))


class Update:
    """Backward of the members' summed losses, each member's gradient clipped to ``clip_norm``
    (None: no clip), ``optimizer``'s step, then the stopped members restored (``stopping``).

    Examples:
        >>> layer = torch.nn.Linear(1, 1, bias=False)
        >>> w = torch.nn.init.ones_(layer.weight)
        >>> update = Update([w], torch.optim.SGD([w], lr=0.5), None, EarlyStopping(layer, 1, None))
        >>> update((2 * w).reshape(1))
        >>> w.tolist()
        [[0.0]]
    """

    def __init__(
        self,
        params: list[torch.Tensor],
        optimizer: torch.optim.Optimizer,
        clip_norm: float | None,
        stopping: EarlyStopping,
    ) -> None:
        self.params, self.optimizer = params, optimizer
        self.clip_norm, self.stopping = clip_norm, stopping

    def __call__(self, losses: torch.Tensor, *, captured: bool = False) -> None:
        """``captured``: with no host read (the stopped members restored by their mask)."""
        self.optimizer.zero_grad(set_to_none=True)
        losses.sum().backward()
        self.clip()
        self.optimizer.step()
        self.stopping.restore_stopped(always=captured)

    def clip(self) -> None:
        """Clip the gradients: each member's on its own (stacked members), else all as one."""
        if self.clip_norm is None:
            return
        if self.stopping.stacked:
            grads = [p.grad for p in self.params if p.grad is not None]
            clip_per_member(grads, self.stopping.count, self.clip_norm)
        else:
            torch.nn.utils.clip_grad_norm_(self.params, self.clip_norm)


class FitStep:
    """The eager (or, with ``compile``, ``torch.compile``'d) step: ``losses(batches)`` runs
    ``losses_of`` (static shapes: every batch of a fit has one shape), ``apply(losses)`` the
    ``update`` and the ``schedule`` (None: a constant learning rate). ``skips_input_checks``:
    the losses run without the eager input checks (compiled, captured), so the fit runs the
    eager losses on a failed step's batch to name a bad input.

    Examples:
        >>> layer = torch.nn.Linear(1, 1, bias=False)
        >>> w = torch.nn.init.ones_(layer.weight)
        >>> update = Update([w], torch.optim.SGD([w], lr=0.5), None, EarlyStopping(layer, 1, None))
        >>> step = FitStep(lambda batches: (2 * w).reshape(1), update)
        >>> step.apply(step.losses([None]))
        >>> w.tolist(), step.applies_early
        ([[0.0]], False)
    """

    applies_early = False
    """Whether ``losses`` applies the update too (before the fit checks the losses)."""

    def __init__(
        self,
        losses_of: Callable[[Batches], torch.Tensor],
        update: Update,
        schedule: torch.optim.lr_scheduler.LRScheduler | None = None,
        *,
        compile: bool = False,
    ) -> None:
        self.skips_input_checks = compile
        self.train_losses = torch.compile(losses_of, dynamic=False) if compile else losses_of
        self.update, self.schedule = update, schedule

    def losses(self, batches: Batches) -> torch.Tensor:
        """The members' losses ``[R]`` on their ``batches``."""
        return self.train_losses(batches)

    def apply(self, losses: torch.Tensor) -> None:
        """The update from ``losses`` (checked), then the learning-rate schedule's step."""
        self.update(losses)
        self._scheduled()

    def _scheduled(self) -> None:
        if self.schedule is not None:
            self.schedule.step()


class GraphStep(FitStep):
    """The captured step: ``losses(batches)`` runs the losses and the whole update (without a
    host read) through ``capture(whole_step)``, a :class:`~torchrl_recon.fitting.CapturedStep`
    or a callable alike, on the batches as one tensordict; ``apply`` only steps the schedule.
    """

    applies_early = True

    def __init__(
        self,
        losses_of: Callable[[Batches], torch.Tensor],
        update: Update,
        schedule: torch.optim.lr_scheduler.LRScheduler | None,
        capture: Callable[[Callable[[TensorDictBase], torch.Tensor]], Callable],
    ) -> None:
        super().__init__(losses_of, update, schedule)
        self.skips_input_checks = True  # left out while captured, as compiled
        self.captured = capture(self._whole_step)

    def _whole_step(self, inputs: TensorDictBase) -> torch.Tensor:
        """Losses, backward, clip, Adam and the stopped members' restore, with no host sync."""
        step_losses = self.train_losses(inputs)
        self.update(step_losses, captured=True)
        return step_losses.detach()

    def losses(self, batches: Batches) -> torch.Tensor:
        return self.captured(graph_inputs(batches))

    def apply(self, losses: torch.Tensor) -> None:
        self._scheduled()
