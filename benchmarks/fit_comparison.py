"""The library's fit against TorchRL's plain optimiser step on InvertedDoublePendulum-v5, on the
world model's error (issue 55, item 6: why did the agent fitted by ``ModelFitStepper`` score
94-192 where TorchRL's own optimiser step on ``WorldModelPredictionLoss`` scored 259.7?).

Run: OMP_NUM_THREADS=1 python benchmarks/fit_comparison.py [--seeds 0 1 2] [--frames 4000]
     [--steps 1000] [--train random mixed] [--threads 1] [--out FILE.json]

What it measures, per seed (training data, split, weights and batches all drawn from it):

* Data, collected by the library's own path (``make_env`` + ``collect_random``/``collect``,
  TorchRL's ``Collector``): ``random``, ``--frames`` uniform random steps (the online recipe's
  first data; IDP's random episodes last ~5-10 steps); ``mixed``, the first quarter of them
  plus three quarters of steps of a noisy stabilising controller (what later online fits see:
  short random episodes beside longer ones). The controller is a linear state feedback (LQR,
  Q = I, R = 1, on MuJoCo's own model linearised upright by finite differences of one env
  step) plus Gaussian action noise σ = 0.4, clipped to the action bounds; its episodes
  (at most 100 steps) last ~6-90 steps, ~20 (median).
* Two test sets of separate episodes (the same for every seed): ``random`` (uniform random
  actions) and ``ctrl`` (the noisy controller, closer to what MPC visits).
* The world model of ``gym/online_inverted_double_pendulum`` (its sizes, window 4, one-step
  loss), fitted from the same initial weights at the same budget of ``--steps`` gradient steps
  (the recipe's first fit: 1,000) in several ways:

  - ``plain``: TorchRL's way, as a ``Trainer`` with its default optimiser step does it:
    ``FitNormalization`` on the first (random) batch, then one Adam step (the recipe's lr,
    constant, no clipping) per batch of 32 slices sampled from all the data by TorchRL's
    ``SliceSampler`` (short episodes padded: ``make_sequence_buffer(pad_short=True)``), no
    validation, the last weights.
  - ``library``: ``fit_models``' world-model fit with the recipe's ``FitSchedule`` (split by
    trajectory, ``val_fraction`` 0.2 held out, slices of 20, every episode that ended shorter
    padded (``short_episodes="pad"``); cosine lr to lr/20, gradient norm clipped at 10,
    validation every 100 steps, patience 10, best weights). ``the rule before 2026-11-29``:
    ``short_episodes="pad_if_no_window"``, padded only when a split holds no trajectory of 20
    steps, else the shorter ones left out (what the fits did until then).
  - ablations of ``library``, one factor each: ``patience None`` (no early stopping),
    ``val_fraction 0.05``, ``slice 10`` (as ``fit_models`` pads: not at all on random data,
    which holds episodes of 10 steps), ``slice 10 padded`` and ``slice 20 padded`` (padding
    forced on), and ``FitSchedule()``'s own sizes (slices of 40, ``val_fraction`` 0.1, what a
    ``ModelFitStepper`` given no schedule fits with); and ``plain`` with the library's
    optimiser (its cosine lr, then also its clipping). On ``mixed`` data: ``plain``, the recipe,
    the rule before, the recipe padded, ``FitSchedule()``.

* Errors on each test set, from every step of every episode, as the planner predicts: a context
  of the 4 steps before (before an episode's start: its first observation and the zero action,
  as ``MPCPolicy(warmup="plan")``), then ``imagine`` with the real actions. ``1-step``: the
  mean square of the predicted next state's error over the test set's standard deviation of
  the state change Δs, per dim (the standardised Δs error). ``10-step``: the open-loop rollout
  of up to 10 steps (fewer where the episode ends), the mean square of each predicted state's
  error over the test set's state standard deviation, over all predicted steps. Both over the
  first 8 dims: the 9th, the constraint force, is read by no cost or termination and is 0 in
  all random data (no model fitted on it can predict the force at the rail, which the
  controller's episodes reach). Also: the gradient steps each fit ran, the step whose weights
  it kept, the training episodes (and steps) its sampler can draw, and its wall time.

Prints a table (mean ± std over seeds); ``--out`` appends one JSON line per arm (per-seed
figures included). The default run (3 seeds, 4,000 frames, 1,000 steps, 39 fits) took 5-8
minutes on one thread of a 2-core machine shared with other jobs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_recon.collectors import collect, collect_random, concat_trajectories
from torchrl_recon.data import (
    FIT_KEYS,
    TRAJ_KEY,
    make_sequence_buffer,
    needs_padding,
    sequence_buffers,
    split_by_trajectory,
)
from torchrl_recon.envs import closing_env, make_env
from torchrl_recon.experiments.online import recipe_schedule
from torchrl_recon.experiments.recipe import load_recipe, resolve_recipe_path
from torchrl_recon.experiments.recipe_models import build_world_model
from torchrl_recon.fitting import FitSchedule, fit_world_model
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.objectives import WorldModelPredictionLoss
from torchrl_recon.trainers import FitNormalization

ENV = "InvertedDoublePendulum-v5"
RECIPE = "gym/online_inverted_double_pendulum"
SIGMA = 0.4  # the controller's action noise
CTRL_EPISODE_STEPS = 100
HORIZON = 10  # the multi-step error's open-loop steps
TEST_SEED = 10_000
FORCE_DIM = 8  # the observation's constraint force: read by no cost, 0 in all random data


# ---------------------------------------------------------------------------------------------
# The noisy stabilising controller


def lqr_gain(q: Sequence[float] = (1.0,) * 6, r: float = 1.0) -> np.ndarray:
    """LQR gain ``K`` [6] of the env's one step (``frame_skip`` MuJoCo steps) linearised by
    central finite differences at rest upright, for the state (x, θ1, θ2, ẋ, ω1, ω2)."""
    env = gym.make(ENV).unwrapped
    model, data = env.model, mujoco.MjData(env.model)
    nq = model.nq

    def step(x: np.ndarray, u: float) -> np.ndarray:
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:], data.ctrl[:] = x[:nq], x[nq:], u
        for _ in range(env.frame_skip):
            mujoco.mj_step(model, data)
        return np.concatenate([data.qpos, data.qvel])

    n, eps = nq + model.nv, 1e-5
    x0 = np.zeros(n)
    a = np.stack(
        [(step(x0 + eps * e, 0.0) - step(x0 - eps * e, 0.0)) / (2 * eps) for e in np.eye(n)], 1
    )
    b = ((step(x0, eps) - step(x0, -eps)) / (2 * eps))[:, None]
    env.close()
    p, qm = np.diag(q), np.diag(q)
    for _ in range(5000):  # the discrete Riccati equation by value iteration
        k = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
        p_next = qm + a.T @ p @ (a - b @ k)
        if np.abs(p_next - p).max() < 1e-10:
            break
        p = p_next
    return np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)[0]


class NoisyFeedback(nn.Module):
    """``clip(-K·s + σ·ε, -1, 1)`` with s = (x, θ1, θ2, ẋ, ω1, ω2) read from IDP's observation
    (angles from their sines and cosines); ε from torch's RNG, which ``collect`` seeds."""

    def __init__(self, gain: np.ndarray, sigma: float) -> None:
        super().__init__()
        self.register_buffer("gain", torch.as_tensor(gain, dtype=torch.float32))
        self.sigma = sigma

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        angles = torch.atan2(obs[..., 1:3], obs[..., 3:5])
        state = torch.cat([obs[..., :1], angles, obs[..., 5:8]], -1)
        u = -(state * self.gain).sum(-1, keepdim=True)
        return (u + self.sigma * torch.randn_like(u)).clamp(-1.0, 1.0)


