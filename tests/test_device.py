"""The device follows the module: every entry point makes its tensors where its module or inputs are.

CPU-only check: models and inputs are built on the CPU, then each entry point is called inside
``with torch.device("meta"):``. A factory call that neither names a device nor takes it from an
input then makes a meta tensor; mixing it with CPU tensors raises, and where an op lets it
through (indexing, matmul), the result changes. So every call runs twice from the same seed,
once plainly and once inside the context, and the two results must be identical bit for bit
and on the CPU.

CUDA check (skipped without a GPU): the same entry points with models and inputs moved to
``cuda``. Every output tensor must be on ``cuda``; deterministic entry points must match the
CPU within float32 tolerance (random ones draw from the CUDA generator, so only their device is
checked, and a plan is compared across devices by drawing its candidates from one CPU
``torch.Generator``: see :func:`test_plan_agrees_on_cpu_and_cuda`).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from collections.abc import Callable

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import DeviceCastTransform
from torchrl.envs.utils import step_mdp

from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.envs import make_env
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.envs.industrial_benchmark import industrial_benchmark_cost
from torchrl_recon.evaluation import (
    auroc,
    imagined_uncertainty_and_error,
    multi_step_errors,
    spearman,
)
from torchrl_recon.fitting import (
    fit_population,
    fit_uncertainty,
    fit_world_model,
    load_checkpoint,
    load_modules,
    save_checkpoint,
    train_loss_module,
)
from torchrl_recon.modules import (
    ESTIMATORS,
    LinearDeltaModel,
    LSTMWorldModel,
    ReconstructionPopulation,
    WorldModelPopulation,
    make_estimator,
)
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
    UncertaintyBand,
)
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.policies import ExplorationPolicy, MPCPolicy, exploration_objective

logging.getLogger("torchrl").setLevel(logging.WARNING)

N, M, T = 12, 4, 3  # Drone sizes, a short window
KINDS = sorted(ESTIMATORS)
RANDOM_ON_DEVICE = ("mc_dropout", "ensemble", "world_model_ensemble")
"""Estimators whose masks or bootstrap draws come from the device's generator: on CUDA only
the outputs' devices are checked (CPU and CUDA generators give different numbers)."""
NEEDS_CUDA = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)"
)
DEVICES = [
    pytest.param("meta", id="cpu-under-meta-default"),
    pytest.param("cuda", id="cuda", marks=NEEDS_CUDA),
]
# float32 results of the same ops on CUDA and on the CPU (different kernels, summation orders).
RTOL, ATOL = 1e-4, 1e-5


# ---------------------------------------------------------------- harness


@pytest.fixture(autouse=True)
def _no_tf32():
    """CUDA results are compared with the CPU's in float32: no TensorFloat-32 matmuls or RNNs."""
    if not torch.cuda.is_available():
        yield
        return
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def _leaves(x, path: str = "out"):
    """(path, value) of every tensor or plain number in a nested result."""
    if isinstance(x, torch.Tensor):
        yield path, x
    elif isinstance(x, TensorDictBase):
        for key, value in x.items(include_nested=True, leaves_only=True):
            yield f"{path}[{key}]", value
    elif dataclasses.is_dataclass(x) and not isinstance(x, type):
        for f in dataclasses.fields(x):
            yield from _leaves(getattr(x, f.name), f"{path}.{f.name}")
    elif isinstance(x, dict):
        for key, value in x.items():
            yield from _leaves(value, f"{path}[{key!r}]")
    elif isinstance(x, (list, tuple)):
        for i, value in enumerate(x):
            yield from _leaves(value, f"{path}[{i}]")
    elif isinstance(x, (bool, int, float)):
        yield path, x


def _assert_identical(out, ref) -> None:
    got, want = list(_leaves(out)), list(_leaves(ref))
    assert [p for p, _ in got] == [p for p, _ in want]
    for (path, a), (_, b) in zip(got, want, strict=True):
        if isinstance(b, torch.Tensor):
            assert a.device.type == "cpu", f"{path} is on {a.device}; expected cpu"
            assert a.dtype == b.dtype and a.shape == b.shape, path
            same = (a == b) | (a.isnan() & b.isnan()) if a.is_floating_point() else a == b
            assert bool(same.all()), f"{path} differs under a meta default device"
        else:
            assert a == b or (a != a and b != b), f"{path}: {a} != {b}"


