"""Fit the world model and the uncertainty estimators from TorchRL replay buffers.

Every fit runs one loop, :func:`_fit_loop`, over R members (one model: R = 1): what it trains
is a :class:`~torchrl_recon.fitting.fit_data.FitData`, its settings one :class:`FitSettings`,
its step one :class:`~torchrl_recon.fitting.fit_step.FitStep` (eager, compiled or captured),
its early stopping and best weights one :class:`~torchrl_recon.fitting.early_stopping.EarlyStopping`.
The entry points check their arguments, fit the normalisation and build those four.
"""

from __future__ import annotations

import contextlib
import inspect
import numbers
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, NoReturn

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import ReplayBuffer, TensorDictReplayBuffer
from torchrl.objectives import LossModule
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_recon.data.buffers import buffer_contents
from torchrl_recon.devices import check_compile_support, module_device
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.fitting.checkpoint import save_checkpoint
from torchrl_recon.fitting.early_stopping import EarlyStopping
from torchrl_recon.fitting.fit_data import (
    Batches,
    FitData,
    MemberRNG,
    ProcessRNG,
    one_member,
    population_loss,
)
from torchrl_recon.fitting.fit_graph import CapturedStep, capturable_adam, check_cuda_graph
from torchrl_recon.fitting.fit_step import COMPILING, FitStep, GraphStep, Update
from torchrl_recon.modules.checks import check_finite_keys, check_int, check_real, check_type
from torchrl_recon.modules.members import StackedMembers
from torchrl_recon.modules.reward_model import RewardModel
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.objectives import RewardLoss, UncertaintyLoss, WorldModelPredictionLoss


@dataclass
class FitResult:
    """What :func:`train_loss_module` did: steps run, best validation loss, and the loss history."""

    steps: int
    best_val_loss: float
    history: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class FitSettings:
    """The settings of a fit's loop, every fit's: :func:`train_loss_module`'s keywords (and
    :func:`fit_population`'s ``cuda_graph``), checked when made (:func:`check_fit_settings`).

    Examples:
        >>> FitSettings(steps=10, eval_every=5).clip_norm
        10.0
        >>> FitSettings(lr=0.0)
        Traceback (most recent call last):
        ...
        ValueError: lr must be a finite number > 0, got 0.0.
    """

    steps: int = 2000
    lr: float = 1e-3
    lr_decay: bool = True
    weight_decay: float = 0.0
    clip_norm: float | None = 10.0
    eval_every: int = 100
    val_batches: int = 8
    patience: int | None = 10
    logger: Logger | None = None
    log_prefix: str = ""
    progress: bool = True
    compile: bool = False
    cuda_graph: bool = False

    def __post_init__(self) -> None:
        check_fit_settings(**{f.name: getattr(self, f.name) for f in fields(self)})

    @classmethod
    def of(cls, arguments: dict[str, Any]) -> FitSettings:
        """The settings among an entry point's ``arguments`` (its ``locals()``), the others left."""
        return cls(**{f.name: arguments[f.name] for f in fields(cls) if f.name in arguments})


def _check_compile(compile: bool, module: nn.Module) -> None:
    """Refuse ``compile=True`` where torch.compile cannot build kernels for ``module``'s device,
    before the fit changes anything (its normalisation included)."""
    if compile:
        check_compile_support(module_device(module))


def _input_error(eager_fn: Callable[..., torch.Tensor], batch) -> ValueError | None:
    """After a compiled or captured training step's non-finite loss: the ``ValueError`` the
    eager step's input checks (left out there, see
    :func:`~torchrl_recon.modules.checks.check_finite`) raise on the same ``batch``, naming the
    input as an eager fit would; None where the inputs are finite (the loss itself diverged)."""
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


def _fit_bar(steps: int, log_prefix: str, progress: bool, compile: bool) -> tqdm:
    """The fit's progress bar over steps ``1..steps``; with ``compile`` it says so (see
    :data:`COMPILING`) until the caller clears it after the first step."""
    desc = log_prefix.rstrip("/") or "fit"
    bar = tqdm(range(1, steps + 1), desc=desc, disable=not progress, leave=False)
    if compile:
        bar.set_postfix_str(COMPILING)
    return bar


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
    settings = FitSettings.of(locals())
    _check_seed(seed)
    _check_compile(compile, loss_module)
    if len(buffer) == 0:
        raise ValueError("The training replay buffer is empty; collect data before fitting.")
    val_source = val_buffer if val_buffer is not None and len(val_buffer) > 0 else buffer
    with _cached_boundaries(buffer, val_buffer):
        data = FitData(
            loss_module,
            one_member(loss_module),
            [buffer],
            [val_source],
            ProcessRNG(seed),  # the process's RNG, seeded: as this fit has always drawn
            data_keys=_loss_keys(loss_module),
        )
        (result,) = _fit_loop(data, settings, checkpoint_path, checkpoint_modules)
    return result


