from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector, MultiSyncCollector

from tests.normalized import fitted
from torchrl_recon.envs import get_entry, make_env
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.modules import LinearDeltaModel, LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.planners import (
    CEMPlanner,
    GradientPlanner,
    ICEMPlanner,
    MPPIPlanner,
    Objective,
    PlanningModel,
    RandomShootingPlanner,
)
from torchrl_recon.policies import MPCPolicy

CONTEXT, PLAN_H = 3, 6  # the small policy's context (window) and plan horizon


def _small_drone_model() -> PlanningModel:
    torch.manual_seed(0)
    return PlanningModel(
        fitted(LSTMWorldModel(12, 4, window=CONTEXT, hidden_size=8, dense_size=8)),
        drone_cost,
        uncertainty=fitted(ReconstructionUncertainty(12, 4, window=CONTEXT, hidden_size=8)),
    )


def _small_drone_policy(**kwargs) -> MPCPolicy:
    planner = RandomShootingPlanner(
        _small_drone_model(), Objective(beta=0.1), horizon=PLAN_H, num_candidates=16
    )
    return MPCPolicy(planner, **kwargs)


def _make_drone(policy: MPCPolicy, **kwargs):
    return make_env("drone", seed=0, **kwargs).append_transform(policy.make_tensordict_primer())


def test_state_is_carried_and_reset_at_episode_start():
    policy = _small_drone_policy(replan="every_n", replan_every=4)
    env = _make_drone(policy, max_episode_steps=10)
    td = env.rollout(20, policy, break_when_any_done=False)
    replanned = td["mpc_replanned"].squeeze(-1).tolist()
    # context of 3 random actions, then a plan every 4 steps; the episode restarts at step 10.
    assert replanned == [False] * 3 + [True, False, False, False, True, False, False] + [
        False
    ] * 3 + [True, False, False, False, True, False, False]
    assert td["mpc_steps_seen"][:, 0].tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9] * 2
    # Between episode ends the carried history is the previous step's next-history.
    same = td["next", "mpc_obs_history"][:9] == td["mpc_obs_history"][1:10]
    assert same.all()
    # The predicted next observation is the plan's, and NaN during the random warm-up.
    assert torch.isnan(td["mpc_predicted_next_observation"][:3]).all()
    assert torch.isfinite(td["mpc_predicted_next_observation"][3:10]).all()


def test_every_step_replans_at_every_step_after_warm_up():
    policy = _small_drone_policy(replan="every_step")
    td = _make_drone(policy).rollout(8, policy)
    assert td["mpc_replanned"].squeeze(-1).tolist() == [False] * 3 + [True] * 5


def _replans_and_drift(error_threshold: float | None) -> tuple[list[bool], torch.Tensor]:
    """One 10-step rollout with plans of 6 steps; the RMS drift of each step from its plan."""
    policy = _small_drone_policy(
        replan="every_n", replan_every=100, error_threshold=error_threshold
    )
    # drift is measured in obs_norm standard deviations: make them differ from 1
    policy.planner.model.world_model.obs_norm.scale.copy_(torch.linspace(0.02, 2.0, 12))
    torch.manual_seed(1)
    td = _make_drone(policy).rollout(10, policy)
    scale = policy.planner.model.world_model.obs_norm.scale
    predicted = td["mpc_predicted_next_observation"][:-1]  # prediction of the next step's obs
    drift = ((td["observation"][1:] - predicted) / scale).pow(2).mean(-1).sqrt()
    return td["mpc_replanned"].squeeze(-1).tolist(), drift


def test_error_threshold_replans_where_the_state_leaves_the_plan():
    replanned, drift = _replans_and_drift(None)
    # warm-up of 3 steps, one 6-step plan (steps 3-8), then the plan runs out.
    assert replanned == [False] * 3 + [True] + [False] * 5 + [True]
    on_plan = drift[3:8]  # drift at steps 4..8, each against the plan made at step 3
    first = next(i for i in range(1, 5) if on_plan[i] > on_plan[:i].max())
    threshold = float(on_plan[:first].max() + on_plan[first]) / 2
    replanned, _ = _replans_and_drift(threshold)
    # identical up to the first step whose drift crosses the threshold, which re-plans
    assert replanned[: 4 + first + 1] == [False] * 3 + [True] + [False] * first + [True]
    # a tiny threshold re-plans at every step after the first plan; a huge one never adds one
    assert _replans_and_drift(1e-9)[0] == [False] * 3 + [True] * 7
    assert _replans_and_drift(1e9)[0] == _replans_and_drift(None)[0]


