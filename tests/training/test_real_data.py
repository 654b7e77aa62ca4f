"""Issue-3 acceptance on real data: the world model beats simple baselines and u flags the unfamiliar."""

from __future__ import annotations

import logging

import pytest
import torch
from tensordict.nn import TensorDictModuleBase

from torchrl_recon.collectors import collect_random
from torchrl_recon.data import cut_sequences, make_sequence_buffer, split_by_trajectory
from torchrl_recon.envs import make_env
from torchrl_recon.evaluation import (
    auroc,
    imagined_uncertainty_and_error,
    multi_step_errors,
    spearman,
)
from torchrl_recon.modules import LinearDeltaModel, LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.training import fit_uncertainty, fit_world_model

logging.getLogger("torchrl").setLevel(logging.WARNING)
WINDOW, HORIZON = 10, 20
# The LSTM must beat the linear model by this factor. Random-action Drone data stays near hover, where
# the dynamics are nearly linear, so the margin there is small (we measured ~0.82); on IB it is ~0.4.
LINEAR_MARGIN = {"industrial_benchmark": 0.6, "drone": 0.9}


class OffsetNoisePolicy(TensorDictModuleBase):
    """Actions = clip(offset + noise): a larger offset makes the trajectory less like uniform random data."""

    in_keys: list = []
    out_keys = ["action"]

    def __init__(self, offset: torch.Tensor, generator: torch.Generator) -> None:
        super().__init__()
        self.offset, self.generator = offset, generator

    def forward(self, td):
        noise = torch.rand(self.offset.shape, generator=self.generator) * 2 - 1
        td["action"] = (self.offset + 0.5 * noise).clamp(-1, 1)
        return td


@pytest.fixture(scope="module", params=["industrial_benchmark", "drone"])
def trained(request):
    torch.manual_seed(0)
    name = request.param
    train = collect_random(make_env(name, seed=0, max_episode_steps=500), frames=3000, seed=0)
    held_out = collect_random(make_env(name, seed=1, max_episode_steps=500), frames=1500, seed=1)
    fit_part, val_part = split_by_trajectory(
        train, 0.2, seed=0
    )  # early stopping never sees held_out
    rb = make_sequence_buffer(3000, slice_len=WINDOW + HORIZON, num_slices=32)
    val_rb = make_sequence_buffer(3000, slice_len=WINDOW + HORIZON, num_slices=32)
    rb.extend(fit_part), val_rb.extend(val_part)
    obs_dim, action_dim = train["observation"].shape[-1], train["action"].shape[-1]
    model = LSTMWorldModel(obs_dim, action_dim, window=WINDOW)
    fit_world_model(
        model, rb, val_buffer=val_rb, steps=1500, lr=3e-3, eval_every=100, progress=False, seed=0
    )
    estimator = ReconstructionUncertainty(obs_dim, action_dim, window=WINDOW)
    fit_uncertainty(
        estimator,
        rb,
        val_buffer=val_rb,
        steps=3000,
        lr=3e-3,
        eval_every=250,
        progress=False,
        seed=0,
    )
    std = train["observation"].std(0)
    scale = torch.where(std < 1e-6, torch.ones_like(std), std)
    return {
        "name": name,
        "train": train,
        "held_out": held_out,
        "model": model,
        "estimator": estimator,
        "scale": scale,
    }


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