def _fit_loop(
    data: FitData,
    settings: FitSettings,
    checkpoint_path: str | Path | None = None,
    checkpoint_modules: dict[str, nn.Module] | None = None,
) -> list[FitResult]:
    """The loop of every fit, for R = ``data.count`` members (arguments checked): Adam on the
    members' summed losses, each member validated every ``eval_every`` steps, stopped on its
    own and given back its best weights at the end. One model (R = 1) saves its best weights to
    ``checkpoint_path`` (``checkpoint_modules``) when given."""
    s, device, count = settings, module_device(data.module), data.count
    stopping = EarlyStopping(data.module, count, s.patience)
    fixed_val = data.validation(s.val_batches, device)
    step_fn = _fit_step(data, s, stopping, device)
    where = f"; the last good checkpoint is {checkpoint_path}" if checkpoint_path else ""
    save = (checkpoint_path, checkpoint_modules) if checkpoint_path and checkpoint_modules else None
    histories: list[list[dict]] = [[] for _ in range(count)]
    bar = _fit_bar(s.steps, s.log_prefix, s.progress, s.compile)
    for step in bar:
        batches = data.sample(stopping.active, device)
        losses = _run_step(step_fn, batches, step, data, stopping, where)
        stopping.ran(step)
        if s.compile and step == 1:
            bar.set_postfix_str("")
        if step % s.eval_every == 0 or step == s.steps:
            val = _validation_losses(data.losses_of, fixed_val)
            for r in range(count):
                if not stopping.active[r]:
                    continue
                train_loss, val_loss = float(losses[r].detach()), float(val[r])
                histories[r].append({"step": step, "train_loss": train_loss, "val_loss": val_loss})
                _log(s, histories[r][-1], member=r if count > 1 else None)
                if stopping.validated(r, val_loss) and save is not None:
                    save_checkpoint(*save, extra={"step": step, "val_loss": val_loss})
            _postfix(bar, stopping, histories)
            if not any(stopping.active):
                break
    stopping.restore_all()
    return [
        FitResult(steps=stopping.last_step[r], best_val_loss=stopping.best_loss[r], history=h)
        for r, h in enumerate(histories)
    ]


def _fit_step(
    data: FitData, s: FitSettings, stopping: EarlyStopping, device: torch.device
) -> FitStep:
    """The fit's step: Adam (``capturable`` with ``cuda_graph``) on ``data.module``'s trainable
    parameters, the cosine schedule from ``lr`` to ``lr / 20`` (with ``lr_decay``), eager,
    compiled or captured as ``s`` says."""
    params = [p for p in data.module.parameters() if p.requires_grad]
    optimizer = (
        capturable_adam(params, s.lr, s.weight_decay)
        if s.cuda_graph
        else torch.optim.Adam(params, lr=s.lr, weight_decay=s.weight_decay)
    )
    schedule = (
        torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, s.steps, eta_min=s.lr * 0.05)
        if s.lr_decay
        else None
    )
    update = Update(params, optimizer, s.clip_norm, stopping)
    if s.cuda_graph:
        capture = lambda whole_step: CapturedStep(whole_step, device)  # noqa: E731
        return GraphStep(data.losses_of, update, schedule, capture)
    return FitStep(data.losses_of, update, schedule, compile=s.compile)


def _run_step(
    step_fn: FitStep,
    batches: Batches,
    step: int,
    data: FitData,
    stopping: EarlyStopping,
    where: str,
) -> torch.Tensor:
    """One training step on ``batches``: the members' losses, checked, then applied."""
    try:
        losses = step_fn.losses(batches)
        _check_losses(losses, stopping.active)
    except (FloatingPointError, ValueError) as err:
        _stop(err, step, batches, step_fn, data, stopping, where)
    step_fn.apply(losses)
    return losses


def _check_losses(losses: torch.Tensor, active: list[bool]) -> None:
    """Refuse a non-finite loss of an active member (one host read when all are finite)."""
    finite = torch.isfinite(losses.detach())
    if bool(finite.all()):
        return
    bad = [r for r in range(len(active)) if active[r] and not finite[r]]
    if bad:
        which = "the loss" if len(active) == 1 else f"the loss of member(s) {bad}"
        raise FloatingPointError(f"{which} is not finite; check the data and the learning rate")


