"""Planning time per call: TorchRL's CEMPlanner and MPPIPlanner vs ours (CEM, MPPI, iCEM, with
and without u; gradient; shooting).

Run: python benchmarks/planner_speed.py [--candidates 1000] [--horizons 30 200] [--threads N]
     [--device cuda] [--compile] [--reduce-overhead] [--time-limit-s S]
All planners use the same paper-size world model (state 6, action 3, LSTM 32, dense 32) and
autoencoder (90 → 100 → 90, T = 10) and the Industrial Benchmark torch cost. The baseline is
TorchRL's own ``CEMPlanner`` on a ``ModelBasedEnvBase`` whose world model is TorchRL's
``LSTMModule`` (sharing our LSTM weights), no uncertainty term: once on our
``WorldModelPlanningEnv`` adapter and once on the same env composed from plain
``TensorDictModule`` wrappers. The last two lines are the speed-ups at the first horizon against
the latter, the issue's baseline ("the plain way a TorchRL user would plan today"); the line
before them gives the speed-ups against the former, which is ~15% faster because our adapter's
step modules skip ``TensorDictModule``'s key handling.

Above the table it prints the GEMM rate measured in this run (one 1024 × 1024 × 1024 float32
product); each of our rows ends with its arithmetic limit (the call's FLOPs, counted from the
weights by ``_common.plan_flops``, over that rate) and ``N.Nx its arithmetic limit``.

TorchRL's ``MPPIPlanner`` runs on the plain env at the same budget (K candidates × iterations,
top-k = the elites) with the reward-to-go as its advantage (no value network: what MPPI
optimises without one); the line ``speed-up vs TorchRL MPPIPlanner`` compares ours (no u) with it.

``--compile`` adds, at the first horizon, our two CEM rows with the planning model's one-block
pass (rollout, cost, u) under ``torch.compile`` (``--compile-mode``), timed round-robin with
the eager rows.

``--reduce-overhead`` adds, at the first horizon and on CUDA only, CEM, MPPI and iCEM (with u)
with ``PlanningModel(compile="reduce-overhead")``: each plan's whole call one graph replayed as
a CUDA graph, with ``TORCHINDUCTOR_CUDAGRAPH_OR_ERROR=1`` (set here too): a graph that cannot be
captured fails the row instead of running eagerly. Each ends in ``x its arithmetic limit`` as
the eager rows do, and ``reduce-overhead vs eager`` compares it with its eager row.

The compiled rows are timed after the eager ones (round-robin among themselves). Each
compiles first (its first call, then two more: a CUDA graph is recorded at the second and
replayed from the third) and prints how long that took. With ``--time-limit-s`` (the run's
whole time; gpu_check passes its step's), a compiled row whose compile would not fit in the time
left (estimated as the longest compile so far, at first ``--compile-estimate-s``), after a
reserve for the timed calls, is left out with a line saying so: the run ends within its limit
instead of being killed at it.
"""

from __future__ import annotations

import argparse
import time
from functools import partial

import torch
from _common import (
    COST,
    context,
    gemm_gflops,
    gemm_line,
    limit_ms,
    limit_text,
    paper_models,
    parse_device_args,
    plan_flops,
    setup_done,
)
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner
from torchrl.modules import LSTMModule
from torchrl.modules import MPPIPlanner as TorchRLMPPIPlanner

from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
)
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.runs.timing import interleaved_median_ms

GRAPH_ROWS = (
    "ours CEM (with u, beta=0.1)",
    "ours MPPI (with u, beta=0.1)",
    "ours iCEM (with u, beta=0.1)",
)
"""The rows that ``--reduce-overhead`` times again as one CUDA graph a plan."""
COMPILE_ESTIMATE_S = 90.0
"""A compiled row's compile time (its first three calls) until one was measured in the run: not
yet measured on a GPU for the whole call (an assumption: on the 2-core CPU the Inductor build
of a whole CEM plan at these sizes took several minutes; a GPU host compiles Triton kernels on
many cores)."""
TIMING_RESERVE_S = 5.0
"""Seconds kept for the summary and the exit after the compiled rows' timed calls."""


class CompileBudget:
    """Which compiled rows fit in the run's time limit: the time left from ``started`` after
    ``reserve`` seconds, against the longest compile measured so far (at first ``estimate``)."""

    def __init__(self, started: float, limit_s: float | None, estimate_s: float) -> None:
        self.started, self.limit_s, self.estimate_s = started, limit_s, estimate_s
        self.longest: float | None = None

    def left(self, reserve: float) -> float:
        return self.limit_s - (time.perf_counter() - self.started) - reserve

    def fits(self, reserve: float) -> bool:
        """Whether one more compile is expected to end in time (always, without a limit)."""
        return self.limit_s is None or self.left(reserve) >= (self.longest or self.estimate_s)

    def why(self, reserve: float) -> str:
        expected = self.longest or self.estimate_s
        return (
            f"its compile, ~{expected:.0f} s, would not fit in the {max(self.left(reserve), 0):.0f}"
            f" s left of --time-limit-s {self.limit_s:.0f} after {reserve:.0f} s for the timing"
        )

    def compile(self, call, device: torch.device) -> float:
        """Seconds of ``call``'s first three calls (compile, CUDA graph record, first replay)."""
        start = time.perf_counter()
        for _ in range(3):
            call()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds = time.perf_counter() - start
        self.longest = max(self.longest or 0.0, seconds)
        return seconds