def test_open_loop_execution_takes_the_plans_current_step():
    """After a plan is made, step k of the episode executes plan[k], with plan[k]'s predictions."""
    policy = _small_drone_policy(replan="every_n", replan_every=PLAN_H)
    td = _make_drone(policy).rollout(CONTEXT + PLAN_H, policy)
    assert td["mpc_replanned"].squeeze(-1).tolist() == [False] * CONTEXT + [True] + [False] * (
        PLAN_H - 1
    )
    plan = td["next", "mpc_plan"][CONTEXT]  # the plan made at the first planned step
    assert not torch.equal(plan[0], plan[1])  # so executing plan[0] twice would be seen
    executed = td["action"][CONTEXT:]
    torch.testing.assert_close(executed, plan, rtol=0, atol=0)
    torch.testing.assert_close(
        td["mpc_predicted_next_observation"][CONTEXT:], td["next", "mpc_plan_states"][CONTEXT]
    )
    torch.testing.assert_close(
        td["mpc_predicted_cost"][CONTEXT:].squeeze(-1), td["next", "mpc_plan_cost"][CONTEXT]
    )
    assert td["next", "mpc_plan_step"][CONTEXT:].squeeze(-1).tolist() == list(range(1, PLAN_H + 1))


def _uncertainty_rollout(threshold: float, threshold_on: str) -> tuple[list[bool], torch.Tensor]:
    policy = _small_drone_policy(
        replan="uncertainty", threshold=threshold, threshold_on=threshold_on
    )
    torch.manual_seed(1)
    td = _make_drone(policy).rollout(CONTEXT + PLAN_H + 1, policy)
    return td["mpc_replanned"].squeeze(-1).tolist(), td["next", "mpc_plan_u"][CONTEXT]


def _expected_replans(u: torch.Tensor, threshold: float, cumulative: bool) -> list[bool]:
    """By hand: after the plan made at step CONTEXT, the next re-plan is at the first step
    k >= 1 of the plan whose predicted u (or Σu of plan steps 0..k) exceeds the threshold, or
    at k = H when the plan runs out. The flags up to and including that re-plan."""
    score = u.cumsum(0) if cumulative else u
    k = next((k for k in range(1, PLAN_H) if score[k] > threshold), PLAN_H)
    return [False] * CONTEXT + [True] + [False] * (k - 1) + [True]


def test_uncertainty_replanning_thresholds_the_step_u_or_the_cumulative_u():
    replanned, u = _uncertainty_rollout(1e9, "cumulative")  # the first plan's u
    assert replanned == [False] * CONTEXT + [True] + [False] * (PLAN_H - 1) + [True]  # ran out
    total = u.cumsum(0)
    assert (u > 0).all()
    # between Σu of steps 0..1 and 0..2, and above every single step's u
    threshold = float(max(total[1], u.max()) + total[2]) / 2
    assert total[1] < threshold < total[2] and (u < threshold).all()
    expected = {
        "step": _expected_replans(u, threshold, cumulative=False),
        "cumulative": _expected_replans(u, threshold, cumulative=True),
    }
    assert expected["step"] != expected["cumulative"]
    for mode, flags in expected.items():
        replanned, plan_u = _uncertainty_rollout(threshold, mode)
        torch.testing.assert_close(plan_u, u)  # the same first plan in both modes
        assert replanned[: len(flags)] == flags, mode
    # and a threshold below u[1] re-plans one step after the plan in both modes
    low = float(u[1]) / 2
    for mode in ("step", "cumulative"):
        assert _uncertainty_rollout(low, mode)[0][CONTEXT + 1], mode


U_ROWS = torch.tensor([[0.1, 0.2, 0.3, 0.4, 0.5, 0.9], [0.01, 0.01, 0.01, 0.01, 0.01, 0.6]])