def controller_data(gain: np.ndarray, frames: int, seed: int) -> TensorDictBase:
    policy = TensorDictModule(NoisyFeedback(gain, SIGMA), ["observation"], ["action"])
    env = make_env(ENV, seed=seed, max_episode_steps=CTRL_EPISODE_STEPS)
    with closing_env(env):
        return collect(env, policy, frames=frames, seed=seed)


def random_data(frames: int, seed: int) -> TensorDictBase:
    env = make_env(ENV, seed=seed, max_episode_steps=1000)
    with closing_env(env):
        return collect_random(env, frames=frames, seed=seed)


def episode_lengths(data: TensorDictBase) -> torch.Tensor:
    return torch.unique_consecutive(data[TRAJ_KEY], return_counts=True)[1]


# ---------------------------------------------------------------------------------------------
# The fits


def library_fit(
    world: LSTMWorldModel,
    data: TensorDictBase,
    schedule: FitSchedule,
    *,
    seed: int,
    pad: bool | None = None,
) -> dict:
    """``fit_models``' first world-model fit with ``schedule`` (its split, its buffers, its
    ``fit_world_model`` call, step for step), returning what ``fit_models`` does not: the steps
    run, the step of the weights kept and the episodes its sampler can draw. ``pad``: None as
    ``fit_models`` (``sequence_buffers`` with ``schedule.short_episodes``: by default padded
    where an episode ended shorter than ``slice_len`` steps); True or False forces it."""
    parts = split_by_trajectory(data, schedule.val_fraction, seed=seed)
    sizes = dict(
        slice_len=schedule.slice_len, num_slices=schedule.num_slices, sampling=schedule.sampling
    )
    if pad is None:
        short = schedule.short_episodes
        pad = needs_padding(schedule.slice_len, *parts, short_episodes=short)
        buffers = sequence_buffers(parts, **sizes, keys=FIT_KEYS, short_episodes=short)
    else:
        buffers = tuple(make_sequence_buffer(len(p), **sizes, pad_short=pad) for p in parts)
        for buffer, part in zip(buffers, parts, strict=True):
            buffer.extend(part.select(*FIT_KEYS, TRAJ_KEY))
    lengths = episode_lengths(parts[0])
    drawn = lengths if pad else lengths[lengths >= schedule.slice_len]
    result = fit_world_model(
        world,
        buffers[0],
        val_buffer=buffers[1],
        mode=schedule.mode,
        seed=seed,
        fit_normalization=True,
        checkpoint_modules={},
        progress=False,
        **schedule.world_model_settings(),
    )
    best = min(result.history, key=lambda h: h["val_loss"])["step"] if result.history else 0
    return {
        "steps_run": result.steps,
        "kept_step": best,
        "drawn_episodes": len(drawn),
        "drawn_steps": int(drawn.sum()),
        "train_episodes": len(lengths),
        "train_steps": int(lengths.sum()),
    }


