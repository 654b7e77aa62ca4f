"""A probe of the public API with wrong inputs (issue 56 item 4).

Every public constructor and entry point of ``torchrl_recon.planners``, ``policies``,
``modules``, ``objectives``, ``training``, ``trainers`` and ``data`` (their ``__all__``, and the
``__all__`` of the planners' modules, where the names the package does not export are public) is
called with wrong shapes, dtypes, types, NaN/inf, out-of-range and unknown values. Each call
must raise one clear line before any work: a ``ValueError`` or ``TypeError`` (a
``FileNotFoundError`` for a missing file, a ``KeyError`` where the library names a missing
TensorDict key) raised by the library itself, naming the argument; never a raw torch
``RuntimeError``/``IndexError``, an ``AttributeError`` from deep inside, or silence.

Cases the library cannot fix yet (their code is someone else's to change now) are marked
``xfail(strict=True)`` with the reason: when one is fixed the probe says so.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, LazyTensorStorage, ReplayBuffer, Unbounded

import torchrl_recon
from tests.normalized import fitted
from torchrl_recon import data as D
from torchrl_recon import modules as M
from torchrl_recon import objectives as O
from torchrl_recon import planners as P
from torchrl_recon import policies as Po
from torchrl_recon import trainers as Tr
from torchrl_recon import training as T
from torchrl_recon.envs import make_env
from torchrl_recon.planners.beta import cost_to_u_ratio, window_uncertainty
from torchrl_recon.planners.bounds import action_bounds, bounds_from_spec, check_bounds_match
from torchrl_recon.planners.cpu_threads import run_aside, run_blocks
from torchrl_recon.planners.executors import compile_mode, threaded_pass
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.planners.noise import colored_noise
from torchrl_recon.planners.planning_model import check_step_fn
from torchrl_recon.planners.registry import check_planner_kwargs, get_planner_class
from torchrl_recon.planners.torchrl_models import (
    LSTMWorldModelModule,
    TorchRLWorldModelAdapter,
    planning_model_from_torchrl,
)

NAN, INF = float("nan"), float("inf")
N, A = 3, 1  # the probe's obs and action dims
PACKAGE = Path(torchrl_recon.__file__).resolve().parent
PROBED = ("planners", "policies", "modules", "objectives", "training", "trainers", "data")
PROBED += tuple(
    f"planners.{module}"
    for module in ("base", "beta", "bounds", "cem", "cpu_threads", "elite_memory", "model_env")
    + ("noise", "planning_model", "registry", "sampling", "torchrl_models")
)
SETTINGS = settings(
    max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)


def cost(s: torch.Tensor, a: torch.Tensor, s1: torch.Tensor) -> torch.Tensor:
    return s1.pow(2).sum(-1) + a.pow(2).sum(-1)


# ------------------------------------------------------------------ the parts the probe uses
# Built once, at the first case that needs them (not at collection); a case that could change
# one builds its own.


def world(**kwargs) -> M.LSTMWorldModel:
    return fitted(M.LSTMWorldModel(N, A, window=2, hidden_size=8, dense_size=8, **kwargs))


def estimator() -> M.ReconstructionUncertainty:
    return fitted(M.ReconstructionUncertainty(N, A, window=2, hidden_size=8))


@functools.cache
def model() -> P.PlanningModel:
    return P.PlanningModel(world(), cost, uncertainty=estimator(), action_low=-2.0, action_high=2.0)


def planner_kwargs(cls: type) -> dict:
    if cls is P.GradientPlanner:
        return dict(horizon=3, restarts=2, steps=2)
    extra = {"num_elites": 2} if cls in (P.CEMPlanner, P.ICEMPlanner) else {}
    return dict(horizon=3, num_candidates=8, **extra)


@functools.cache
def planner(cls: type = P.RandomShootingPlanner) -> P.PlannerBase:
    return cls(model(), P.Objective(), **planner_kwargs(cls))


@functools.cache
def policy() -> Po.MPCPolicy:
    return Po.MPCPolicy(planner())


@functools.cache
def env():
    return make_env("Pendulum-v1", seed=0, max_episode_steps=10)


@functools.cache
def reset() -> TensorDict:
    """A reset of an env of its own with the policy's primer (appending changes the env)."""
    primed = make_env("Pendulum-v1", seed=0, max_episode_steps=10)
    return primed.append_transform(policy().make_tensordict_primer()).reset()


@functools.cache
def explorer_planner() -> P.PlannerBase:
    return P.RandomShootingPlanner(model(), Po.exploration_objective(), horizon=3, num_candidates=8)


