"""The online model-based agent (PETS's loop) as a ``torchrl.trainers.Trainer``."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Sequence
from typing import Any

from tensordict import TensorDictBase
from torchrl.collectors import BaseCollector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger
from torchrl.trainers import ReplayBufferTrainer, TrainerHookBase

from torchrl_recon.data import quiet_storage_init
from torchrl_recon.fitting.online import FitSchedule, IterationRecord
from torchrl_recon.modules import LSTMWorldModel, RewardModel, UncertaintyEstimator
from torchrl_recon.modules.checks import check_type
from torchrl_recon.objectives import WorldModelPredictionLoss
from torchrl_recon.planners import PlannerBase
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy
from torchrl_recon.trainers.buffer import ReplayBufferSteps
from torchrl_recon.trainers.checkpoint import VerifiedTrainer
from torchrl_recon.trainers.collector import OnlineCollector, check_schedule
from torchrl_recon.trainers.fit import ModelFitStepper
from torchrl_recon.trainers.log_iteration import LogIteration


def quiet_extend(extender: ReplayBufferTrainer) -> Callable[[TensorDictBase], Any]:
    """``extender.extend`` without TorchRL's ``Initialized LazyTensorStorage`` INFO line at the
    first batch (:func:`~torchrl_recon.data.quiet_storage_init`).

    Examples:
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from tensordict import TensorDict
        >>> buffer = ReplayBuffer(storage=LazyTensorStorage(4))
        >>> _ = quiet_extend(ReplayBufferTrainer(buffer))(TensorDict({"x": [1.0, 2.0]}, [2]))
        >>> len(buffer)
        2
    """

    def extend(batch: TensorDictBase) -> Any:
        with quiet_storage_init():
            return extender.extend(batch)

    return extend


class OnlineTrainer(VerifiedTrainer):
    """A ``torchrl.trainers.Trainer`` that learns a task online with the library's parts:
    collect a batch (``collector``) → extend the replay buffer (TorchRL's
    ``ReplayBufferTrainer.extend``, ``batch_process``) → record the batch
    (:class:`LogIteration`, ``pre_steps_log``) → fit or refit the world model and the estimator
    on everything collected (:class:`ModelFitStepper`, the optimisation step) → log
    (``post_steps_log``) → repeat. Each hook is TorchRL's or the library's and can be used alone
    in a Trainer of one's own; this class only wires them.

    Keyword Args:
        collector: the data source; an :class:`OnlineCollector` (random batch, then one batch
            per iteration) or TorchRL's ``Collector`` with ``init_random_frames``.
        world_model, estimator: the networks the collector's planners hold.
        schedule: the fits' :class:`~torchrl_recon.fitting.online.FitSchedule`.
        replay_buffer: where the batches go (default: a ``LazyTensorStorage`` of the
            collector's ``total_frames``); it must keep every step.
        stepper: the fit step (default: a :class:`ModelFitStepper` of the above).
        seed: the first fit's seed (the collector is seeded by its own argument).
        progress: TorchRL's progress bar with the last return, model error and u.
        logger: a TorchRL logger: the Trainer's metrics and the fits' validation losses.
        on_iteration: called with each :class:`~torchrl_recon.fitting.online.IterationRecord`.
        reward_model: a learned reward and termination the planners read
            (:class:`~torchrl_recon.modules.RewardModel`), fitted with the world model and in
            the Trainer's checkpoints; None (default) when the cost is given.
        hooks: more Trainer hooks (TorchRL's or the library's), each registered at its default
            stage after the above.
        trainer_kwargs: more of ``Trainer``'s keywords (``save_trainer_file``, ``checkpoint``,
            ``log_timings``, ...). Checkpoints are a :class:`VerifiedTrainer`'s: checked
            against a manifest of their files' sizes and SHA-256 before anything is loaded.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
        >>> env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
        >>> world = LSTMWorldModel(3, 1, window=4)
        >>> cost = lambda s, a, s1: s1[..., 2].pow(2) + (1 - s1[..., 0])
        >>> planner = CEMPlanner(PlanningModel.from_env(world, cost, env), Objective(), horizon=5,
        ...                      num_candidates=16, iterations=2, num_elites=4)
        >>> collector = OnlineCollector(env, MPCPolicy(planner), iterations=1,
        ...                             steps_per_iteration=20, random_steps=60)
        >>> trainer = OnlineTrainer(collector=collector, world_model=world, estimator=None,
        ...     schedule=FitSchedule(steps=4, refit_steps=2, eval_every=2, slice_len=8,
        ...                          num_slices=4, val_fraction=0.34), progress=False)
        >>> trainer.train()
        >>> [(r.iteration, r.policy, r.env_steps) for r in trainer.records]
        [(0, 'random', 60), (1, 'mpc', 80)]
    """

    def __init__(
        self,
        *,
        collector: Any,
        world_model: LSTMWorldModel,
        estimator: UncertaintyEstimator | None,
        schedule: FitSchedule | None = None,
        replay_buffer: ReplayBuffer | None = None,
        stepper: ModelFitStepper | None = None,
        seed: int = 0,
        progress: bool = True,
        logger: Logger | None = None,
        on_iteration: Callable[[IterationRecord], None] | None = None,
        reward_model: RewardModel | None = None,
        hooks: Sequence[TrainerHookBase] | None = None,
        **trainer_kwargs: Any,
    ) -> None:
        check_type(
            "collector",
            collector,
            BaseCollector,
            "a torchrl collector (an OnlineCollector or torchrl's Collector)",
        )
        schedule = schedule or FitSchedule()
        if replay_buffer is None:
            replay_buffer = ReplayBuffer(storage=LazyTensorStorage(collector.total_frames))
        if stepper is None:
            stepper = ModelFitStepper(
                world_model,
                estimator,
                replay_buffer,
                schedule=schedule,
                seed=seed,
                progress=progress,
                logger=logger,
                reward_model=reward_model,
            )
        trainer_kwargs.setdefault("log_interval", 0)  # every batch is an iteration: log each
        super().__init__(
            collector=collector,
            total_frames=collector.total_frames,
            frame_skip=1,
            optim_steps_per_batch=1,
            loss_module=WorldModelPredictionLoss(world_model, mode=schedule.mode),
            optimization_stepper=stepper,
            logger=logger,
            progress_bar=progress,
            **trainer_kwargs,
        )
        self.buffer = replay_buffer  # not Trainer's replay_buffer: see ReplayBufferSteps
        self.register_op("batch_process", quiet_extend(ReplayBufferTrainer(replay_buffer)))
        ReplayBufferSteps(replay_buffer).register(self)
        self.log_iteration = LogIteration(
            world_model, estimator, slice_len=schedule.slice_len, on_iteration=on_iteration
        )
        self.log_iteration.register(self)
        if estimator is not None:
            self.register_module("uncertainty", estimator)
        if reward_model is not None:
            self.register_module("reward_model", reward_model)
        for hook in hooks or ():
            if not isinstance(hook, TrainerHookBase):
                raise TypeError(
                    f"hooks must be TrainerHookBase instances, got {type(hook).__name__}."
                )
            hook.register(self)

    @classmethod
    def from_env(
        cls,
        env: EnvBase,
        world_model: LSTMWorldModel,
        estimator: UncertaintyEstimator | None,
        make_planner: Callable[[], PlannerBase] | None,
        *,
        iterations: int,
        steps_per_iteration: int,
        random_steps: int,
        schedule: FitSchedule | None = None,
        make_policy: Callable[[PlannerBase], MPCPolicy] = MPCPolicy,
        explore_iterations: int = 0,
        make_explorer: Callable[[], PlannerBase] | None = None,
        seed: int = 0,
        progress: bool = True,
        **kwargs: Any,
    ) -> OnlineTrainer:
        """The online agent's Trainer from its planners: the one builder, which
        :func:`learn_online` and the config store's ``trainer: online``
        (:func:`~torchrl_recon.trainers.configs.make_online_trainer`) call. An
        :class:`OnlineCollector` plays ``make_policy(make_planner())`` on ``env`` (an
        :class:`~torchrl_recon.policies.ExplorationPolicy` of ``make_explorer()`` in the first
        ``explore_iterations``); the learned reward model the planners read, if any, is fitted
        with the networks (``learned_reward``). Every argument is checked before the env
        is touched (the schedule before a planner is built).

        Args:
            env, world_model, estimator: as in :func:`learn_online`.
            make_planner: returns the controlling planner; called once, here (None when every
                iteration explores).

        Keyword Args:
            make_policy: wraps the planner into the MPC policy (default
                :class:`~torchrl_recon.policies.MPCPolicy`).
            make_explorer: returns the exploring planner (needs an ``estimator``).
            kwargs: this class's other keywords (``logger``, ``on_iteration``, ``hooks``, ...).

        Examples:
            >>> from torchrl_recon.envs import make_env
            >>> from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
            >>> env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
            >>> world = LSTMWorldModel(3, 1, window=4)
            >>> cost = lambda s, a, s1: s1[..., 2].pow(2) + (1 - s1[..., 0])
            >>> model = PlanningModel.from_env(world, cost, env)
            >>> trainer = OnlineTrainer.from_env(env, world, None,
            ...     lambda: CEMPlanner(model, Objective(), horizon=5, num_candidates=16,
            ...                        num_elites=4),
            ...     iterations=1, steps_per_iteration=20, random_steps=60, progress=False)
            >>> trainer.collector.policy_name(1), trainer.collector.total_frames
            ('mpc', 80)
        """
        controls = iterations > explore_iterations
        check_online(iterations, steps_per_iteration, random_steps, explore_iterations, schedule)
        if explore_iterations and (make_explorer is None or estimator is None):
            raise ValueError(
                f"explore_iterations={explore_iterations} needs make_explorer and an estimator "
                "(exploration seeks the estimator's uncertainty)."
            )
        if controls and make_planner is None:
            raise ValueError(
                f"iterations={iterations} with explore_iterations={explore_iterations}: the "
                "MPC iterations need make_planner."
            )
        explorer = ExplorationPolicy(make_explorer()) if explore_iterations else None
        policy = make_policy(make_planner()) if controls else None
        planners = [p.planner for p in (policy, explorer) if p is not None]
        collector = OnlineCollector(
            env,
            policy,
            iterations=iterations,
            steps_per_iteration=steps_per_iteration,
            random_steps=random_steps,
            explorer=explorer,
            explore_iterations=explore_iterations,
            seed=seed,
            progress=progress,
        )
        return cls(
            collector=collector,
            world_model=world_model,
            estimator=estimator,
            schedule=schedule,
            seed=seed,
            progress=progress,
            reward_model=learned_reward(planners),
            **kwargs,
        )

    @property
    def records(self) -> list[IterationRecord]:
        """One record per batch collected so far, the random data's (iteration 0) first."""
        return self.log_iteration.records

    def data(self) -> TensorDictBase:
        """Every step collected so far, in order."""
        return self.buffer[:]


