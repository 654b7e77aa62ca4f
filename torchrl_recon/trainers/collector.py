"""The online agent's data source for TorchRL's ``Trainer``: one batch per iteration."""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Iterator
from typing import Any

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_recon.collectors import collect, collect_random, renumber_trajectories
from torchrl_recon.modules.checks import FIX_ENV, check_finite_keys, check_int, check_type
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.policies.mpc import REPLANNED


class TimedPolicy(TensorDictModuleBase):
    """``policy`` with the wall time of its calls summed in ``seconds`` (the planning time of a
    collection: the rest is the env's).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> timed = TimedPolicy(TensorDictModule(torch.nn.Linear(2, 1), ["x"], ["action"]))
        >>> _ = timed(TensorDict({"x": torch.zeros(2)}, []))
        >>> timed.seconds > 0, timed.out_keys
        (True, ['action'])
    """

    def __init__(self, policy: TensorDictModuleBase) -> None:
        super().__init__()
        check_type("policy", policy, TensorDictModuleBase, "a TensorDict policy (e.g. MPCPolicy)")
        self.policy, self.seconds = policy, 0.0
        self.in_keys, self.out_keys = policy.in_keys, policy.out_keys

    def make_tensordict_primer(self):
        """The wrapped policy's primer (an MPC policy's state, to append to the env)."""
        return self.policy.make_tensordict_primer()

    @property
    def spec(self) -> Any:
        """The wrapped policy's output specs, or None where it has none.

        TorchRL's ``Collector`` reads them at construction instead of calling the policy before
        any data."""
        return getattr(self.policy, "spec", None)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        out = self.policy(tensordict)
        self.seconds += time.perf_counter() - start
        return out


def play(
    env: EnvBase, policy: MPCPolicy, *, frames: int, seed: int, progress: bool = False
) -> tuple[TensorDictBase, float]:
    """``frames`` steps of ``policy`` on ``env`` (the policy's primer appended) through
    TorchRL's ``Collector``, seeded with ``seed``; returns the steps and the seconds spent
    planning."""
    check_type("env", env, EnvBase, "a torchrl env (make_env)")
    check_int("frames", frames)
    timed = TimedPolicy(policy)
    data = collect(env, timed, frames=frames, seed=seed, progress=progress, desc="mpc")
    return data, timed.seconds