def plain_model_env(world) -> WorldModelPlanningEnv:
    """The same model env, composed the plain way: ``TensorDictModule`` wrappers around functions."""
    env = WorldModelPlanningEnv(world, COST)

    def step(features, obs, action):
        z = torch.relu(world.dense(features))
        next_obs = obs + world.delta_norm.denormalize(world.head(z))
        reward = -COST(obs, action, next_obs).unsqueeze(-1)
        return next_obs, reward, torch.zeros_like(reward, dtype=torch.bool)

    env.world_model = TensorDictSequential(
        TensorDictModule(
            world.normalize_inputs, in_keys=["observation", "action"], out_keys=["wm_input"]
        ),
        LSTMModule(
            lstm=world.lstm,
            in_keys=["wm_input", "wm_h", "wm_c"],
            out_keys=["wm_features", "wm_h", "wm_c"],
        ),
        TensorDictModule(
            step,
            in_keys=["wm_features", "observation", "action"],
            out_keys=["observation", "reward", "is_init"],
        ),
    )
    return env


def compiled(model: PlanningModel, mode: str) -> PlanningModel:
    """A planning model sharing ``model``'s networks whose one-block pass is ``torch.compile``d
    (``PlanningModel(compile=mode)``)."""
    return PlanningModel(
        model.world_model, model.cost_fn, uncertainty=model.uncertainty, compile=mode
    )


def _plan_no_grad(planner: TorchRLCEMPlanner, start) -> object:
    with torch.no_grad():
        return planner(start.clone())