def _assert_close_on(out, ref, device: str, *, compare: bool) -> None:
    got, want = list(_leaves(out)), list(_leaves(ref))
    assert [p for p, _ in got] == [p for p, _ in want]
    for (path, a), (_, b) in zip(got, want, strict=True):
        if isinstance(b, torch.Tensor):
            assert a.device.type == device, f"{path} is on {a.device}; expected {device}"
            if compare:
                torch.testing.assert_close(a.cpu(), b, rtol=RTOL, atol=ATOL, equal_nan=True)
        elif compare and isinstance(b, float):
            assert a == pytest.approx(b, rel=RTOL, abs=ATOL, nan_ok=True), path


def _to(objects: tuple, device: str) -> tuple:
    """Modules, tensors and TensorDicts moved to ``device``; anything else as it is."""
    moved = []
    for x in objects:
        if isinstance(x, (torch.nn.Module, torch.Tensor, TensorDictBase)):
            x = x.to(device)
        moved.append(x)
    return tuple(moved)


def check(build: Callable[[], tuple], run: Callable, device: str, *, compare: bool = True):
    """Run ``run(*build())`` on the CPU, then under a meta default device or on CUDA; compare.

    ``compare=False`` (random entry points on CUDA) checks only the device of every output.
    Returns both results, ``(out, ref)``.
    """
    objects = build()
    torch.manual_seed(0)
    ref = run(*objects)
    objects = build()
    torch.manual_seed(0)
    if device == "meta":
        with torch.device("meta"):
            out = run(*objects)
        _assert_identical(out, ref)
    else:
        out = run(*_to(objects, device))
        _assert_close_on(out, ref, device, compare=compare)
    return out, ref


def _world_model(window: int = T) -> LSTMWorldModel:
    torch.manual_seed(1)
    model = LSTMWorldModel(N, M, window=window, hidden_size=8, dense_size=8)
    s, a = torch.randn(100, N), torch.rand(100, M) * 2 - 1
    model.fit_normalization(s, a, s + 0.1 * torch.randn(100, N))
    return model


def _estimator(kind: str):
    torch.manual_seed(2)
    est = make_estimator(kind, N, M, window=T, hidden_size=8)
    est.fit_normalization(torch.randn(100, N), torch.rand(100, M) * 2 - 1)
    return est


def _sequences(batch=(2,), length: int = 7) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    obs = torch.randn(*batch, length, N, generator=g)
    action = torch.rand(*batch, length, M, generator=g) * 2 - 1
    return obs, action, obs + 0.1 * torch.randn(*batch, length, N, generator=g)


def _grads(module: torch.nn.Module) -> list:
    return [p.grad for p in module.parameters() if p.grad is not None]


# ---------------------------------------------------------------- modules


@pytest.mark.parametrize("device", DEVICES)
def test_world_model(device):
    def build():
        obs, action, next_obs = _sequences()
        candidates = torch.rand(2, 5, 4, M, generator=torch.Generator().manual_seed(4))
        return _world_model(), obs, action, next_obs, candidates

    def run(model, obs, action, next_obs, candidates):
        ctx_obs, ctx_action, now = obs[:, :T], action[:, :T], obs[:, T]
        with torch.no_grad():
            no_grad = model.imagine(ctx_obs, ctx_action, now, candidates)
        candidates = candidates.clone().requires_grad_(True)
        states = model.imagine(ctx_obs, ctx_action, now, candidates)  # the fused BPTT node
        states.square().sum().backward()
        td = model(TensorDict({"observation": obs, "action": action}, [2, obs.shape[1]]))
        stepped = model.step(now, candidates[:, 0, 0], model.warmup(ctx_obs, ctx_action))
        recorded = model.rollout(
            now, candidates[:, 0].detach(), model.warmup(ctx_obs, ctx_action), recorded=True
        )
        return no_grad, states, candidates.grad, _grads(model), td, stepped, recorded

    check(build, run, device)


@pytest.mark.parametrize("device", DEVICES)
def test_linear_delta_model(device):
    def build():
        obs, action, next_obs = _sequences()
        return LinearDeltaModel(N, M), obs, action, next_obs

    def run(model, obs, action, next_obs):
        model.fit(obs, action, next_obs)
        return model.imagine(obs[:, :2], action[:, :2], obs[:, 2], action[:, None, 2:])

    check(build, run, device)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("device", DEVICES)