def steps(n: int = 40, *, bad: tuple | None = None) -> TensorDict:
    """``n`` flat transitions of two trajectories; ``bad=(key, row)`` puts a NaN there."""
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, N, generator=g)
    td = TensorDict(
        {
            "observation": obs,
            "action": torch.rand(n, A, generator=g),
            ("next", "observation"): 0.9 * obs,
            ("next", "reward"): -obs.pow(2).sum(-1, keepdim=True),
            ("next", "done"): (torch.arange(n) % (n // 2) == n // 2 - 1)[:, None],
            ("collector", "traj_ids"): torch.arange(n) // (n // 2),
        },
        [n],
    )
    if bad is not None:
        key, row = bad
        td[key][row, 0] = NAN
    return td


def buffer(data: TensorDict | None = None):
    rb = D.make_sequence_buffer(100, slice_len=4, num_slices=2)
    rb.extend(steps() if data is None else data)
    return rb


CONTEXT = (torch.zeros(2, N), torch.zeros(2, A), torch.zeros(N))


# ------------------------------------------------------------------------------- the check
CALLS = [0]
"""Calls the probe made (cases and hypothesis examples), for the report."""


def raised_in_library(excinfo: pytest.ExceptionInfo) -> bool:
    """Whether the error was raised by the library's own code, or is Python's own binding error
    of a call's arguments (an unknown keyword: a ``TypeError`` naming it)."""
    tb = excinfo.tb
    while tb.tb_next is not None:
        tb = tb.tb_next
    where = Path(tb.tb_frame.f_code.co_filename).resolve()
    if where.is_relative_to(PACKAGE):
        return True
    return where == Path(__file__).resolve() and isinstance(excinfo.value, TypeError)


def refused(call: Callable[[], object], match: str, errors: tuple = (ValueError, TypeError)):
    """Call ``call``; it must raise one of ``errors`` from the library, in one line matching
    ``match`` (the argument's name, what was given or expected)."""
    CALLS[0] += 1
    with pytest.raises(errors) as info:
        call()
    error = info.value
    message = error.args[0] if isinstance(error, KeyError) and error.args else str(error)
    assert isinstance(message, str) and message.strip(), f"an empty message: {error!r}"
    assert "\n" not in message.strip(), f"more than one line: {message!r}"
    assert re.search(match, message), f"{match!r} not in {message!r}"
    assert raised_in_library(info), f"raised outside the library: {error!r}"
    assert not isinstance(error, RuntimeError | IndexError | AttributeError | ZeroDivisionError)
    return error


@dataclass(frozen=True)
class Case:
    id: str
    call: Callable[[], object]
    match: str
    errors: tuple = (ValueError, TypeError)
    xfail: str | None = field(default=None)


OTHERS = "in a file another engineer owns now (issue 56): "
CASES: list[Case] = []


def case(id: str, call: Callable[[], object], match: str, **kwargs) -> None:
    CASES.append(Case(id, call, match, **kwargs))


# ----------------------------------------------------------------------------------- planners
case(
    "PlanningModel/world_model-type",
    lambda: P.PlanningModel("wm", cost),
    "world_model",
)
case("PlanningModel/cost_fn-type", lambda: P.PlanningModel(world(), 3), "cost_fn")
case(
    "PlanningModel/cost_fn-shape",
    lambda: P.PlanningModel(world(), lambda s, a, s1: s1),
    r"cost_fn.*\[2, 3\]",
)
case(
    "PlanningModel/uncertainty-type",
    lambda: P.PlanningModel(world(), cost, uncertainty="u"),
    "uncertainty",
)
case(
    "PlanningModel/uncertainty-dims",
    lambda: P.PlanningModel(world(), cost, uncertainty=M.ReconstructionUncertainty(4, 1)),
    "dims",
)
case(
    "PlanningModel/termination-not-bool",
    lambda: P.PlanningModel(world(), cost, termination_fn=cost),
    "termination_fn.*bools",
)
case(
    "PlanningModel/action_low-shape",
    lambda: P.PlanningModel(world(), cost, action_low=torch.tensor([-1.0, -1.0])),
    r"action_low has shape \[2\]; expected .*\[1\]",
)
case(
    "PlanningModel/action_high-2d",
    lambda: P.PlanningModel(world(), cost, action_high=torch.tensor([[1.0]])),
    r"action_high has shape \[1, 1\]",
)
case(
    "PlanningModel/action_low-str",
    lambda: P.PlanningModel(world(), cost, action_low="-1"),
    "action_low must be",
)
case(
    "PlanningModel/action_low-nan", lambda: P.PlanningModel(world(), cost, action_low=NAN), "finite"
)
case(
    "PlanningModel/action_high-inf",
    lambda: P.PlanningModel(world(), cost, action_high=INF),
    "finite",
)
case(
    "PlanningModel/bounds-order",
    lambda: P.PlanningModel(world(), cost, action_low=1.0, action_high=-1.0),
    "below action_high",
)
case(
    "PlanningModel/compile-unknown",
    lambda: P.PlanningModel(world(), cost, compile="fast"),
    "compile",
)
case("PlanningModel/threads-zero", lambda: P.PlanningModel(world(), cost, threads=0), "threads")
case("PlanningModel/threads-eager", lambda: P.PlanningModel(world(), cost, threads=2), "threads=2")
case(
    "PlanningModel.from_env/env-type",
    lambda: P.PlanningModel.from_env(world(), cost, "Pendulum-v1"),
    "env must be",
)
case(
    "PlanningModel.from_env/discrete",
    lambda: P.PlanningModel.from_env(world(), cost, _cartpole()),
    "discrete action space",
)
case(
    "PlanningModel.from_env/action-size",
    lambda: P.PlanningModel.from_env(M.LSTMWorldModel(3, 2), cost, env()),
    "action_dim",
)
case("PlanningModel()/actions-dim", lambda: model()(*CONTEXT, torch.zeros(4, 5, 2)), "actions|2")
case(
    "PlanningModel()/actions-ndim",
    lambda: model()(*CONTEXT, torch.zeros(5, A)),
    "actions",
)
case(
    "PlanningModel()/actions-nan",
    lambda: model()(*CONTEXT, torch.full((4, 5, A), NAN)),
    "actions",
)
case(
    "PlanningModel()/observation-dim",
    lambda: model()(torch.zeros(2, N), torch.zeros(2, A), torch.zeros(N + 1), torch.zeros(4, 5, A)),
    "observation",
)
case(
    "PlanningModel()/context-short",
    lambda: model()(torch.zeros(1, N), torch.zeros(1, A), torch.zeros(N), torch.zeros(4, 5, A)),
    "context_obs.*window",
)
case(
    "PlanningModel()/context-nan",
    lambda: model()(
        torch.full((2, N), NAN), torch.zeros(2, A), torch.zeros(N), torch.zeros(4, 5, A)
    ),
    r"context_obs .*NaN.*\[0, 0\]",
)
case(
    "PlanningModel()/context-dtype",  # (the planners check it, see .plan/dtype)
    lambda: model()(
        torch.zeros(2, N, dtype=torch.float64),
        torch.zeros(2, A),
        torch.zeros(N),
        torch.zeros(4, 5, A),
    ),
    "dtype",
)
case(
    "PlanningModel()/block_rows",
    lambda: model()(*CONTEXT, torch.zeros(4, 5, A), block_rows="all"),
    "block_rows",
)
case(
    "Prediction.concat/empty",
    lambda: P.Prediction.concat([]),
    "predictions",
)
case("compile_mode/unknown", lambda: compile_mode("fast"), "compile")
case(
    "threaded_pass/mode",
    lambda: threaded_pass(cost, "fast"),
    "mode",
)

PLANNERS = (P.RandomShootingPlanner, P.CEMPlanner, P.MPPIPlanner, P.ICEMPlanner, P.GradientPlanner)
for _cls in PLANNERS:
    _n = _cls.__name__

    def _build(cls=_cls, **change):
        return lambda: cls(model(), P.Objective(), **(planner_kwargs(cls) | change))

    def _plan(cls=_cls, *context, **kwargs):
        return lambda: planner(cls).plan(*context, **kwargs)

    case(
        f"{_n}/model-type",
        lambda cls=_cls: cls("model", P.Objective(), **planner_kwargs(cls)),
        "model",
    )
    case(
        f"{_n}/objective-type",
        lambda cls=_cls: cls(model(), "J", **planner_kwargs(cls)),
        "objective",
    )
    case(f"{_n}/horizon-zero", _build(horizon=0), "horizon")
    case(f"{_n}/horizon-float", _build(horizon=2.5), "horizon")
    case(f"{_n}/on_infeasible", _build(on_infeasible="ignore"), "on_infeasible")
    case(f"{_n}/unknown-keyword", _build(top_k=2), "top_k")
    case(
        f"{_n}.plan/observation-dim",
        _plan(_cls, torch.zeros(2, N), torch.zeros(2, A), torch.zeros(N + 1)),
        "observation",
    )
    case(
        f"{_n}.plan/context_action-dim",
        _plan(_cls, torch.zeros(2, N), torch.zeros(2, A + 1), torch.zeros(N)),
        "context_action",
    )
    case(
        f"{_n}.plan/observation-nan",
        _plan(_cls, torch.zeros(2, N), torch.zeros(2, A), torch.full((N,), NAN)),
        r"observation .*NaN",
    )
    case(
        f"{_n}.plan/observation-list",
        _plan(_cls, [[0.0] * N] * 2, torch.zeros(2, A), torch.zeros(N)),
        "context_obs",
    )
    case(
        f"{_n}.plan/batch-mismatch",
        _plan(_cls, torch.zeros(3, 2, N), torch.zeros(3, 2, A), torch.zeros(2, N)),
        "batch",
    )
    case(
        f"{_n}.plan/dtype",
        _plan(_cls, torch.zeros(2, N, dtype=torch.float64), torch.zeros(2, A), torch.zeros(N)),
        "dtype",
    )
    case(f"{_n}.plan/init-shape", _plan(_cls, *CONTEXT, init=torch.zeros(4, A)), "init")
    case(
        f"{_n}.plan/init-nan",
        _plan(_cls, *CONTEXT, init=torch.full((3, A), NAN)),
        "init",
    )
    case(
        f"{_n}.plan/generator-type",
        _plan(_cls, *CONTEXT, generator=3),
        "generator",
    )

for _cls in (P.CEMPlanner, P.ICEMPlanner):
    for _value in (None, 2.5, True):
        case(
            f"{_cls.__name__}/num_elites-{_value}",
            lambda cls=_cls, value=_value: cls(
                model(), P.Objective(), horizon=3, num_candidates=8, num_elites=value
            ),
            "num_elites",
        )
    case(
        f"{_cls.__name__}/num_elites-zero",
        lambda cls=_cls: cls(model(), P.Objective(), horizon=3, num_candidates=8, num_elites=0),
        "num_elites",
    )
case(
    "CEMPlanner/iterations",
    lambda: P.CEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, iterations=0
    ),
    "iterations",
)
case(
    "CEMPlanner/num_elites",
    lambda: P.CEMPlanner(model(), P.Objective(), horizon=3, num_candidates=8, num_elites=9),
    "num_elites",
)
case(
    "CEMPlanner/smoothing",
    lambda: P.CEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, smoothing=1.5
    ),
    "smoothing",
)
case(
    "CEMPlanner/min_std",
    lambda: P.CEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, min_std=-1.0
    ),
    "min_std",
)
case(
    "CEMPlanner/warm_start_uniform",
    lambda: P.CEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, warm_start_uniform=2.0
    ),
    "warm_start_uniform",
)
case(
    "CEMPlanner/block_rows",
    lambda: P.CEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, block_rows="all"
    ),
    "block_rows",
)
case(
    "MPPIPlanner/temperature",
    lambda: P.MPPIPlanner(model(), P.Objective(), horizon=3, num_candidates=8, temperature=0.0),
    "temperature",
)
case(
    "MPPIPlanner/noise_std",
    lambda: P.MPPIPlanner(model(), P.Objective(), horizon=3, num_candidates=8, noise_std=NAN),
    "noise_std",
)
case(
    "ICEMPlanner/population_decay",
    lambda: P.ICEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, population_decay=0.5
    ),
    "population_decay",
)
case(
    "ICEMPlanner/keep_elites",
    lambda: P.ICEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, keep_elites=2.0
    ),
    "keep_elites",
)
case(
    "ICEMPlanner/noise_beta",
    lambda: P.ICEMPlanner(
        model(), P.Objective(), horizon=3, num_candidates=8, num_elites=2, noise_beta=-1.0
    ),
    "noise_beta",
)
case(
    "GradientPlanner/lr", lambda: P.GradientPlanner(model(), P.Objective(), horizon=3, lr=0.0), "lr"
)
case(
    "GradientPlanner/restarts",
    lambda: P.GradientPlanner(model(), P.Objective(), horizon=3, restarts=0),
    "restarts",
)
case(
    "GradientPlanner/steps",
    lambda: P.GradientPlanner(model(), P.Objective(), horizon=3, steps=-1),
    "steps",
)
case("Objective/alpha-nan", lambda: P.Objective(alpha=NAN), "alpha")
case("Objective/beta-str", lambda: P.Objective(beta="0.1"), "beta")
case("Objective/band-type", lambda: P.Objective(band=(0.0, 1.0)), "band")
case("Objective/cost_threshold-inf", lambda: P.Objective(cost_threshold=INF), "cost_threshold")
case("UncertaintyBand/order", lambda: P.UncertaintyBand(2.0, 1.0), "low")
case("UncertaintyBand/kind", lambda: P.UncertaintyBand(1.0, 2.0, kind="relative"), "kind")
case("UncertaintyBand/nan", lambda: P.UncertaintyBand(NAN, 1.0), "low")
case("get_planner_class/unknown", lambda: get_planner_class("pets"), "pets")
case(
    "make_planner/unknown-keyword",
    lambda: P.make_planner("cem", model(), P.Objective(), horizon=3, top_k=2),
    "top_k",
)
case("check_planner_kwargs/cls", lambda: check_planner_kwargs("cem", {}), "cls")
case("check_step_fn/not-callable", lambda: check_step_fn("cost_fn", 3, N, A), "cost_fn")
case("action_bounds/shape", lambda: action_bounds(torch.zeros(2), 1.0, 1), r"action_low.*\[2\]")
case("action_bounds/order", lambda: action_bounds(1.0, -1.0, 1), "action_low")
case("bounds_from_spec/type", lambda: bounds_from_spec("Box"), "action_spec")
case("bounds_from_spec/unbounded", lambda: bounds_from_spec(Unbounded(shape=(2,))), "Unbounded")
case(
    "check_bounds_match/list",
    lambda: check_bounds_match([-1.0], [1.0], Bounded(-1.0, 1.0, shape=(1,))),
    "low",
)
case(
    "check_bounds_match/range",
    lambda: check_bounds_match(
        torch.tensor([-1.0]), torch.tensor([1.0]), Bounded(-2.0, 2.0, shape=(1,))
    ),
    "differs",
)
case("colored_noise/white-type", lambda: colored_noise([0.0], 4, 1.0), "white")
case("colored_noise/beta", lambda: colored_noise(torch.zeros(2, 3), 4, -1.0), "beta")
case("colored_noise/white-shape", lambda: colored_noise(torch.zeros(2, 5), 4, 1.0), "white")
case("run_blocks/blocks", lambda: run_blocks(lambda i: i, 0, 1), "blocks")
case("run_blocks/threads", lambda: run_blocks(lambda i: i, 2, 0), "threads")
case("run_aside/threads", lambda: run_aside(lambda: 1, -1), "threads")
case("WorldModelPlanningEnv/world_model", lambda: WorldModelPlanningEnv("wm", cost), "world_model")
case("WorldModelPlanningEnv/beta", lambda: WorldModelPlanningEnv(world(), cost, beta=NAN), "beta")
case(
    "WorldModelPlanningEnv/action_low",
    lambda: WorldModelPlanningEnv(world(), cost, action_low=torch.zeros(2)),
    r"action_low has shape \[2\]",
)
case(
    "WorldModelPlanningEnv/cost_fn",
    lambda: WorldModelPlanningEnv(world(), lambda s, a, s1: s1),
    "cost_fn",
)
case("window_uncertainty/data", lambda: window_uncertainty("data", estimator()), "data")
case("window_uncertainty/estimator", lambda: window_uncertainty(steps(), "ae"), "estimator")
case(
    "window_uncertainty/missing-key",
    lambda: window_uncertainty(steps().exclude("action"), estimator()),
    "'action'",
)
case(
    "window_uncertainty/sequence_length",
    lambda: window_uncertainty(steps(), estimator(), sequence_length=0),
    "sequence_length",
)
case("relative_beta/nan", lambda: P.relative_beta(NAN, steps(), estimator()), "beta")
case(
    "cost_to_u_ratio/missing-reward",
    lambda: cost_to_u_ratio(steps().exclude(("next", "reward")), torch.ones(3)),
    "reward",
)
case("cost_to_u_ratio/u-type", lambda: cost_to_u_ratio(steps(), [1.0]), "per_window_u")
case(
    "LSTMWorldModelModule/world_model",
    lambda: LSTMWorldModelModule("wm", cost),
    "wraps one LSTMWorldModel",
)
case(
    "LSTMWorldModelModule.make_env/action_low",
    lambda: LSTMWorldModelModule(world(), cost).make_env(
        action_low=torch.tensor([-1.0, -1.0]), action_high=1.0
    ),
    r"action_low has shape \[2\]; expected .*\[1\]",
)
case("TorchRLWorldModelAdapter/world_model", lambda: TorchRLWorldModelAdapter("wm"), "world_model")
case(
    "planning_model_from_torchrl/world_model",
    lambda: planning_model_from_torchrl("wm", cost_fn=cost, action_low=-1.0, action_high=1.0),
    "world_model",
)

