"""Fit the world model and the uncertainty estimators from TorchRL replay buffers."""

from __future__ import annotations

import contextlib
import copy
import inspect
import math
import numbers
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import ReplayBuffer, TensorDictReplayBuffer
from torchrl.objectives import LossModule
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_recon.data.buffers import MASK_KEY, buffer_contents
from torchrl_recon.devices import check_compile_support
from torchrl_recon.modules.checks import check_finite_keys, check_int, check_real, check_type
from torchrl_recon.modules.device import module_device
from torchrl_recon.modules.members import StackedMembers
from torchrl_recon.modules.population import ReconstructionPopulation
from torchrl_recon.modules.reconstruction import ReconstructionUncertainty
from torchrl_recon.modules.reward_model import RewardModel
from torchrl_recon.modules.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.objectives import (
    RewardLoss,
    UncertaintyLoss,
    WorldModelPredictionLoss,
    as_sequences,
)
from torchrl_recon.training.checkpoint import save_checkpoint
from torchrl_recon.training.fit_graph import (
    CapturedStep,
    capturable_adam,
    check_cuda_graph,
    restore_frozen,
)


@dataclass
class FitResult:
    """What :func:`train_loss_module` did: steps run, best validation loss, and the loss history."""

    steps: int
    best_val_loss: float
    history: list[dict] = field(default_factory=list)


def _loss_value(loss_module: LossModule, batch) -> torch.Tensor:
    out = loss_module(batch)
    return sum(v for k, v in out.items() if k.startswith("loss"))


def _check_compile(compile: bool, module: nn.Module) -> None:
    """Refuse ``compile=True`` where torch.compile cannot build kernels for ``module``'s device,
    before the fit changes anything (its normalisation included)."""
    if compile:
        check_compile_support(module_device(module))


def _training_loss(fn: Callable[..., torch.Tensor], compile: bool) -> Callable[..., torch.Tensor]:
    """``fn`` for the training steps: itself, or with ``compile`` under ``torch.compile``
    (static shapes: every batch of a fit has one shape). Validation stays eager."""
    return torch.compile(fn, dynamic=False) if compile else fn


def _input_error(eager_fn: Callable[..., torch.Tensor], batch) -> ValueError | None:
    """After a compiled training step's non-finite loss: the ``ValueError`` the eager step's
    input checks (left out while compiled, see :func:`~torchrl_recon.modules.checks.check_finite`)
    raise on the same ``batch``, naming the input as an eager fit would; None where the inputs
    are finite (the loss itself diverged)."""
    try:
        with torch.no_grad():
            eager_fn(batch)
    except ValueError as err:
        return err
    except FloatingPointError:
        pass
    return None


WORLD_MODEL_KEYS: tuple = ("observation", "action", ("next", "observation"))
"""What a world model's fit reads of a transition."""
ESTIMATOR_KEYS: tuple = ("observation", "action")
"""What an uncertainty estimator's fit reads of a transition."""


def _checked_contents(buffer: TensorDictReplayBuffer, keys: Sequence) -> TensorDictBase:
    """``buffer``'s contents (:func:`~torchrl_recon.data.buffer_contents`) for a normalisation
    fit, refused with one line naming the first of ``keys`` that holds NaN or inf and its row."""
    data = buffer_contents(buffer)
    check_finite_keys(data, keys, where="the replay buffer")
    return data


def _loss_keys(loss_module: nn.Module) -> list | None:
    """The entries ``loss_module`` reads (its ``*_key`` attributes), or None (every one)."""
    keys = [
        getattr(loss_module, name)
        for name in ("obs_key", "action_key", "next_obs_key", "reward_key", "done_key")
        if getattr(loss_module, name, None) is not None
    ]
    return keys or None


def _data_error(batches: TensorDictBase | list, keys: Sequence | None) -> ValueError | None:
    """After a training step failed (a non-finite loss, an input check): the ``ValueError``
    naming the first of ``keys`` that holds NaN or inf in the sampled batch(es) and its buffer
    row (the sample's ``"index"``), or None when they are finite (the loss itself diverged)."""
    for batch in batches if isinstance(batches, list) else [batches]:
        if batch is None:
            continue
        try:
            check_finite_keys(batch, keys, where="the replay buffer", rows=batch.get("index", None))
        except ValueError as err:
            return err
    return None


def _stopped(step: int, err: BaseException, where: str = "") -> str:
    """``"Training stopped at step N: <err><where>."`` (one full stop)."""
    return f"Training stopped at step {step}: {str(err).rstrip('.')}{where}."


COMPILING = "torch.compile: the first step compiles"
"""What a compiled fit's progress bar says until its first step is done (on a CPU a cold
compile takes tens of seconds, with the bar at 0)."""


