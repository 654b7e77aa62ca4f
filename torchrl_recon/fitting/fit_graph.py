"""A population fit's training step as one CUDA graph (``fit_population(cuda_graph=True)``).

On a GPU a population fit's step is hundreds of small kernels (an LSTM rollout's forward and
hand-written backward per step of the slice, the members' clip, Adam over every tensor), each
launched from Python: the launches, not the arithmetic, set its time. Here the step (forward,
backward, per-member clip, ``capturable`` Adam, the stopped members' restore) is one callable
with no host synchronisation, run eagerly for its first :data:`WARMUP_STEPS` steps (on a side
stream, as CUDA graph capture requires), captured once with ``torch.cuda.graph`` and replayed
for every later step on static copies of the batches. The value checks that read a tensor on
the host are left out while capturing (:func:`~torchrl_recon.modules.checks.in_graph`);
the fit checks each step's losses after the replay and, on a non-finite one, runs the eager
loss on that batch to name a bad input, as a ``compile=True`` fit does.

tensordict's ``CudaGraphModule`` does the same capture, but building one removes TensorDict
from ``torch.utils._pytree``'s registry for the whole process, irreversibly (its constructor
calls ``_exclude_td_from_pytree().set()``): a fit should not change how the rest of a program
flattens tensordicts, so the few lines of PyTorch's own "whole network capture" recipe are here.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from torchrl_recon.modules.checks import check_flag

__all__ = ["WARMUP_STEPS", "CapturedStep", "capturable_adam", "check_cuda_graph", "restore_frozen"]

WARMUP_STEPS = 3
"""Eager steps before the capture, as PyTorch's whole-network capture example runs (the first
builds Adam's state; the later ones run as every replay will)."""


def check_cuda_graph(cuda_graph: object, device: torch.device, compile: bool) -> None:
    """Refuse ``cuda_graph`` unless it is a bool, and True only for a model on a CUDA device
    and without ``compile`` (one graph or the other).

    Examples:
        >>> check_cuda_graph(True, torch.device("cpu"), compile=False)
        Traceback (most recent call last):
        ...
        ValueError: cuda_graph=True captures the fit step as a CUDA graph: the models must be on a CUDA device, got cpu.
    """
    check_flag("cuda_graph", cuda_graph)
    if not cuda_graph:
        return
    if device.type != "cuda":
        raise ValueError(
            "cuda_graph=True captures the fit step as a CUDA graph: the models must be on a "
            f"CUDA device, got {device}."
        )
    if compile:
        raise ValueError("cuda_graph=True and compile=True are two ways to one end: pick one.")


def capturable_adam(params: list[torch.Tensor], lr: float, weight_decay: float) -> torch.optim.Adam:
    """Adam whose step can be captured in a CUDA graph: its learning rate a tensor on the
    parameters' device (a scheduler's ``step()`` writes it in place, so a replay reads the
    current one) and, on a CUDA device, ``capturable=True`` (its step counts on the device).

    Examples:
        >>> p = torch.nn.Parameter(torch.zeros(2))
        >>> capturable_adam([p], 1e-3, 0.0).param_groups[0]["lr"]
        tensor(0.0010)
    """
    device = params[0].device
    return torch.optim.Adam(
        params,
        lr=torch.tensor(lr, device=device),
        weight_decay=weight_decay,
        capturable=device.type == "cuda",
        foreach=device.type == "cuda",
    )


def restore_frozen(
    state: dict[str, torch.Tensor], best: dict[str, torch.Tensor], frozen: torch.Tensor
) -> None:
    """Write ``best[key][r]`` into ``state[key][r]`` for every member r where ``frozen[r]``,
    without reading ``frozen`` on the host (``torch.where``: the same values as an indexed copy).

    Examples:
        >>> state, best = {"w": torch.zeros(3, 2)}, {"w": torch.ones(3, 2)}
        >>> restore_frozen(state, best, torch.tensor([False, True, False]))
        >>> state["w"][:, 0].tolist()
        [0.0, 1.0, 0.0]
    """
    with torch.no_grad():
        for key, value in state.items():
            mask = frozen.reshape(-1, *([1] * (value.dim() - 1)))
            value.copy_(torch.where(mask, best[key], value))


class CapturedStep:
    """``step(inputs)``: eager for its first ``warmup`` calls, each on a side stream, then
    captured as one CUDA graph; every later call copies ``inputs`` into the captured copy
    (same keys and shapes) and replays it. ``step`` must not synchronise with the host, and
    its output is the tensor the graph writes (overwritten by the next call). Off CUDA it runs
    ``step`` eagerly on every call.

    Examples:
        >>> from tensordict import TensorDict
        >>> w = torch.nn.Parameter(torch.ones(2))
        >>> step = CapturedStep(lambda td: (td["x"] * w).sum().detach(), torch.device("cpu"))
        >>> float(step(TensorDict(x=torch.ones(2))))
        2.0
    """

    def __init__(
        self,
        step: Callable[[TensorDictBase], torch.Tensor],
        device: torch.device,
        warmup: int = WARMUP_STEPS,
    ) -> None:
        self.step, self.warmup, self.calls = step, warmup, 0
        self.stream = torch.cuda.Stream(device) if device.type == "cuda" else None
        self.graph: torch.cuda.CUDAGraph | None = None
        self.inputs: TensorDictBase | None = None
        self.output: torch.Tensor | None = None

    @property
    def replays(self) -> int:
        """How many calls replayed the graph."""
        return max(self.calls - self.warmup, 0) if self.graph is not None else 0

    def __call__(self, inputs: TensorDictBase) -> torch.Tensor:
        self.calls += 1
        if self.graph is not None:
            self.inputs.update_(inputs)
            self.graph.replay()
            return self.output
        if self.stream is None:
            return self.step(inputs)
        self.stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self.stream):
            out = self.step(inputs)
        torch.cuda.current_stream().wait_stream(self.stream)
        if self.calls == self.warmup:
            self._capture(inputs)
        return out

    def _capture(self, inputs: TensorDictBase) -> None:
        """Record ``step`` on a copy of ``inputs`` (recorded, not run: the eager call just ran)."""
        self.inputs = inputs.clone()
        graph = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(graph):
                self.output = self.step(self.inputs)
        except RuntimeError as err:  # an op the capture does not allow: name the way out
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise RuntimeError(
                f"cuda_graph=True: the fit step could not be captured as a CUDA graph ({first}); "
                "fit with cuda_graph=False."
            ) from err
        self.graph = graph