# ----------------------------------------------------------------------------------- policies
_mpc = Po.MPCPolicy
case("MPCPolicy/planner", lambda: _mpc("cem"), "planner")
case("MPCPolicy/replan", lambda: _mpc(planner(), replan="sometimes"), "replan")
case(
    "MPCPolicy/replan_every",
    lambda: _mpc(planner(), replan="every_n", replan_every=0),
    "replan_every",
)
case("MPCPolicy/threshold-missing", lambda: _mpc(planner(), replan="uncertainty"), "threshold")
case(
    "MPCPolicy/threshold-nan",
    lambda: _mpc(planner(), replan="uncertainty", threshold=NAN),
    "threshold",
)
case(
    "MPCPolicy/threshold_on",
    lambda: _mpc(planner(), replan="uncertainty", threshold=1.0, threshold_on="sum"),
    "threshold_on",
)
case("MPCPolicy/error_threshold", lambda: _mpc(planner(), error_threshold=-1.0), "error_threshold")
case("MPCPolicy/warm_start", lambda: _mpc(planner(), warm_start="yes"), "warm_start")
case("MPCPolicy/warmup", lambda: _mpc(planner(), warmup="shake"), "warmup")
case(
    "MPCPolicy/warmup_steps-short",
    lambda: _mpc(planner(), warmup="random", warmup_steps=1),
    "warmup_steps",
)
case(
    "MPCPolicy/warmup_steps-plan",
    lambda: _mpc(planner(), warmup="plan", warmup_steps=3),
    "warmup_steps",
)
case("MPCPolicy/obs_key", lambda: _mpc(planner(), obs_key=3), "obs_key")
case("MPCPolicy()/tensordict-type", lambda: policy()("td"), "tensordict")
case(
    "MPCPolicy()/observation-dim",
    lambda: policy()(reset().clone().set("observation", torch.zeros(N + 1))),
    "observation",
)
case(
    "MPCPolicy()/observation-nan",
    lambda: policy()(reset().clone().set("observation", torch.full((N,), NAN))),
    "observation.*NaN",
)
case(
    "MPCPolicy()/observation-missing",
    lambda: policy()(reset().clone().exclude("observation")),
    "observation",
    errors=(KeyError,),
)
case("MPCPolicy()/no-primer", lambda: policy()(env().reset()), "primer", errors=(KeyError,))
case(
    "MPCPolicy.check_env/bounds",
    lambda: _mpc(
        P.RandomShootingPlanner(
            P.PlanningModel(world(), cost), P.Objective(), horizon=3, num_candidates=8
        )
    ).check_env(env()),
    r"\[-1, 1\]",
)
case(
    "ExplorationPolicy/replan_every",
    lambda: Po.ExplorationPolicy(explorer_planner(), replan_every=0),
    "replan_every",
)
case(
    "ExplorationPolicy/replan",
    lambda: Po.ExplorationPolicy(explorer_planner(), replan="often"),
    "replan",
)
case(
    "ExplorationPolicy/objective",
    lambda: Po.ExplorationPolicy(planner()),
    "exploration_objective",
)
case(
    "PlannerStatePrimer/primers",
    lambda: Po.PlannerStatePrimer(
        "specs", action_low=torch.tensor([-1.0]), action_high=torch.tensor([1.0])
    ),
    "primers",
)
case(
    "PlannerStatePrimer/action_low",
    lambda: Po.PlannerStatePrimer(Composite(x=Unbounded(2)), action_low=[-1.0], action_high=[1.0]),
    "action_low",
)
case(
    "PlannerStatePrimer/action_high-shape",
    lambda: Po.PlannerStatePrimer(
        Composite(x=Unbounded(2)),
        action_low=torch.tensor([-1.0]),
        action_high=torch.tensor([[1.0]]),
    ),
    "action_high",
)
case("exploration_objective/ratio", lambda: Po.exploration_objective(ratio=0), "ratio")
case("exploration_objective/cap", lambda: Po.exploration_objective(cap=0.5), "cap")
case("exploration_objective/beta", lambda: Po.exploration_objective(beta=NAN), "beta")