@pytest.mark.parametrize("threshold_on", ["step", "cumulative"])
def test_uncertainty_replanning_rule_row_by_row(threshold_on):
    """Rows at every step 1..H of two plans' u, in one batch: re-plan where the u of the plan's
    current step (or Σu up to it) exceeds 0.45, or where the plan ran out (step H)."""
    policy = _small_drone_policy(replan="uncertainty", threshold=0.45, threshold_on=threshold_on)
    steps = torch.arange(1, PLAN_H + 1).repeat(2)  # [1..H, 1..H]
    u = U_ROWS.repeat_interleave(PLAN_H, 0)
    td = _make_drone(policy).reset().expand(len(steps)).clone()
    td["is_init"] = torch.zeros_like(td["is_init"])
    td["mpc_steps_seen"] = torch.full_like(td["mpc_steps_seen"], CONTEXT)
    td["mpc_plan_u"], td["mpc_plan_step"] = u, steps[:, None]
    replanned = policy(td)["mpc_replanned"]
    assert replanned.dtype == torch.bool and replanned.shape == (len(steps), 1)
    score = u.cumsum(-1) if threshold_on == "cumulative" else u
    index = steps.clamp(max=PLAN_H - 1)[:, None]
    expected = (score.gather(-1, index).squeeze(-1) > 0.45) | (steps >= PLAN_H)
    assert replanned.squeeze(-1).tolist() == expected.tolist()
    assert (
        expected.tolist()
        == {  # the same, written out
            "step": [False] * 3 + [True] * 3 + [False] * 4 + [True] * 2,
            "cumulative": [False] + [True] * 5 + [False] * 4 + [True] * 2,
        }[threshold_on]
    )


def test_declared_keys_match_what_the_policy_reads_and_writes():
    policy = _small_drone_policy(replan="every_n", replan_every=2)
    env = _make_drone(policy)
    td = env.reset()
    assert set(policy.in_keys) <= set(td.keys())  # the env with the primer provides them all
    spec = policy.state_spec()
    assert spec["mpc_plan_step"].dtype == spec["mpc_steps_seen"].dtype == torch.int64
    assert td["mpc_steps_seen"].dtype == torch.int64
    rollout = env.rollout(CONTEXT + 2, policy)
    for key in policy.out_keys:
        assert key in rollout.keys(include_nested=True), key
    assert rollout["mpc_replanned"].dtype == rollout["mpc_feasible"].dtype == torch.bool


def test_drift_is_measured_in_raw_units_for_a_model_without_obs_norm():
    """A LinearDeltaModel has no obs_norm: the drift is the plain RMS of observed − predicted."""
    model = LinearDeltaModel(2, 1, window=2)
    planner = RandomShootingPlanner(
        PlanningModel(model, lambda s, a, s2: s2.pow(2).sum(-1)), Objective(), horizon=4
    )
    policy = MPCPolicy(planner, replan="every_n", replan_every=100, error_threshold=0.5)
    replanned = []
    for observed in ([0.4, -0.4], [0.6, 0.6]):  # RMS 0.4 (on the plan) and 0.6 (off it)
        td = policy.state_spec().zero()
        td["observation"], td["is_init"] = torch.tensor(observed), torch.zeros(1, dtype=torch.bool)
        td["mpc_steps_seen"][:], td["mpc_plan_step"][:] = 2, 1  # one planned step done
        replanned.append(policy(td)["mpc_replanned"].item())  # predicted state: zeros
    assert replanned == [False, True]


def _identity_planner_policy(**kwargs) -> MPCPolicy:
    """A real planner that returns its warm start unchanged: one restart (the warm start, or a
    uniform sequence without one) and one Adam step of 1e-20, below float32 resolution."""
    planner = GradientPlanner(
        _small_drone_model(), Objective(), horizon=PLAN_H, restarts=1, steps=1, lr=1e-20
    )
    return MPCPolicy(planner, **kwargs)


def _step_from_plan(policy: MPCPolicy, plan: torch.Tensor, step: int):
    """One policy step from a hand-made state: after the warm-up, ``step`` actions of ``plan`` done."""
    td = _make_drone(policy).reset()
    td["is_init"] = torch.zeros_like(td["is_init"])
    td["mpc_steps_seen"] = torch.full_like(td["mpc_steps_seen"], CONTEXT)
    td["mpc_plan"] = plan.clone()
    td["mpc_plan_step"] = torch.full_like(td["mpc_plan_step"], step)
    return policy(td)