def _fit_bar(steps: int, log_prefix: str, progress: bool, compile: bool) -> tqdm:
    """The fit's progress bar over steps ``1..steps``; with ``compile`` it says so (see
    :data:`COMPILING`) until the caller clears it after the first step."""
    desc = log_prefix.rstrip("/") or "fit"
    bar = tqdm(range(1, steps + 1), desc=desc, disable=not progress, leave=False)
    if compile:
        bar.set_postfix_str(COMPILING)
    return bar


@torch.no_grad()
def _evaluate(loss_module: LossModule, batches: list) -> float:
    return float(sum(_loss_value(loss_module, b) for b in batches) / len(batches))


@contextlib.contextmanager
def _cached_boundaries(*buffers: TensorDictReplayBuffer | None) -> Iterator[None]:
    """Let each buffer's ``SliceSampler`` cache its trajectory boundaries while a fit samples it.

    Without ``cache_values`` a SliceSampler finds every trajectory's start and end anew for each
    batch, which costs more than the batch itself on a large buffer. TorchRL keys that cache by
    the storage's revision, so a buffer extended later is never sampled with stale boundaries;
    the samples are the same either way. The sampler's own setting is restored on exit.
    """
    saved = []
    for buffer in buffers:
        sampler = getattr(buffer, "sampler", None)
        if sampler is not None and hasattr(sampler, "cache_values"):
            saved.append((sampler, sampler.cache_values))
            sampler.cache_values = True
    try:
        yield
    finally:
        for sampler, value in saved:
            sampler.cache_values = value


def check_fit_settings(prefix: str = "", **settings: Any) -> None:
    """Refuse any given fit setting (``steps``, ``eval_every``, ``val_batches``, ``patience``,
    ``lr``, ``weight_decay``, ``clip_norm``) out of its range, in one line naming it as
    ``prefix`` + its name, before any work. Other keywords are left to their own checks.

    Examples:
        >>> check_fit_settings(steps=10, patience=0, lr=1e-3)
        Traceback (most recent call last):
        ...
        ValueError: patience must be an int >= 1, got 0.
        >>> check_fit_settings("uncertainty.", lr=-1.0)
        Traceback (most recent call last):
        ...
        ValueError: uncertainty.lr must be a finite number > 0, got -1.0.
    """
    for name in ("steps", "eval_every", "val_batches"):
        if name in settings:
            check_int(prefix + name, settings[name])
    if settings.get("patience") is not None:  # None: no early stopping
        check_int(prefix + "patience", settings["patience"])
    if "lr" in settings:
        check_real(prefix + "lr", settings["lr"], minimum=0, exclusive=True)
    if "weight_decay" in settings:
        check_real(prefix + "weight_decay", settings["weight_decay"], minimum=0)
    if settings.get("clip_norm") is not None:  # None: no clipping
        check_real(prefix + "clip_norm", settings["clip_norm"], minimum=0, exclusive=True)


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
    compile: bool = False,
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
    ``compile=True`` runs each training step's loss (forward and backward) under
    ``torch.compile``: the same fit up to float rounding, faster per step once compiled, at a
    compile of seconds to a minute per process and batch shape (figures in
    ``docs/benchmarks.md``); on the CPU it needs a C++ compiler.

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
    check_type("loss_module", loss_module, nn.Module, "a torchrl LossModule")
    _check_buffer("buffer", buffer)
    counts = dict(steps=steps, eval_every=eval_every, val_batches=val_batches, patience=patience)
    check_fit_settings(**counts, lr=lr, weight_decay=weight_decay, clip_norm=clip_norm)
    _check_seed(seed)
    _check_compile(compile, loss_module)
    if len(buffer) == 0:
        raise ValueError("The training replay buffer is empty; collect data before fitting.")
    with _cached_boundaries(buffer, val_buffer):
        return _train_loss_module(
            loss_module,
            buffer,
            val_buffer=val_buffer,
            steps=steps,
            lr=lr,
            lr_decay=lr_decay,
            weight_decay=weight_decay,
            clip_norm=clip_norm,
            eval_every=eval_every,
            val_batches=val_batches,
            patience=patience,
            seed=seed,
            logger=logger,
            log_prefix=log_prefix,
            progress=progress,
            checkpoint_path=checkpoint_path,
            checkpoint_modules=checkpoint_modules,
            compile=compile,
        )