def learn_online(
    env: EnvBase,
    world_model: LSTMWorldModel,
    estimator: UncertaintyEstimator | None,
    make_planner: Callable[[], PlannerBase],
    *,
    iterations: int,
    steps_per_iteration: int,
    random_steps: int,
    schedule: FitSchedule | None = None,
    policy_kwargs: dict | None = None,
    explore_iterations: int = 0,
    make_explorer: Callable[[], PlannerBase] | None = None,
    seed: int = 0,
    progress: bool = False,
    logger: Logger | None = None,
    on_iteration: Callable[[IterationRecord], None] | None = None,
) -> tuple[list[IterationRecord], TensorDictBase]:
    """Learn a task online through an :class:`OnlineTrainer`: ``random_steps`` random steps,
    then ``iterations`` rounds of ``steps_per_iteration`` MPC steps, refitting both networks
    after each round; the first ``explore_iterations`` of those rounds explore instead of
    controlling.

    Args:
        env: the TorchRL env (episodes of its own length; terminations end them early); each
            policy plays it through a ``TransformedEnv`` that adds the policy's primer.
        world_model, estimator: the networks the planner's model holds (``estimator`` may be
            None for β = 0).
        make_planner: returns the planner (its model built on ``world_model`` and
            ``estimator``); called once, before the first fit (it plans only after it).

    Keyword Args:
        policy_kwargs: keywords of :class:`~torchrl_recon.policies.MPCPolicy` (re-planning).
        explore_iterations: how many of the ``iterations`` rounds (the first ones) an
            :class:`~torchrl_recon.policies.ExplorationPolicy` plays, seeking high but capped u
            (paper §2.4) to widen the data before control starts; needs ``make_explorer``
            and an ``estimator``.
        make_explorer: returns the exploring planner, whose objective comes from
            :func:`~torchrl_recon.policies.exploration_objective`.
        on_iteration: called with each record as it is made (e.g. to log or save).

    Returns:
        The records (iteration 0 is the random data) and all data collected (the env's keys).

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
        >>> env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
        >>> world = LSTMWorldModel(3, 1, window=4)
        >>> cost = lambda s, a, s1: s1[..., 2].pow(2) + (1 - s1[..., 0])
        >>> model = PlanningModel.from_env(world, cost, env)
        >>> records, data = learn_online(env, world, None,
        ...     lambda: CEMPlanner(model, Objective(), horizon=5, num_candidates=16, iterations=2,
        ...                        num_elites=4),
        ...     iterations=1, steps_per_iteration=20, random_steps=60,
        ...     schedule=FitSchedule(steps=4, refit_steps=2, eval_every=2, slice_len=8, num_slices=4,
        ...                          val_fraction=0.34))
        >>> [r.iteration for r in records], [r.env_steps for r in records], len(data)
        ([0, 1], [60, 80], 80)
    """
    try:  # checked, like every argument, before the random data are collected
        inspect.signature(MPCPolicy).bind(None, **(policy_kwargs or {}))
    except TypeError as err:
        raise TypeError(f"policy_kwargs: {err} (they are MPCPolicy's keywords).") from None
    trainer = OnlineTrainer.from_env(
        env,
        world_model,
        estimator,
        make_planner,
        iterations=iterations,
        steps_per_iteration=steps_per_iteration,
        random_steps=random_steps,
        schedule=schedule,
        make_policy=functools.partial(MPCPolicy, **(policy_kwargs or {})),
        explore_iterations=explore_iterations,
        make_explorer=make_explorer,
        seed=seed,
        progress=progress,
        logger=logger,
        on_iteration=on_iteration,
    )
    trainer.train()
    return trainer.records, trainer.data()


