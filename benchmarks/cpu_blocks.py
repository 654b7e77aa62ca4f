"""Row blocks across CPU cores: what each way of running a planning pass's independent blocks
on two cores gives, against one call on one core.

Run: python benchmarks/cpu_blocks.py [--candidates 1000] [--horizon 30] [--u] [--repeats 15]

One planning pass (rollout, cost and, with ``--u``, u) of K candidates at paper sizes, timed
round-robin (median), each way computing the same predictions:

* ``one call, 1 thread``: the whole pass on one core (the baseline);
* ``one call, 2 intra-op threads``: ``torch.set_num_threads(2)``, each op split across cores;
* ``2 halves, 2 Python threads``: each half of the candidates in its own thread (eager ops hold
  the GIL between kernels);
* ``2 halves, traced + torch.jit.fork``: the pass traced once (``torch.jit.trace``, the
  weights as its constants), both halves forked onto torch's inter-op thread pool, where the
  traced graph runs without the GIL;
* ``2 halves, traced, one after the other``: the same traced graph on one core (what tracing
  alone saves);
* ``2 halves, compiled (C++ wrapper), 2 threads``: ``PlanningModel(compile=True, threads=2)``,
  each half one call of Inductor's C++ wrapper, which releases the GIL for the whole call
  (``torchrl_recon.planners.cpu_threads``);
* ``2 halves, compiled (C++ wrapper), 1 thread``: the same compiled halves one after the other.

Then a whole CEM call (5 iterations, the same generator seed, so the same plans up to float
rounding; checked): eager at 1 thread, eager at 2 intra-op threads, ``compile=True`` at one
thread, and ``compile=True, threads=2``. Each row ends ``speed-up X.XXXx`` against its
1-thread call. The first compiled call compiles (tens of seconds; cached on disk after).

Last, the machine's own ceiling for two cores on this work: the same eager pass timed in one
process over all K, then in two processes at once over a half each (nothing shared, no GIL).
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import threading
import time

import torch
from _common import COST, context, paper_models, parse_args, setup_done

from torchrl_recon.allocator import keep_freed_memory
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel, cpu_threads
from torchrl_recon.timing import interleaved_median_ms


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
    """What two cores give when nothing is shared: the median ms of one process's eager pass
    over all K candidates, then of two processes' passes over a half each, run at once."""
    spawn = multiprocessing.get_context("spawn")
    candidates = torch.rand(args.candidates, args.horizon, 3) * 2 - 1
    half = -(-args.candidates // 2)
    ms = []
    for parts in ([slice(None)], [slice(0, half), slice(half, None)]):
        barrier, results = spawn.Barrier(len(parts)), spawn.Queue()
        children = [
            spawn.Process(target=_timed_passes, args=(candidates, rows, args, barrier, results))
            for rows in parts
        ]
        for child in children:
            child.start()
        got = [results.get() for _ in children]
        for child in children:
            child.join()
        ms.append(max(got))  # the call ends when its slower half does
    return ms[0], ms[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--u", action="store_true", help="the pass scores u too")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1)
    args = parse_args(parser)
    setup_done()
    torch.manual_seed(0)
    world, estimator = paper_models()
    model = PlanningModel(world, COST, uncertainty=estimator if args.u else None)
    compiled = PlanningModel(world, COST, uncertainty=model.uncertainty, compile=True, threads=2)
    ctx = context()
    actions = torch.rand(args.candidates, args.horizon, 3) * 2 - 1
    halves = [h.contiguous() for h in actions.split(-(-args.candidates // 2), dim=0)]
    with torch.inference_mode():
        state = model.warmup(ctx[0], ctx[1])

    def block(co, ca, ob, a, h, c):
        p = model(co, ca, ob, a, state=(h, c))
        return (p.states, p.cost) if p.uncertainty is None else (p.states, p.cost, p.uncertainty)

    with torch.no_grad():  # the weights are the trace's constants (a refit would re-trace)
        traced = torch.jit.trace(block, (*ctx, halves[0], *state), check_trace=False)

    def run(a):
        with torch.no_grad():
            return block(*ctx, a, *state)

    def one_call():
        return run(actions)

    def on_two_threads(fn):
        """``fn()`` with 2 intra-op threads, the run's thread count restored after."""
        threads = torch.get_num_threads()
        torch.set_num_threads(2)
        try:
            return fn()
        finally:
            torch.set_num_threads(threads)

    def intra_op():
        return on_two_threads(one_call)

    def python_threads():
        out = [None, None]

        def work(i):  # at the run's --threads (the intra-op count is the process's)
            out[i] = run(halves[i])

        threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return out

    def traced_fork():
        with torch.no_grad():
            futures = [torch.jit.fork(traced, *ctx, h, *state) for h in halves]
            return [torch.jit.wait(f) for f in futures]

    def traced_sequential():
        with torch.no_grad():
            return [traced(*ctx, h, *state) for h in halves]

    def compiled_halves(threads: int):
        predict = cpu_threads.threaded_pass(PlanningModel._predict, "default")

        def call():
            with torch.inference_mode():
                parts = cpu_threads.run_blocks(
                    lambda i: predict(compiled, *ctx, halves[i], state), 2, threads
                )
            return [(p.states,) for p in parts]

        return call

    def compiled_threads():  # what PlanningModel(threads=2) runs
        with torch.inference_mode():
            return [(compiled(*ctx, actions, state=state).states,)]

    reference = one_call()
    for way in (python_threads, traced_fork, traced_sequential, compiled_threads):
        got = torch.cat([parts[0] for parts in way()], 0)
        torch.testing.assert_close(got, reference[0], rtol=1e-4, atol=1e-4)
    calls = {
        "one call, 1 thread": one_call,
        "one call, 2 intra-op threads": intra_op,
        "2 halves, 2 Python threads": python_threads,
        "2 halves, traced + torch.jit.fork": traced_fork,
        "2 halves, traced, one after the other": traced_sequential,
        "2 halves, compiled (C++ wrapper), 2 threads": compiled_threads,
        "2 halves, compiled (C++ wrapper), 1 thread": compiled_halves(1),
    }
    print(
        f"K={args.candidates}, H={args.horizon}, u={'on' if args.u else 'off'}, "
        f"inter-op threads {torch.get_num_interop_threads()}, median of {args.repeats}"
    )
    times = interleaved_median_ms(calls, args.repeats)
    base = times["one call, 1 thread"]
    for name, ms in times.items():
        print(f"  {name:<42}{ms:8.2f} ms   speed-up {base / ms:6.3f}x")

    def cem(m: PlanningModel) -> CEMPlanner:
        return CEMPlanner(
            m,
            Objective(beta=0.1 if args.u else 0.0),
            horizon=args.horizon,
            num_candidates=args.candidates,
            num_elites=max(1, args.candidates // 10),
        )

    def plan(planner: CEMPlanner):
        return lambda: planner.plan(*ctx, generator=torch.Generator().manual_seed(0))

    one_thread = PlanningModel(world, COST, uncertainty=model.uncertainty, compile=True)
    plans = {
        "eager, 1 thread": plan(cem(model)),
        "eager, 2 intra-op threads": lambda: on_two_threads(plan(cem(model))),
        "compile=True, 1 thread": plan(cem(one_thread)),
        "compile=True, threads=2": plan(cem(compiled)),
    }
    reference = plans["eager, 1 thread"]().actions
    for name, fn in plans.items():  # the same plans
        torch.testing.assert_close(
            fn().actions, reference, rtol=1e-4, atol=1e-4, msg=lambda m, n=name: f"{n}: {m}"
        )
    plan_ms = interleaved_median_ms(plans, args.repeats)
    one = plan_ms["eager, 1 thread"]
    print(f"CEM call ({cem(model).iterations} iterations), the same plans:")
    for name, ms in plan_ms.items():
        print(f"  {name:<42}{ms:8.2f} ms   speed-up {one / ms:6.3f}x")
    full, halves_ms = processes_ceiling(args)
    print(
        "the machine's ceiling, eager passes in separate processes (no GIL, no shared memory): "
        f"all K in one process {full:.2f} ms, 2 halves in 2 processes at once {halves_ms:.2f} ms, "
        f"speed-up {full / halves_ms:6.3f}x"
    )


if __name__ == "__main__":
    main()
