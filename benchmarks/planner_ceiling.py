"""The planner's ceiling on a MuJoCo task: the same planner with the true simulator as its model.

Run: python benchmarks/planner_ceiling.py --task InvertedDoublePendulum-v5 --planner cem
     [--horizon 30] [--candidates 350] [--iterations 5] [--episodes 3] [--steps N]
     [--seed 0] [--threads 1] [--kwargs '{"warm_start_uniform": 0}'] [--out ceiling.jsonl]
     [--shape '{"0": 1.0}']

What it separates: when an agent with a learned model falls short on a task, is it the model or
the planner? Here the planner (the library's CEM, MPPI, iCEM or random shooting, with the
task's cost and termination from ``torchrl_recon.envs.gym_costs``) plans every step from the
env's exact state with MuJoCo itself as its model: each candidate is rolled out by
``mujoco.rollout`` (all candidates in one call, the env's ``frame_skip`` sim steps an action),
so the plan is what the planner would choose with a perfect model. Each episode runs MPC
(re-plan every step, the rest of the last plan as the warm start, as ``MPCPolicy`` does) and the
script prints the env's own return and length per episode, and the mean plan time a step.

The simulator model reads the live env's state, so it is a benchmark device, not a part of the
library: a learned model sees only observations.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import torch
from mujoco import rollout

from torchrl_recon.envs import gym_costs
from torchrl_recon.planners import Objective, PlanningModel
from torchrl_recon.planners.registry import PLANNERS

FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS


def _double_pendulum_obs(qpos: torch.Tensor, qvel: torch.Tensor) -> torch.Tensor:
    """InvertedDoublePendulum-v5's observation of states ``[..., 3]``, ``[..., 3]`` (its last
    entry, a constraint force, is not in the rolled-out state: 0, which no cost reads)."""
    angles = qpos[..., 1:]
    force = torch.zeros_like(qpos[..., :1])
    return torch.cat([qpos[..., :1], angles.sin(), angles.cos(), qvel.clamp(-10, 10), force], -1)


def _reacher_obs(qpos: torch.Tensor, qvel: torch.Tensor) -> torch.Tensor:
    """Reacher-v5's observation of states ``[..., 4]``, ``[..., 4]`` (fingertip from the arm's
    0.1 m and 0.11 m links)."""
    a, b = qpos[..., 0], qpos[..., 0] + qpos[..., 1]
    tip = torch.stack([0.1 * a.cos() + 0.11 * b.cos(), 0.1 * a.sin() + 0.11 * b.sin()], -1)
    theta = qpos[..., :2]
    return torch.cat(
        [theta.cos(), theta.sin(), qpos[..., 2:], qvel[..., :2], tip - qpos[..., 2:]], -1
    )


TASKS: dict[str, tuple[Callable, Callable, Callable | None]] = {
    "InvertedPendulum-v5": (
        lambda qpos, qvel: torch.cat([qpos, qvel], -1),
        gym_costs.inverted_pendulum,
        gym_costs.inverted_pendulum_fallen,
    ),
    "InvertedDoublePendulum-v5": (
        _double_pendulum_obs,
        gym_costs.inverted_double_pendulum,
        gym_costs.inverted_double_pendulum_fallen,
    ),
    "Reacher-v5": (_reacher_obs, gym_costs.reacher, None),
    "HalfCheetah-v5": (
        lambda qpos, qvel: torch.cat([qpos[..., 1:], qvel], -1),
        gym_costs.half_cheetah,
        None,
    ),
}
"""Each task's observation of the simulator's (qpos, qvel), its cost and its termination."""


def shaped(cost: Callable, weights: dict[int | str, float]) -> Callable:
    """``cost`` plus Σ wᵢ·xᵢ² over the observation entries ``weights`` names (of the state a
    step reaches), and w·Σ a² of the action under the key ``"a"``: a quadratic shaping on top
    of the env's own reward, to ask whether the planner's objective, not its search, is what
    limits it.

    Examples:
        >>> cost = shaped(lambda s, a, s2: s2[..., 1], {0: 2.0, "a": 1.0})
        >>> cost(None, torch.tensor([[0.5]]), torch.tensor([[0.5, 1.0]]))
        tensor([1.7500])
    """
    entries = sorted(k for k in weights if k != "a")
    index, weight = (
        torch.tensor(entries, dtype=torch.long),
        torch.tensor([weights[i] for i in entries]),
    )
    action_weight = weights.get("a", 0.0)

    def shaped_cost(obs, action, next_obs):
        extra = (next_obs[..., index].pow(2) * weight.to(next_obs)).sum(-1)
        if action_weight:
            extra = extra + action_weight * action.pow(2).sum(-1)
        return cost(obs, action, next_obs) + extra

    return shaped_cost


class SimulatorModel:
    """A planning model's world model that is the env's own MuJoCo simulator: ``imagine`` rolls
    every candidate out from the env's current exact state (``mujoco.rollout``, one call)."""

    window = 1

    def __init__(self, env: gym.Env, observe: Callable) -> None:
        self.env, self.observe = env.unwrapped, observe
        self.obs_dim = env.observation_space.shape[0]
        self.action_dim = env.action_space.shape[0]
        model = self.env.model
        self.nq, self.nv, self.skip = model.nq, model.nv, self.env.frame_skip
        self.datas = [mujoco.MjData(model) for _ in range(torch.get_num_threads())]

    def imagine(self, context_obs, context_action, observation, actions) -> torch.Tensor:
        """The observations each candidate ``[*B, K, H, M]`` reaches, ``[*B, K, H, N]``."""
        env = self.env
        state = np.empty(mujoco.mj_stateSize(env.model, FULL))
        mujoco.mj_getState(env.model, env.data, state, FULL)
        *lead, horizon, m = actions.shape
        control = actions.detach().reshape(-1, horizon, m).double().numpy()
        control = np.repeat(
            control, self.skip, axis=1
        )  # the env holds each action frame_skip steps
        states, _ = rollout.rollout(env.model, self.datas, state[None], control)
        states = torch.from_numpy(states[:, self.skip - 1 :: self.skip]).to(actions.dtype)
        qpos, qvel = states[..., 1 : 1 + self.nq], states[..., 1 + self.nq : 1 + self.nq + self.nv]
        return self.observe(qpos, qvel).reshape(*lead, horizon, self.obs_dim)


