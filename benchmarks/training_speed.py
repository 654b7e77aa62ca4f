"""Time per fit step: R world models trained as one population vs R sequential single fits.

Paper sizes by default (LSTM 32, dense 32, window 10, 40-step slices, 32 windows per member,
Industrial Benchmark dims 6 / 3) on random trajectories. Each timed call is a whole fit of
``--steps`` steps (``fit_world_model`` once per model, or ``fit_population`` once), with one
validation batch at the end and no early stopping, so a call's time over ``--steps`` is the
time per step. Sequential and population calls are interleaved (median of ``--repeats``).

``fit_population`` runs twice: as by default (each member samples its own batches, exactly
its separate fit's) and with ``shared_sampling=True`` (one sample per step for all members,
statistically equivalent). The headline is the shared one's: it is how the explore experiment
fits Table 1's retrainings (``explore.retrain_stage``).

Above the table it prints the GEMM rate measured in this run (one 1024 × 1024 × 1024 float32
product) and the arithmetic limit of one member's fit step (``_common.fit_step_flops``: the
teacher-forced warm-up's LSTM steps and the imagined steps' LSTM, dense and head products,
forward + backward ≈ 3 × forward, over that rate); each row, one per R and way of fitting,
ends with ``N.Nx its arithmetic limit`` (its time per step over R × that limit).

``--compile`` adds, for each R, the sequential and the shared population fits with
``compile=True`` (their training steps under ``torch.compile``), timed round-robin with the eager
ones after a first, untimed call that compiles (its seconds are printed), and a line
``torch.compile vs eager, R=..: sequential X.XXx, population X.XXx``. ``--compile shared``
compiles the shared population fit only (one compile fewer: the gpu-check's choice, to stay in
its time budget).

``--cuda-graph`` (on a CUDA device; elsewhere it says so and times the rest) adds, for each R,
the shared population fit with ``cuda_graph=True`` (each step one replayed CUDA graph,
``fit_population``) in two rows: ``shared, CUDA graph``, a whole call of ``--graph-steps``
steps over its steps (its first steps are eager and the capture follows them), and ``CUDA
graph, per replay``, the extra time of a call of twice as many steps over the extra steps (the
steady state: a replay, its batch's sampling and copy, and the loss check); a line ``CUDA graph
vs eager, R=..: X.XXx`` (per replay against the shared eager fit); and a row ``sampling
alone``: one shared sample of R members' slices moved to the device, the part of every step
that stays on the host.

Run: python benchmarks/training_speed.py [--device auto] [--threads 1] [--members 1 10 20]
[--compile [sequential] [shared]]
Its last line is ``speed-up of R vectorised retrainings vs sequential: X.Xx`` for the largest R
(both eager).
"""

from __future__ import annotations

import argparse
import os
import time

import torch
from _common import (
    ACTION_DIM,
    OBS_DIM,
    fit_step_flops,
    gemm_gflops,
    gemm_line,
    limit_ms,
    limit_text,
    parse_device_args,
    setup_done,
)
from tensordict import TensorDict

from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.fitting import fit_population, fit_world_model
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.runs.timing import interleaved_median_ms

COMPILED_FITS = ("sequential", "shared")  # the fits --compile can time with compile=True


def random_buffer(args: argparse.Namespace, trajectories: int = 16, length: int = 200):
    """Random-walk states and uniform actions, ``trajectories`` episodes of ``length`` steps."""
    g = torch.Generator().manual_seed(0)
    act = torch.rand(trajectories, length, ACTION_DIM, generator=g) * 2 - 1
    obs = torch.randn(trajectories, length + 1, OBS_DIM, generator=g).cumsum(1)
    data = TensorDict(
        {
            "observation": obs[:, :-1],
            "action": act,
            ("next", "observation"): obs[:, 1:],
            ("collector", "traj_ids"): torch.arange(trajectories)[:, None].expand(-1, length),
        },
        [trajectories, length],
    ).reshape(-1)
    rb = make_sequence_buffer(len(data), slice_len=args.slice_len, num_slices=args.windows)
    rb.extend(data)
    return rb


