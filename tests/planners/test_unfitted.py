"""Planning refuses a world model or estimator whose normalisation was never fitted (at the first
plan, not when the planner is built), and the losses warn once when computed on one."""

from __future__ import annotations

import re
import warnings

import pytest
import torch
from tensordict import TensorDict

import torchrl_recon.modules.fitted as fitted_module
from tests.normalized import fitted
from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.envs import make_env
from torchrl_recon.envs.drone import drone_cost
from torchrl_recon.fitting import fit_uncertainty, fit_world_model
from torchrl_recon.modules import (
    LinearDeltaModel,
    LSTMWorldModel,
    ReconstructionUncertainty,
    WorldModelEnsembleUncertainty,
    check_fitted,
    make_estimator,
    unfitted_normalizers,
)
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel, RandomShootingPlanner
from torchrl_recon.planners.model_env import WorldModelPlanningEnv
from torchrl_recon.policies import MPCPolicy

HOW = (
    "or register torchrl_recon.trainers.FitNormalization(world_model, estimator) on your torchrl "
    "Trainer (it fits them from the first batch)."
)
WORLD_MESSAGE = (
    "the world model's normalisation (obs_norm, action_norm, delta_norm of LSTMWorldModel) was "
    "never fitted; fit it from data before planning: world_model.fit_normalization(obs, action, "
    "next_obs), torchrl_recon.fitting.fit_world_model(world_model, buffer), " + HOW
)
SMALL = {
    "reconstruction": {"hidden_size": 8},
    "ensemble": {"hidden_size": 8, "num_members": 2},
    "mc_dropout": {"hidden_size": 8, "samples": 2},
    "rnd": {"hidden_size": 8, "embedding_size": 4},
    "world_model_ensemble": {"hidden_size": 4, "dense_size": 4, "num_members": 2},
}


def _cost(obs, action, next_obs):
    return next_obs.pow(2).sum(-1)


def _world(**kwargs) -> LSTMWorldModel:
    return LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8, **kwargs)


def _context() -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(0)
    return (
        torch.randn(4, 3, generator=g),
        torch.rand(4, 2, generator=g),
        torch.randn(3, generator=g),
    )


def _planner(model: PlanningModel) -> RandomShootingPlanner:
    objective = Objective(beta=0.0 if model.uncertainty is None else 0.1)
    return RandomShootingPlanner(model, objective, horizon=3, num_candidates=8)


def test_an_unfitted_world_model_is_refused_at_the_first_plan_and_plans_once_fitted():
    world = _world()
    model = PlanningModel(world, _cost)  # built before any data: not refused
    planner = _planner(model)
    with pytest.raises(ValueError, match="^" + re.escape(WORLD_MESSAGE) + "$"):
        planner.plan(*_context())
    with pytest.raises(ValueError, match=re.escape(WORLD_MESSAGE)):  # a direct call too
        model(*_context(), torch.zeros(5, 3, 2))
    fitted(world)
    assert planner.plan(*_context()).actions.shape == (3, 2)


@pytest.mark.parametrize("kind", list(SMALL))
def test_an_unfitted_estimator_is_refused_naming_it_and_how_to_fit_it(kind):
    est = make_estimator(kind, 3, 2, window=4, **SMALL[kind])
    planner = _planner(PlanningModel(fitted(_world()), _cost, uncertainty=est))
    with pytest.raises(ValueError) as info:
        planner.plan(*_context())
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("the uncertainty estimator's normalisation (")
    assert f"of {type(est).__name__}) was never fitted" in message
    assert "input_norm" in message
    assert "estimator.fit_normalization(obs, action)" in message
    assert "torchrl_recon.fitting.fit_uncertainty(estimator, buffer)" in message
    assert message.endswith(HOW)
    fitted(est)
    assert torch.isfinite(planner.plan(*_context()).uncertainty).all()


def test_members_must_all_be_fitted_and_the_unfitted_ones_are_named():
    members = [fitted(_world()), _world(), fitted(_world())]
    stacked = LSTMWorldModel.from_members(members)
    assert stacked.obs_norm.fitted.tolist() == [True, False, True]
    assert unfitted_normalizers(stacked) == ["obs_norm", "action_norm", "delta_norm"]
    planner = _planner(PlanningModel(stacked, _cost))
    with pytest.raises(ValueError) as info:
        planner.plan(*_context())
    message = str(info.value)
    assert message.startswith(
        "the world model's normalisation (obs_norm, action_norm, delta_norm of LSTMWorldModel "
        "members [1] of 3) was never fitted"
    )
    assert "torchrl_recon.fitting.fit_world_members(world_model, buffer)" in message
    assert "before LSTMWorldModel.from_members" in message
    stacked.load_member(1, fitted(members[1]))
    assert unfitted_normalizers(stacked) == []
    assert planner.plan(*_context()).actions.shape == (3, 2)


def test_an_estimator_of_unfitted_world_models_is_refused_naming_its_members():
    """``from_world_models`` marks its own input statistics fitted; its members' are theirs."""
    est = WorldModelEnsembleUncertainty.from_world_models([_world(), _world()])
    assert unfitted_normalizers(est) == [
        "members.obs_norm",
        "members.action_norm",
        "members.delta_norm",
    ]
    expected = (
        r"^the uncertainty estimator's normalisation \(members\.obs_norm, members\.action_norm, "
    )
    with pytest.raises(ValueError, match=expected):
        check_fitted(est, "uncertainty estimator")
    planner = _planner(PlanningModel(fitted(_world()), _cost, uncertainty=est))
    with pytest.raises(ValueError, match=expected):
        planner.plan(*_context())
    fitted(est)  # its fit_normalization gives every member the estimator's statistics
    assert planner.plan(*_context()).actions.shape == (3, 2)