def test_estimator_score_and_loss(device, kind):
    def build():
        obs, action, _ = _sequences()
        return _estimator(kind), obs, action

    def run(est, obs, action):
        with torch.no_grad():  # the blocked, in-place paths
            no_grad = est.score(obs, action)
        obs = obs.clone().requires_grad_(True)
        score = est.score(obs, action)
        score.sum().backward()
        loss = est.loss(obs.detach(), action)
        loss.backward()
        td = est(TensorDict({"observation": obs.detach(), "action": action}, [2, 7]))
        windows = est.score_windows(torch.cat([obs, action], -1)[:, :T].detach())
        return no_grad, score, obs.grad, loss, _grads(est), td, windows

    check(build, run, device, compare=kind not in RANDOM_ON_DEVICE)


@pytest.mark.parametrize("loss_kind", ["multi_step", "one_step", *KINDS])
@pytest.mark.parametrize("device", DEVICES)
def test_losses_backward(device, loss_kind):
    def build():
        obs, action, next_obs = _sequences(batch=(3,))
        td = TensorDict(
            {"observation": obs, "action": action, ("next", "observation"): next_obs}, [3, 7]
        ).reshape(-1)
        if loss_kind in ("multi_step", "one_step"):
            return WorldModelPredictionLoss(_world_model(), mode=loss_kind, slice_len=7), td
        return UncertaintyLoss(_estimator(loss_kind), slice_len=7), td

    def run(loss_module, td):
        out = loss_module(td)
        sum(out.values()).backward()
        return out, _grads(loss_module)

    check(build, run, device, compare=loss_kind not in RANDOM_ON_DEVICE)


@pytest.mark.parametrize("env", ["industrial_benchmark", "drone", "minitaur"])
@pytest.mark.parametrize("device", DEVICES)
def test_env_cost_functions(device, env):
    if env == "minitaur":  # its module imports pybullet (a GPU image may lack it)
        pytest.importorskip("pybullet")
        from torchrl_recon.envs.minitaur import minitaur_cost
    else:
        minitaur_cost = None
    cost_fn, n, m = {
        "industrial_benchmark": (industrial_benchmark_cost, 6, 3),
        "drone": (drone_cost, 12, 4),
        "minitaur": (minitaur_cost, 34, 8),
    }[env]

    def build():
        g = torch.Generator().manual_seed(5)
        return torch.randn(4, 3, n, generator=g), torch.rand(4, 3, m, generator=g)

    def run(obs, action):
        obs = obs.clone().requires_grad_(True)
        cost = cost_fn(obs, action, obs + 1.0)
        cost.sum().backward()
        return cost, obs.grad

    check(build, run, device)


# ---------------------------------------------------------------- planners


def _planning_model(kind: str | None) -> PlanningModel:
    return PlanningModel(
        _world_model(), drone_cost, uncertainty=None if kind is None else _estimator(kind)
    )