def _train_loss_module(
    loss_module: LossModule,
    buffer: TensorDictReplayBuffer,
    *,
    val_buffer: TensorDictReplayBuffer | None,
    steps: int,
    lr: float,
    lr_decay: bool,
    weight_decay: float,
    clip_norm: float | None,
    eval_every: int,
    val_batches: int,
    patience: int | None,
    seed: int,
    logger: Logger | None,
    log_prefix: str,
    progress: bool,
    checkpoint_path: str | Path | None,
    checkpoint_modules: dict[str, nn.Module] | None,
    compile: bool,
) -> FitResult:
    """The loop of :func:`train_loss_module` (arguments checked)."""
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
    eager_loss = partial(_loss_value, loss_module)
    train_loss = _training_loss(eager_loss, compile)
    data_keys = _loss_keys(loss_module)
    fixed_val = [val_source.sample().to(device) for _ in range(val_batches)]
    best_loss, best_state, since_best = math.inf, copy.deepcopy(loss_module.state_dict()), 0
    history: list[dict] = []
    bar = _fit_bar(steps, log_prefix, progress, compile)
    step = 0
    for step in bar:
        batch = buffer.sample().to(device)
        try:
            loss = train_loss(batch)
        except (FloatingPointError, ValueError) as err:
            if (data := _data_error(batch, data_keys)) is not None:  # NaN or inf in the data
                loss_module.load_state_dict(best_state)
                raise ValueError(_stopped(step, data)) from err
            if isinstance(err, ValueError):
                raise
            if compile and (named := _input_error(eager_loss, batch)) is not None:
                raise named from None
            loss_module.load_state_dict(best_state)
            where = f"; the last good checkpoint is {checkpoint_path}" if checkpoint_path else ""
            raise FloatingPointError(_stopped(step, err, where)) from err
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if clip_norm is not None:
            torch.nn.utils.clip_grad_norm_(params, clip_norm)
        optimizer.step()
        if schedule is not None:
            schedule.step()
        if compile and step == 1:
            bar.set_postfix_str("")
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


def _check_seed(seed: object) -> None:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise TypeError(f"seed must be an int, got {seed!r}.")


def _check_buffer(name: str, buffer: object) -> None:
    """Refuse a ``buffer`` that is not a TorchRL replay buffer."""
    check_type(name, buffer, ReplayBuffer, "a torchrl replay buffer (make_sequence_buffer)")


def _check_train_keywords(kwargs: dict, module: nn.Module) -> None:
    """Check the keywords a fit hands on to :func:`train_loss_module` as it would (an unknown
    one included), before the fit does any work of its own (its normalisation)."""
    try:
        bound = inspect.signature(train_loss_module).bind(None, None, **kwargs)
    except TypeError as err:
        raise TypeError(f"{err}; the keywords are train_loss_module's.") from None
    bound.apply_defaults()
    given = bound.arguments
    check_fit_settings(**given)
    _check_seed(given["seed"])
    _check_compile(given["compile"], module)


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
    check_type("model", model, LSTMWorldModel, "an LSTMWorldModel")
    _check_buffer("buffer", buffer)
    if getattr(model, "num_members", None) is not None:
        raise ValueError(
            f"fit_world_model fits one model; this one has num_members={model.num_members} "
            "(fit members with fit_population(model.split(), ...))."
        )
    _check_train_keywords(kwargs, model)
    if fit_normalization:
        data = _checked_contents(buffer, WORLD_MODEL_KEYS)
        model.fit_normalization(data["observation"], data["action"], data["next", "observation"])
    loss = WorldModelPredictionLoss(model, mode=mode, slice_len=_slice_len(buffer))
    kwargs.setdefault("log_prefix", "world_model/")
    kwargs.setdefault("checkpoint_modules", {"world_model": model})
    return train_loss_module(loss, buffer, **kwargs)


def fit_world_members(
    model: LSTMWorldModel,
    buffer: TensorDictReplayBuffer,
    *,
    mode: str = "multi_step",
    fit_normalization: bool = True,
    seed: int = 0,
    val_buffer: TensorDictReplayBuffer | None = None,
    checkpoint_modules: dict[str, nn.Module] | None = None,
    **kwargs,
) -> FitResult:
    """:func:`fit_world_model` for a world model of R members (``num_members=R``): each member
    fits on ``buffer`` from its own weights, as :func:`fit_population` does (member r draws its
    batches with ``seed + r``, stops early on its own), and its best weights are loaded back.
    Returns one :class:`FitResult`: the most steps a member ran and the members' mean best
    validation loss. ``checkpoint_modules`` is accepted for :func:`fit_world_model`'s callers
    and must be empty (the members' best weights are kept in memory).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.data import make_sequence_buffer
        >>> rb = make_sequence_buffer(100, slice_len=8, num_slices=4)
        >>> obs = torch.randn(40, 3)
        >>> _ = rb.extend(TensorDict({"observation": obs, "action": torch.randn(40, 2),
        ...     ("next", "observation"): 0.9 * obs, ("collector", "traj_ids"): torch.arange(40) // 20}, [40]))
        >>> model = LSTMWorldModel(3, 2, window=4, num_members=3)
        >>> fit_world_members(model, rb, steps=10, eval_every=5, progress=False).steps
        10
    """
    if getattr(model, "num_members", None) is None:
        raise ValueError("fit_world_members fits a world model of members (num_members=R).")
    if checkpoint_modules:
        raise ValueError(
            "fit_world_members keeps the best weights in memory: no checkpoint_modules."
        )
    members = model.split()
    results = fit_population(
        members,
        buffer,
        seeds=[seed + r for r in range(len(members))],
        val_buffers=val_buffer,
        mode=mode,
        fit_normalization=fit_normalization,
        **kwargs,
    )
    for r, member in enumerate(members):
        model.load_member(r, member)
    losses = [r.best_val_loss for r in results]
    return FitResult(max(r.steps for r in results), sum(losses) / len(losses))