def plain_fit(
    world: LSTMWorldModel,
    data: TensorDictBase,
    first_batch: TensorDictBase,
    *,
    steps: int,
    lr: float,
    slice_len: int,
    num_slices: int,
    seed: int,
    lr_decay: bool = False,
    clip_norm: float | None = None,
) -> dict:
    """TorchRL's way: ``FitNormalization`` on ``first_batch``, then per batch sampled from all
    ``data`` (TorchRL's ``SliceSampler``, short episodes padded) one step of Adam on
    ``WorldModelPredictionLoss`` (``DefaultOptimizationStepper``: the loss entries summed, no
    clipping unless ``clip_norm``); the last weights. ``lr_decay``: the library's cosine
    schedule to lr/20."""
    FitNormalization(world)(first_batch)
    buffer = make_sequence_buffer(
        len(data), slice_len=slice_len, num_slices=num_slices, pad_short=True
    )
    buffer.extend(data.select(*FIT_KEYS, TRAJ_KEY))
    loss_module = WorldModelPredictionLoss(world, mode="one_step", slice_len=slice_len)
    params = [p for p in loss_module.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=lr)
    schedule = (
        torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps, eta_min=lr * 0.05)
        if lr_decay
        else None
    )
    torch.manual_seed(seed)
    for _ in range(steps):
        losses = loss_module(buffer.sample())
        sum(v for k, v in losses.items() if k.startswith("loss")).backward()
        if clip_norm is not None:
            nn.utils.clip_grad_norm_(params, clip_norm)
        optimizer.step()
        optimizer.zero_grad()
        if schedule is not None:
            schedule.step()
    episodes = len(episode_lengths(data))
    return {
        "steps_run": steps,
        "kept_step": steps,
        "drawn_episodes": episodes,
        "drawn_steps": len(data),
        "train_episodes": episodes,
        "train_steps": len(data),
    }


Fit = Callable[[LSTMWorldModel, TensorDictBase, TensorDictBase, FitSchedule, int], dict]


def library_arm(pad: bool | None = None, **changes) -> Fit:
    def fit(world, data, first_batch, schedule, seed):
        return library_fit(
            world, data, dataclasses.replace(schedule, **changes), seed=seed, pad=pad
        )

    return fit


def plain_arm(**options) -> Fit:
    def fit(world, data, first_batch, schedule, seed):
        s = schedule
        return plain_fit(
            world,
            data,
            first_batch,
            steps=s.steps,
            lr=s.lr,
            slice_len=s.slice_len,
            num_slices=s.num_slices,
            seed=seed,
            **options,
        )

    return fit