# ------------------------------------------------------------------------------------ modules
for _name, _cls in sorted(M.ESTIMATORS.items()):
    case(f"{_cls.__name__}/obs_dim", lambda cls=_cls: cls(0, A), "obs_dim")
    case(f"{_cls.__name__}/action_dim-float", lambda cls=_cls: cls(N, 1.5), "action_dim")
    case(f"{_cls.__name__}/window", lambda cls=_cls: cls(N, A, window=0), "window")
    case(f"{_cls.__name__}/activation", lambda cls=_cls: cls(N, A, activation="gelu"), "activation")
    case(
        f"{_cls.__name__}.score/obs-dim",
        lambda cls=_cls: fitted(cls(N, A, window=2)).score(
            torch.zeros(5, N + 1), torch.zeros(5, A)
        ),
        "obs",
    )
    case(
        f"{_cls.__name__}.score/short",
        lambda cls=_cls: fitted(cls(N, A, window=4)).score(torch.zeros(3, N), torch.zeros(3, A)),
        "window",
    )
    case(
        f"{_cls.__name__}.score/nan",
        lambda cls=_cls: fitted(cls(N, A, window=2)).score(
            torch.full((5, N), NAN), torch.zeros(5, A)
        ),
        r"obs .*NaN",
    )
    case(
        f"{_cls.__name__}.fit_normalization/nan",
        lambda cls=_cls: cls(N, A, window=2).fit_normalization(
            torch.zeros(5, N), torch.full((5, A), INF)
        ),
        r"action .*NaN or inf",
    )
    case(
        f"{_cls.__name__}.fit_normalization/rows",
        lambda cls=_cls: cls(N, A, window=2).fit_normalization(
            torch.zeros(5, N), torch.zeros(4, A)
        ),
        "disagree",
    )