class IterationCollector(BaseCollector):
    """A collector for TorchRL's ``Trainer`` that yields one batch per iteration of an online
    schedule: iteration 0 is ``random_steps`` random steps, each iteration ``1..iterations``
    ``steps_per_iteration`` steps of a policy (an explorer in the first
    ``explore_iterations``). Subclasses say how an iteration's steps are had
    (:meth:`collect_iteration`); this class numbers the trajectories on from the earlier
    batches' (a ``SliceSampler`` never joins two iterations' episodes), counts iterations
    (``state_dict``) and sets ``init_random_frames`` to ``random_steps``, so the Trainer fits
    after the random batch and after every later one. A batch holding NaN or inf (an
    observation, action or reward) is refused before the Trainer sees it (``check_batch``).
    :attr:`batch_info` describes the last
    batch (``iteration``, ``policy``, ``plan_s``, ``env_s``, ``replans``) for
    :class:`~torchrl_recon.trainers.LogIteration`.
    """

    trajs_per_batch = None

    def __init__(
        self,
        *,
        iterations: int,
        steps_per_iteration: int,
        random_steps: int,
        explore_iterations: int = 0,
    ) -> None:
        super().__init__()
        check_schedule(iterations, steps_per_iteration, random_steps, explore_iterations)
        self.iterations, self.steps_per_iteration = iterations, steps_per_iteration
        self.random_steps, self.explore_iterations = random_steps, explore_iterations
        self.init_random_frames = random_steps
        self.total_frames = random_steps + iterations * steps_per_iteration
        self.requested_frames_per_batch = steps_per_iteration
        self.iteration = 0  # the next one to collect
        self.next_traj_id = 0
        self.batch_info: dict[str, Any] = {}
        """The last batch's ``iteration``, ``policy``, ``plan_s``, ``env_s`` and ``replans``."""

    def policy_name(self, iteration: int) -> str:
        """Which policy plays ``iteration``: ``"random"``, ``"explore"`` or ``"mpc"``."""
        if iteration == 0:
            return "random"
        return "explore" if iteration <= self.explore_iterations else "mpc"

    def collect_iteration(self, iteration: int) -> TensorDictBase:
        """``iteration``'s steps (flat, the env's keys); sets :attr:`batch_info`."""
        raise NotImplementedError

    def iterator(self) -> Iterator[TensorDictBase]:
        while self.iteration <= self.iterations:
            data = self.renumber(self.collect_iteration(self.iteration))
            check_batch(data, f"iteration {self.iteration}'s batch")
            self.iteration += 1  # before the yield: a Trainer checkpoints while it holds the batch
            yield data

    def renumber(self, data: TensorDictBase) -> TensorDictBase:
        """``data`` with trajectory ids ``0, 1, ...`` in their order, shifted past the ids of the
        batches before it (as :func:`~torchrl_recon.collectors.concat_trajectories` numbers them)."""
        data, self.next_traj_id = renumber_trajectories(data.clone(False), self.next_traj_id)
        return data

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Iterations are seeded by the subclass (each its own seed); nothing to set."""
        return seed

    def state_dict(self) -> OrderedDict:
        return OrderedDict(iteration=self.iteration, next_traj_id=self.next_traj_id)

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        self.iteration = int(state_dict["iteration"])
        self.next_traj_id = int(state_dict["next_traj_id"])

    def shutdown(
        self, timeout: float | None = None, close_env: bool = True, raise_on_error: bool = True
    ) -> None:
        """Nothing to stop: each iteration's collection ends with it (its env is the caller's)."""

    def __len__(self) -> int:
        return self.iterations + 1


class OnlineCollector(IterationCollector):
    """The online agent's :class:`IterationCollector`: each iteration ``i`` is played through
    TorchRL's own ``Collector`` on fresh episodes seeded ``seed + i`` (iteration 0 with uniform
    random actions, then ``policy`` or ``explorer`` with its primer appended to ``env``): an
    iteration's data depend on the models and its seed only, so a run resumed at any iteration
    collects what an uninterrupted one does. Each batch holds the env's keys only (the
    policy's state keys are dropped, so every batch fits one replay-buffer storage).

    Args:
        env: the TorchRL env (CPU; episodes of its own length).
        policy: the MPC policy; called only after the first fit (a policy whose models were
            never fitted refuses to plan).

    Keyword Args:
        iterations, steps_per_iteration, random_steps: the schedule.
        explorer, explore_iterations: an :class:`~torchrl_recon.policies.ExplorationPolicy`
            that plays the first ``explore_iterations`` iterations.
        seed: iteration ``i`` is seeded ``seed + i``.
        progress: a progress bar per collection.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
        >>> collector = OnlineCollector(env, None, iterations=0, steps_per_iteration=20,
        ...                             random_steps=40)
        >>> [batch.numel() for batch in collector], collector.batch_info["policy"]
        ([40], 'random')
    """

    def __init__(
        self,
        env: EnvBase,
        policy: MPCPolicy | None,
        *,
        iterations: int,
        steps_per_iteration: int,
        random_steps: int,
        explorer: MPCPolicy | None = None,
        explore_iterations: int = 0,
        seed: int = 0,
        progress: bool = False,
    ) -> None:
        super().__init__(
            iterations=iterations,
            steps_per_iteration=steps_per_iteration,
            random_steps=random_steps,
            explore_iterations=explore_iterations,
        )
        check_type("env", env, EnvBase, "a torchrl env (make_env)")
        for name, value in (("policy", policy), ("explorer", explorer)):
            if value is not None:
                check_type(name, value, MPCPolicy, "an MPCPolicy (or ExplorationPolicy) or None")
        if explore_iterations and explorer is None:
            raise ValueError(f"explore_iterations={explore_iterations} needs an explorer.")
        if iterations > explore_iterations and policy is None:
            raise ValueError(
                f"iterations={iterations} with explore_iterations={explore_iterations}: the "
                "MPC iterations need a policy."
            )
        self.env, self.seed, self.progress = env, seed, progress
        self.policies = {"mpc": policy, "explore": explorer}
        self._envs: dict[str, EnvBase] = {}

    def collect_iteration(self, iteration: int) -> TensorDictBase:
        """Play ``iteration``'s steps and set :attr:`batch_info`."""
        start, name = time.perf_counter(), self.policy_name(iteration)
        if iteration == 0:
            data = collect_random(
                self.env, frames=self.random_steps, seed=self.seed, progress=self.progress
            )
            plan_s, replans = 0.0, 0
        else:
            policy = self.policies[name]
            if name not in self._envs:
                primer = policy.make_tensordict_primer()
                self._envs[name] = TransformedEnv(self.env, primer, auto_unwrap=False)
            data, plan_s = play(
                self._envs[name],
                policy,
                frames=self.steps_per_iteration,
                seed=self.seed + iteration,
                progress=self.progress,
            )
            replans = int(data[REPLANNED].sum())
            data = data.select(*env_keys(data, self.env))
        env_s = time.perf_counter() - start - plan_s
        self.batch_info = dict(
            iteration=iteration, policy=name, plan_s=plan_s, env_s=env_s, replans=replans
        )
        return data

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Seed iteration ``i`` with ``seed + i`` from now on."""
        self.seed = seed
        return seed


COLLECTED_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"))
"""What the online agent's fits and records read of a collected step (checked finite)."""


