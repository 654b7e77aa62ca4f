"""Backpropagation through the world-model rollout: plain PyTorch vs ours (recorded graph, fused).

Run: python benchmarks/gradient_planning.py [--rows 16] [--horizon 200] [--repeats 15] [--threads 1]
Gradient planning (``GradientPlanner``) differentiates a rollout of ``rows`` action sequences
over ``horizon`` steps with respect to the actions, once per Adam step. Timed here, forward
plus backward, round-robin so a change of machine load hits all alike:

* plain PyTorch: the world model's own ``nn.LSTM`` called one step at a time
  (``LSTMWorldModel.step``), the way a user would write an autoregressive rollout (the
  baseline);
* ours, recorded graph: our rollout with every op recorded by autograd
  (``LSTMWorldModel.rollout(..., recorded=True)``, the reference; what the library used before
  the fused node);
* ours, fused: one autograd node with a hand-written backward (what ``imagine`` and
  ``rollout`` use; bitwise the recorded graph's gradients).

Then one whole gradient plan (16 restarts × 50 Adam steps, with u), the gradients of the
weights of a multi-step training batch (32 windows × 30 steps) both ways, and the speed-ups of
the fused rollout.
"""

from __future__ import annotations

import argparse
import copy
import time

import torch
from _common import COST, context, paper_models, parse_device_args, setup_done

from torchrl_recon.planners import GradientPlanner, Objective, PlanningModel
from torchrl_recon.runs.timing import interleaved_median_ms


def plain_rollout(world, s, h, c, actions: torch.Tensor) -> torch.Tensor:
    """Autoregressive rollout with ``world.lstm`` stepped once per action, ``[R, H, N]``."""
    state, states = (h, c), []
    for t in range(actions.shape[1]):
        s, state = world.step(s, actions[:, t], state)
        states.append(s)
    return torch.stack(states, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rows", type=int, default=16)
    parser.add_argument("--horizon", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1)
    args, device = parse_device_args(parser)
    setup_done()
    world, estimator = paper_models(device=device)  # frozen weights, as the planner has them
    ctx = context(device=device)
    state = world.warmup(ctx[0], ctx[1])
    rows = args.rows
    s0 = ctx[2].expand(rows, -1)
    h, c = (x.expand(rows, -1) for x in state)
    actions = (
        torch.rand(rows, args.horizon, world.action_dim, device=device) * 2 - 1
    ).requires_grad_(True)

    def backward(rollout):
        return lambda: torch.autograd.grad(rollout().square().sum(), actions)

    fns = {
        "plain PyTorch (nn.LSTM stepped)": backward(
            lambda: plain_rollout(world, s0, h, c, actions)
        ),
        "ours, recorded graph": backward(lambda: world.rollout(s0, actions, (h, c), recorded=True)),
        "ours, fused": backward(lambda: world.imagine(*ctx, actions, state=state)),
    }
    print(
        f"rows={rows}, H={args.horizon}, threads={args.threads}, forward + backward, "
        f"median of {args.repeats} round-robin calls"
    )
    times = interleaved_median_ms(fns, args.repeats, device=device)
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
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    print(
        f"one gradient plan (16 restarts x 50 steps, with u): {time.perf_counter() - start:.2f} s"
    )
    # Multi-step training differentiates w.r.t. the weights: 32 windows x 30 steps (the recipes').
    trainable = copy.deepcopy(world).requires_grad_(True)
    weights = list(trainable.parameters())
    train_s0 = s0[:1].expand(32, -1)
    train_state = (h[:1].expand(32, -1), c[:1].expand(32, -1))
    train_actions = torch.rand(32, 30, world.action_dim, device=device) * 2 - 1

    def train(recorded: bool):
        states = trainable.rollout(train_s0, train_actions, train_state, recorded=recorded)
        return torch.autograd.grad(states.square().sum(), weights)

    training = interleaved_median_ms(
        {"recorded": lambda: train(True), "fused": lambda: train(False)},
        args.repeats,
        device=device,
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