case(
    "ReconstructionUncertainty/hidden_size",
    lambda: M.ReconstructionUncertainty(N, A, hidden_size=0),
    "hidden_size",
)
case("MCDropoutUncertainty/dropout", lambda: M.MCDropoutUncertainty(N, A, dropout=1.0), "dropout")
case("MCDropoutUncertainty/samples", lambda: M.MCDropoutUncertainty(N, A, samples=1), "samples")
case(
    "EnsembleUncertainty/num_members",
    lambda: M.EnsembleUncertainty(N, A, num_members=1),
    "num_members",
)
case(
    "RNDUncertainty/embedding_size",
    lambda: M.RNDUncertainty(N, A, embedding_size=0),
    "embedding_size",
)
case(
    "WorldModelEnsembleUncertainty/num_members",
    lambda: M.WorldModelEnsembleUncertainty(N, A, num_members=0),
    "num_members",
)
case("get_estimator_class/unknown", lambda: M.get_estimator_class("gp"), "gp")
case(
    "make_estimator/unknown-keyword",
    lambda: M.make_estimator("reconstruction", N, A, depth=3),
    "depth",
)
case("make_estimator/window", lambda: M.make_estimator("rnd", N, A, window=-1), "window")
case("LSTMWorldModel/obs_dim", lambda: M.LSTMWorldModel(0, A), "obs_dim")
case("LSTMWorldModel/hidden_size", lambda: M.LSTMWorldModel(N, A, hidden_size=2.5), "hidden_size")
case("LSTMWorldModel/activation", lambda: M.LSTMWorldModel(N, A, activation="gelu"), "activation")
case("LSTMWorldModel/num_members", lambda: M.LSTMWorldModel(N, A, num_members=0), "num_members")
case(
    "LSTMWorldModel.imagine/actions-dim",
    lambda: world().imagine(
        torch.zeros(2, N), torch.zeros(2, A), torch.zeros(N), torch.zeros(4, 5, A + 1)
    ),
    "actions",
)
case(
    "LSTMWorldModel.imagine/context-short",
    lambda: world().imagine(
        torch.zeros(1, N), torch.zeros(1, A), torch.zeros(N), torch.zeros(4, 5, A)
    ),
    "context_obs",
)
case(
    "LSTMWorldModel.imagine/nan",
    lambda: world().imagine(
        torch.zeros(2, N), torch.zeros(2, A), torch.full((N,), NAN), torch.zeros(4, 5, A)
    ),
    "observation.*NaN",
)
case(
    "LSTMWorldModel.fit_normalization/dims",
    lambda: M.LSTMWorldModel(N, A).fit_normalization(
        torch.zeros(5, N + 1), torch.zeros(5, A), torch.zeros(5, N)
    ),
    "obs",
)
case(
    "LSTMWorldModel.fit_normalization/nan",
    lambda: M.LSTMWorldModel(N, A).fit_normalization(
        torch.full((5, N), NAN), torch.zeros(5, A), torch.zeros(5, N)
    ),
    "obs",
)
case(
    "LSTMWorldModel.fit_normalization/rows",
    lambda: M.LSTMWorldModel(N, A).fit_normalization(
        torch.zeros(5, N), torch.zeros(4, A), torch.zeros(5, N)
    ),
    "action",
)
case("LinearDeltaModel/obs_dim", lambda: M.LinearDeltaModel(0, A), "obs_dim")
case(
    "LinearDeltaModel.fit/dims",
    lambda: M.LinearDeltaModel(N, A).fit(
        torch.zeros(5, N), torch.zeros(5, A + 1), torch.zeros(5, N)
    ),
    "action",
)
case(
    "Normalizer/num_features",
    lambda: M.Normalizer(0),
    "num_features",
)
case(
    "Normalizer/min_scale",
    lambda: M.Normalizer(N, min_scale=-1.0),
    "min_scale",
)
case(
    "Normalizer.fit/dims",
    lambda: M.Normalizer(N).fit(torch.zeros(4, N + 1)),
    "Normalizer|features|shape",
)
case(
    "ReconstructionPopulation/num_members",
    lambda: M.ReconstructionPopulation(N, A, num_members=0),
    "num_members",
)
case(
    "WorldModelPopulation/num_members",
    lambda: M.WorldModelPopulation(N, A, num_members=0),
    "num_members",
)
case("RewardModel/obs_dim", lambda: M.RewardModel(0, A), "obs_dim")
case(
    "RewardModel/nothing",
    lambda: M.RewardModel(N, A, reward=False, termination=False),
    "reward=True",
)
case("RewardModel/layers", lambda: M.RewardModel(N, A, layers=0), "layers")
case("LearnedCost/type", lambda: M.LearnedCost("rm"), "RewardModel")
case(
    "LearnedTermination/threshold",
    lambda: M.LearnedTermination(M.RewardModel(N, A, termination=True), threshold=1.5),
    "threshold",
)
case("module_device/type", lambda: M.module_device("cpu"), "module")
case("module_dtype/type", lambda: M.module_dtype(3), "module")
case("check_fitted/unfitted", lambda: M.check_fitted(M.LSTMWorldModel(N, A)), "never fitted")