def reward_to_go() -> TensorDictModule:
    """TorchRL MPPI's advantage without a value network: Σ of the rewards from each step on."""
    return TensorDictModule(
        lambda r: r.flip(-2).cumsum(-2).flip(-2),
        in_keys=[("next", "reward")],
        out_keys=["advantage"],
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--elites", type=int, default=100)
    parser.add_argument("--horizons", type=int, nargs="+", default=[30, 200])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument(
        "--compile",
        action="store_true",
        help="also time our CEM rows with torch.compile at the first horizon",
    )
    parser.add_argument("--compile-mode", default="default", help="torch.compile's mode")
    parser.add_argument(
        "--reduce-overhead",
        action="store_true",
        help="also time CEM, MPPI and iCEM (with u) as one CUDA graph a plan (CUDA only)",
    )
    parser.add_argument(
        "--time-limit-s",
        type=float,
        default=None,
        help="the run's time limit: compiled rows that would not fit are left out",
    )
    parser.add_argument(
        "--compile-estimate-s",
        type=float,
        default=COMPILE_ESTIMATE_S,
        help="a compiled row's compile time until one was measured (for --time-limit-s)",
    )
    started = time.perf_counter()
    args, device = parse_device_args(parser)
    graphs = args.reduce_overhead and device.type == "cuda"
    if args.reduce_overhead and not graphs:
        print(f"reduce-overhead rows: CUDA only, left out on {device.type}")
    if graphs:  # what TORCHINDUCTOR_CUDAGRAPH_OR_ERROR=1 sets: no silent eager fall-back
        torch._inductor.config.triton.cudagraph_or_error = True
        print("reduce-overhead rows: torch._inductor.config.triton.cudagraph_or_error = True")
    world, estimator = paper_models(device=device)
    ctx = context(device=device)
    plain = PlanningModel(world, COST)
    with_u = PlanningModel(world, COST, uncertainty=estimator)
    env = WorldModelPlanningEnv(world, COST)
    plain_env = plain_model_env(world)
    start = env.initial_state(*ctx)
    cem = dict(num_candidates=args.candidates, iterations=args.iterations, num_elites=args.elites)
    setup_done()
    mppi = dict(num_candidates=args.candidates, iterations=args.iterations)
    print(
        f"K={args.candidates}, {args.iterations} iterations, top-k {args.elites}, threads={args.threads}, "
        f"median of {args.repeats} round-robin calls (at H>30: of {max(1, args.repeats // 2)})"
    )
    rate = gemm_gflops(device)
    print(gemm_line(rate))
    first = {}
    for horizon in args.horizons:
        baselines = {
            name: TorchRLCEMPlanner(
                model_env,
                planning_horizon=horizon,
                optim_steps=args.iterations,
                num_candidates=args.candidates,
                top_k=args.elites,
            )
            for name, model_env in (
                ("TorchRL CEMPlanner (no u)", env),
                ("TorchRL CEMPlanner (no u), plain TensorDictModule env", plain_env),
            )
        }
        baselines["TorchRL MPPIPlanner (no u), plain TensorDictModule env"] = TorchRLMPPIPlanner(
            plain_env,
            reward_to_go(),
            temperature=1.0,
            planning_horizon=horizon,
            optim_steps=args.iterations,
            num_candidates=args.candidates,
            top_k=args.elites,
        )
        ours = {
            "ours CEM (no u)": CEMPlanner(plain, Objective(), horizon=horizon, **cem),
            "ours CEM (with u, beta=0.1)": CEMPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, **cem
            ),
            "ours MPPI (no u)": MPPIPlanner(plain, Objective(), horizon=horizon, **mppi),
            "ours MPPI (with u, beta=0.1)": MPPIPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, **mppi
            ),
            "ours iCEM (with u, beta=0.1)": ICEMPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, **cem
            ),
            "ours random shooting (with u)": RandomShootingPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, num_candidates=args.candidates
            ),
            "ours gradient (with u, 16 restarts x 20 steps)": GradientPlanner(
                with_u, Objective(beta=0.1), horizon=horizon, restarts=16, steps=20
            ),
        }
        twins = {}
        if args.compile and not first:
            for name, model in (
                ("ours CEM (no u)", plain),
                ("ours CEM (with u, beta=0.1)", with_u),
            ):
                objective = ours[name].objective
                twin = CEMPlanner(
                    compiled(model, args.compile_mode), objective, horizon=horizon, **cem
                )
                twins[f"{name}, torch.compile"] = twin
        if graphs and not first:
            graph_model = compiled(with_u, "reduce-overhead")
            for name in GRAPH_ROWS:
                twin = type(ours[name])(
                    graph_model,
                    ours[name].objective,
                    horizon=horizon,
                    **(mppi if isinstance(ours[name], MPPIPlanner) else cem),
                )
                twins[f"{name}, reduce-overhead"] = twin
        repeats = args.repeats if horizon <= 30 else max(1, args.repeats // 2)
        calls = {name: partial(_plan_no_grad, b, start) for name, b in baselines.items()}
        calls |= {name: partial(planner.plan, *ctx) for name, planner in ours.items()}
        times = interleaved_median_ms(calls, repeats, device=device)
        # the compiled rows after the eager ones, each compiled while the time limit allows
        budget = CompileBudget(started, args.time_limit_s, args.compile_estimate_s)
        ready, reserve = {}, TIMING_RESERVE_S
        for name, planner in twins.items():
            # its timed calls, at most twice as long as its eager row's
            timed = (repeats + 1) * 2 * times[name.rsplit(", ", 1)[0]] / 1e3
            if not budget.fits(reserve + timed):
                print(f"  left out: {name} ({budget.why(reserve + timed)})")
                continue
            seconds = budget.compile(lambda p=planner: p.plan(*ctx), device)
            print(f"  compiled {name} in {seconds:.1f} s (its first call and two more)")
            ready[name], reserve = planner, reserve + timed
        if ready:
            calls = {name: partial(planner.plan, *ctx) for name, planner in ready.items()}
            times |= interleaved_median_ms(calls, repeats, device=device)
            ours |= ready
        print(f"H={horizon}")
        for name, ms in times.items():
            row = f"  {name:<56}{ms:9.1f} ms"
            if name in ours:
                limit = limit_ms(plan_flops(ours[name]), rate)
                row += f"   limit {limit:8.2f} ms   {limit_text(ms, limit)}"
            print(row)
        first = first or times
    adapter = first["TorchRL CEMPlanner (no u)"]
    print(
        f"(against TorchRL CEMPlanner on our WorldModelPlanningEnv adapter: "
        f"{adapter / first['ours CEM (no u)']:.1f}x without u, "
        f"{adapter / first['ours CEM (with u, beta=0.1)']:.1f}x with u)"
    )
    for name in ("ours CEM (no u)", "ours CEM (with u, beta=0.1)"):
        if f"{name}, torch.compile" in first:
            print(
                f"torch.compile ({args.compile_mode}) vs eager, {name}: "
                f"{first[name] / first[f'{name}, torch.compile']:.2f}x"
            )
    for name in GRAPH_ROWS:
        if f"{name}, reduce-overhead" in first:
            print(
                f"reduce-overhead (one CUDA graph a plan) vs eager, {name}: "
                f"{first[name] / first[f'{name}, reduce-overhead']:.2f}x"
            )
    mppi_base = first["TorchRL MPPIPlanner (no u), plain TensorDictModule env"]
    print(f"speed-up vs TorchRL MPPIPlanner: {mppi_base / first['ours MPPI (no u)']:.1f}x")
    base = first["TorchRL CEMPlanner (no u), plain TensorDictModule env"]
    print(
        f"speed-up vs TorchRL CEMPlanner (no uncertainty): {base / first['ours CEM (no u)']:.1f}x"
    )
    print(
        f"speed-up vs TorchRL CEMPlanner (ours with uncertainty): "
        f"{base / first['ours CEM (with u, beta=0.1)']:.1f}x"
    )


if __name__ == "__main__":
    main()