ARMS: dict[str, Fit] = {
    "plain (TorchRL step)": plain_arm(),
    "plain + cosine lr": plain_arm(lr_decay=True),
    "plain + cosine lr, clip 10": plain_arm(lr_decay=True, clip_norm=10.0),
    "library (recipe)": library_arm(),
    "library, the rule before 2026-11-29": library_arm(short_episodes="pad_if_no_window"),
    "library, patience None": library_arm(patience=None),
    "library, val_fraction 0.05": library_arm(val_fraction=0.05),
    "library, slice 10": library_arm(slice_len=10),
    "library, slice 10 padded": library_arm(slice_len=10, pad=True),
    "library, slice 20 padded": library_arm(pad=True),
    "library, FitSchedule() slice 40, val 0.1": library_arm(slice_len=40, val_fraction=0.1),
}
"""Each arm's fit, from the recipe's schedule (``--steps`` its steps)."""

TRAIN_ARMS = {
    "random": [  # always padded there
        a
        for a in ARMS
        if a not in ("library, slice 20 padded", "library, the rule before 2026-11-29")
    ],
    "mixed": [
        "plain (TorchRL step)",
        "library (recipe)",
        "library, the rule before 2026-11-29",
        "library, slice 20 padded",
        "library, FitSchedule() slice 40, val 0.1",
    ],
}


# ---------------------------------------------------------------------------------------------
# The errors


def planner_windows(data: TensorDictBase, window: int, horizon: int) -> tuple[torch.Tensor, ...]:
    """From every step of every episode of flat ``data``: the ``window`` steps before it as the
    planner's context (an episode's first observation and the zero action before its start),
    its observation, the next ``horizon`` real actions and states (clamped at the episode's
    end) and which of them are real, ``[S, W, N]``, ``[S, W, M]``, ``[S, N]``, ``[S, H, M]``,
    ``[S, H, N]``, ``[S, H]``."""
    ids = data[TRAJ_KEY]
    n = len(ids)
    idx = torch.arange(n)
    starts = torch.ones(n, dtype=torch.bool)
    starts[1:] = ids[1:] != ids[:-1]
    ends = torch.ones(n, dtype=torch.bool)
    ends[:-1] = ids[1:] != ids[:-1]
    first = torch.cummax(torch.where(starts, idx, 0), 0).values
    last = torch.cummin(torch.where(ends, idx, n).flip(0), 0).values.flip(0)
    obs, act, nxt = data["observation"], data["action"], data["next", "observation"]
    ctx = idx[:, None] - window + torch.arange(window)
    before = ctx < first[:, None]
    ctx = torch.maximum(ctx, first[:, None])
    ctx_act = torch.where(before[..., None], torch.zeros(()), act[ctx])
    fut = idx[:, None] + torch.arange(horizon)
    real = fut <= last[:, None]
    fut = torch.minimum(fut, last[:, None])
    return obs[ctx], ctx_act, obs, act[fut], nxt[fut], real


@torch.no_grad()
def model_errors(world: LSTMWorldModel, test: TensorDictBase) -> dict[str, float]:
    """The standardised 1-step Δs error and the ≤10-step open-loop state error on ``test``."""
    ctx_obs, ctx_act, obs, actions, targets, real = planner_windows(test, world.window, HORIZON)
    pred = world.imagine(ctx_obs, ctx_act, obs, actions[:, None])[:, 0]
    nxt = test["next", "observation"]
    delta_std, state_std = (nxt - test["observation"]).std(0), nxt.std(0)
    keep = (delta_std > 1e-6) & (state_std > 1e-6)
    keep[FORCE_DIM] = False
    one = ((pred[:, 0] - nxt) / delta_std)[:, keep].pow(2).mean()
    sq = ((pred - targets) / state_std)[..., keep].pow(2).mean(-1)
    multi = sq[real].mean()
    return {"1-step": float(one), f"{HORIZON}-step": float(multi)}


# ---------------------------------------------------------------------------------------------


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return math.nan, math.nan
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def fmt(values: Sequence[float], digits: int = 4) -> str:
    m, s = mean_std(values)
    return f"{m:.{digits}f} ± {s:.{digits}f}"


def describe(name: str, data: TensorDictBase) -> str:
    lengths = episode_lengths(data).float()
    return (
        f"{name}: {len(data)} steps, {len(lengths)} episodes of {lengths.mean():.1f} steps "
        f"(median {lengths.median():.0f}, {int(lengths.min())}-{int(lengths.max())})"
    )