def _stop(
    err: FloatingPointError | ValueError,
    step: int,
    batches: Batches,
    step_fn: FitStep,
    data: FitData,
    stopping: EarlyStopping,
    where: str,
) -> NoReturn:
    """End the fit whose ``step`` failed with ``err``: NaN or inf in the data named with its
    buffer row, a compiled or captured step's bad input named as the eager fit names it, else
    ``err`` (a ``ValueError`` as it is, a non-finite loss with ``where`` the last checkpoint is).
    The members are back at their best weights unless the step raised an input's ``ValueError``
    before any update."""
    restored = step_fn.applies_early
    if restored:  # the captured step applied its update: undo it before anything else
        stopping.restore_all()
    if (bad := _data_error(batches, data.data_keys)) is not None:  # NaN or inf in the data
        if not restored:
            stopping.restore_all()
        raise ValueError(_stopped(step, bad)) from err
    if isinstance(err, ValueError):
        raise err
    if step_fn.skips_input_checks and (named := _input_error(data.losses_of, batches)) is not None:
        raise named from None
    if not restored:
        stopping.restore_all()
    raise FloatingPointError(_stopped(step, err, where)) from err


@torch.no_grad()
def _validation_losses(
    losses_of: Callable[[Batches], torch.Tensor], fixed_val: list[list[TensorDictBase]]
) -> torch.Tensor:
    """The members' mean losses ``[R]`` over their fixed validation batches."""
    count, batches = len(fixed_val), len(fixed_val[0])
    total = sum(losses_of([fixed_val[r][b] for r in range(count)]) for b in range(batches))
    return total / batches


def _log(s: FitSettings, record: dict, member: int | None) -> None:
    """``record``'s losses to ``s.logger`` (a member's under ``member_<r>/``)."""
    if s.logger is None:
        return
    prefix = s.log_prefix if member is None else f"{s.log_prefix}member_{member}/"
    for name in ("train_loss", "val_loss"):
        s.logger.log_scalar(f"{prefix}{name}", record[name], step=record["step"])


def _postfix(bar: tqdm, stopping: EarlyStopping, histories: list[list[dict]]) -> None:
    """The bar's note after a validation: one model's last losses, else the members' state."""
    if stopping.count == 1:
        last = histories[0][-1]
        bar.set_postfix(train=f"{last['train_loss']:.4g}", val=f"{last['val_loss']:.4g}")
    else:
        bar.set_postfix(active=sum(stopping.active), val=f"{min(stopping.best_loss):.4g}")


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


def _check_models(models: object) -> list[nn.Module]:
    """``models`` as a list of one kind of single models, or one line saying what is wrong."""
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
    return models


def _check_seeds(seeds: Sequence[int] | None, count: int) -> list[int]:
    """One int seed per member (default ``0..count-1``)."""
    seeds = list(range(count)) if seeds is None else list(seeds)
    if len(seeds) != count:
        raise ValueError(f"seeds has {len(seeds)} entries; expected one per member ({count}).")
    if any(isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in seeds):
        raise TypeError(f"seeds must be ints, got {seeds!r}.")
    return seeds


def _check_member_buffers(buffers: list[TensorDictReplayBuffer]) -> None:
    """Refuse an empty member buffer, or buffers that sample different shapes."""
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


def _fit_normalizations(models: list[nn.Module], buffers: list[TensorDictReplayBuffer]) -> None:
    """Each model's normalisation from its buffer's contents (checked finite)."""
    for model, buffer in zip(models, buffers, strict=True):
        if isinstance(model, LSTMWorldModel):
            data = _checked_contents(buffer, WORLD_MODEL_KEYS)
            model.fit_normalization(
                data["observation"], data["action"], data["next", "observation"]
            )
        else:
            data = _checked_contents(buffer, ESTIMATOR_KEYS)
            model.fit_normalization(data["observation"], data["action"])


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
    :func:`fit_world_model` does) or R :class:`~torchrl_recon.estimators.ReconstructionUncertainty`
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
    (:class:`~torchrl_recon.fitting.CapturedStep`), so a step costs one launch
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
    settings = FitSettings.of(locals())
    models = _check_models(models)
    count = len(models)
    buffers = _per_member("buffers", buffers, count)
    val_buffers = _per_member("val_buffers", val_buffers, count, optional=True)
    seeds = _check_seeds(seeds, count)
    _check_member_buffers(buffers)
    _check_compile(compile, models[0])
    check_cuda_graph(cuda_graph, module_device(models[0]), compile)
    world = isinstance(models[0], LSTMWorldModel)
    if fit_normalization:
        _fit_normalizations(models, buffers)
    if log_prefix is None:
        settings = replace(settings, log_prefix="world_model/" if world else "uncertainty/")
    module, losses_of = population_loss(models, mode, _slice_len(buffers[0]))
    val_sources = [
        v if v is not None and len(v) > 0 else b for v, b in zip(val_buffers, buffers, strict=True)
    ]
    with _cached_boundaries(*buffers, *val_buffers):
        data = FitData(
            module,
            losses_of,
            buffers,
            val_sources,
            MemberRNG(seeds),
            data_keys=WORLD_MODEL_KEYS if world else ESTIMATOR_KEYS,
            shared_sampling=shared_sampling,
        )
        results = _fit_loop(data, settings)
    if count > 1:
        for i, model in enumerate(models):
            model.load_state_dict(module.member(i).state_dict())
    return results