# --------------------------------------------------------------------------------- objectives
case(
    "WorldModelPredictionLoss/world_model", lambda: O.WorldModelPredictionLoss("wm"), "world_model"
)
case(
    "WorldModelPredictionLoss/mode",
    lambda: O.WorldModelPredictionLoss(world(), mode="two_step"),
    "mode",
)
case(
    "WorldModelPredictionLoss/slice_len",
    lambda: O.WorldModelPredictionLoss(world(), slice_len=0),
    "slice_len",
)
case(
    "WorldModelPredictionLoss()/flat-batch",
    lambda: O.WorldModelPredictionLoss(world())(steps()),
    "slice_len",
)
case(
    "WorldModelPredictionLoss()/short",
    lambda: O.WorldModelPredictionLoss(world(), slice_len=2)(steps()),
    "window",
)
case("UncertaintyLoss/estimator", lambda: O.UncertaintyLoss("ae"), "estimator")
case("UncertaintyLoss/slice_len", lambda: O.UncertaintyLoss(estimator(), slice_len=-1), "slice_len")
case(
    "UncertaintyLoss()/split",
    lambda: O.UncertaintyLoss(estimator(), slice_len=3)(steps()),
    "slices of 3",
)
case("RewardLoss/type", lambda: O.RewardLoss("rm"), "RewardModel")
case("as_sequences/type", lambda: O.as_sequences("td", 4), "tensordict")
case("as_sequences/slice_len", lambda: O.as_sequences(steps(), 0), "slice_len")

# ----------------------------------------------------------------------------------- training
FIT = dict(steps=2, eval_every=1, progress=False)
case("fit_world_model/model", lambda: T.fit_world_model("wm", buffer(), **FIT), "model")
case("fit_world_model/buffer", lambda: T.fit_world_model(world(), steps(), **FIT), "buffer")
case(
    "fit_world_model/mode",
    lambda: T.fit_world_model(world(), buffer(), mode="two_step", **FIT),
    "mode",
)
case(
    "fit_world_model/dims",
    lambda: T.fit_world_model(M.LSTMWorldModel(N + 1, A, window=2), buffer(), **FIT),
    "obs",
)
case("fit_world_model/steps", lambda: T.fit_world_model(world(), buffer(), steps=0), "steps")
case("fit_world_model/lr", lambda: T.fit_world_model(world(), buffer(), lr=NAN), "lr")
case(
    "fit_world_model/unknown-keyword",
    lambda: T.fit_world_model(world(), buffer(), epochs=3),
    "epochs",
)
case(
    "fit_world_model/nan-data",
    lambda: T.fit_world_model(world(), buffer(steps(bad=("action", 7)))),
    r"'action' in the replay buffer .*row 7",
)
case(
    "fit_world_model/members",
    lambda: T.fit_world_model(M.LSTMWorldModel(N, A, num_members=2), buffer()),
    "num_members",
)
case(
    "fit_reward/reward_model",
    lambda: T.fit_reward("rm", buffer(), **FIT),
    "reward_model",
)
case(
    "RewardModel.fit_normalization/nan",
    lambda: M.RewardModel(N, A).fit_normalization(
        torch.zeros(5, N), torch.zeros(5, A), torch.zeros(5, N), torch.full((5, 1), NAN)
    ),
    r"reward contains NaN or inf",
)
case(
    "fit_reward/nan-reward",
    lambda: T.fit_reward(M.RewardModel(N, A), buffer(steps(bad=(("next", "reward"), 9)))),
    r"\('next', 'reward'\) in the replay buffer .*row 9",
)
case("fit_world_members/one", lambda: T.fit_world_members(world(), buffer()), "num_members")
case("fit_uncertainty/estimator", lambda: T.fit_uncertainty("ae", buffer(), **FIT), "estimator")
case(
    "fit_uncertainty/dims",
    lambda: T.fit_uncertainty(M.ReconstructionUncertainty(N, A + 1, window=2), buffer(), **FIT),
    "action",
)
case(
    "fit_uncertainty/nan-data",
    lambda: T.fit_uncertainty(estimator(), buffer(steps(bad=("observation", 3)))),
    r"'observation' in the replay buffer .*row 3",
)
case("fit_population/empty", lambda: T.fit_population([], buffer(), **FIT), "at least one")
case("fit_population/type", lambda: T.fit_population("wm", buffer(), **FIT), "models")
case(
    "fit_population/seeds",
    lambda: T.fit_population([world(), world()], buffer(), seeds=[0], **FIT),
    "seeds",
)
case(
    "fit_population/kinds",
    lambda: T.fit_population([world(), estimator()], buffer(), **FIT),
    "LSTMWorldModel",
)
case(
    "train_loss_module/loss_module",
    lambda: T.train_loss_module("loss", buffer(), **FIT),
    "loss_module",
)
case(
    "train_loss_module/clip_norm",
    lambda: T.train_loss_module(
        O.UncertaintyLoss(estimator(), slice_len=4), buffer(), clip_norm=-1.0
    ),
    "clip_norm",
)
case(
    "train_loss_module/seed",
    lambda: T.train_loss_module(O.UncertaintyLoss(estimator(), slice_len=4), buffer(), seed="0"),
    "seed",
)
case(
    "train_loss_module/empty",
    lambda: T.train_loss_module(
        O.UncertaintyLoss(estimator(), slice_len=4),
        D.make_sequence_buffer(10, slice_len=4, num_slices=2),
    ),
    "empty",
)
case("FitSchedule/steps", lambda: T.FitSchedule(steps=0), "steps")
case("FitSchedule/lr", lambda: T.FitSchedule(lr=-1.0), "lr")
case("FitSchedule/val_fraction", lambda: T.FitSchedule(val_fraction=1.0), "val_fraction")
case("FitSchedule/slice_len", lambda: T.FitSchedule(slice_len=0), "slice_len")
case("FitSchedule/mode", lambda: T.FitSchedule(mode="two_step"), "mode")
case("save_checkpoint/modules", lambda: T.save_checkpoint(_tmp() / "c.pt", "wm"), "modules")
case(
    "save_checkpoint/module",
    lambda: T.save_checkpoint(_tmp() / "c.pt", {"wm": torch.nn.Linear(2, 2)}),
    "config",
)
case(
    "load_checkpoint/missing",
    lambda: T.load_checkpoint(_tmp() / "none.pt", {"wm": world()}),
    "none.pt",
    errors=(FileNotFoundError,),
)
case(
    "load_modules/missing",
    lambda: T.load_modules(_tmp() / "none.pt"),
    "none.pt",
    errors=(FileNotFoundError,),
)
case("load_modules/garbage", lambda: T.load_modules(_junk()), "junk.pt")

