"""Issue-3 acceptance on real data: the world model beats simple baselines and u flags the unfamiliar."""

from __future__ import annotations

import pytest
import torch

from tests.trained import HORIZON, WINDOW, OffsetNoisePolicy
from torchrl_recon.data import cut_sequences
from torchrl_recon.envs import make_env
from torchrl_recon.evaluation import (
    auroc,
    imagined_uncertainty_and_error,
    multi_step_errors,
    spearman,
)
from torchrl_recon.modules import LinearDeltaModel

# The LSTM must beat the linear model by this factor. Random-action Drone data stays near hover, where
# the dynamics are nearly linear, so the margin there is small (we measured ~0.82); on IB it is ~0.4.
LINEAR_MARGIN = {"industrial_benchmark": 0.6, "drone": 0.9}


@pytest.fixture(  # both in make test-all: trained models on real data (IB 48 s, the Drone 39 s)
    scope="module",
    params=[pytest.param(e, marks=pytest.mark.slow) for e in ("industrial_benchmark", "drone")],
)
def trained(request, trained_models):
    return trained_models(request.param)


def test_world_model_beats_no_change_and_linear_models(trained):
    seqs = cut_sequences(trained["held_out"], WINDOW + 50)
    linear = LinearDeltaModel(trained["model"].obs_dim, trained["model"].action_dim)
    train = trained["train"]
    linear.fit(train["observation"], train["action"], train["next", "observation"])
    no_change = LinearDeltaModel(trained["model"].obs_dim, trained["model"].action_dim)
    errors = {
        name: multi_step_errors(m, seqs, window=WINDOW, scale=trained["scale"]).mean().item()
        for name, m in (("lstm", trained["model"]), ("linear", linear), ("no_change", no_change))
    }
    print(trained["name"], "50-step MSE (standardised units):", errors)
    assert errors["lstm"] < 0.3 * errors["no_change"]
    assert errors["lstm"] < LINEAR_MARGIN[trained["name"]] * errors["linear"]


def test_uncertainty_is_higher_out_of_distribution(trained):
    est = trained["estimator"]
    seqs = cut_sequences(trained["held_out"], WINDOW)
    obs, act = seqs["observation"], seqs["action"]
    with torch.no_grad():
        u_in = est.score(obs, act)[:, 0]
        u_bound = est.score(obs, torch.ones_like(act))[
            :, 0
        ]  # actions held at a bound for the whole window
        u_far = est.score(obs + 3 * trained["scale"], act)[
            :, 0
        ]  # states far outside the training range
    scores = {"bound": auroc(u_in, u_bound), "far": auroc(u_in, u_far)}
    print(trained["name"], "OOD AUROC:", scores)
    assert scores["bound"] >= 0.8
    assert scores["far"] >= 0.8


def test_uncertainty_correlates_with_real_prediction_error(trained):
    env = make_env(trained["name"], seed=5, max_episode_steps=500)
    action_dim = trained["model"].action_dim
    generator = torch.Generator().manual_seed(0)
    trajectories = []
    for i in range(40):
        offset = (torch.rand(action_dim, generator=generator) * 2 - 1) * (i % 4) / 3
        td = env.rollout(
            WINDOW + HORIZON, policy=OffsetNoisePolicy(offset, generator), break_when_any_done=True
        )
        if td.shape[0] == WINDOW + HORIZON:
            trajectories.append(td)
    assert len(trajectories) >= 20
    cum_u, error = imagined_uncertainty_and_error(
        trained["model"],
        trained["estimator"],
        torch.stack(trajectories),
        window=WINDOW,
        scale=trained["scale"],
    )
    rho = spearman(cum_u, error)
    print(
        trained["name"],
        f"Spearman(cumulative u, real error) = {rho:.3f} over {len(trajectories)} trajectories",
    )
    assert rho > 0


def test_gradients_of_cumulative_u_and_states_reach_actions(trained):
    model, est = trained["model"], trained["estimator"]
    seq = cut_sequences(trained["held_out"], WINDOW + 1)[:2]
    actions = torch.zeros(2, 3, HORIZON, model.action_dim, requires_grad=True)
    states = model.imagine(
        seq["observation"][:, :WINDOW],
        seq["action"][:, :WINDOW],
        seq["observation"][:, WINDOW],
        actions,
    )
    states.sum().backward(retain_graph=True)
    assert actions.grad.abs().sum() > 0
    actions.grad = None
    full_states = torch.cat([seq["observation"][:, None, :WINDOW].expand(2, 3, -1, -1), states], 2)
    full_actions = torch.cat([seq["action"][:, None, :WINDOW].expand(2, 3, -1, -1), actions], 2)
    est.score(full_states, full_actions).sum().backward()
    assert actions.grad.abs().sum() > 0


if __name__ == "__main__":
    pytest.main([__file__, "-q", "-s"])
