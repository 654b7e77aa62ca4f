"""Early stopping and best weights of a fit of R members (one model: R = 1), one small object."""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

from torchrl_recon.devices import module_device
from torchrl_recon.fitting.fit_graph import restore_frozen


class EarlyStopping:
    """Each member's best validation loss, its best weights, and its stop after ``patience``
    validations without improvement (None: never). ``module`` holds R members stacked on the
    first dim of every tensor of its state when ``count > 1``, else one model.

    A stopped member is frozen at its best weights: :meth:`restore_stopped` writes them back
    after each step (by a mask on the device, :attr:`frozen`, so that a captured step can do it
    without reading the host). The best weights of stacked members are kept in place, in
    tensors a captured step reads; one model's are a copy of its state dict.

    Examples:
        >>> layer = torch.nn.Linear(1, 1)
        >>> stop = EarlyStopping(layer, 1, patience=1)
        >>> stop.validated(0, 2.0), stop.validated(0, 3.0), stop.active
        (True, False, [False])
        >>> stop.best_loss
        [2.0]
    """

    def __init__(self, module: nn.Module, count: int, patience: int | None) -> None:
        self.module, self.count, self.patience = module, count, patience
        self.stacked = count > 1  # else: one plain model, no member dim
        self.best_loss = [math.inf] * count
        self.since_best, self.last_step = [0] * count, [0] * count
        self.active = [True] * count
        self.frozen = torch.zeros(count, dtype=torch.bool, device=module_device(module))
        if self.stacked:
            self.state = module.state_dict()
            self.best = {k: v.detach().clone() for k, v in self.state.items()}
        else:
            self.best = copy.deepcopy(module.state_dict())

    def ran(self, step: int) -> None:
        """Count ``step`` as the last step of every active member."""
        for r in range(self.count):
            if self.active[r]:
                self.last_step[r] = step

    def validated(self, r: int, val_loss: float) -> bool:
        """Member ``r``'s validation loss: True (and its weights kept) when it is its best
        yet; else one more without improvement, and the member stops at ``patience``."""
        if val_loss < self.best_loss[r]:
            self.best_loss[r], self.since_best[r] = val_loss, 0
            self._keep(r)
            return True
        self.since_best[r] += 1
        if self.patience is not None and self.since_best[r] >= self.patience:
            self.active[r] = False
            self.frozen[r] = True  # restored after each step from the next on
        return False

    def _keep(self, r: int) -> None:
        if not self.stacked:
            self.best = copy.deepcopy(self.module.state_dict())
            return
        for key, value in self.state.items():
            self.best[key][r].copy_(value[r])

    @torch.no_grad()
    def restore_all(self) -> None:
        """Every member back to its best weights."""
        if not self.stacked:
            self.module.load_state_dict(self.best)
            return
        for key, value in self.state.items():
            value.copy_(self.best[key])

    def restore_stopped(self, *, always: bool = False) -> None:
        """The stopped members back to their best weights (stacked members only). Read on the
        host, nothing to do while all are active; ``always``: by the mask alone, as a captured
        step must."""
        if self.stacked and (always or not all(self.active)):
            restore_frozen(self.state, self.best, self.frozen)
