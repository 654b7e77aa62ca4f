"""The online fits as a TorchRL ``OptimizationStepper``: one Trainer step is one fit of the
library's schedule on everything the replay buffer holds."""

from __future__ import annotations

import time
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import ReplayBuffer
from torchrl.record.loggers import Logger
from torchrl.trainers import OptimizationStepper, Trainer

from torchrl_recon.fitting.online import FitSchedule, fit_models
from torchrl_recon.modules import LSTMWorldModel, RewardModel, UncertaintyEstimator
from torchrl_recon.modules.checks import check_type


class ModelFitStepper(OptimizationStepper):
    """Fit the world model (and the estimator) on the replay buffer's contents as
    :class:`~torchrl_recon.fitting.online.FitSchedule` says: the Trainer's first optimisation
    step fits from scratch (normalisation from the data, then ``schedule.steps``), each later
    one refits warm (``schedule.refit_steps`` from the current weights and normalisation; the
    estimator only with ``schedule.refit_uncertainty``). Each fit splits the data by trajectory
    (``seed + index`` for the ``index``-th fit) for its validation set and early stopping; a
    world model of members (``num_members=R``) fits every member as one batch.

    Give it as ``Trainer(optimization_stepper=..., optim_steps_per_batch=1)``: one fit after each
    collected batch (``Trainer`` fits from ``collector.init_random_frames`` on). It reads the
    buffer whole (``replay_buffer[:]``), so the buffer's storage must hold every step collected.
    The Trainer averages and logs what :meth:`step` returns (``val_loss_world_model``,
    ``val_loss_uncertainty``, ``fit_s``); :attr:`last_fit` holds the last fit's.

    Args:
        world_model: the world model the planner plans with.
        estimator: the estimator (None: β = 0 and no re-planning on u).
        replay_buffer: the Trainer's buffer (extended with each batch, e.g. by TorchRL's
            ``ReplayBufferTrainer.extend`` at ``batch_process``).

    Keyword Args:
        schedule: the fits' settings (default ``FitSchedule()``).
        seed: the first fit's seed.
        progress, logger: a progress bar per fit; the fits' validation losses logged.
        reward_model: a learned reward and termination
            (:class:`~torchrl_recon.modules.RewardModel`, the planner's
            :class:`~torchrl_recon.modules.LearnedCost`), fitted and refitted with the world
            model from the buffer's ``("next", "reward")`` and ``("next", "terminated")``.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(100))
        >>> obs = torch.randn(60, 3)
        >>> _ = rb.extend(TensorDict({"observation": obs, "action": torch.rand(60, 1),
        ...     ("next", "observation"): 0.9 * obs, ("collector", "traj_ids"): torch.arange(60) // 20}, [60]))
        >>> world = LSTMWorldModel(3, 1, window=4)
        >>> stepper = ModelFitStepper(world, None, rb, schedule=FitSchedule(steps=4, eval_every=2,
        ...     slice_len=8, num_slices=4, val_fraction=0.34))
        >>> sorted(stepper.step(None, None).keys()), bool(world.obs_norm.fitted)
        (['fit_s', 'val_loss_world_model'], True)
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        estimator: UncertaintyEstimator | None,
        replay_buffer: ReplayBuffer,
        *,
        schedule: FitSchedule | None = None,
        seed: int = 0,
        progress: bool = False,
        logger: Logger | None = None,
        reward_model: RewardModel | None = None,
    ) -> None:
        check_type("world_model", world_model, LSTMWorldModel, "an LSTMWorldModel")
        if estimator is not None:
            check_type(
                "estimator", estimator, UncertaintyEstimator, "an UncertaintyEstimator or None"
            )
        check_type("replay_buffer", replay_buffer, ReplayBuffer, "a torchrl ReplayBuffer")
        if reward_model is not None and not isinstance(reward_model, RewardModel):
            raise TypeError(
                f"reward_model must be a RewardModel or None, got {type(reward_model).__name__}."
            )
        if schedule is not None and not isinstance(schedule, FitSchedule):
            raise TypeError(
                f"schedule must be a FitSchedule or None, got {type(schedule).__name__}."
            )
        self.world_model, self.estimator, self.reward_model = world_model, estimator, reward_model
        self.replay_buffer, self.schedule = replay_buffer, schedule or FitSchedule()
        self.schedule.check_world_model(world_model)  # before any data is collected
        self.seed, self.progress, self.logger = seed, progress, logger
        self.fits = 0  # fits done
        self.fitted_steps = 0  # the buffer's steps at the last fit
        self.last_fit: dict[str, Any] = {}
        """The last fit's ``index``, ``val_loss`` (per network) and ``fit_s``."""

    def register(self, trainer: Trainer, name: str = "optimization_stepper") -> None:
        if trainer.optim_steps_per_batch != 1:
            raise ValueError(
                f"ModelFitStepper runs one whole fit per optimisation step: build the Trainer "
                f"with optim_steps_per_batch=1, got {trainer.optim_steps_per_batch}."
            )
        super().register(trainer, name)

    def data(self) -> TensorDictBase:
        """Every step the replay buffer holds, in the order written; refuses a buffer that
        dropped steps (a full storage overwrites the oldest) or holds none."""
        rb = self.replay_buffer
        written = getattr(rb, "write_count", len(rb))
        if written > len(rb):
            raise ValueError(
                f"the replay buffer holds {len(rb)} of the {written} steps written (its storage "
                "is full and overwrote the oldest); ModelFitStepper fits on every step "
                "collected: give the buffer a storage of at least the Trainer's total_frames."
            )
        if len(rb) == 0:
            raise ValueError(
                "the replay buffer is empty at the first fit: extend it with each batch "
                "(register ReplayBufferTrainer(rb).extend at 'batch_process')."
            )
        data = rb[:]
        if len(data) != len(rb):
            raise ValueError(
                f"the replay buffer counts {len(rb)} steps but its storage returns {len(data)} "
                "(a storage state of another size loaded into it?); resume a Trainer with the "
                "configuration it was saved with."
            )
        return data

    def fit(self, data: TensorDictBase, *, index: int, new_steps: int) -> dict[str, float]:
        """The ``index``-th fit (0: from scratch) on ``data``, whose last ``new_steps`` steps
        are new; returns the best validation loss of each network fitted (override to fit
        otherwise, e.g. from a run directory's checkpoints)."""
        return fit_models(
            self.world_model,
            self.estimator,
            data,
            self.schedule,
            seed=self.seed + index,
            warm=index > 0,
            new_steps=new_steps,
            progress=self.progress,
            logger=self.logger,
            log_prefix=f"iteration_{index}/",
            reward_model=self.reward_model,
        )

    def step(self, trainer: Trainer | None, sub_batch: TensorDictBase | None) -> TensorDictBase:
        """One fit (``trainer`` and ``sub_batch`` are not read: the fit samples its own
        windows from the whole buffer)."""
        data = self.data()
        start = time.perf_counter()
        losses = self.fit(data, index=self.fits, new_steps=len(data) - self.fitted_steps)
        self.last_fit = {"index": self.fits, "val_loss": losses}
        self.last_fit["fit_s"] = time.perf_counter() - start
        self.fits, self.fitted_steps = self.fits + 1, len(data)
        metrics = {f"val_loss_{k}": torch.tensor(float(v)) for k, v in losses.items()}
        return TensorDict(metrics | {"fit_s": torch.tensor(self.last_fit["fit_s"])}, [])

    def state_dict(self) -> dict[str, Any]:
        return {"fits": self.fits, "fitted_steps": self.fitted_steps}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.fits, self.fitted_steps = int(state_dict["fits"]), int(state_dict["fitted_steps"])