# ----------------------------------------------------------------------------------- trainers
case("FitNormalization/world_model", lambda: Tr.FitNormalization("wm"), "world_model")
case("FitNormalization/estimator", lambda: Tr.FitNormalization(world(), "ae"), "estimator")
case(
    "FitNormalization()/missing-key",
    lambda: Tr.FitNormalization(M.LSTMWorldModel(N, A))(steps().exclude("action")),
    "'action'",
)
case(
    "FitNormalization()/nan",
    lambda: Tr.FitNormalization(M.LSTMWorldModel(N, A))(steps(bad=(("next", "observation"), 5))),
    r"\('next', 'observation'\) in the collected batch .*row 5",
)
case(
    "IterationCollector/iterations",
    lambda: Tr.IterationCollector(iterations=-1, steps_per_iteration=1, random_steps=1),
    "iterations",
)
case(
    "IterationCollector/explore_iterations",
    lambda: Tr.IterationCollector(
        iterations=1, steps_per_iteration=1, random_steps=1, explore_iterations=2
    ),
    "explore_iterations",
)
case("LogIteration/slice_len", lambda: Tr.LogIteration(world(), slice_len=0), "slice_len")
case("LogIteration/world_model", lambda: Tr.LogIteration("wm", slice_len=4), "world_model")
case(
    "LogIteration()/nan-reward",
    lambda: Tr.LogIteration(world(), slice_len=4).before_fit(steps(bad=(("next", "reward"), 2))),
    r"\('next', 'reward'\) .*row 2",
)
case(
    "ModelFitStepper/world_model",
    lambda: Tr.ModelFitStepper("wm", None, ReplayBuffer(storage=LazyTensorStorage(10))),
    "world_model",
)
case(
    "ModelFitStepper/replay_buffer",
    lambda: Tr.ModelFitStepper(world(), None, "rb"),
    "replay_buffer",
)
case(
    "OnlineCollector/env",
    lambda: Tr.OnlineCollector(
        "env", policy(), iterations=1, steps_per_iteration=10, random_steps=10
    ),
    "env",
)
case(
    "OnlineCollector/policy",
    lambda: Tr.OnlineCollector(env(), "mpc", iterations=1, steps_per_iteration=10, random_steps=10),
    "policy",
)
case(
    "OnlineCollector/no-policy",
    lambda: Tr.OnlineCollector(env(), None, iterations=1, steps_per_iteration=10, random_steps=10),
    "policy",
)
case(
    "OnlineCollector/steps_per_iteration",
    lambda: Tr.OnlineCollector(
        env(), policy(), iterations=1, steps_per_iteration=0, random_steps=10
    ),
    "steps_per_iteration",
)
case(
    "OnlineTrainer/collector",
    lambda: Tr.OnlineTrainer(collector="c", world_model=world(), estimator=None),
    "collector",
)
case("ReplayBufferSteps/replay_buffer", lambda: Tr.ReplayBufferSteps("rb"), "replay_buffer")
case("TimedPolicy/policy", lambda: Tr.TimedPolicy("mpc"), "policy")
case("env_keys/env", lambda: Tr.env_keys(steps(), "env"), "env")
case("play/frames", lambda: Tr.play(env(), policy(), frames=0, seed=0), "frames")
case("play/env", lambda: Tr.play("env", policy(), frames=10, seed=0), "env")
case(
    "verify_checkpoint/missing",
    lambda: Tr.verify_checkpoint(_tmp() / "none"),
    "none",
    errors=(FileNotFoundError,),
)
case("VerifiedTrainer/checkpoint", lambda: Tr.VerifiedTrainer(checkpoint="ckpt"), "checkpoint")
case(
    "learn_online/iterations",
    lambda: Tr.learn_online(
        env(), world(), None, planner, iterations=-1, steps_per_iteration=10, random_steps=10
    ),
    "iterations",
)

# --------------------------------------------------------------------------------------- data
case("GatherTensorStorage/max_size", lambda: D.GatherTensorStorage(0), "max_size")
case(
    "StepUniformSliceSampler/slice_len", lambda: D.StepUniformSliceSampler(slice_len=0), "slice_len"
)
case(
    "make_sequence_buffer/max_size",
    lambda: D.make_sequence_buffer(0, slice_len=4, num_slices=2),
    "max_size",
)
case(
    "make_sequence_buffer/slice_len",
    lambda: D.make_sequence_buffer(10, slice_len=0, num_slices=2),
    "slice_len",
)
case(
    "make_sequence_buffer/sampling",
    lambda: D.make_sequence_buffer(10, slice_len=4, num_slices=2, sampling="uniform"),
    "sampling",
)
case(
    "make_sequence_buffer/pad_short",
    lambda: D.make_sequence_buffer(10, slice_len=4, num_slices=2, sampling="step", pad_short=True),
    "pad_short",
)
case("buffer_contents/type", lambda: D.buffer_contents("rb"), "buffer")
case(
    "buffer_contents/empty",
    lambda: D.buffer_contents(D.make_sequence_buffer(10, slice_len=4, num_slices=2)),
    "empty",
)
case("cut_sequences/length", lambda: D.cut_sequences(steps(), 0), "length")
case(
    "cut_sequences/no-ids",
    lambda: D.cut_sequences(steps().exclude(("collector", "traj_ids")), 4),
    "traj_ids",
)
case("cut_sequences/data", lambda: D.cut_sequences("td", 4), "data")
case("cut_sequences/too-long", lambda: D.cut_sequences(steps(), 30), "30 steps")
case("long_trajectories/length", lambda: D.long_trajectories(steps(), 0), "length")
case("needs_padding/slice_len", lambda: D.needs_padding(0, steps()), "slice_len")
case("padded_trajectories/length", lambda: D.padded_trajectories(steps(), -1), "length")
case("sequence_buffers/empty", lambda: D.sequence_buffers((), slice_len=4, num_slices=2), "parts")
case(
    "sequence_buffers/part", lambda: D.sequence_buffers(("td",), slice_len=4, num_slices=2), "data"
)
case(
    "split_by_trajectory/val_fraction",
    lambda: D.split_by_trajectory(steps(), 1.5, seed=0),
    "val_fraction",
)
case("split_by_trajectory/nan", lambda: D.split_by_trajectory(steps(), NAN, seed=0), "val_fraction")
case("split_by_trajectory/seed", lambda: D.split_by_trajectory(steps(), 0.5, seed="0"), "seed")
case(
    "split_by_trajectory/one-trajectory",
    lambda: D.split_by_trajectory(steps()[:10], 0.5, seed=0),
    "2 trajectories",
)
case("save_buffer/type", lambda: D.save_buffer("rb", _tmp() / "rb"), "buffer")
case(
    "save_buffer/empty",
    lambda: D.save_buffer(D.make_sequence_buffer(10, slice_len=4, num_slices=2), _tmp() / "rb"),
    "empty",
)
case("load_buffer/type", lambda: D.load_buffer("rb", _tmp() / "rb"), "buffer")
case(
    "load_buffer/missing",
    lambda: D.load_buffer(D.make_sequence_buffer(10, slice_len=4, num_slices=2), _tmp() / "none"),
    "none",
    errors=(FileNotFoundError,),
)
case(
    "load_buffer_data/missing",
    lambda: D.load_buffer_data(_tmp() / "none"),
    "none",
    errors=(FileNotFoundError,),
)


@functools.cache
def _tmp() -> Path:
    """A scratch folder of this process's probes, removed when it exits."""
    import atexit
    import shutil
    import tempfile

    path = Path(tempfile.mkdtemp(prefix="api_probe_"))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