def check_online(
    iterations: int,
    steps_per_iteration: int,
    random_steps: int,
    explore_iterations: int,
    schedule: Any,
) -> None:
    """Refuse an online schedule out of range (:func:`~.collector.check_schedule`) or a
    ``schedule`` that is not a :class:`~torchrl_recon.fitting.online.FitSchedule` (or None).

    Examples:
        >>> check_online(2, 10, 20, 0, {"steps": 2})
        Traceback (most recent call last):
        ...
        TypeError: schedule must be a FitSchedule or None, got dict.
    """
    check_schedule(iterations, steps_per_iteration, random_steps, explore_iterations)
    if schedule is not None and not isinstance(schedule, FitSchedule):
        raise TypeError(f"schedule must be a FitSchedule or None, got {type(schedule).__name__}.")


def learned_reward(planners: list[PlannerBase]) -> RewardModel | None:
    """The one :class:`~torchrl_recon.modules.RewardModel` the ``planners``' models read (a
    learned cost or termination), or None; two different ones are refused (one fit trains one).
    """
    found = {id(m): m for p in planners if (m := p.model.reward_model) is not None}
    if len(found) > 1:
        raise ValueError(
            "the planners read different learned reward models; build them on one RewardModel "
            "(the fits train one)."
        )
    return next(iter(found.values()), None)