def main(argv: Sequence[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--frames", type=int, default=4000, help="training steps collected")
    parser.add_argument(
        "--steps", type=int, default=None, help="gradient steps (default: the recipe's)"
    )
    parser.add_argument("--eval-every", type=int, default=None, help="(default: the recipe's)")
    parser.add_argument(
        "--test-frames",
        type=int,
        nargs=2,
        default=[1000, 2000],
        help="steps of the random and the controller test sets",
    )
    parser.add_argument(
        "--train", nargs="+", choices=sorted(TRAIN_ARMS), default=["random", "mixed"]
    )
    parser.add_argument("--arms", nargs="+", default=None, help="a subset of the arms, by name")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="append one JSON line per arm")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = load_recipe(resolve_recipe_path(RECIPE))
    schedule = recipe_schedule(cfg)
    changes = {"steps": args.steps, "eval_every": args.eval_every}
    schedule = dataclasses.replace(schedule, **{k: v for k, v in changes.items() if v is not None})
    print(
        f"{ENV}: the world model of {RECIPE} ({dict(cfg.models.world_model)}, window "
        f"{cfg.models.window}, {schedule.mode}), {schedule.steps} gradient steps of "
        f"{schedule.num_slices} slices, lr {schedule.lr}; threads={args.threads}"
    )
    start = time.perf_counter()
    gain = lqr_gain()
    tests = {
        "random": random_data(args.test_frames[0], TEST_SEED),
        "ctrl": controller_data(gain, args.test_frames[1], TEST_SEED + 1),
    }
    print(f"controller: clip(-K·s + {SIGMA}·ε, -1, 1), K = {np.round(gain, 3).tolist()}")
    for name, test in tests.items():
        print("  test " + describe(name, test))
    rows: dict[tuple[str, str], list[dict]] = {}
    for seed in args.seeds:
        uniform = random_data(args.frames, seed)
        sets = {"random": (uniform, uniform)}
        if "mixed" in args.train:
            quarter = uniform[: args.frames // 4]
            ctrl = controller_data(gain, args.frames - len(quarter), seed + 500)
            sets["mixed"] = (concat_trajectories(quarter, ctrl), quarter)
        for train in args.train:
            data, first_batch = sets[train]
            print(f"seed {seed}: train " + describe(train, data), flush=True)
            for arm in TRAIN_ARMS[train]:
                if args.arms is not None and arm not in args.arms:
                    continue
                torch.manual_seed(seed)  # every arm starts from the same weights
                world = build_world_model(
                    cfg, *(data[k].shape[-1] for k in ("observation", "action"))
                )
                t0 = time.perf_counter()
                record = ARMS[arm](world, data, first_batch, schedule, seed)
                record["fit_s"] = time.perf_counter() - t0
                for name, test in tests.items():
                    for metric, value in model_errors(world, test).items():
                        record[f"{name} {metric}"] = value
                rows.setdefault((train, arm), []).append({"seed": seed, **record})
    metrics = [f"{t} {m}" for t in tests for m in ("1-step", f"{HORIZON}-step")]
    header = ["train", "arm", *metrics, "steps run", "kept step", "drawn of train episodes"]
    header += ["drawn of train steps", "fit s"]
    print(f"\nmean ± std over seeds {args.seeds} (errors: mean squares, standardised)")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    records = []
    for (train, arm), per_seed in rows.items():

        def col(key: str, per_seed: list[dict] = per_seed) -> list:
            return [r[key] for r in per_seed]

        cells = [train, arm, *(fmt(col(m)) for m in metrics)]
        cells += [fmt(col("steps_run"), 0), fmt(col("kept_step"), 0)]
        for what in ("episodes", "steps"):
            drawn, train_n = (statistics.fmean(col(f"{k}_{what}")) for k in ("drawn", "train"))
            cells.append(f"{drawn:.0f} of {train_n:.0f}")
        cells.append(fmt(col("fit_s"), 1))
        print("| " + " | ".join(cells) + " |")
        summary = {m: dict(zip(("mean", "std"), mean_std(col(m)), strict=True)) for m in metrics}
        settings = {k: v for k, v in vars(args).items() if k not in ("out", "train")}
        settings |= {"steps": schedule.steps, "eval_every": schedule.eval_every}
        records.append(
            settings | {"train": train, "arm": arm, "per_seed": per_seed, "summary": summary}
        )
    print(f"total {time.perf_counter() - start:.0f} s", flush=True)
    if args.out is not None:
        with args.out.open("a") as f:
            for record in records:
                f.write(json.dumps(record) + "\n")
    return records


if __name__ == "__main__":
    main()