def test_warm_start_passes_the_rest_of_the_plan_to_the_planner():
    plan = torch.linspace(-0.9, 0.9, PLAN_H * 4).reshape(PLAN_H, 4)
    policy = _identity_planner_policy(replan="every_step")
    assert policy.warm_start  # on by default
    for step in (1, 4):
        td = _step_from_plan(policy, plan, step)
        assert td["mpc_replanned"].item()
        # the unexecuted rest of the plan, padded with its last action
        rest = torch.cat([plan[step:], plan[-1:].expand(step, -1)])
        torch.testing.assert_close(td["next", "mpc_plan"], rest, rtol=0, atol=0)
        torch.testing.assert_close(td["action"], plan[step], rtol=0, atol=0)
    # a plan that ran out warm-starts from zeros (as the first plan of an episode does)
    td = _step_from_plan(policy, plan, PLAN_H)
    assert (td["next", "mpc_plan"] == 0).all()
    # without warm start the planner gets no init: its one restart is uniform
    td = _step_from_plan(_identity_planner_policy(replan="every_step", warm_start=False), plan, 1)
    fresh = td["next", "mpc_plan"]
    assert (fresh != torch.cat([plan[1:], plan[-1:]])).all() and (fresh != 0).all()


def test_warmup_steps_take_random_actions_before_the_first_plan():
    warmup = CONTEXT + 2
    policy = _small_drone_policy(replan="every_step", warmup_steps=warmup)
    assert policy.warmup_steps == warmup
    td = _make_drone(policy).rollout(warmup + 2, policy)
    assert td["mpc_replanned"].squeeze(-1).tolist() == [False] * warmup + [True] * 2
    assert torch.isnan(td["mpc_predicted_next_observation"][:warmup]).all()
    assert torch.isnan(td["mpc_predicted_uncertainty"][:warmup]).all()
    assert torch.isfinite(td["mpc_predicted_next_observation"][warmup:]).all()
    random = td["action"][:warmup]
    assert (random.abs() <= 1).all() and random.std() > 0.1  # uniform in the bounds
    assert (random[:, :-1] != random[:, 1:]).all()  # drawn for each action dimension
    # the first plan's context is the last CONTEXT real (s, a) pairs of the warm-up
    torch.testing.assert_close(
        td["mpc_obs_history"][warmup], td["observation"][warmup - CONTEXT : warmup]
    )
    torch.testing.assert_close(
        td["mpc_action_history"][warmup], td["action"][warmup - CONTEXT : warmup]
    )
    assert _small_drone_policy().warmup_steps == CONTEXT  # default: the context length
    with pytest.raises(ValueError, match=r"warmup_steps=2 is shorter than the context.*\(3\)"):
        _small_drone_policy(warmup_steps=CONTEXT - 1)


def test_rows_of_an_env_batch_replan_on_their_own_state():
    """Two drones in one SerialEnv: each row re-plans when its own plan's Σu crosses the
    threshold (or its plan runs out); the rows' re-plan steps differ."""
    policy = _small_drone_policy(replan="uncertainty", threshold=5.0, threshold_on="cumulative")
    env = make_env("drone", seed=[0, 1], parallel=False)
    env.append_transform(policy.make_tensordict_primer())
    torch.manual_seed(0)
    td = env.rollout(20, policy)
    replanned = td["mpc_replanned"].squeeze(-1)  # [2, 20]
    assert replanned.any(1).all() and not torch.equal(replanned[0], replanned[1])
    step = td["mpc_plan_step"].squeeze(-1).masked_fill(td["is_init"].squeeze(-1), PLAN_H)
    ready = td["mpc_steps_seen"].squeeze(-1).masked_fill(td["is_init"].squeeze(-1), 0) >= CONTEXT
    sum_u = td["mpc_plan_u"].cumsum(-1).gather(-1, step.clamp(max=PLAN_H - 1)[..., None])
    expected = ready & ((step >= PLAN_H) | (sum_u.squeeze(-1) > 5.0))
    assert torch.equal(replanned, expected)
    env.close()


