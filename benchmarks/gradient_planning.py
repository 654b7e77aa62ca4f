"""Backpropagation through the world-model rollout: plain PyTorch vs ours (recorded graph, fused).

Run: python benchmarks/gradient_planning.py [--rows 16] [--horizon 200] [--repeats 15] [--threads 1]
Gradient planning (``GradientPlanner``) differentiates a rollout of ``rows`` action sequences
over ``horizon`` steps with respect to the actions, once per Adam step. Timed here, forward
plus backward, round-robin so a change of machine load hits all alike:

* plain PyTorch: the world model's own ``nn.LSTM`` called one step at a time, the way a user
  would write an autoregressive rollout (the baseline);
* ours, recorded graph: our rollout with every op recorded by autograd (``recorded_rollout``,
  the reference; what the library used before the fused node);
* ours, fused: :class:`~torchrl_recon.modules._lstm_rollout.LSTMRollout`, one autograd node
  with a hand-written backward (what ``imagine`` uses; bitwise the recorded graph's gradients).

Then one whole gradient plan (16 restarts × 50 Adam steps, with u), the weight gradients of a
multi-step training batch (32 windows × 30 steps) both ways, and the speed-ups of the fused
rollout.
"""

from __future__ import annotations

import argparse
import time

import torch
from _common import COST, context, paper_models

from torchrl_recon._timing import interleaved_median_ms
from torchrl_recon.modules._lstm_rollout import LSTMRollout, recorded_rollout
from torchrl_recon.planners import GradientPlanner, Objective, PlanningModel


def plain_rollout(world, s, h, c, actions: torch.Tensor) -> torch.Tensor:
    """Autoregressive rollout with ``world.lstm`` stepped once per action, ``[R, H, N]``."""
    h, c = h[None].contiguous(), c[None].contiguous()
    states = []
    for t in range(actions.shape[1]):
        x = world._inputs(s, actions[:, t])[:, None]
        out, (h, c) = world.lstm(x, (h, c))
        z = torch.relu(world.dense(out[:, 0]))
        s = s + world.delta_norm.denormalize(world.head(z))
        states.append(s)
    return torch.stack(states, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rows", type=int, default=16)
    parser.add_argument("--horizon", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    world, estimator = paper_models()  # frozen weights, as the planner has them
    ctx = context()
    state = world.warmup(ctx[0], ctx[1])
    rows = args.rows
    s0 = ctx[2].expand(rows, -1)
    h, c = (x.expand(rows, -1) for x in state)
    actions = (torch.rand(rows, args.horizon, world.action_dim) * 2 - 1).requires_grad_(True)

    def backward(rollout):
        return lambda: torch.autograd.grad(rollout().square().sum(), actions)

    fns = {
        "plain PyTorch (nn.LSTM stepped)": backward(
            lambda: plain_rollout(world, s0, h, c, actions)
        ),
        "ours, recorded graph": backward(
            lambda: recorded_rollout(s0, h, c, actions, "relu", *world._folded_weights())
        ),
        "ours, fused": backward(lambda: world.imagine(*ctx, actions, state=state)),
    }
    print(
        f"rows={rows}, H={args.horizon}, threads={args.threads}, forward + backward, "
        f"median of {args.repeats} round-robin calls"
    )
    times = interleaved_median_ms(fns, args.repeats)
    for name, ms in times.items():
        print(f"  {name:<40}{ms:9.1f} ms")
    planner = GradientPlanner(
        PlanningModel(world, COST, uncertainty=estimator),
        Objective(beta=0.1),
        horizon=args.horizon,
        restarts=16,
        steps=50,
    )
    start = time.perf_counter()
    planner.plan(*ctx)
    print(
        f"one gradient plan (16 restarts x 50 steps, with u): {time.perf_counter() - start:.2f} s"
    )
    # Multi-step training differentiates w.r.t. the weights: 32 windows x 30 steps (the recipes').
    weights = [w.detach().requires_grad_(True) for w in world._folded_weights()]
    train_s0, train_h, train_c = s0[:1].expand(32, -1), h[:1].expand(32, -1), c[:1].expand(32, -1)
    train_actions = torch.rand(32, 30, world.action_dim) * 2 - 1

    def train(rollout):
        states = rollout(train_s0, train_h, train_c, train_actions, "relu", *weights)
        return torch.autograd.grad(states.square().sum(), weights)

    training = interleaved_median_ms(
        {"recorded": lambda: train(recorded_rollout), "fused": lambda: train(LSTMRollout.apply)},
        args.repeats,
    )
    print(
        f"weight gradients, 32 x 30 steps (training): recorded graph {training['recorded']:.1f} ms, "
        f"fused {training['fused']:.1f} ms"
    )
    fused = times["ours, fused"]
    print(f"speed-up vs plain PyTorch: {times['plain PyTorch (nn.LSTM stepped)'] / fused:.1f}x")
    print(f"speed-up vs the recorded graph: {times['ours, recorded graph'] / fused:.1f}x")
    print(
        f"speed-up of training's weight gradients: {training['recorded'] / training['fused']:.1f}x"
    )


if __name__ == "__main__":
    main()