def test_the_no_change_model_has_nothing_to_fit_and_plans():
    """``LinearDeltaModel`` never fitted is the documented "no change" model (a zero weight,
    no normaliser): it plans as it always did."""
    model = LinearDeltaModel(3, 2)
    assert unfitted_normalizers(model) == []
    result = _planner(PlanningModel(model, _cost)).plan(*_context())
    torch.testing.assert_close(result.states, _context()[2].expand(3, 3))


def test_the_check_runs_once_and_again_after_the_state_is_reloaded(monkeypatch):
    calls = []
    check = fitted_module.check_fitted

    def counted(module, role):
        calls.append(role)
        check(module, role)

    monkeypatch.setattr(fitted_module, "check_fitted", counted)
    world, est = fitted(_world()), fitted(ReconstructionUncertainty(3, 2, window=4))
    model = PlanningModel(world, _cost, uncertainty=est)
    planner = CEMPlanner(model, Objective(beta=0.1), horizon=3, num_candidates=8, num_elites=2)
    for _ in range(3):
        planner.plan(*_context())
    assert calls == ["world model", "uncertainty estimator"]  # once each, then remembered
    assert model._world_model_fitted.passed is not None
    world.load_state_dict(_world().state_dict())  # a checkpoint with unfitted statistics
    with pytest.raises(ValueError, match=re.escape(WORLD_MESSAGE)):
        planner.plan(*_context())
    assert calls == ["world model", "uncertainty estimator", "world model"]


def test_a_policy_is_built_unfitted_and_refuses_at_its_first_plan():
    """A TorchRL user builds the policy before any data: only its first plan (after the random
    warm-up steps) refuses, with the same message."""
    world = LSTMWorldModel(12, 4, window=3, hidden_size=8, dense_size=8)
    planner = RandomShootingPlanner(
        PlanningModel(world, drone_cost), Objective(), horizon=4, num_candidates=8
    )
    policy = MPCPolicy(planner, warmup_steps=3)
    env = make_env("drone", seed=0).append_transform(policy.make_tensordict_primer())
    td = env.rollout(3, policy)  # the warm-up steps plan nothing
    assert not td["mpc_replanned"].any()
    with pytest.raises(ValueError, match=r"^the world model's normalisation \(obs_norm, "):
        env.rollout(5, policy)
    fitted(world)
    assert env.rollout(5, policy)["mpc_replanned"].any()


def test_the_torchrl_model_env_refuses_at_reset_and_step():
    world, est = _world(), ReconstructionUncertainty(3, 2, window=4)
    env = WorldModelPlanningEnv(world, _cost, uncertainty=est, beta=0.1)  # built: not refused
    ctx = _context()
    with pytest.raises(ValueError, match=re.escape(WORLD_MESSAGE)):
        env.initial_state(*ctx)
    with pytest.raises(ValueError, match=re.escape(WORLD_MESSAGE)):
        env.reset()
    fitted(world)
    with pytest.raises(
        ValueError, match=r"^the uncertainty estimator's normalisation \(input_norm"
    ):
        env.reset()
    fitted(est)
    td = env.initial_state(*ctx)
    td["action"] = torch.zeros(2)
    env.step(td.clone())
    world.load_state_dict(_world().state_dict())
    with pytest.raises(ValueError, match=re.escape(WORLD_MESSAGE)):
        env.step(td.clone())


def _batch() -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(16, 3, generator=g)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.rand(16, 2, generator=g),
            ("next", "observation"): obs + 0.1,
        },
        [16],
    )


def _unfitted_warnings(caught) -> list[str]:
    return [str(w.message) for w in caught if "never fitted" in str(w.message)]


@pytest.mark.parametrize("which", ["world_model", "uncertainty"])
def test_a_loss_on_an_unfitted_module_warns_once(which):
    if which == "world_model":
        module = _world()
        loss = WorldModelPredictionLoss(module, slice_len=8)
        role, fit = "world model", "world_model.fit_normalization(obs, action, next_obs)"
    else:
        module = ReconstructionUncertainty(3, 2, window=4)
        loss, role = UncertaintyLoss(module, slice_len=8), "uncertainty estimator"
        fit = "estimator.fit_normalization(obs, action)"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            loss(_batch())
    [message] = _unfitted_warnings(caught)
    assert [w.category for w in caught if str(w.message) == message] == [UserWarning]
    assert message.startswith(f"{type(loss).__name__} is computed with the {role}'s normalisation")
    assert "never fitted (identity statistics); fit it from data first: " + fit in message
    fresh = type(loss)(fitted(module), slice_len=8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fresh(_batch())
    assert _unfitted_warnings(caught) == [] and fresh.fit_checked


def test_the_librarys_fits_fit_the_normalisation_first_and_never_warn():
    rb = make_sequence_buffer(100, slice_len=8, num_slices=2)
    data = _batch().expand(2, 16).reshape(32).clone()
    data["collector", "traj_ids"] = torch.arange(32) // 16
    rb.extend(data)
    world, est = _world(), ReconstructionUncertainty(3, 2, window=4, hidden_size=8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit_world_model(world, rb, steps=2, eval_every=1, progress=False)
        fit_uncertainty(est, rb, steps=2, eval_every=1, progress=False)
        fit_world_model(world, rb, steps=2, fit_normalization=False, progress=False)
    assert _unfitted_warnings(caught) == []
    PlanningModel(world, _cost, uncertainty=est).check_fitted()