def world_model_fit(model: nn.Module) -> Callable[..., FitResult]:
    """The fit of ``model``: :func:`fit_world_members` for a world model of members
    (``num_members=R``), else :func:`fit_world_model` (both take the same keywords).

    Examples:
        >>> one, members = LSTMWorldModel(3, 2), LSTMWorldModel(3, 2, num_members=2)
        >>> world_model_fit(one).__name__, world_model_fit(members).__name__
        ('fit_world_model', 'fit_world_members')
    """
    return fit_world_model if getattr(model, "num_members", None) is None else fit_world_members


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
    check_type("estimator", estimator, UncertaintyEstimator, "an UncertaintyEstimator")
    _check_buffer("buffer", buffer)
    _check_train_keywords(kwargs, estimator)
    if fit_normalization:
        data = _checked_contents(buffer, ESTIMATOR_KEYS)
        estimator.fit_normalization(data["observation"], data["action"])
    loss = UncertaintyLoss(estimator, slice_len=_slice_len(buffer))
    kwargs.setdefault("log_prefix", "uncertainty/")
    kwargs.setdefault("checkpoint_modules", {"uncertainty": estimator})
    return train_loss_module(loss, buffer, **kwargs)


def fit_reward(
    reward_model: RewardModel,
    buffer: TensorDictReplayBuffer,
    *,
    fit_normalization: bool = True,
    **kwargs,
) -> FitResult:
    """Fit normalisation from ``buffer``'s contents (with ``fit_normalization``), then train a
    learned reward and termination (:class:`~torchrl_recon.objectives.RewardLoss`, see
    :func:`train_loss_module`). The buffer's samples must hold ``("next", "reward")`` (and
    ``("next", "terminated")`` where it learns the termination): with
    :func:`~torchrl_recon.data.sequence_buffers`, pass ``keys=REWARD_FIT_KEYS``.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.data import make_sequence_buffer
        >>> from torchrl_recon.modules import RewardModel
        >>> rb = make_sequence_buffer(100, slice_len=5, num_slices=4)
        >>> s = torch.randn(40, 2)
        >>> _ = rb.extend(TensorDict({"observation": s, "action": torch.randn(40, 1),
        ...     ("next", "observation"): s + 0.1, ("next", "reward"): s[:, :1],
        ...     ("next", "terminated"): s[:, :1] > 1,
        ...     ("collector", "traj_ids"): torch.arange(40) // 20}, [40]))
        >>> fit_reward(RewardModel(2, 1, termination=True), rb, steps=4, eval_every=2,
        ...            progress=False).steps
        4
    """
    check_type("reward_model", reward_model, RewardModel, "a RewardModel")
    _check_buffer("buffer", buffer)
    _check_train_keywords(kwargs, reward_model)
    if fit_normalization:
        data = _checked_contents(buffer, (*WORLD_MODEL_KEYS, ("next", "reward")))
        reward_model.fit_normalization(
            data["observation"], data["action"], data["next", "observation"], data["next", "reward"]
        )
    kwargs.setdefault("log_prefix", "reward/")
    kwargs.setdefault("checkpoint_modules", {"reward": reward_model})
    return train_loss_module(RewardLoss(reward_model), buffer, **kwargs)


# ---------------------------------------------------------------------------------------------
# Populations: R independent fits run as one batch


def _per_member(name: str, value, count: int, *, optional: bool = False) -> list:
    if value is None and optional:
        return [None] * count
    if isinstance(value, TensorDictReplayBuffer):
        return [value] * count
    value = list(value)
    if len(value) != count:
        raise ValueError(f"{name} has {len(value)} entries; expected one per member ({count}).")
    return value