def check_batch(data: TensorDictBase, where: str = "the collected batch") -> None:
    """Refuse a collected batch whose observation, action, next observation or reward holds
    NaN or inf, before any fit or record reads it: one ``ValueError`` naming the key and the
    first row (a key the batch lacks is skipped).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> batch = TensorDict({("next", "reward"): torch.zeros(5, 1)}, [5])
        >>> batch["next", "reward"][3] = float("nan")
        >>> check_batch(batch)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: ('next', 'reward') in the collected batch holds NaN or inf (first at row 3, feature 0); the env returned it: ...
    """
    check_finite_keys(data, COLLECTED_KEYS, where=where, remedy=FIX_ENV)


def check_schedule(
    iterations: int, steps_per_iteration: int, random_steps: int, explore_iterations: int = 0
) -> None:
    """Refuse an online schedule out of range, naming the value.

    Examples:
        >>> check_schedule(2, 10, 20, explore_iterations=3)
        Traceback (most recent call last):
        ...
        ValueError: explore_iterations=3 must be between 0 and iterations=2.
    """
    check_int("iterations", iterations, minimum=0)
    check_int("steps_per_iteration", steps_per_iteration)
    check_int("random_steps", random_steps)
    if not 0 <= explore_iterations <= iterations:
        raise ValueError(
            f"explore_iterations={explore_iterations} must be between 0 and "
            f"iterations={iterations}."
        )


def env_keys(data: TensorDictBase, env: EnvBase) -> list:
    """The leaf keys of ``data`` that a random collection from ``env`` holds too: the env's
    observations, action, reward, done flags and the collector's trajectory ids."""
    check_type("data", data, TensorDictBase, "a TensorDict of collected steps")
    check_type("env", env, EnvBase, "a torchrl env")
    specs = (env.full_observation_spec, env.full_action_spec, env.full_done_spec)
    own = {k for spec in specs for k in spec.keys(True, True)}
    own |= {("next", k) for k in own} | {("next", k) for k in env.full_reward_spec.keys(True, True)}
    own = {k[0] if isinstance(k, tuple) and len(k) == 1 else k for k in own}
    return [k for k in data.keys(True, True) if k in own or _under(k, "collector")]


def _under(key, root: str) -> bool:
    return isinstance(key, tuple) and key[0] == root