def _junk() -> Path:
    path = _tmp() / "junk.pt"
    path.write_bytes(b"not a checkpoint")
    return path


@functools.cache
def _cartpole():
    from torchrl.envs import GymEnv

    return GymEnv("CartPole-v1")


def _param(c: Case):
    marks = [pytest.mark.xfail(strict=True, reason=c.xfail)] if c.xfail else []
    return pytest.param(c, id=c.id, marks=marks)


@pytest.mark.parametrize("probe", [_param(c) for c in CASES])
def test_a_wrong_input_is_one_clear_line_from_the_library(probe: Case):
    refused(probe.call, probe.match, probe.errors)


def test_the_probe_calls_every_public_name():
    """Each name of the probed packages' ``__all__`` that can be called is probed above."""
    import importlib

    probed_ids = " ".join(c.id for c in CASES)
    left = []
    for package in PROBED:
        module = importlib.import_module(f"torchrl_recon.{package}")
        for name in module.__all__:
            obj = getattr(module, name)
            data_only = not callable(obj) or name in NOT_CALLED
            if not data_only and not re.search(rf"(^|[ .]){re.escape(name)}[/.(]", probed_ids):
                left.append(f"{package}.{name}")
    assert not left, f"public names the probe never calls: {left}"


NOT_CALLED = {
    # exceptions, warnings, results and type aliases: nothing to call wrongly
    "InfeasiblePlanError",
    "InfeasiblePlanWarning",
    "PlanResult",
    "PlanOutput",
    "PlanFlags",
    "Prediction",
    "Iteration",
    "Gaussian",
    "TerminationFn",
    "FitResult",
    "IterationRecord",
    "PlannerBase",
    "SamplingPlanner",
    "UncertaintyEstimator",
    "EliteMemory",
    # registries (dicts) and the callable that only knows its device (fit_graph's CUDA step)
    "PLANNERS",
    "ESTIMATORS",
    "CapturedStep",
    "quiet_storage_init",
    "world_model_fit",
    "BatchedWorldModelEnv",
    "FittedCheck",
    "unfitted_normalizers",
    "VerifiedCheckpoint",
    "relative_beta",
}


# --------------------------------------------------------------------- property-based probes
@SETTINGS
@given(
    action_dim=st.integers(1, 3),
    shape=st.lists(st.integers(0, 3), max_size=3),
    which=st.sampled_from(["action_low", "action_high"]),
)
def test_bounds_of_any_shape_are_taken_or_refused_naming_the_argument(action_dim, shape, which):
    value = torch.full(shape, -1.0 if which == "action_low" else 1.0)
    wm = M.LSTMWorldModel(2, action_dim, window=1, hidden_size=4, dense_size=4)
    build = lambda: P.PlanningModel(wm, cost, **{which: value})  # noqa: E731
    if tuple(shape) in ((), (1,), (action_dim,)):
        assert build().action_low.shape == (action_dim,)
        return
    refused(
        build, rf"^{which} has shape \[{', '.join(map(str, shape))}\]; expected .*\[{action_dim}\]"
    )


WRONG_INTS = st.one_of(
    st.integers(-5, 0), st.floats(allow_nan=True), st.text(max_size=2), st.booleans(), st.none()
)
INT_ARGS = [
    (cls, name)
    for cls in PLANNERS
    for name in ("horizon", "num_candidates", "iterations", "restarts", "steps")
    if name in planner_kwargs(cls)
    or name in ("iterations",)
    and cls not in (P.RandomShootingPlanner, P.GradientPlanner)
]


@pytest.mark.parametrize("cls, name", INT_ARGS, ids=[f"{c.__name__}-{n}" for c, n in INT_ARGS])
@SETTINGS
@given(value=WRONG_INTS)
def test_a_planners_count_out_of_range_or_of_another_type_is_refused_by_name(cls, name, value):
    refused(lambda: cls(model(), P.Objective(), **(planner_kwargs(cls) | {name: value})), name)


@SETTINGS
@given(
    which=st.sampled_from(["context_obs", "context_action", "observation"]),
    dim=st.integers(1, 5),
    batch=st.sampled_from([(), (2,)]),
)
def test_a_context_of_another_width_is_refused_naming_it(which, dim, batch):
    width = {"context_obs": N, "context_action": A, "observation": N}[which]
    if dim == width:
        dim += 1
    shapes = {
        "context_obs": (*batch, 2, N),
        "context_action": (*batch, 2, A),
        "observation": (*batch, N),
    }
    shapes[which] = (*shapes[which][:-1], dim)
    args = [torch.zeros(shapes[k]) for k in ("context_obs", "context_action", "observation")]
    refused(lambda: planner(P.CEMPlanner).plan(*args), which)


@SETTINGS
@given(
    which=st.sampled_from(["context_obs", "context_action", "observation"]),
    at=st.integers(0, 5),
    value=st.sampled_from([NAN, INF, -INF]),
)
def test_a_non_finite_context_value_is_named_with_its_index(which, at, value):
    args = {
        "context_obs": torch.zeros(2, N),
        "context_action": torch.zeros(2, A),
        "observation": torch.zeros(N),
    }
    flat = args[which].view(-1)
    flat[at % flat.numel()] = value
    index = list(torch.unravel_index(torch.tensor(at % flat.numel()), args[which].shape))
    error = refused(lambda: planner().plan(*args.values()), rf"{which} contains NaN or inf")
    assert f"{[int(i) for i in index]}" in str(error)


@SETTINGS
@given(
    key=st.sampled_from(["observation", "action", ("next", "observation")]),
    row=st.integers(0, 39),
)
def test_nan_in_a_buffer_is_named_by_key_and_row_before_a_fit(key, row):
    rb = buffer(steps(bad=(key, row)))
    shown = re.escape(repr(key))
    refused(
        lambda: T.fit_world_model(world(), rb, **FIT),
        rf"^{shown} in the replay buffer .*first at row {row},",
    )


@SETTINGS
@given(
    kind=st.sampled_from(sorted(M.ESTIMATORS)),
    obs_dim=st.integers(1, 5),
    length=st.integers(1, 4),
)
def test_an_estimator_refuses_windows_of_another_width_or_too_short(kind, obs_dim, length):
    est = fitted(M.ESTIMATORS[kind](N, A, window=3))
    obs, action = torch.zeros(2, length, obs_dim), torch.zeros(2, length, A)
    if obs_dim == N and length >= 3:
        assert est.score(obs, action).shape == (2, length - 2)
        return
    refused(lambda: est.score(obs, action), "obs")


def test_the_probe_is_counted(capsys):
    """How many calls the probe makes (printed with ``-s``): cases plus hypothesis examples."""
    with capsys.disabled():
        print(f"\napi probe: {len(CASES)} cases, {CALLS[0]} refused calls so far")
    assert len(CASES) > 150
