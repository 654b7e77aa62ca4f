"""Row blocks across CPU cores: what each way of running a planning pass's independent blocks
on N cores gives, against one call on one core.

Run: python benchmarks/cpu_blocks.py [--candidates 1000] [--horizon 30] [--u] [--repeats 15]
     [--block-threads 2]

One planning pass (rollout, cost and, with ``--u``, u) of K candidates at paper sizes, under
``torch.inference_mode()`` as the planners run it, timed round-robin (median), each way
computing the same predictions:

* ``one call, 1 thread``: the whole pass on one core (the baseline);
* ``one call, N intra-op threads``: ``torch.set_num_threads(N)``, each op split across cores;
* ``N parts, N Python threads``: each part of the candidates in its own thread (eager ops hold
  the GIL between kernels);
* ``N parts, traced + torch.jit.fork``: the pass traced once (``torch.jit.trace``, the
  weights as its constants), the parts forked onto torch's inter-op thread pool, where the
  traced graph runs without the GIL;
* ``N parts, traced, one after the other``: the same traced graph on one core;
* ``N parts, compiled (C++ wrapper), N threads``: ``PlanningModel(compile=True, threads=N)``,
  each part one call of Inductor's C++ wrapper, which releases the GIL for the whole call
  (``torchrl_recon.planners.cpu_threads``);
* ``N parts, compiled (C++ wrapper), 1 thread``: the same compiled parts one after the other.

Then a whole CEM call (5 iterations, the same generator seed, so the same plans up to float
rounding; checked): eager at 1 thread, eager at N intra-op threads, ``compile=True`` at one
thread, and ``compile=True, threads=N``. Each row ends ``speed-up X.XXXx`` against its
1-thread call. The first compiled call compiles (tens of seconds; cached on disk after).

Last, the machine's own ceiling for N cores on this work: the same eager pass timed in one
process over all K, then in N processes at once over a part each (nothing shared, no GIL).
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import threading
import time
from collections.abc import Callable

import torch
from _common import COST, context, paper_models, parse_args, setup_done

from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.planners.cpu_threads import run_blocks
from torchrl_recon.planners.executors import threaded_pass
from torchrl_recon.runs.allocator import keep_freed_memory
from torchrl_recon.runs.timing import interleaved_median_ms


def _timed_passes(candidates, rows, args, barrier, results) -> None:
    """In a child process: the median ms of ``args.repeats`` eager passes over ``rows`` of the
    same ``candidates`` (one thread), started together with the other children."""
    torch.set_num_threads(1)
    keep_freed_memory()
    world, estimator = paper_models()
    model = PlanningModel(world, COST, uncertainty=estimator if args.u else None)
    ctx = context()
    actions = candidates[rows].contiguous()
    with torch.inference_mode():
        state = model.warmup(ctx[0], ctx[1])
        for _ in range(3):
            model(*ctx, actions, state=state)
        barrier.wait()
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            model(*ctx, actions, state=state)
            times.append(time.perf_counter() - start)
    results.put(statistics.median(times) * 1e3)


def processes_ceiling(args: argparse.Namespace) -> tuple[float, float]:
    """What N cores give when nothing is shared: the median ms of one process's eager pass
    over all K candidates, then of N processes' passes over a part each, run at once."""
    spawn = multiprocessing.get_context("spawn")
    candidates = torch.rand(args.candidates, args.horizon, 3) * 2 - 1
    size = -(-args.candidates // args.block_threads)
    parts = [slice(i, i + size) for i in range(0, args.candidates, size)]
    ms = []
    for rows in ([slice(None)], parts):
        barrier, results = spawn.Barrier(len(rows)), spawn.Queue()
        children = [
            spawn.Process(target=_timed_passes, args=(candidates, r, args, barrier, results))
            for r in rows
        ]
        for child in children:
            child.start()
        got = [results.get() for _ in children]
        for child in children:
            child.join()
        ms.append(max(got))  # the call ends when its slowest part does
    return ms[0], ms[1]


def on_threads(n: int, fn: Callable[[], object]) -> Callable[[], object]:
    """``fn`` run with ``n`` intra-op threads, the run's thread count restored after."""

    def call():
        before = torch.get_num_threads()
        torch.set_num_threads(n)
        try:
            return fn()
        finally:
            torch.set_num_threads(before)

    return call


def inference(fn: Callable[[], object]) -> Callable[[], object]:
    """``fn`` under ``torch.inference_mode()`` (the planners' mode)."""

    def call():
        with torch.inference_mode():
            return fn()

    return call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--u", action="store_true", help="the pass scores u too")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--block-threads", type=int, default=2, help="N: cores to spread over")
    args = parse_args(parser)
    setup_done()
    n = args.block_threads
    torch.manual_seed(0)
    world, estimator = paper_models()
    model = PlanningModel(world, COST, uncertainty=estimator if args.u else None)
    compiled = PlanningModel(world, COST, uncertainty=model.uncertainty, compile=True, threads=n)
    ctx = context()
    actions = torch.rand(args.candidates, args.horizon, 3) * 2 - 1
    parts = [p.contiguous() for p in actions.split(-(-args.candidates // n), dim=0)]
    with torch.inference_mode():
        state = model.warmup(ctx[0], ctx[1])

    def block(co, ca, ob, a, h, c):
        p = model(co, ca, ob, a, state=(h, c))
        return (p.states, p.cost) if p.uncertainty is None else (p.states, p.cost, p.uncertainty)

    with torch.no_grad():  # the weights are the trace's constants (a refit would re-trace)
        traced = torch.jit.trace(block, (*ctx, parts[0], *state), check_trace=False)

    def python_threads():
        out = [None] * len(parts)

        def work(i):  # at the run's --threads (the intra-op count is the process's)
            with torch.inference_mode():
                out[i] = block(*ctx, parts[i], *state)

        threads = [threading.Thread(target=work, args=(i,)) for i in range(len(parts))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return out

    def traced_fork():
        futures = [torch.jit.fork(traced, *ctx, p, *state) for p in parts]
        return [torch.jit.wait(f) for f in futures]

    predict = threaded_pass(PlanningModel._predict, "default")

    def compiled_parts(threads: int):
        def call():
            done = run_blocks(
                lambda i: predict(compiled, *ctx, parts[i], state), len(parts), threads
            )
            return [(p.states,) for p in done]

        return call

    calls = {
        "one call, 1 thread": inference(lambda: [block(*ctx, actions, *state)]),
        f"one call, {n} intra-op threads": on_threads(
            n, inference(lambda: [block(*ctx, actions, *state)])
        ),
        f"{n} parts, {n} Python threads": python_threads,
        f"{n} parts, traced + torch.jit.fork": inference(traced_fork),
        f"{n} parts, traced, one after the other": inference(
            lambda: [traced(*ctx, p, *state) for p in parts]
        ),
        f"{n} parts, compiled (C++ wrapper), {n} threads": inference(  # PlanningModel(threads=n)
            lambda: [(compiled(*ctx, actions, state=state).states,)]
        ),
        f"{n} parts, compiled (C++ wrapper), 1 thread": inference(compiled_parts(1)),
    }
    reference = calls["one call, 1 thread"]()[0][0]
    for name, way in calls.items():
        got = torch.cat([out[0] for out in way()], 0)
        torch.testing.assert_close(
            got, reference, rtol=1e-4, atol=1e-4, msg=lambda m, w=name: f"{w}: {m}"
        )
    print(
        f"K={args.candidates}, H={args.horizon}, u={'on' if args.u else 'off'}, "
        f"inter-op threads {torch.get_num_interop_threads()}, median of {args.repeats}"
    )
    times = interleaved_median_ms(calls, args.repeats)
    base = times["one call, 1 thread"]
    for name, ms in times.items():
        print(f"  {name:<46}{ms:8.2f} ms   speed-up {base / ms:6.3f}x")

    def cem(m: PlanningModel) -> Callable[[], object]:
        planner = CEMPlanner(
            m,
            Objective(beta=0.1 if args.u else 0.0),
            horizon=args.horizon,
            num_candidates=args.candidates,
            num_elites=max(1, args.candidates // 10),
        )
        return lambda: planner.plan(*ctx, generator=torch.Generator().manual_seed(0))

    one_thread = PlanningModel(world, COST, uncertainty=model.uncertainty, compile=True)
    plans = {
        "eager, 1 thread": cem(model),
        f"eager, {n} intra-op threads": on_threads(n, cem(model)),
        "compile=True, 1 thread": cem(one_thread),
        f"compile=True, threads={n}": cem(compiled),
    }
    reference = plans["eager, 1 thread"]().actions
    for name, fn in plans.items():  # the same plans
        torch.testing.assert_close(
            fn().actions, reference, rtol=1e-4, atol=1e-4, msg=lambda m, w=name: f"{w}: {m}"
        )
    plan_ms = interleaved_median_ms(plans, args.repeats)
    one = plan_ms["eager, 1 thread"]
    print("CEM call (5 iterations), the same plans:")
    for name, ms in plan_ms.items():
        print(f"  {name:<46}{ms:8.2f} ms   speed-up {one / ms:6.3f}x")
    full, split = processes_ceiling(args)
    print(
        "the machine's ceiling, eager passes in separate processes (no GIL, nothing shared): "
        f"all K in one process {full:.2f} ms, {n} parts in {n} processes at once {split:.2f} ms, "
        f"speed-up {full / split:6.3f}x"
    )


if __name__ == "__main__":
    main()