class _MemberRNG:
    """One global-RNG stream per member: member r samples as if ``torch.manual_seed(seeds[r])`` ran first."""

    def __init__(self, seeds: list[int]) -> None:
        self.states = [torch.Generator().manual_seed(int(s)).get_state() for s in seeds]

    def sample(self, r: int, buffer: TensorDictReplayBuffer, device: torch.device):
        with torch.random.fork_rng(devices=[]):
            torch.set_rng_state(self.states[r])
            batch = buffer.sample()
            self.states[r] = torch.get_rng_state()
        return batch.to(device)


def _sample_shared(
    rng: _MemberRNG, buffers: list, active: list[bool], device: torch.device
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
    _fill_masks(parts)
    rows = torch.cat(parts, 0) if len(parts) > 1 else parts[0]
    if order != list(range(len(buffers))):  # members out of order, or stopped ones
        block = dict(zip(order, range(len(order)), strict=True))
        rows = rows[torch.tensor([block.get(r, 0) for r in range(len(buffers))])]
    return rows.to(device)


def _fill_masks(batches: list[TensorDictBase]) -> None:
    """Give the batches without a mask of real steps an all-True one when another has one (a
    padded buffer's samples carry :data:`MASK_KEY`, a plain buffer's do not), so they stack."""
    if len(batches) < 2 or all(b.get(MASK_KEY, None) is None for b in batches):
        return
    for b in batches:
        if b.get(MASK_KEY, None) is None:
            b.set(MASK_KEY, torch.ones(b.shape, dtype=torch.bool, device=b.device))


GRAPH_KEYS = ("observation", "action", ("next", "observation"), MASK_KEY)
"""What a population's training loss reads from a batch (a captured step's static inputs)."""


def _graph_inputs(batches: list[TensorDictBase] | TensorDictBase) -> TensorDictBase:
    """The members' batches as one ``[R, B·L]`` tensordict of :data:`GRAPH_KEYS` (the layout of
    a shared sample, which the population losses read alike): a captured step's inputs."""
    if isinstance(batches, TensorDictBase):
        return batches.select(*GRAPH_KEYS, strict=False)
    _fill_masks(batches)
    return torch.stack([b.select(*GRAPH_KEYS, strict=False) for b in batches])


def _clip_per_member(grads: list[torch.Tensor], members: int, max_norm: float) -> None:
    """``clip_grad_norm_`` applied to each member's slice ``[r]`` of every gradient on its own."""
    norms = torch.stack([torch.linalg.vector_norm(g.reshape(members, -1), dim=1) for g in grads])
    coef = (max_norm / (torch.linalg.vector_norm(norms, dim=0) + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.reshape(members, *([1] * (g.dim() - 1))))


def _member_sequences(
    batches: list[TensorDictBase] | TensorDictBase, slice_len: int, keys: tuple
) -> list[torch.Tensor]:
    """``keys`` of R members' batches as ``[R, B, L, ...]``: from a list of R flat batches, or
    one ``[R, B·L]`` batch (shared sampling)."""
    if isinstance(batches, TensorDictBase):
        members = batches.shape[0]
        seqs = as_sequences(batches.reshape(-1), slice_len)
        return [seqs.get(k).reshape(members, -1, *seqs.get(k).shape[1:]) for k in keys]
    seqs = [as_sequences(b, slice_len) for b in batches]
    return [torch.stack([s.get(k) for s in seqs]) for k in keys]


def _member_mask(
    batches: list[TensorDictBase] | TensorDictBase, slice_len: int
) -> torch.Tensor | None:
    """The members' masks of real steps ``[R, B, L]`` (padded buffers' samples), None when no
    batch carries one; a member's batch without one is all real steps."""
    if isinstance(batches, TensorDictBase):
        mask = batches.get(MASK_KEY, None)
        return None if mask is None else mask.reshape(batches.shape[0], -1, slice_len)
    if all(b.get(MASK_KEY, None) is None for b in batches):
        return None
    batches = [b.clone(False) for b in batches]
    _fill_masks(batches)
    return _member_sequences(batches, slice_len, (MASK_KEY,))[0]


def _population_loss(models: list[nn.Module], mode: str, slice_len: int):
    """``(module, losses(batches) -> [R])`` for R models: the models' own loss for one, else a population's."""
    first = models[0]
    if len(models) == 1:
        if isinstance(first, LSTMWorldModel):
            loss_module = WorldModelPredictionLoss(first, mode=mode, slice_len=slice_len)
        else:
            loss_module = UncertaintyLoss(first, slice_len=slice_len)
        return loss_module, lambda batches: _loss_value(loss_module, batches[0]).reshape(1)
    if isinstance(first, LSTMWorldModel):
        pop = LSTMWorldModel.from_members(models)
        keys = ("observation", "action", ("next", "observation"))

        def losses(batches):
            obs, action, next_obs = _member_sequences(batches, slice_len, keys)
            mask = _member_mask(batches, slice_len)
            return pop.prediction_loss(obs, action, next_obs, mode, mask=mask)

        return pop, losses
    if isinstance(first, ReconstructionUncertainty):
        pop = ReconstructionPopulation.from_members(models)

        def losses(batches):
            obs, action = _member_sequences(batches, slice_len, ("observation", "action"))
            return pop.loss(obs, action, mask=_member_mask(batches, slice_len))

        return pop, losses
    raise TypeError(
        f"fit_population runs populations of LSTMWorldModel or ReconstructionUncertainty; got "
        f"{type(first).__name__} (fit those one at a time with fit_uncertainty)."
    )


def fit_population(
    models: Sequence[nn.Module],
    buffers: TensorDictReplayBuffer | Sequence[TensorDictReplayBuffer],
    *,
    seeds: Sequence[int] | None = None,
    val_buffers: TensorDictReplayBuffer | Sequence[TensorDictReplayBuffer | None] | None = None,
    mode: str = "multi_step",
    fit_normalization: bool = True,
    steps: int = 2000,
    lr: float = 1e-3,
    lr_decay: bool = True,
    weight_decay: float = 0.0,
    clip_norm: float | None = 10.0,
    eval_every: int = 100,
    val_batches: int = 8,
    patience: int | None = 10,
    logger: Logger | None = None,
    log_prefix: str | None = None,
    progress: bool = True,
    shared_sampling: bool = False,
    compile: bool = False,
    cuda_graph: bool = False,
) -> list[FitResult]:
    """Train R models of one kind at once, as R independent fits run as one batch.

    ``models`` are R :class:`~torchrl_recon.modules.LSTMWorldModel` (trained as
    :func:`fit_world_model` does) or R :class:`~torchrl_recon.modules.ReconstructionUncertainty`
    (as :func:`fit_uncertainty`), each with its own initialisation. Member r fits on
    ``buffers[r]`` (one buffer for all, or one each, so several arms' data go into one fit),
    validates on ``val_buffers[r]`` and draws its batches as ``seed=seeds[r]`` would (default
    ``0..R-1``): the same batches, in the same order, as its own :func:`fit_world_model` call.
    Every member has its own early stopping, best weights and gradient clipping (``clip_norm``
    per member), and Adam is per element, so each member follows its separate fit up to float
    rounding (R = 1 is that fit bit for bit). A stopped member stays frozen at its best weights;
    the fit ends when every member has stopped or after ``steps``. The best weights are written
    back into ``models``. Other arguments are :func:`train_loss_module`'s.

    ``shared_sampling=True`` trades that exactness for speed: the active members that share a
    buffer draw their training batches as one ``R·num_slices`` sample (one RNG stream, seeded
    by the first of their seeds), split into one batch each. Members still see different,
    independently drawn slices, so the fits are statistically those of separate fits, but
    not their exact data order. Sampling a ``SliceSampler`` costs about as much as a member's
    step, so this is the faster mode for many members on one buffer. ``compile=True`` runs
    the members' training loss under ``torch.compile`` (see :func:`train_loss_module`).

    ``cuda_graph=True`` (models on a CUDA device) runs each training step, forward, backward,
    clip, Adam (``capturable``, its learning rate a tensor) and the stopped members' restore,
    as one CUDA graph: eager for its first three steps, then captured once and replayed
    (:class:`~torchrl_recon.training.CapturedStep`), so a step costs one launch
    instead of hundreds. The same fit up to float rounding; a non-finite loss stops it with
    the same messages (its step is applied, then every member is restored to its best weights,
    as the eager fit ends too).

    Returns:
        One :class:`FitResult` per member.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.data import make_sequence_buffer
        >>> rb = make_sequence_buffer(100, slice_len=8, num_slices=4)
        >>> _ = rb.extend(TensorDict({"observation": torch.randn(60, 2), "action": torch.randn(60, 1),
        ...     ("next", "observation"): torch.randn(60, 2),
        ...     ("collector", "traj_ids"): torch.arange(60) // 20}, [60]))
        >>> models = [LSTMWorldModel(2, 1, window=4, hidden_size=8) for _ in range(3)]
        >>> results = fit_population(models, rb, steps=10, eval_every=5, progress=False)
        >>> [r.steps for r in results]
        [10, 10, 10]
    """
    counts = dict(steps=steps, eval_every=eval_every, val_batches=val_batches, patience=patience)
    check_fit_settings(**counts, lr=lr, weight_decay=weight_decay, clip_norm=clip_norm)
    check_type("models", models, list | tuple, "a list of models")
    models = list(models)
    if not models:
        raise ValueError("fit_population needs at least one model.")
    for i, model in enumerate(models):
        check_type(f"models[{i}]", model, nn.Module, "a model (LSTMWorldModel or an estimator)")
    kinds = sorted({type(m).__name__ for m in models})
    if len({isinstance(m, LSTMWorldModel) for m in models}) > 1:
        raise TypeError(
            f"fit_population fits models of one kind (world models or estimators), got {kinds}."
        )
    stacked = [i for i, m in enumerate(models) if isinstance(m, StackedMembers) and m.num_members]
    if stacked:
        raise ValueError(
            f"fit_population fits one model per entry; models {stacked} hold several "
            "(num_members is set): pass their split() instead."
        )
    count = len(models)
    buffers = _per_member("buffers", buffers, count)
    val_buffers = _per_member("val_buffers", val_buffers, count, optional=True)
    seeds = list(range(count)) if seeds is None else list(seeds)
    if len(seeds) != count:
        raise ValueError(f"seeds has {len(seeds)} entries; expected one per member ({count}).")
    if any(isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in seeds):
        raise TypeError(f"seeds must be ints, got {seeds!r}.")
    for i, buffer in enumerate(buffers):
        if len(buffer) == 0:
            raise ValueError(
                f"The training replay buffer of member {i} is empty; collect data first."
            )
    shapes = {(_slice_len(b), b.batch_size) for b in buffers}
    if len(shapes) != 1:
        raise ValueError(
            f"Every member's buffer must sample one shape (slice_len, batch_size); got {sorted(shapes)}."
        )
    _check_compile(compile, models[0])
    check_cuda_graph(cuda_graph, module_device(models[0]), compile)
    world = isinstance(models[0], LSTMWorldModel)
    data_keys = WORLD_MODEL_KEYS if world else ESTIMATOR_KEYS
    if fit_normalization:
        for model, buffer in zip(models, buffers, strict=True):
            data = _checked_contents(buffer, data_keys)
            if world:
                model.fit_normalization(
                    data["observation"], data["action"], data["next", "observation"]
                )
            else:
                model.fit_normalization(data["observation"], data["action"])
    if log_prefix is None:
        log_prefix = "world_model/" if world else "uncertainty/"
    module, losses_of = _population_loss(models, mode, _slice_len(buffers[0]))
    with _cached_boundaries(*buffers, *val_buffers):
        results = _train_members(
            module,
            losses_of,
            count,
            buffers,
            [
                v if v is not None and len(v) > 0 else b
                for v, b in zip(val_buffers, buffers, strict=True)
            ],
            _MemberRNG(seeds),
            shared_sampling=shared_sampling,
            steps=steps,
            lr=lr,
            lr_decay=lr_decay,
            weight_decay=weight_decay,
            clip_norm=clip_norm,
            eval_every=eval_every,
            val_batches=val_batches,
            patience=patience,
            logger=logger,
            log_prefix=log_prefix,
            progress=progress,
            compile=compile,
            cuda_graph=cuda_graph,
            data_keys=data_keys,
        )
    if count > 1:
        for i, model in enumerate(models):
            model.load_state_dict(module.member(i).state_dict())
    return results


def _train_members(
    module: nn.Module,
    losses_of,
    count: int,
    buffers: list,
    val_sources: list,
    rng: _MemberRNG,
    *,
    steps: int,
    lr: float,
    lr_decay: bool,
    weight_decay: float,
    clip_norm: float | None,
    eval_every: int,
    val_batches: int,
    patience: int | None,
    logger: Logger | None,
    log_prefix: str,
    progress: bool,
    shared_sampling: bool = False,
    compile: bool = False,
    cuda_graph: bool = False,
    data_keys: Sequence | None = None,
) -> list[FitResult]:
    """:func:`train_loss_module`'s loop for ``count`` members; ``losses_of(batches)`` gives ``[count]``.
    With ``cuda_graph`` each step is one :class:`~torchrl_recon.training.CapturedStep`."""
    stacked = count > 1  # else: one plain model, no member dim
    params = [p for p in module.parameters() if p.requires_grad]
    optimizer = (
        capturable_adam(params, lr, weight_decay)
        if cuda_graph
        else torch.optim.Adam(params, lr=lr, weight_decay=weight_decay)
    )
    schedule = (
        torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps, eta_min=lr * 0.05)
        if lr_decay
        else None
    )
    device = module_device(module)
    train_losses = _training_loss(losses_of, compile)
    fixed_val = [
        [rng.sample(r, val_sources[r], device) for _ in range(val_batches)] for r in range(count)
    ]
    state = module.state_dict()
    best_state = {k: v.detach().clone() for k, v in state.items()}
    best_loss = [math.inf] * count
    since_best, last_step = [0] * count, [0] * count
    histories: list[list[dict]] = [[] for _ in range(count)]
    active = [True] * count
    batches: list = [None] * count

    def keep_best(r: int) -> None:
        for key, value in state.items():
            (best_state[key][r] if stacked else best_state[key]).copy_(
                value[r] if stacked else value
            )

    @torch.no_grad()
    def restore_all() -> None:
        for key, value in state.items():
            value.copy_(best_state[key])

    frozen_mask = torch.zeros(count, dtype=torch.bool, device=device)  # the stopped members

    def clip_gradients() -> None:
        if clip_norm is None:
            return
        if stacked:
            _clip_per_member([p.grad for p in params if p.grad is not None], count, clip_norm)
        else:
            torch.nn.utils.clip_grad_norm_(params, clip_norm)

    def whole_step(inputs: TensorDictBase) -> torch.Tensor:
        """Losses, backward, clip, Adam and the stopped members' restore, with no host sync."""
        step_losses = losses_of(inputs)
        optimizer.zero_grad(set_to_none=True)
        step_losses.sum().backward()
        clip_gradients()
        optimizer.step()
        if stacked:
            restore_frozen(state, best_state, frozen_mask)
        return step_losses.detach()

    captured = CapturedStep(whole_step, device) if cuda_graph else None
    bar = _fit_bar(steps, log_prefix, progress, compile)
    for step in bar:
        if shared_sampling and count > 1:
            batches = _sample_shared(rng, buffers, active, device)
        else:
            for r in range(count):
                if active[r]:  # a stopped member's batch stays: it is frozen anyway
                    batches[r] = rng.sample(r, buffers[r], device)
        try:
            if captured is not None:  # the whole step: checked after it, restored below if bad
                losses = captured(_graph_inputs(batches))
            else:
                losses = train_losses(batches)
            finite = torch.isfinite(losses.detach())
            bad = (
                []
                if bool(finite.all())
                else [r for r in range(count) if active[r] and not finite[r]]
            )
            if bad:
                raise FloatingPointError(
                    f"the loss of member(s) {bad} is not finite; check the data and the learning rate"
                )
        except (FloatingPointError, ValueError) as err:
            if cuda_graph:  # the captured step applied its update: undo it before anything else
                restore_all()
            if (data := _data_error(batches, data_keys)) is not None:  # NaN or inf in the data
                if not cuda_graph:
                    restore_all()
                raise ValueError(_stopped(step, data)) from err
            if isinstance(err, ValueError):
                raise
            if (compile or cuda_graph) and (named := _input_error(losses_of, batches)) is not None:
                raise named from None
            if not cuda_graph:  # (restored above)
                restore_all()
            raise FloatingPointError(_stopped(step, err)) from err
        if captured is None:
            optimizer.zero_grad(set_to_none=True)
            losses.sum().backward()
            clip_gradients()
            optimizer.step()
            if stacked and not all(active):
                restore_frozen(state, best_state, frozen_mask)
        if schedule is not None:
            schedule.step()
        if compile and step == 1:
            bar.set_postfix_str("")
        if step % eval_every == 0 or step == steps:
            with torch.no_grad():
                val = sum(
                    losses_of([fixed_val[r][b] for r in range(count)]) for b in range(val_batches)
                )
                val = val / val_batches
            for r in range(count):
                if not active[r]:
                    continue
                last_step[r] = step
                record = {
                    "step": step,
                    "train_loss": float(losses[r].detach()),
                    "val_loss": float(val[r]),
                }
                histories[r].append(record)
                if logger is not None:
                    prefix = f"{log_prefix}member_{r}/" if stacked else log_prefix
                    logger.log_scalar(f"{prefix}train_loss", record["train_loss"], step=step)
                    logger.log_scalar(f"{prefix}val_loss", record["val_loss"], step=step)
                if record["val_loss"] < best_loss[r]:
                    best_loss[r], since_best[r] = record["val_loss"], 0
                    keep_best(r)
                else:
                    since_best[r] += 1
                    if patience is not None and since_best[r] >= patience:
                        active[r] = False
                        frozen_mask[r] = True  # restored after each step from the next on
            bar.set_postfix(active=sum(active), val=f"{min(best_loss):.4g}")
            if not any(active):
                break
        else:
            for r in range(count):
                if active[r]:
                    last_step[r] = step
    restore_all()
    return [
        FitResult(steps=last_step[r], best_val_loss=best_loss[r], history=histories[r])
        for r in range(count)
    ]