@pytest.mark.parametrize("planner_cls", [MPPIPlanner, ICEMPlanner])
def test_mppi_and_icem_drive_the_policy_in_an_env_batch(planner_cls):
    """Two drones re-planning on their own uncertainty, as with CEM; iCEM finds the elites of
    each row's previous plan from the policy's warm start (shifted by the steps executed)."""
    kwargs = {"num_elites": 4} if planner_cls is ICEMPlanner else {}
    planner = planner_cls(
        _small_drone_model(), Objective(beta=0.1), horizon=PLAN_H, num_candidates=16, **kwargs
    )
    found = []
    if planner_cls is ICEMPlanner:
        recall = planner.memory.recall

        def spy(init):
            recalled = recall(init)
            found.append(0 if recalled is None else int(recalled[1].sum()))
            return recalled

        planner.memory.recall = spy
    policy = MPCPolicy(planner, replan="uncertainty", threshold=5.0, threshold_on="cumulative")
    env = make_env("drone", seed=[0, 1], parallel=False)
    env.append_transform(policy.make_tensordict_primer())
    torch.manual_seed(0)
    td = env.rollout(20, policy)
    replanned = td["mpc_replanned"].squeeze(-1)
    assert replanned.sum() > 2 and torch.isfinite(td["action"]).all()
    assert (td["action"].abs() <= 1).all()
    if planner_cls is ICEMPlanner:
        # every re-planned row is found but those with a zero warm start: the first plan of each
        # row and those whose previous plan ran out (plan step H, as after a reset)
        zero_start = (td["mpc_plan_step"].squeeze(-1) >= PLAN_H) & replanned
        assert sum(found) > 0
        assert sum(found) == int(replanned.sum()) - int(zero_start.sum())
    env.close()


def test_rows_a_partial_step_leaves_out_are_not_planned():
    policy = _small_drone_policy(replan="every_step")
    td = _make_drone(policy).reset().expand(3).clone()
    td["is_init"] = torch.zeros_like(td["is_init"])
    td["mpc_steps_seen"] = torch.full_like(td["mpc_steps_seen"], CONTEXT)
    td["_step"] = torch.tensor([True, False, True])  # TorchRL: row 1 is done and waits
    assert policy(td)["mpc_replanned"].squeeze(-1).tolist() == [True, False, True]


@pytest.fixture(scope="module")
def ib_policy_factory(trained_models):
    trained = trained_models("industrial_benchmark")
    model = PlanningModel(
        trained["model"],
        get_entry("industrial_benchmark").cost_fn(),
        uncertainty=trained["estimator"],
    )

    def build(threshold: float, kind: str = "cem") -> MPCPolicy:
        budget = dict(horizon=30, num_candidates=200, iterations=3)
        if kind == "cem":
            planner = CEMPlanner(model, Objective(beta=0.1), num_elites=20, **budget)
        elif kind == "mppi":
            planner = MPPIPlanner(model, Objective(beta=0.1), **budget)
        else:
            planner = ICEMPlanner(model, Objective(beta=0.1), num_elites=20, **budget)
        return MPCPolicy(planner, replan="uncertainty", threshold=threshold)

    return trained, build


@pytest.mark.slow  # 50 s with its trained IB models; the drone policy's u re-plan tests cover the logic
@pytest.mark.parametrize("kind", ["cem", "mppi", "icem"])
def test_uncertainty_triggered_replanning_on_a_trained_model(ib_policy_factory, kind):
    trained, build = ib_policy_factory
    held_out = trained["held_out"]
    with torch.no_grad():
        in_dist_u = float(
            trained["estimator"]
            .score(held_out["observation"][None, :200], held_out["action"][None, :200])
            .median()
        )
    counts = {}
    for factor in (0.5, 1.0, 2.0, 4.0):
        torch.manual_seed(0)
        policy = build(threshold=factor * in_dist_u, kind=kind)
        env = make_env("industrial_benchmark", seed=3).append_transform(
            policy.make_tensordict_primer()
        )
        td = env.rollout(60, policy)
        counts[factor] = int(td["mpc_replanned"].sum())
        assert torch.isfinite(td["action"]).all()
    print(f"{kind}: re-plans in 50 planned steps by threshold factor:", counts)
    assert counts[4.0] < 50  # fewer re-plans than classic every-step MPC
    assert counts[0.5] >= counts[1.0] >= counts[2.0] >= counts[4.0]
    assert counts[0.5] > counts[4.0]


