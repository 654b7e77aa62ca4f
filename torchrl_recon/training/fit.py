"""Fit the world model and the uncertainty estimators from TorchRL replay buffers."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.objectives import LossModule
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_recon.data.buffers import buffer_contents
from torchrl_recon.modules.checks import check_int
from torchrl_recon.modules.device import module_device
from torchrl_recon.modules.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss
from torchrl_recon.training.checkpoint import save_checkpoint


@dataclass
class FitResult:
    """What :func:`train_loss_module` did: steps run, best validation loss, and the loss history."""

    steps: int
    best_val_loss: float
    history: list[dict] = field(default_factory=list)


def _loss_value(loss_module: LossModule, batch) -> torch.Tensor:
    out = loss_module(batch)
    return sum(v for k, v in out.items() if k.startswith("loss"))


@torch.no_grad()
def _evaluate(loss_module: LossModule, batches: list) -> float:
    return float(sum(_loss_value(loss_module, b) for b in batches) / len(batches))


def train_loss_module(
    loss_module: LossModule,
    buffer: TensorDictReplayBuffer,
    *,
    val_buffer: TensorDictReplayBuffer | None = None,
    steps: int = 2000,
    lr: float = 1e-3,
    lr_decay: bool = True,
    weight_decay: float = 0.0,
    clip_norm: float | None = 10.0,
    eval_every: int = 100,
    val_batches: int = 8,
    patience: int | None = 10,
    seed: int = 0,
    logger: Logger | None = None,
    log_prefix: str = "",
    progress: bool = True,
    checkpoint_path: str | Path | None = None,
    checkpoint_modules: dict[str, nn.Module] | None = None,
) -> FitResult:
    """Adam on ``loss_module`` with batches sampled from ``buffer``; early stopping on ``val_buffer``.

    The learning rate follows a cosine decay from ``lr`` to ``lr / 20`` over ``steps``
    (``lr_decay=False`` keeps it constant). The buffers may stay on the CPU: each sampled
    batch is moved to the device of ``loss_module``'s parameters.
    Every ``eval_every`` steps the validation loss (on ``val_batches`` batches drawn once,
    or on training batches when there is no ``val_buffer``) is measured; the best weights
    are kept, saved to ``checkpoint_path`` when given, and restored at the end. Training
    stops after ``patience`` evaluations without improvement. A non-finite loss restores
    the best weights and raises ``FloatingPointError`` (the saved checkpoint stays).

    Examples:
        >>> from torchrl_recon.data import make_sequence_buffer
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> from tensordict import TensorDict
        >>> rb = make_sequence_buffer(100, slice_len=5, num_slices=4)
        >>> _ = rb.extend(TensorDict({"observation": torch.randn(40, 2), "action": torch.randn(40, 1),
        ...     ("collector", "traj_ids"): torch.arange(40) // 20}, [40]))
        >>> ae = ReconstructionUncertainty(2, 1, window=5)
        >>> ae.fit_normalization(torch.randn(40, 2), torch.randn(40, 1))
        >>> result = train_loss_module(UncertaintyLoss(ae, slice_len=5), rb, steps=20, eval_every=10, progress=False)
        >>> result.steps
        20
    """
    for name, value in (("steps", steps), ("eval_every", eval_every), ("val_batches", val_batches)):
        check_int(name, value)
    if len(buffer) == 0:
        raise ValueError("The training replay buffer is empty; collect data before fitting.")
    torch.manual_seed(seed)
    params = [p for p in loss_module.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=lr, weight_decay=weight_decay)
    schedule = (
        torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps, eta_min=lr * 0.05)
        if lr_decay
        else None
    )
    val_source = val_buffer if val_buffer is not None and len(val_buffer) > 0 else buffer
    device = module_device(loss_module)  # the buffers' storage may stay on the CPU
    fixed_val = [val_source.sample().to(device) for _ in range(val_batches)]
    best_loss, best_state, since_best = math.inf, copy.deepcopy(loss_module.state_dict()), 0
    history: list[dict] = []
    bar = tqdm(
        range(1, steps + 1), desc=log_prefix.rstrip("/") or "fit", disable=not progress, leave=False
    )
    step = 0
    for step in bar:
        try:
            loss = _loss_value(loss_module, buffer.sample().to(device))
        except FloatingPointError as err:
            loss_module.load_state_dict(best_state)
            where = f"; the last good checkpoint is {checkpoint_path}" if checkpoint_path else ""
            raise FloatingPointError(f"Training stopped at step {step}: {err}{where}.") from err
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if clip_norm is not None:
            torch.nn.utils.clip_grad_norm_(params, clip_norm)
        optimizer.step()
        if schedule is not None:
            schedule.step()
        if step % eval_every == 0 or step == steps:
            val_loss = _evaluate(loss_module, fixed_val)
            record = {"step": step, "train_loss": float(loss.detach()), "val_loss": val_loss}
            history.append(record)
            bar.set_postfix(train=f"{record['train_loss']:.4g}", val=f"{val_loss:.4g}")
            if logger is not None:
                logger.log_scalar(f"{log_prefix}train_loss", record["train_loss"], step=step)
                logger.log_scalar(f"{log_prefix}val_loss", val_loss, step=step)
            if val_loss < best_loss:
                best_loss, since_best = val_loss, 0
                best_state = copy.deepcopy(loss_module.state_dict())
                if checkpoint_path is not None and checkpoint_modules:
                    save_checkpoint(
                        checkpoint_path,
                        checkpoint_modules,
                        extra={"step": step, "val_loss": val_loss},
                    )
            else:
                since_best += 1
                if patience is not None and since_best >= patience:
                    break
    loss_module.load_state_dict(best_state)
    return FitResult(steps=step, best_val_loss=best_loss, history=history)


def _slice_len(buffer: TensorDictReplayBuffer) -> int:
    slice_len = getattr(buffer.sampler, "slice_len", None)
    if slice_len is None:
        raise ValueError(
            "The buffer's sampler must be a SliceSampler with slice_len set (see make_sequence_buffer)."
        )
    return slice_len


def fit_world_model(
    model: LSTMWorldModel,
    buffer: TensorDictReplayBuffer,
    *,
    mode: str = "multi_step",
    fit_normalization: bool = True,
    **kwargs,
) -> FitResult:
    """Fit normalisation from ``buffer``'s contents, then train ``model`` (see :func:`train_loss_module`).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.data import make_sequence_buffer
        >>> rb = make_sequence_buffer(100, slice_len=8, num_slices=4)
        >>> obs = torch.randn(40, 3)
        >>> _ = rb.extend(TensorDict({"observation": obs, "action": torch.randn(40, 2),
        ...     ("next", "observation"): 0.9 * obs, ("collector", "traj_ids"): torch.arange(40) // 20}, [40]))
        >>> model = LSTMWorldModel(3, 2, window=4)
        >>> result = fit_world_model(model, rb, steps=10, eval_every=5, progress=False)
        >>> [h["step"] for h in result.history], bool(model.obs_norm.fitted)
        ([5, 10], True)
    """
    if fit_normalization:
        data = buffer_contents(buffer)
        model.fit_normalization(data["observation"], data["action"], data["next", "observation"])
    loss = WorldModelPredictionLoss(model, mode=mode, slice_len=_slice_len(buffer))
    kwargs.setdefault("log_prefix", "world_model/")
    kwargs.setdefault("checkpoint_modules", {"world_model": model})
    return train_loss_module(loss, buffer, **kwargs)


def fit_uncertainty(
    estimator: UncertaintyEstimator,
    buffer: TensorDictReplayBuffer,
    *,
    fit_normalization: bool = True,
    **kwargs,
) -> FitResult:
    """Fit normalisation from ``buffer``'s contents, then train ``estimator`` (see :func:`train_loss_module`).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.data import make_sequence_buffer
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> rb = make_sequence_buffer(100, slice_len=5, num_slices=4)
        >>> _ = rb.extend(TensorDict({"observation": torch.randn(40, 2), "action": torch.randn(40, 1),
        ...     ("collector", "traj_ids"): torch.arange(40) // 20}, [40]))
        >>> fit_uncertainty(ReconstructionUncertainty(2, 1, window=5), rb, steps=4, eval_every=2,
        ...                 progress=False).steps
        4
    """
    if fit_normalization:
        data = buffer_contents(buffer)
        estimator.fit_normalization(data["observation"], data["action"])
    loss = UncertaintyLoss(estimator, slice_len=_slice_len(buffer))
    kwargs.setdefault("log_prefix", "uncertainty/")
    kwargs.setdefault("checkpoint_modules", {"uncertainty": estimator})
    return train_loss_module(loss, buffer, **kwargs)