def _context(batch=(2,)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    obs, action, _ = _sequences(batch=batch, length=T + 1)
    return obs[..., :T, :], action[..., :T, :], obs[..., T, :]


@pytest.mark.parametrize("kind", [None, *KINDS])
@pytest.mark.parametrize("device", DEVICES)
def test_planning_model(device, kind):
    def build():
        actions = torch.rand(2, 5, 4, M, generator=torch.Generator().manual_seed(6))
        return _planning_model(kind), *_context(), actions

    def run(model, ctx_obs, ctx_action, obs, actions):
        return model(ctx_obs, ctx_action, obs, actions, state=model.warmup(ctx_obs, ctx_action))

    check(build, run, device, compare=kind != "mc_dropout")


PLANNERS = {
    "shooting": lambda model, objective: RandomShootingPlanner(
        model, objective, horizon=4, num_candidates=8
    ),
    "cem": lambda model, objective: CEMPlanner(
        model, objective, horizon=4, num_candidates=8, num_elites=3, iterations=2
    ),
    "gradient": lambda model, objective: GradientPlanner(
        model, objective, horizon=4, restarts=3, steps=2
    ),
    "mppi": lambda model, objective: MPPIPlanner(
        model, objective, horizon=4, num_candidates=8, iterations=2
    ),
    "icem": lambda model, objective: ICEMPlanner(
        model, objective, horizon=4, num_candidates=8, num_elites=3, iterations=2
    ),
}


@pytest.mark.parametrize("kind", [None, *KINDS])
@pytest.mark.parametrize("planner", sorted(PLANNERS))
@pytest.mark.parametrize("device", DEVICES)
def test_planner(device, planner, kind):
    # A relative band (resolved on the uniform candidates) when there is an estimator.
    objective = (
        Objective()
        if kind is None
        else Objective(beta=0.1, band=UncertaintyBand(high=0.9, kind="quantile"))
    )

    def build():
        return PLANNERS[planner](_planning_model(kind), objective), *_context()

    def run(p, ctx_obs, ctx_action, obs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            first = p.plan(ctx_obs, ctx_action, obs)
            warm = p.plan(ctx_obs, ctx_action, obs, init=first.actions)
        return first, warm

    check(build, run, device, compare=False)


@pytest.mark.parametrize("device", DEVICES)
def test_world_model_planning_env(device):
    """The env is built on the world model's device (TorchRL's default would move it to the CPU)."""

    def build():
        return _world_model(), _estimator("reconstruction"), *_context()

    def run(model, est, ctx_obs, ctx_action, obs):
        env = WorldModelPlanningEnv(model, drone_cost, uncertainty=est, beta=0.1)
        assert env.device == obs.device and model.dense.weight.device == obs.device
        td = env.initial_state(ctx_obs, ctx_action, obs)
        td["action"] = torch.zeros_like(ctx_action[..., 0, :])
        return env.step(td)

    check(build, run, device)


# ---------------------------------------------------------------- policies


def _policies() -> dict[str, Callable[[], MPCPolicy]]:
    def mpc(kind: str = "cem"):
        model = _planning_model("reconstruction")
        planner = PLANNERS[kind](model, Objective(beta=0.1))
        return MPCPolicy(planner, replan="uncertainty", threshold=0.5, error_threshold=1.0)

    def explore():
        model = _planning_model("reconstruction")
        planner = RandomShootingPlanner(
            model, exploration_objective(ratio=1.1), horizon=4, num_candidates=8
        )
        return ExplorationPolicy(planner, replan_every=2)

    return {
        "mpc": mpc,
        # iCEM's elites carried from plan to plan through the policy's warm start, on the device
        "mpc_icem": lambda: mpc("icem"),
        "mpc_mppi": lambda: mpc("mppi"),
        "exploration": explore,
    }


@pytest.mark.parametrize("policy", ["mpc", "mpc_icem", "mpc_mppi", "exploration"])
@pytest.mark.parametrize("device", DEVICES)
def test_policy_steps(device, policy):
    """Seven env steps (three random, then plans); the env on the CPU, the policy on ``device``.

    As in a collector with ``env_device="cpu"`` and ``policy_device=device``, each step's input
    is moved to the policy's device and its output back. The env is not ours: it steps outside
    the meta default device, the policy inside it.
    """

    def build():
        return (_policies()[policy](),)

    def run(pol):
        default = torch.get_default_device()  # meta under the check
        with torch.device("cpu"):
            env = make_env("drone", seed=0).append_transform(pol.make_tensordict_primer())
            td, outputs = env.reset(), []
            for _ in range(7):
                td = td.to(pol.device)
                with torch.device(default):
                    td = pol(td)
                outputs.append(td.clone())
                td = step_mdp(env.step(td.to("cpu")))
        return torch.stack(outputs)

    out, _ = check(build, run, device, compare=False)
    assert out["mpc_replanned"].squeeze(-1)[:4].tolist() == [False] * 3 + [True]


@NEEDS_CUDA
def test_policy_in_a_collector_with_env_on_cpu_and_policy_on_cuda():
    from torchrl.collectors import Collector

    pol = _policies()["mpc"]().to("cuda")
    env = make_env("drone", seed=0).append_transform(pol.make_tensordict_primer())
    collector = Collector(
        env,
        pol,
        frames_per_batch=8,
        total_frames=8,
        env_device="cpu",
        policy_device="cuda",
        storing_device="cpu",  # TorchRL stores on neither when the two differ
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert batch["mpc_replanned"].squeeze(-1).tolist()[:4] == [False] * 3 + [True]
    assert torch.isfinite(batch["action"]).all()


@NEEDS_CUDA
def test_policy_on_cuda_through_a_device_cast_of_a_cpu_env():
    """The experiments' composition: a CPU env, its data cast to the GPU, the primer after it."""
    pol = _policies()["mpc"]().to("cuda")
    env = make_env("drone", seed=0)
    env.append_transform(DeviceCastTransform("cuda", env.device))
    env.append_transform(pol.make_tensordict_primer())
    td = env.rollout(5, pol)
    assert td["mpc_replanned"].squeeze(-1).tolist()[:4] == [False] * 3 + [True]
    assert {v.device.type for v in td.values(True, True)} == {"cuda"}


# ---------------------------------------------------------------- training


def _buffer():
    obs, action, next_obs = _sequences(batch=(3,), length=20)
    data = TensorDict(
        {
            "observation": obs,
            "action": action,
            ("next", "observation"): next_obs,
            ("collector", "traj_ids"): torch.arange(3)[:, None].expand(3, 20),
        },
        [3, 20],
    ).reshape(-1)
    rb = make_sequence_buffer(100, slice_len=6, num_slices=2)
    rb.extend(data)
    return rb


@pytest.mark.parametrize("fit", ["fit_world_model", "fit_uncertainty", "train_loss_module"])
@pytest.mark.parametrize("device", DEVICES)
def test_fit_one_step(device, fit):
    """Storage stays on the CPU; the sampled batches go to the model's device."""

    def build():
        if fit == "fit_world_model":
            return _world_model(), _buffer()
        return _estimator("reconstruction"), _buffer()

    def run(module, rb):
        kwargs = dict(steps=2, eval_every=1, val_batches=1, progress=False)
        if fit == "fit_world_model":
            result = fit_world_model(module, rb, **kwargs)
        elif fit == "fit_uncertainty":
            result = fit_uncertainty(module, rb, **kwargs)
        else:
            result = train_loss_module(UncertaintyLoss(module, slice_len=6), rb, **kwargs)
        return result, list(module.parameters())

    # Adam's first steps are sign-like, so weights whose gradient is ~0 can move apart across
    # devices by ~lr: on CUDA only the losses are compared, and loosely.
    (out, _), (ref, _) = check(build, run, device, compare=False)
    assert out.steps == ref.steps == 2
    for got, want in zip(out.history, ref.history, strict=True):
        assert got["val_loss"] == pytest.approx(want["val_loss"], rel=1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_checkpoint_round_trip(device, tmp_path):
    path = tmp_path / "checkpoint.pt"

    def build():
        fresh = LSTMWorldModel(N, M, window=T, hidden_size=8, dense_size=8)
        return _world_model(), _estimator("ensemble"), fresh

    def run(model, est, fresh):
        save_checkpoint(path, {"world_model": model, "uncertainty": est}, extra={"step": 1})
        extra = load_checkpoint(path, {"world_model": fresh})
        return extra, fresh.state_dict()

    (_, state), _ = check(build, run, device)
    # load_modules rebuilds on the CPU (the checkpoint is read with map_location="cpu").
    loaded = load_modules(path)["world_model"].state_dict()
    torch.testing.assert_close(loaded, {k: v.cpu() for k, v in state.items()})


@pytest.mark.parametrize("members", [1, 2])
@pytest.mark.parametrize("device", DEVICES)
def test_populations(device, members):
    """Population modules (one member: the single model's ops; two: batched) and their fit."""

    def build():
        worlds = [_world_model() for _ in range(members)]
        estimators = [_estimator("reconstruction") for _ in range(members)]
        obs, action, _ = _sequences(batch=(members, 2))
        candidates = torch.rand(members, 2, 5, 4, M, generator=torch.Generator().manual_seed(4))
        return worlds, estimators, obs, action, candidates, [_buffer() for _ in range(members)]

    def run(worlds, estimators, obs, action, candidates, buffers):
        if device != "meta":
            worlds = [w.to(device) for w in worlds]
            estimators = [e.to(device) for e in estimators]
            obs, action, candidates = obs.to(device), action.to(device), candidates.to(device)
        pop = WorldModelPopulation.from_members(worlds)
        ae = ReconstructionPopulation.from_members(estimators)
        ctx_obs, ctx_action, now = obs[:, :, :T], action[:, :, :T], obs[:, :, T]
        with torch.no_grad():
            no_grad = pop.imagine(ctx_obs, ctx_action, now, candidates)
            score = ae.score(obs, action)
        candidates = candidates.clone().requires_grad_(True)
        states = pop.imagine(ctx_obs, ctx_action, now, candidates)
        (states.square().sum() + ae.loss(obs, action).sum()).backward()
        stepped = pop.step(now, candidates[:, :, 0, 0], pop.warmup(ctx_obs, ctx_action))
        split = [m.state_dict() for m in pop.split()]
        kwargs = dict(steps=2, eval_every=1, val_batches=1, progress=False)
        results = fit_population(worlds, buffers, **kwargs)
        results += fit_population(estimators, buffers, **kwargs)
        return (
            no_grad,
            score,
            states,
            candidates.grad,
            _grads(pop),
            _grads(ae),
            stepped,
            split,
            [r.history for r in results],
            [w.state_dict() for w in worlds],
        )

    if device == "meta":
        check(build, run, device)
    else:  # the fits' Adam steps move ~lr apart across devices: check devices only
        objects = build()
        out = run(*objects)
        for path, value in _leaves(out):
            if isinstance(value, torch.Tensor):
                assert value.device.type == device, f"{path} is on {value.device}"


@NEEDS_CUDA
def test_compiled_fits_on_cuda_match_eager():
    """``compile=True`` on CUDA (Triton kernels): the same fits as eager on the GPU, up to float
    rounding, one model and a population of two (the gpu-check times them).

    Adam divides each step by the gradient's running scale, so a weight whose gradient is near
    zero can move up to one learning rate on a rounding difference (seen on an H200: 1 of 32
    bias entries 1.7e-5 apart after 4 steps): all but 1 % of the weights must agree at rounding,
    and none may be more than one Adam step (``lr``) apart."""
    lr = 1e-3
    fit = dict(steps=4, eval_every=2, val_batches=1, progress=False, fit_normalization=False)
    fit["lr"] = lr
    results = {}
    for compile in (False, True):
        one = _world_model().to("cuda")
        members = [_world_model().to("cuda") for _ in range(2)]
        single = fit_world_model(one, _buffer(), seed=0, compile=compile, **fit)
        population = fit_population(
            members, _buffer(), shared_sampling=True, compile=compile, **fit
        )
        results[compile] = (single, population, one, members)
    (s0, p0, one0, m0), (s1, p1, one1, m1) = results[False], results[True]
    assert s1.best_val_loss == pytest.approx(s0.best_val_loss, rel=RTOL)
    for a, b in zip(p0, p1, strict=True):
        assert b.best_val_loss == pytest.approx(a.best_val_loss, rel=RTOL)
    for a, b in zip([one0, *m0], [one1, *m1], strict=True):
        apart, total = 0, 0
        for (key, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
            assert y.device.type == "cuda", key
            x, y = x.double(), y.double()  # buffers include bools
            gap = (y - x).abs()
            assert gap.max() <= lr, f"{key}: {gap.max():.3g} apart, more than one Adam step"
            apart += int((gap > ATOL + RTOL * x.abs()).sum())
            total += x.numel()
        assert apart <= 0.01 * total, f"{apart} of {total} weights differ beyond rounding"


def _graph_fits(monkeypatch, poison_after: int | None = None):
    """The shared population fit of three world models on CUDA, eager and with ``cuda_graph``,
    and the graph fit's :class:`CapturedStep`. ``poison_after``: from that sample on, the
    buffer's batches hold NaN observations."""
    import torchrl_recon.fitting.fit as fit_module

    steps: list = []

    class Recorded(fit_module.CapturedStep):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            steps.append(self)

    monkeypatch.setattr(fit_module, "CapturedStep", Recorded)
    fit = dict(steps=30, eval_every=2, lr=0.05, val_batches=1, progress=False)
    fit["patience"] = 1 if poison_after is None else None  # stops; or every member meets the NaN
    results, weights = {}, {}
    for graph in (False, True):
        rb = _buffer()
        if poison_after is not None:
            drawn, sample = [0], rb.sample

            def poisoned(*args, _sample=sample, _drawn=drawn, **kwargs):
                _drawn[0] += 1
                batch = _sample(*args, **kwargs)
                if _drawn[0] > poison_after:
                    batch["observation"] = torch.full_like(batch["observation"], float("nan"))
                return batch

            monkeypatch.setattr(rb, "sample", poisoned)
        members = [_world_model().to("cuda") for _ in range(3)]
        try:
            results[graph] = fit_population(
                members, rb, shared_sampling=True, cuda_graph=graph, **fit
            )
        except ValueError as err:
            results[graph] = err
        weights[graph] = members
    return results, weights, steps


@NEEDS_CUDA
def test_cuda_graph_fits_on_cuda_match_eager(monkeypatch):
    """``fit_population(cuda_graph=True)``: three eager steps, one capture, a replay for every
    later step; the same fit as eager on the GPU up to float rounding (Adam ``capturable``
    with a tensor learning rate rounds as float32), members stopping at the same steps."""
    results, weights, captured = _graph_fits(monkeypatch)
    eager, graphed = results[False], results[True]
    assert [r.steps for r in graphed] == [r.steps for r in eager]
    for a, b in zip(eager, graphed, strict=True):
        assert b.best_val_loss == pytest.approx(a.best_val_loss, rel=1e-3)
    (step,) = captured
    assert step.graph is not None and step.replays == max(r.steps for r in eager) - step.warmup
    for member in weights[True]:
        assert {p.device.type for p in member.state_dict().values()} == {"cuda"}


@NEEDS_CUDA
def test_cuda_graph_fit_names_a_bad_input_after_capture(monkeypatch):
    """NaN observations from the 11th sample on (after the capture, whose steps do not check
    their inputs): the graph fit stops with the eager fit's error, naming the input, and the
    members' weights stay finite."""
    results, weights, _ = _graph_fits(monkeypatch, poison_after=10)
    eager, graphed = results[False], results[True]
    assert isinstance(eager, ValueError) and isinstance(graphed, ValueError), results
    assert "'observation' in the replay buffer holds NaN or inf" in str(graphed)
    assert str(graphed) == str(eager)
    for member in weights[True]:
        assert all(bool(torch.isfinite(p).all()) for p in member.parameters())


# ---------------------------------------------------------------- evaluation


@pytest.mark.parametrize("device", DEVICES)
def test_evaluation_helpers(device):
    def build():
        obs, action, next_obs = _sequences(batch=(3,), length=8)
        td = TensorDict(
            {"observation": obs, "action": action, ("next", "observation"): next_obs}, [3, 8]
        )
        return _world_model(), _estimator("reconstruction"), td, torch.tensor([0.1, 0.2, 0.2, 0.4])

    def run(model, est, td, scores):
        errors = multi_step_errors(model, td, window=T, scale=td["observation"].std((0, 1)))
        u, err = imagined_uncertainty_and_error(model, est, td, window=T)
        return errors, u, err, auroc(scores[:2], scores[2:]), spearman(scores, scores.flip(0) ** 2)

    check(build, run, device)


# ---------------------------------------------------------------- built where the model is


def test_planning_model_bounds_and_policy_state_follow_the_world_model():
    """Built around a model on another device (meta, here), the bounds, the policy's state specs
    (so the primer's) and the model env are on that device; nothing is moved to the CPU."""
    model = LSTMWorldModel(N, M, window=T, hidden_size=8, dense_size=8).to("meta")
    planning = PlanningModel(model, drone_cost, action_low=-0.5)
    assert planning.action_low.device.type == "meta"
    policy = MPCPolicy(RandomShootingPlanner(planning, Objective(), horizon=4, num_candidates=8))
    assert policy.device.type == "meta"
    assert {spec.device.type for spec in policy.state_spec().values(True, True)} == {"meta"}
    env = WorldModelPlanningEnv(model, drone_cost)
    assert env.device.type == "meta" and model.dense.weight.device.type == "meta"


def test_a_context_on_another_device_than_the_planner_is_a_clear_error():
    model = LSTMWorldModel(N, M, window=T, hidden_size=8, dense_size=8).to("meta")
    planner = RandomShootingPlanner(
        PlanningModel(model, drone_cost), Objective(), horizon=4, num_candidates=8
    )
    with pytest.raises(
        ValueError, match=r"observation is on cpu but the planning model is on meta"
    ):
        planner.plan(*_context())


@pytest.mark.parametrize("kind", [None, "reconstruction", "mc_dropout"])
@pytest.mark.parametrize("planner", sorted(PLANNERS))
def test_plan_in_float64_follows_the_models_dtype(planner, kind):
    """The dtype follows the model like the device does: a float64 model plans in float64."""
    model = _planning_model(kind).double()
    assert model.action_low.dtype == torch.float64
    result = PLANNERS[planner](model, Objective(beta=0.0 if kind is None else 0.1)).plan(
        *(x.double() for x in _context())
    )
    assert result.actions.dtype == result.states.dtype == result.objective.dtype == torch.float64


# ---------------------------------------------------------------- CPU ↔ CUDA


@pytest.mark.parametrize("planner", sorted(PLANNERS))
def test_plan_with_a_generator_is_reproducible(planner):
    """Candidates drawn from a given generator do not touch the global RNG and repeat with it."""
    p = PLANNERS[planner](_planning_model("reconstruction"), Objective(beta=0.1))
    ctx = _context()
    results = []
    for seed in (0, 1):
        torch.manual_seed(seed)  # the global RNG must not matter
        results.append(p.plan(*ctx, generator=torch.Generator().manual_seed(7)))
    _assert_identical(results[0], results[1])


@NEEDS_CUDA
@pytest.mark.parametrize("planner", sorted(PLANNERS))
def test_plan_agrees_on_cpu_and_cuda(planner):
    """One plan from the same seed on the CPU and on CUDA: the candidates come from one CPU
    ``torch.Generator`` (drawn on the CPU, then moved), so both devices score the same
    candidates; the chosen plan agrees within float32 tolerance (rtol 1e-4, atol 1e-4; MPPI's
    1e-3: its mean is a smooth function of every score, so their rounding reaches the plan)."""
    results = {}
    for device in ("cpu", "cuda"):
        p = PLANNERS[planner](_planning_model("reconstruction"), Objective(beta=0.1)).to(device)
        ctx = [x.to(device) for x in _context()]
        results[device] = p.plan(*ctx, generator=torch.Generator().manual_seed(7))
    cpu, cuda = results["cpu"], results["cuda"]
    assert cuda.actions.device.type == "cuda"
    tol = 1e-3 if planner == "mppi" else 1e-4
    for name in ("actions", "states", "cost", "uncertainty", "objective"):
        torch.testing.assert_close(
            getattr(cuda, name).cpu(), getattr(cpu, name), rtol=tol, atol=tol
        )


@NEEDS_CUDA
@pytest.mark.parametrize("mode", ["default", "reduce-overhead"])
def test_compiled_planning_on_cuda_matches_eager(mode):
    """``PlanningModel(compile=mode)`` on CUDA (Triton; ``reduce-overhead``: CUDA graphs): the
    same predictions as the eager pass on the GPU, and a CEM plan from them."""
    eager = _planning_model("reconstruction").to("cuda")
    compiled = PlanningModel(
        eager.world_model, drone_cost, uncertainty=eager.uncertainty, compile=mode
    ).to("cuda")
    ctx = [x.to("cuda") for x in _context()]
    actions = torch.rand(2, 16, 5, M, generator=torch.Generator().manual_seed(5)).to("cuda")
    with torch.no_grad():
        a = eager(*ctx, actions)
        compiled(*ctx, actions)  # the first call compiles (reduce-overhead: records its graph)
        b = compiled(*ctx, actions)  # the second runs it (reduce-overhead: replays the graph)
    for x, y in ((a.states, b.states), (a.cost, b.cost), (a.uncertainty, b.uncertainty)):
        assert y.device.type == "cuda"
        torch.testing.assert_close(y, x, rtol=RTOL, atol=ATOL)
    plan = CEMPlanner(compiled, Objective(beta=0.1), horizon=5, num_candidates=16, num_elites=4)
    assert plan.plan(*ctx).actions.device.type == "cuda"


@NEEDS_CUDA
def test_sampling_planners_plan_every_row_in_one_pass_on_cuda(monkeypatch):
    """``block_rows="auto"`` (the default): no row blocks on a GPU, even for K = 3,000 rows of
    two envs, where the CPU splits them into blocks of 512."""
    model = _planning_model(None).to("cuda")
    passes = []
    predict = PlanningModel._predict

    def counted(self, *args, **kwargs):
        passes.append(args[3].shape[-3])
        return predict(self, *args, **kwargs)

    monkeypatch.setattr(PlanningModel, "_predict", counted)
    planner = CEMPlanner(model, Objective(), horizon=5, num_candidates=3000, num_elites=30)
    planner.plan(*(x.cuda() for x in _context()))
    assert passes == [3000] * planner.iterations
    model.cpu()
    passes.clear()
    planner.plan(*_context())
    assert passes == ([512] * 5 + [440]) * planner.iterations  # 2 envs: blocks of 512 x 2 rows