def world_models(
    args: argparse.Namespace, rb, count: int, device: torch.device
) -> list[LSTMWorldModel]:
    """``count`` world models of ``args``' sizes on ``device`` (drawn after
    ``torch.manual_seed(0)``), each with its normalisation fitted on ``rb``'s transitions."""
    torch.manual_seed(0)
    models = [
        LSTMWorldModel(
            OBS_DIM, ACTION_DIM, hidden_size=args.hidden, dense_size=args.dense, window=args.window
        ).to(device)
        for _ in range(count)
    ]
    data = rb[:]
    for model in models:
        model.fit_normalization(
            *(data[k].to(device) for k in ("observation", "action", ("next", "observation")))
        )
    return models


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--members", type=int, nargs="+", default=[1, 10, 20])
    parser.add_argument("--steps", type=int, default=30, help="fit steps per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--hidden", type=int, default=32)
    parser.add_argument("--dense", type=int, default=32)
    parser.add_argument("--window", type=int, default=10)
    parser.add_argument("--slice-len", type=int, default=40)
    parser.add_argument("--windows", type=int, default=32, help="sequences per batch per member")
    parser.add_argument(
        "--compile",
        nargs="*",
        choices=COMPILED_FITS,
        help="also time these fits with compile=True (no names: both)",
    )
    parser.add_argument(
        "--cuda-graph",
        action="store_true",
        help="also time the shared population fit with cuda_graph=True (a CUDA device)",
    )
    parser.add_argument(
        "--graph-steps", type=int, default=50, help="fit steps per timed --cuda-graph call"
    )
    args, device = parse_device_args(parser)
    setup_done()
    if args.cuda_graph and device.type != "cuda":
        print(f"--cuda-graph: not timed (cuda_graph=True needs a CUDA device, this is {device})")
        args.cuda_graph = False
    compiled_fits = () if args.compile is None else tuple(args.compile) or COMPILED_FITS
    rb = random_buffer(args)
    fit = dict(
        steps=args.steps,
        eval_every=args.steps,
        val_batches=1,
        patience=None,
        fit_normalization=False,
        progress=False,
    )

    print(
        f"device={device}, threads={args.threads}, hidden={args.hidden}, dense={args.dense}, "
        f"window={args.window}, slice_len={args.slice_len}, windows/member={args.windows}, "
        f"{args.steps} steps per call, median of {args.repeats} interleaved calls, "
        f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs"
    )
    rate = gemm_gflops(device)
    print(gemm_line(rate))
    template = world_models(args, rb, 1, device)[0]
    flops = fit_step_flops(template, args.windows, args.slice_len)
    member_limit = limit_ms(flops, rate)
    print(
        f"arithmetic limit of one member's fit step: {member_limit:.3f} ms "
        f"({flops / 1e9:.4f} GFLOP, forward + backward = 3 x forward)"
    )
    speed_up = {}
    for count in args.members:
        sequential, population = (
            world_models(args, rb, count, device),
            world_models(args, rb, count, device),
        )
        seeds = list(range(count))

        def run_sequential(ms=sequential, seeds=seeds, compile=False):
            for model, seed in zip(ms, seeds, strict=True):
                fit_world_model(model, rb, seed=seed, compile=compile, **fit)

        def run_population(ms=population, seeds=seeds, shared=False, compile=False):
            fit_population(ms, rb, seeds=seeds, shared_sampling=shared, compile=compile, **fit)

        def run_graph(ms=population, seeds=seeds, steps=args.graph_steps):
            graph_fit = fit | dict(steps=steps, eval_every=steps)
            fit_population(ms, rb, seeds=seeds, shared_sampling=True, cuda_graph=True, **graph_fit)

        def sample(count=count):
            rb.sample(count * rb.batch_size).to(device)

        calls = {
            "sequential": run_sequential,
            "population": run_population,
            "shared": lambda: run_population(shared=True),
        }
        if args.cuda_graph:
            calls |= {
                "shared, CUDA graph": run_graph,
                "CUDA graph, twice the steps": lambda: run_graph(steps=2 * args.graph_steps),
                "sampling alone": sample,
            }
        if compiled_fits:
            compiled = {
                f"{kind}, torch.compile": call
                for kind, call in (
                    ("sequential", lambda: run_sequential(compile=True)),
                    ("shared", lambda: run_population(shared=True, compile=True)),
                )
                if kind in compiled_fits
            }
            for name, call in compiled.items():
                start = time.perf_counter()
                call()
                print(
                    f"R={count:3d}  {name}: first call (compiles) {time.perf_counter() - start:.1f} s"
                )
            calls |= compiled
        call_ms = interleaved_median_ms(calls, args.repeats, device=device)
        per_call = {"shared, CUDA graph": args.graph_steps, "sampling alone": 1}
        ms = {k: v / per_call.get(k, args.steps) for k, v in call_ms.items()}
        seq, pop, shared = (ms[k] for k in ("sequential", "population", "shared"))
        speed_up[count] = seq / shared
        limit = count * member_limit
        rows = [
            ("sequential", seq, ""),
            ("population", pop, f", speed-up {seq / pop:.2f}x"),
            ("population, shared_sampling", shared, f", speed-up {speed_up[count]:.2f}x"),
        ]
        seq_c, shared_c = (ms.get(f"{kind}, torch.compile") for kind in COMPILED_FITS)
        if seq_c is not None:
            rows.append(("sequential, torch.compile", seq_c, ""))
        if shared_c is not None:
            ratio = "" if seq_c is None else f", speed-up {seq_c / shared_c:.2f}x"
            rows.append(("shared, torch.compile", shared_c, ratio))
        if args.cuda_graph:
            whole = ms["shared, CUDA graph"]
            extra = call_ms["CUDA graph, twice the steps"] - call_ms["shared, CUDA graph"]
            ms["replay"] = replay = extra / args.graph_steps
            rows.append(("shared, CUDA graph", whole, f", speed-up {seq / whole:.2f}x"))
            rows.append(("CUDA graph, per replay", replay, f", speed-up {seq / replay:.2f}x"))
            rows.append(("sampling alone", ms["sampling alone"], ""))
        for name, step, ratio in rows:
            per_member = f"({step / count:6.2f} per member{ratio})"
            print(
                f"R={count:3d}  {name:<28}{step:9.2f} ms/step {per_member:<38}"
                f"limit {limit:7.2f} ms   {limit_text(step, limit)}"
            )
        if compiled_fits:
            against = [
                f"{name} {eager / compiled:.2f}x"
                for name, eager, compiled in (
                    ("sequential", seq, seq_c),
                    ("population", shared, shared_c),
                )
                if compiled is not None
            ]
            print(f"torch.compile vs eager, R={count}: {', '.join(against)}")
        if args.cuda_graph:
            print(f"CUDA graph vs eager, R={count}: {shared / ms['replay']:.2f}x (per replay)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    largest = max(args.members)
    print(f"speed-up of {largest} vectorised retrainings vs sequential: {speed_up[largest]:.1f}x")


if __name__ == "__main__":
    main()
