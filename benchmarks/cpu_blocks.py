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
  alone saves).

Then a whole CEM call (5 iterations), measured at 1 thread and at 2 intra-op threads. Each row
ends ``speed-up X.XXXx`` against its 1-thread call.
"""

from __future__ import annotations

import argparse
import threading

import torch
from _common import COST, context, paper_models, parse_args, setup_done

from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.timing import interleaved_median_ms


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

    reference = one_call()
    for way in (python_threads, traced_fork, traced_sequential):
        got = torch.cat([parts[0] for parts in way()], 0)
        torch.testing.assert_close(got, reference[0], rtol=1e-4, atol=1e-4)
    calls = {
        "one call, 1 thread": one_call,
        "one call, 2 intra-op threads": intra_op,
        "2 halves, 2 Python threads": python_threads,
        "2 halves, traced + torch.jit.fork": traced_fork,
        "2 halves, traced, one after the other": traced_sequential,
    }
    print(
        f"K={args.candidates}, H={args.horizon}, u={'on' if args.u else 'off'}, "
        f"inter-op threads {torch.get_num_interop_threads()}, median of {args.repeats}"
    )
    times = interleaved_median_ms(calls, args.repeats)
    base = times["one call, 1 thread"]
    for name, ms in times.items():
        print(f"  {name:<42}{ms:8.2f} ms   speed-up {base / ms:6.3f}x")
    planner = CEMPlanner(
        model,
        Objective(beta=0.1 if args.u else 0.0),
        horizon=args.horizon,
        num_candidates=args.candidates,
        num_elites=max(1, args.candidates // 10),
    )
    plans = {
        "1 thread": lambda: planner.plan(*ctx),
        "2 intra-op threads": lambda: on_two_threads(lambda: planner.plan(*ctx)),
    }
    plan_ms = interleaved_median_ms(plans, args.repeats)
    one, two = plan_ms["1 thread"], plan_ms["2 intra-op threads"]
    print(
        f"CEM call ({planner.iterations} iterations): {one:.1f} ms at 1 thread, {two:.1f} ms at "
        f"2 intra-op threads, speed-up {one / two:6.3f}x"
    )


if __name__ == "__main__":
    main()
