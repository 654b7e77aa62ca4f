"""The parts of online model-based RL (PETS's loop) that its Trainer hooks use: the fit
schedule and the fits (:func:`fit_models`), the iteration record and its metrics (returns,
the model's error on new data before the refit, mean u).

The loop itself is TorchRL's ``Trainer``: :class:`~torchrl_recon.trainers.OnlineTrainer` and
:func:`~torchrl_recon.trainers.learn_online` (the first rounds may explore instead of control:
an :class:`~torchrl_recon.policies.ExplorationPolicy`, the paper's capped-u objective, α = 0).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.record.loggers import Logger

from torchrl_recon.data import (
    FIT_KEYS,
    REWARD_FIT_KEYS,
    SHORT_EPISODES,
    WINDOW_SAMPLINGS,
    cut_sequences,
    sequence_buffers,
    split_by_trajectory,
)
from torchrl_recon.data.buffers import TRAJ_KEY, check_val_fraction
from torchrl_recon.devices import module_device
from torchrl_recon.fitting.fit import (
    check_fit_settings,
    fit_reward,
    fit_uncertainty,
    world_model_fit,
)
from torchrl_recon.fitting.fit_graph import check_cuda_graph
from torchrl_recon.modules import LSTMWorldModel, RewardModel, UncertaintyEstimator
from torchrl_recon.modules.checks import check_finite, check_flag, check_int
from torchrl_recon.objectives import WorldModelPredictionLoss
from torchrl_recon.planners.beta import window_uncertainty


@dataclass
class FitSchedule:
    """How the two networks are fitted online: the first fit from scratch (``steps``), every
    later one warm-started from the current weights with the first fit's normalisation
    (``refit_steps``). Windows of ``slice_len`` steps, ``num_slices`` a batch; ``val_fraction``
    of the trajectories held out for early stopping. ``refit_old_steps``: a refit trains on the
    training split's new steps (those of the last iteration) plus whole earlier trajectories of
    it drawn at random until they hold ``refit_old_steps`` steps (``recent_and_sampled()``);
    None: on the whole training split. ``refit_uncertainty``: False leaves the estimator as
    the first fit made it (when the planner does not read u: β = 0, no re-planning on u, no
    exploring rounds). ``compile``: the world model's fits under ``torch.compile``
    (:func:`~torchrl_recon.fitting.train_loss_module`; compiled once per process, reused by
    every refit). ``uncertainty``: the estimator's fits' own settings, any of
    ``FIT_SETTINGS``: its first fit's ``steps``, and ``lr``, ``eval_every``, ``patience``
    (the world model's where not given) and ``compile`` (False where not given); its refits take
    ``refit_steps`` too. ``cuda_graph``: a world model of members on a CUDA device fits with
    each training step one replayed CUDA graph (``fit_population(cuda_graph=True)``).
    ``renormalize``: before each refit, the world model's (and a learned reward's) statistics
    are refitted on all the data so far, their function kept
    (:meth:`~torchrl_recon.modules.LSTMWorldModel.refit_normalization`); False keeps the first
    fit's. ``reward``: a learned reward's fit settings (as ``uncertainty``; the world model's
    where not given). ``sampling``: how the fits draw their windows, ``"trajectory"``
    (TorchRL's ``SliceSampler``) or ``"step"`` (every window start alike), every fit and refit.
    ``short_episodes``: ``"pad"`` (default) pads and keeps every episode that ended before
    ``slice_len`` steps; ``"pad_if_no_window"`` only where a split holds no episode of
    ``slice_len`` steps (see :func:`~torchrl_recon.data.needs_padding`).

    Examples:
        >>> FitSchedule(lr=3e-3, uncertainty={"lr": 1e-3}).estimator_settings()["lr"]
        0.001
        >>> FitSchedule(uncertainty={"hidden": 8})
        Traceback (most recent call last):
        ...
        ValueError: FitSchedule.uncertainty has unknown key(s) ['hidden']; expected any of ['compile', 'eval_every', 'lr', 'patience', 'steps'].
    """

    steps: int = 1000
    refit_steps: int = 300
    refit_old_steps: int | None = None
    refit_uncertainty: bool = True
    lr: float = 3e-3
    eval_every: int = 100
    patience: int | None = 10
    slice_len: int = 40
    num_slices: int = 32
    val_fraction: float = 0.1
    mode: str = "multi_step"
    compile: bool = False
    cuda_graph: bool = False
    uncertainty: dict[str, Any] = field(default_factory=dict)
    renormalize: bool = False
    reward: dict[str, Any] = field(default_factory=dict)
    sampling: str = "trajectory"
    short_episodes: str = "pad"

    def __post_init__(self) -> None:
        for name in ("uncertainty", "reward"):
            settings = getattr(self, name)
            if not isinstance(settings, Mapping):
                raise TypeError(
                    f"FitSchedule.{name} must be a mapping of fit settings, got "
                    f"{type(settings).__name__}."
                )
            unknown = sorted(set(settings) - set(FIT_SETTINGS))
            if unknown:
                raise ValueError(
                    f"FitSchedule.{name} has unknown key(s) {unknown}; expected any of "
                    f"{sorted(FIT_SETTINGS)}."
                )
        check_flag("renormalize", self.renormalize)
        # checked here, not at the first fit, which comes after the random data are collected
        for name in ("steps", "refit_steps", "slice_len", "num_slices"):
            check_int(name, getattr(self, name))
        if self.refit_old_steps is not None:
            check_int("refit_old_steps", self.refit_old_steps, minimum=0)
        check_val_fraction(self.val_fraction)
        check_flag("cuda_graph", self.cuda_graph)
        if self.sampling not in WINDOW_SAMPLINGS:
            raise ValueError(
                f"sampling must be one of {sorted(WINDOW_SAMPLINGS)}, got {self.sampling!r}."
            )
        if self.short_episodes not in SHORT_EPISODES:
            raise ValueError(
                f"short_episodes must be one of {list(SHORT_EPISODES)}, got "
                f"{self.short_episodes!r}."
            )
        if self.mode not in ("multi_step", "one_step"):
            raise ValueError(f"mode must be 'multi_step' or 'one_step', got {self.mode!r}.")
        for prefix, settings in (
            ("", self.world_model_settings()),
            ("uncertainty.", self.uncertainty),
            ("reward.", self.reward),
        ):
            check_fit_settings(prefix, **settings)
            if "compile" in settings:
                check_flag(f"{prefix}compile", settings["compile"])

    def check_world_model(self, world_model: nn.Module) -> None:
        """Refuse a world model these fits cannot run on: with ``cuda_graph``, one without
        members (``num_members=R``) or off a CUDA device.

        Examples:
            >>> FitSchedule(cuda_graph=True).check_world_model(LSTMWorldModel(3, 1))
            Traceback (most recent call last):
            ...
            ValueError: FitSchedule(cuda_graph=True) captures a population fit's step: the world model must hold members (num_members=R).
        """
        if not self.cuda_graph:
            return
        if getattr(world_model, "num_members", None) is None:
            raise ValueError(
                "FitSchedule(cuda_graph=True) captures a population fit's step: the world "
                "model must hold members (num_members=R)."
            )
        check_cuda_graph(True, module_device(world_model), self.compile)

    def world_model_settings(self) -> dict[str, Any]:
        """The world model's fit settings, those of ``FIT_SETTINGS``."""
        return {k: getattr(self, k) for k in FIT_SETTINGS}

    def estimator_settings(self) -> dict[str, Any]:
        """The estimator's fit settings: the world model's uncompiled, then ``uncertainty``'s."""
        return self.world_model_settings() | {"compile": False} | dict(self.uncertainty)

    def reward_settings(self) -> dict[str, Any]:
        """A learned reward's fit settings: the world model's uncompiled, then ``reward``'s."""
        return self.world_model_settings() | {"compile": False} | dict(self.reward)


FIT_SETTINGS = ("steps", "lr", "eval_every", "patience", "compile")  # each network's own


@dataclass
class IterationRecord:
    """One iteration of :func:`learn_online` (iteration 0: the random warm-up data).

    ``episode_returns``: the summed env reward of every episode that ended in this
    iteration's steps. ``model_error``: the world model's one-step error (standardised Δs,
    mean square) on this iteration's new data before it was refitted on them (NaN for the
    random data; over whole episodes when none is ``slice_len`` steps long, see
    ``model_error()``). ``mean_uncertainty``: the estimator's mean u of the new data's
    windows (``mean_uncertainty()``).
    ``policy``: what played the steps (``"random"``, ``"explore"`` or ``"mpc"``).
    """

    iteration: int
    env_steps: int
    episode_returns: list[float]
    model_error: float
    mean_uncertainty: float
    replans: int
    fit_s: float
    plan_s: float
    env_s: float
    extra: dict = field(default_factory=dict)
    policy: str = "mpc"

    def as_dict(self) -> dict:
        return asdict(self)


def fit_models(
    world_model: LSTMWorldModel,
    estimator: UncertaintyEstimator | None,
    data: TensorDictBase,
    schedule: FitSchedule,
    *,
    seed: int,
    warm: bool,
    new_steps: int | None = None,
    progress: bool = False,
    logger: Logger | None = None,
    log_prefix: str = "",
    reward_model: RewardModel | None = None,
) -> dict[str, float]:
    """Fit (``warm=False``: normalisation and ``schedule.steps``) or refit (``warm=True``: the
    current weights and normalisation, ``schedule.refit_steps``; the estimator only with
    ``schedule.refit_uncertainty``) both networks, and a learned ``reward_model`` when given,
    on ``data``, split by trajectory with ``seed``; returns their best validation losses (a
    world model of members: :func:`~torchrl_recon.fitting.fit_world_members`, their mean).
    With ``schedule.renormalize`` a refit first refits the world model's and the reward
    model's statistics on all ``data``, keeping their function. When a split has no
    trajectory of ``slice_len`` steps (an env whose episodes end early), both buffers pad the
    slices of shorter ones and mask the padding (``make_sequence_buffer(pad_short=True)``), and
    so do they when an episode ended shorter than that (``schedule.short_episodes``).
    ``new_steps``: how many of ``data``'s last steps are new, for a refit with
    ``schedule.refit_old_steps``; the validation split is drawn from all ``data`` either way."""
    s = schedule
    s.check_world_model(world_model)
    if reward_model is not None:
        check_reward_data(reward_model, data)
    if warm and s.renormalize:
        renormalize(world_model, reward_model, data)
    graph = {"cuda_graph": True} if s.cuda_graph else {}
    parts = split_by_trajectory(data, s.val_fraction, seed=seed)
    if warm and s.refit_old_steps is not None:
        if new_steps is None:
            raise ValueError("a refit with schedule.refit_old_steps needs new_steps.")
        first_new = data.get(TRAJ_KEY)[len(data) - new_steps]
        parts = (recent_and_sampled(parts[0], first_new, s.refit_old_steps, seed=seed), parts[1])
    sizes = dict(slice_len=s.slice_len, num_slices=s.num_slices, sampling=s.sampling)
    keys = FIT_KEYS if reward_model is None else REWARD_FIT_KEYS
    buffers = sequence_buffers(parts, **sizes, keys=keys, short_episodes=s.short_episodes)
    common = dict(
        val_buffer=buffers[1],
        seed=seed,
        progress=progress,
        logger=logger,
        fit_normalization=not warm,
        checkpoint_modules={},
    )
    fits = {
        "world_model": s.world_model_settings(),
        "uncertainty": s.estimator_settings(),
        "reward": s.reward_settings(),
    }
    if warm:
        for settings in fits.values():
            settings["steps"] = s.refit_steps
    fit_world = world_model_fit(world_model)
    out = {
        "world_model": fit_world(
            world_model,
            buffers[0],
            mode=s.mode,
            log_prefix=f"{log_prefix}world_model/",
            **common,
            **fits["world_model"],
            **graph,
        ).best_val_loss
    }
    if estimator is not None and (s.refit_uncertainty or not warm):
        out["uncertainty"] = fit_uncertainty(
            estimator,
            buffers[0],
            log_prefix=f"{log_prefix}uncertainty/",
            **common,
            **fits["uncertainty"],
        ).best_val_loss
    if reward_model is not None:
        out["reward_model"] = fit_reward(
            reward_model, buffers[0], log_prefix=f"{log_prefix}reward/", **common, **fits["reward"]
        ).best_val_loss
    return out


def check_reward_data(reward_model: RewardModel, data: TensorDictBase) -> None:
    """Refuse ``data`` a learned reward cannot fit on: without ``("next", "reward")`` (or
    ``("next", "terminated")`` where it learns the termination), or with a non-finite reward
    (one line naming the key and the first index).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import RewardModel
        >>> data = TensorDict({("next", "reward"): torch.tensor([[0.0], [float("nan")]])}, [2])
        >>> check_reward_data(RewardModel(2, 1), data)
        Traceback (most recent call last):
        ...
        ValueError: ('next', 'reward') contains NaN or inf (first at index [1, 0]); expected finite values.
    """
    keys = [
        k
        for k, learns in zip(
            REWARD_FIT_KEYS[-2:],
            (reward_model.learns_reward, reward_model.learns_termination),
            strict=True,
        )
        if learns
    ]
    present = set(data.keys(True, True))
    for key in keys:
        if key not in present:
            raise ValueError(
                f"the data hold no {key} to fit the learned reward on; collect them with a "
                "TorchRL env (it writes ('next', 'reward') and ('next', 'terminated'))."
            )
    if reward_model.learns_reward:
        check_finite(str(REWARD_FIT_KEYS[-2]), data.get(REWARD_FIT_KEYS[-2]))


@torch.no_grad()
def renormalize(
    world_model: LSTMWorldModel, reward_model: RewardModel | None, data: TensorDictBase
) -> None:
    """Refit the world model's (and ``reward_model``'s) statistics on all ``data``, keeping
    their function (:meth:`~torchrl_recon.modules.LSTMWorldModel.refit_normalization`)."""
    device = module_device(world_model)
    obs, action, next_obs = (data.get(k).to(device) for k in FIT_KEYS)
    world_model.refit_normalization(obs, action, next_obs)
    if reward_model is not None:
        reward = data.get(REWARD_FIT_KEYS[-2]).to(module_device(reward_model))
        reward_model.refit_normalization(obs, action, next_obs, reward)


def recent_and_sampled(
    data: TensorDictBase, first_new: int | torch.Tensor, old_steps: int, *, seed: int
) -> TensorDictBase:
    """The steps of ``data``'s trajectories with an id from ``first_new`` on (the new ones: ids
    grow with each batch, as an :class:`~torchrl_recon.trainers.IterationCollector` numbers them), after whole older trajectories drawn at random
    (``seed``) until they hold ``old_steps`` steps (the last one drawn may take it past
    ``old_steps``; all of them if they hold fewer).

    Examples:
        >>> from tensordict import TensorDict
        >>> ids = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3, 3])
        >>> data = TensorDict({TRAJ_KEY: ids, "t": torch.arange(9)}, [9])
        >>> out = recent_and_sampled(data, 3, old_steps=3, seed=0)
        >>> len(out), out[TRAJ_KEY][-3:].tolist()  # two old trajectories (4 steps), then the new
        (7, [3, 3, 3])
    """
    ids = data.get(TRAJ_KEY)
    old, counts = torch.unique(ids[ids < first_new], return_counts=True)
    order = torch.randperm(len(old), generator=torch.Generator().manual_seed(seed))
    drawn = int((counts[order].cumsum(0) < old_steps).sum()) + 1 if old_steps > 0 else 0
    taken = old[order[:drawn]]
    return data[torch.isin(ids, taken) | (ids >= first_new)]


def episode_returns(data: TensorDictBase) -> list[float]:
    """The summed ``("next", "reward")`` of every trajectory in ``data`` that ends (done) in it.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({("next", "reward"): torch.ones(5, 1),
        ...     ("next", "done"): torch.tensor([0, 1, 0, 0, 0]).bool()[:, None],
        ...     ("collector", "traj_ids"): torch.tensor([0, 0, 1, 1, 1])}, [5])
        >>> episode_returns(td)
        [2.0]
    """
    ids = data.get(TRAJ_KEY)
    reward = data["next", "reward"].reshape(len(data), -1).sum(-1).double()
    done = data["next", "done"].reshape(len(data), -1).any(-1)
    unique, inverse = torch.unique(ids, return_inverse=True)
    sums = reward.new_zeros(len(unique)).index_add_(0, inverse, reward)
    ended = done.new_zeros(len(unique)).index_put_((inverse,), done, accumulate=True)
    return sums[ended].tolist()


def shared_keys(data: TensorDictBase, new: TensorDictBase) -> list:
    """The leaf keys of ``data`` that ``new`` holds too, in ``data``'s order."""
    keys = set(new.keys(True, True))
    return [k for k in data.keys(True, True) if k in keys]


@torch.no_grad()
def model_error(world_model: LSTMWorldModel, data: TensorDictBase, length: int) -> float:
    """The world model's one-step (teacher-forced) error on ``data``: mean square of the
    standardised Δs over non-overlapping windows of ``length`` steps; when no trajectory is
    that long (episodes that end early), over every step of each whole trajectory, padded and
    masked (``cut_sequences(..., pad_short=True)``); a world model of members: the members'
    mean error.

    Examples:
        >>> from tensordict import TensorDict
        >>> world = LSTMWorldModel(2, 1, window=2)
        >>> data = TensorDict({"observation": torch.randn(9, 2), "action": torch.rand(9, 1),
        ...     ("next", "observation"): torch.randn(9, 2), TRAJ_KEY: torch.arange(9) // 3}, [9])
        >>> world.fit_normalization(data["observation"], data["action"], data["next", "observation"])
        >>> model_error(world, data, 5) > 0  # episodes of 3 steps, windows of 5
        True
    """
    windows = cut_sequences(data, length, pad_short=True)
    device = next(world_model.parameters()).device
    one = getattr(world_model, "num_members", None) is None
    members = [world_model] if one else world_model.split()
    errors = [
        float(WorldModelPredictionLoss(m, mode="one_step")(windows.to(device))["loss_world_model"])
        for m in members
    ]
    return sum(errors) / len(errors)


@torch.no_grad()
def mean_uncertainty(estimator: UncertaintyEstimator | None, data: TensorDictBase) -> float:
    """The estimator's mean u over the windows of ``data`` (NaN without an estimator); when no
    trajectory is as long as its window, over the windows it trains on in padded slices, each
    short episode started at rest (:func:`~torchrl_recon.planners.beta.window_uncertainty`).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> est = ReconstructionUncertainty(2, 1, window=4)
        >>> data = TensorDict({"observation": torch.randn(9, 2), "action": torch.rand(9, 1),
        ...     TRAJ_KEY: torch.arange(9) // 3}, [9])  # episodes of 3 steps
        >>> mean_uncertainty(est, data) > 0, mean_uncertainty(None, data)
        (True, nan)
    """
    if estimator is None:
        return float("nan")
    return float(window_uncertainty(data, estimator).mean())