@pytest.mark.slow  # 10 s; test_collector_start runs the policy in TorchRL's Collector
def test_policy_in_a_collector_with_two_parallel_envs():
    policy = _small_drone_policy(replan="every_n", replan_every=3)
    primer = policy.make_tensordict_primer()
    collector = Collector(
        lambda: make_env("drone", seed=0, num_envs=2).append_transform(primer.clone()),
        policy=policy,
        frames_per_batch=20,
        total_frames=40,
    )
    batches = [b for b in collector]
    collector.shutdown()
    batch = batches[-1]
    assert batch.batch_size == (2, 10)
    assert torch.isfinite(batch["action"]).all()
    assert batch["mpc_replanned"].any()
    planned = ~torch.isnan(batch["mpc_predicted_next_observation"][..., 0])
    assert torch.isfinite(batch["mpc_predicted_next_observation"][planned]).all()


@pytest.mark.slow  # 12 s; the two-env collector test covers the policy in a collector
def test_policy_in_a_multisync_collector():
    policy = _small_drone_policy(replan="every_n", replan_every=3)
    primer = policy.make_tensordict_primer()
    collector = MultiSyncCollector(
        [lambda: make_env("drone", seed=0).append_transform(primer.clone())] * 2,
        policy=policy,
        frames_per_batch=16,
        total_frames=32,
    )
    total = sum(b.numel() for b in collector)
    collector.shutdown()
    assert total == 32


def test_bad_input_and_missing_primer():
    policy = _small_drone_policy()
    env = make_env("drone", seed=0)
    with pytest.raises(KeyError, match="make_tensordict_primer"):
        env.rollout(2, policy)
    env = _make_drone(policy)
    td = env.reset()
    td["observation"][0] = float("nan")
    with pytest.raises(ValueError, match="'observation' given to MPCPolicy.*NaN"):
        policy(td)
    with pytest.raises(ValueError, match="threshold"):
        _small_drone_policy(replan="uncertainty")
    for bad in (float("nan"), float("inf")):  # a NaN threshold never re-planned
        with pytest.raises(
            ValueError, match=r"^threshold must be a finite number, got (nan|inf)\.$"
        ):
            _small_drone_policy(replan="uncertainty", threshold=bad)
    with pytest.raises(ValueError, match="replan"):
        _small_drone_policy(replan="sometimes")
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="error_threshold"):
            _small_drone_policy(error_threshold=bad)
    with pytest.raises(ValueError, match="replan_every must be an int >= 1, got 0"):
        _small_drone_policy(replan="every_n", replan_every=0)
    with pytest.raises(ValueError, match="threshold_on must be 'step' or 'cumulative'"):
        _small_drone_policy(threshold_on="total")
    no_estimator = RandomShootingPlanner(
        PlanningModel(LSTMWorldModel(12, 4, window=CONTEXT), drone_cost),
        Objective(),
        horizon=PLAN_H,
        num_candidates=4,
    )
    with pytest.raises(ValueError, match="needs a planning model with an uncertainty estimator"):
        MPCPolicy(no_estimator, replan="uncertainty", threshold=1.0)
    assert MPCPolicy(no_estimator, replan="every_step").replan == "every_step"  # fine without u


if __name__ == "__main__":
    pytest.main([__file__, "-q", "-s"])


class _Misplanning(RandomShootingPlanner):
    """A plug-in planner with a bug: its plan's actions are changed by ``damage``."""

    damage = staticmethod(lambda actions: actions)

    def plan(self, *args, **kwargs):
        result = super().plan(*args, **kwargs)
        result.actions = type(self).damage(result.actions)
        return result


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda a: a * 100, r"^_Misplanning\.plan returned an action outside the bounds"),
        (lambda a: a * float("nan"), r"^the actions _Misplanning\.plan returned contains NaN"),
        (
            lambda a: a[:, :-1],
            r"^_Misplanning\.plan returned actions of shape \(1, 5, 4\); expected \(1, 6, 4\)\.$",
        ),
    ],
)
def test_a_plan_the_env_must_not_get_is_refused(damage, message, monkeypatch):
    monkeypatch.setattr(_Misplanning, "damage", staticmethod(damage))
    planner = _Misplanning(
        _small_drone_model(), Objective(beta=0.1), horizon=PLAN_H, num_candidates=16
    )
    policy = MPCPolicy(planner)
    env = _make_drone(policy, max_episode_steps=10)
    with pytest.raises(ValueError, match=message):
        env.rollout(CONTEXT + 1, policy)