def run_episode(env: gym.Env, planner, seed: int, steps: int) -> dict:
    """One episode of MPC with ``planner`` (re-plan every step, warm-started with the rest of
    the last plan): the env's return, its length and the mean plan time."""
    obs, _ = env.reset(seed=seed)
    torch.manual_seed(seed)
    m = env.action_space.shape[0]
    prev_obs, prev_action = torch.as_tensor(obs).float(), torch.zeros(m)
    init, total, plan_s, length = None, 0.0, 0.0, 0
    while length < steps:
        length += 1
        start = time.perf_counter()
        result = planner.plan(
            prev_obs[None], prev_action[None], torch.as_tensor(obs).float(), init=init
        )
        plan_s += time.perf_counter() - start
        action = result.actions[0]
        init = torch.cat([result.actions[1:], torch.zeros(1, m)])
        prev_obs, prev_action = torch.as_tensor(obs).float(), action
        obs, reward, terminated, truncated, _ = env.step(action.numpy())
        total += float(reward)
        if terminated or truncated:
            break
        if length % 25 == 0:  # a run stopped mid-episode still shows how far it got
            print(f"    step {length}: return {total:.1f} so far, obs[0] {obs[0]:.3f}", flush=True)
    last = [round(float(v), 4) for v in obs]  # where it ended: IDP's cart x at the rail, say
    return {"return": total, "length": length, "plan_ms": 1000 * plan_s / length, "last_obs": last}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(TASKS), default="InvertedDoublePendulum-v5")
    parser.add_argument("--planner", choices=["cem", "mppi", "icem", "shooting"], default="cem")
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--candidates", type=int, default=350)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument(
        "--steps", type=int, default=None, help="episode length (default: the env's own limit)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--kwargs", type=json.loads, default={}, help="more planner keywords, as a JSON object"
    )
    parser.add_argument("--out", type=Path, default=None, help="append the result as a JSON line")
    parser.add_argument(
        "--shape",
        type=json.loads,
        default={},
        help="add Σ w·x² of these observation entries to the cost, as a JSON object "
        '{"index": weight} (IDP: 0 the cart\'s x, 5-7 the speeds); "a": w·Σ a² of the action',
    )
    args = parser.parse_args()
    try:
        args.shape = {(k if k == "a" else int(k)): float(w) for k, w in args.shape.items()}
    except (AttributeError, TypeError, ValueError):
        parser.error(f"--shape must map observation indices to weights, got {args.shape!r}")
    torch.set_num_threads(args.threads)
    observe, cost, termination = TASKS[args.task]
    if args.steps is None:  # the task's own episodes (Reacher-v5: 50 steps; the pendulums: 1,000)
        args.steps = gym.spec(args.task).max_episode_steps
    env = gym.make(args.task, max_episode_steps=args.steps)
    sim = SimulatorModel(env, observe)
    if bad := [i for i in args.shape if i != "a" and not 0 <= i < sim.obs_dim]:
        parser.error(f"--shape names observation entries {bad}; {args.task} has {sim.obs_dim}")
    low, high = (
        torch.as_tensor(b, dtype=torch.float32)
        for b in (env.action_space.low, env.action_space.high)
    )
    if args.shape:
        cost = shaped(cost, args.shape)
    model = PlanningModel(sim, cost, termination_fn=termination, action_low=low, action_high=high)
    kwargs = dict(horizon=args.horizon, num_candidates=args.candidates)
    if args.planner != "shooting":
        kwargs |= dict(iterations=args.iterations)
    if args.planner in ("cem", "icem"):
        kwargs |= dict(num_elites=max(2, args.candidates // 10))
    planner = PLANNERS[args.planner](model, Objective(), **(kwargs | args.kwargs))
    print(
        f"{args.task}: {args.planner} {args.candidates} x {args.iterations} x H {args.horizon} "
        f"{args.kwargs or ''}, "
        f"the true simulator as its model, {args.episodes} episodes of at most {args.steps} steps"
    )
    episodes = []
    for e in range(args.episodes):
        episodes.append(run_episode(env, planner, args.seed + e, args.steps))
        print(
            f"  episode {e}: return {episodes[-1]['return']:.1f}, {episodes[-1]['length']} steps, "
            f"{episodes[-1]['plan_ms']:.1f} ms a plan",
            flush=True,
        )
    returns = [ep["return"] for ep in episodes]
    print(
        f"mean return {np.mean(returns):.1f} ± {np.std(returns):.1f} over {len(returns)} episodes"
    )
    if args.out is not None:
        record = vars(args) | {
            "out": None,
            "episodes": episodes,
            "mean_return": float(np.mean(returns)),
        }
        with args.out.open("a") as f:
            f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
