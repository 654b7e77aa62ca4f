from __future__ import annotations

import inspect

import pytest
import torch
from tensordict import TensorDict
from torch.nn import functional as F

from tests.normalized import fitted
from torchrl_recon.data.buffers import make_sequence_buffer
from torchrl_recon.estimators import (
    ESTIMATORS,
    EnsembleUncertainty,
    MCDropoutUncertainty,
    ReconstructionUncertainty,
    RNDUncertainty,
    make_estimator,
)
from torchrl_recon.fitting.checkpoint import load_modules, save_checkpoint
from torchrl_recon.fitting.fit import fit_uncertainty
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import PlanningModel

KINDS = ["reconstruction", "ensemble", "mc_dropout", "rnd", "world_model_ensemble"]
NEW_KINDS = ["ensemble", "mc_dropout", "rnd", "world_model_ensemble"]
SMALL = {
    "reconstruction": {"hidden_size": 16},
    "ensemble": {"hidden_size": 16, "num_members": 3},
    "mc_dropout": {"hidden_size": 16, "samples": 4, "dropout": 0.2},
    "rnd": {"hidden_size": 16, "embedding_size": 8},
    "world_model_ensemble": {"hidden_size": 8, "dense_size": 8, "num_members": 3},
}


def _est(kind: str, obs_dim: int = 3, action_dim: int = 2, window: int = 4, seed: int = 0):
    torch.manual_seed(seed)
    est = make_estimator(kind, obs_dim, action_dim, window=window, **SMALL[kind])
    est.fit_normalization(torch.randn(100, obs_dim) * 3 + 2, torch.rand(100, action_dim))
    return est


def _seeded_score(est, obs, action, seed: int = 1) -> torch.Tensor:
    torch.manual_seed(seed)  # MC dropout draws its masks per call
    return est.score(obs, action)


# ---------------------------------------------------------------- shared interface


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("batch", [(), (3,), (2, 4)])
def test_score_shapes_score_windows_and_forward(kind, batch):
    est = _est(kind)
    obs, action = torch.randn(*batch, 9, 3), torch.randn(*batch, 9, 2)
    u = _seeded_score(est, obs, action)
    assert u.shape == (*batch, 6) and torch.isfinite(u).all() and (u >= 0).all()
    windows = torch.cat([obs, action], -1)[..., 2:6, :]
    torch.manual_seed(1)
    torch.testing.assert_close(est.score_windows(windows), u[..., 2])
    torch.manual_seed(1)
    td = est(TensorDict({"observation": obs, "action": action}, [*batch, 9]))
    assert td["uncertainty"].shape == (*batch, 9)
    assert torch.isnan(td["uncertainty"][..., :3]).all()
    torch.testing.assert_close(td["uncertainty"][..., 3:], u)


@pytest.mark.parametrize("kind", KINDS)
def test_config_is_exactly_the_constructor_kwargs(kind):
    est = _est(kind)
    cls = ESTIMATORS[kind]
    params = set(inspect.signature(cls.__init__).parameters)
    assert set(est.config()) == params - {"self", "obs_key", "action_key", "out_key"}
    assert cls(**est.config()).config() == est.config()


@pytest.mark.parametrize("kind", KINDS)
def test_gradient_reaches_actions(kind):
    est = _est(kind)
    action = torch.randn(4, 10, 2).requires_grad_()
    _seeded_score(est, torch.randn(4, 10, 3), action).sum().backward()
    assert torch.isfinite(action.grad).all()
    assert action.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", NEW_KINDS)
def test_no_grad_blocks_and_autograd_path_agree(kind):
    est = _est(kind)
    obs, action = torch.randn(150, 40, 3), torch.randn(150, 40, 2)  # several no-grad blocks
    torch.manual_seed(3)
    with torch.no_grad():
        fast = est.score(obs, action)
    torch.manual_seed(3)
    slow = est.score(obs, action)
    assert slow.requires_grad and not fast.requires_grad
    torch.testing.assert_close(fast, slow.detach(), atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("kind", KINDS)
def test_checkpoint_round_trip_reproduces_scores(kind, tmp_path):
    est = _est(kind)
    with torch.no_grad():
        for p in est.parameters():
            p.add_(0.1 * torch.randn_like(p))  # not the constructor's init
    save_checkpoint(tmp_path / "u.pt", {"uncertainty": est})
    loaded = load_modules(tmp_path / "u.pt")["uncertainty"]
    assert type(loaded) is type(est) and loaded.config() == est.config()
    obs, action = torch.randn(5, 12, 3), torch.randn(5, 12, 2)
    assert torch.equal(_seeded_score(loaded, obs, action), _seeded_score(est, obs, action))


@pytest.mark.parametrize("kind", KINDS)
def test_scores_are_deterministic_under_manual_seed(kind):
    obs, action = torch.randn(3, 12, 3), torch.randn(3, 12, 2)
    first = _seeded_score(_est(kind, seed=5), obs, action, seed=7)
    second = _seeded_score(_est(kind, seed=5), obs, action, seed=7)
    assert torch.equal(first, second)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "obs, action, match",
    [
        (torch.randn(2, 9, 4), torch.randn(2, 9, 2), "obs has shape"),
        (torch.randn(2, 9, 3), torch.randn(2, 9, 1), "action has shape"),
        (torch.randn(2, 9, 3), torch.randn(2, 8, 2), "disagree"),
        (torch.randn(2, 3, 3), torch.randn(2, 3, 2), "window=4"),
        (torch.full((2, 9, 3), float("nan")), torch.randn(2, 9, 2), "NaN"),
        (torch.randn(2, 9, 3), torch.full((2, 9, 2), float("inf")), "NaN or inf"),
    ],
)
def test_bad_input_is_a_clear_error(kind, obs, action, match):
    with pytest.raises(ValueError, match=match):
        _est(kind).score(obs, action)


@pytest.mark.parametrize("kind", KINDS)
def test_bad_loss_input_is_a_clear_error(kind):
    est = _est(kind)
    with pytest.raises(ValueError, match="NaN"):
        est.loss(torch.full((2, 9, 3), float("nan")), torch.randn(2, 9, 2))
    with pytest.raises(ValueError, match="action has shape"):
        est.loss(torch.randn(2, 9, 3), torch.randn(2, 9, 5))
    with pytest.raises(ValueError, match="at least"):
        est.loss(torch.randn(2, 1, 3), torch.randn(2, 1, 2))


def test_score_windows_rejects_wrong_window_length():
    with pytest.raises(ValueError, match=r"\[\*B, 4, 5\]"):
        _est("ensemble").score_windows(torch.randn(2, 5, 5))


@pytest.mark.parametrize(
    "cls, kwargs, match",
    [
        (EnsembleUncertainty, {"num_members": 1}, "num_members must be an int >= 2, got 1"),
        (EnsembleUncertainty, {"num_members": 2.0}, "num_members .* got 2.0"),
        (EnsembleUncertainty, {"hidden_size": 0}, "hidden_size .* got 0"),
        (EnsembleUncertainty, {"activation": "gelu"}, "'gelu'"),
        (EnsembleUncertainty, {"window": 0}, "window .* got 0"),
        (MCDropoutUncertainty, {"dropout": 0.0}, r"dropout must be in \(0, 1\), got 0.0"),
        (MCDropoutUncertainty, {"dropout": 1.0}, "got 1.0"),
        (MCDropoutUncertainty, {"dropout": "0.1"}, "got '0.1'"),
        (MCDropoutUncertainty, {"samples": 1}, "samples must be an int >= 2, got 1"),
        (MCDropoutUncertainty, {"hidden_size": True}, "hidden_size .* got True"),
        (RNDUncertainty, {"embedding_size": 0}, "embedding_size .* got 0"),
        (RNDUncertainty, {"hidden_size": -3}, "hidden_size .* got -3"),
        (RNDUncertainty, {"activation": "sigmoid"}, "'sigmoid'"),
    ],
)
def test_bad_constructor_args_are_clear_errors(cls, kwargs, match):
    with pytest.raises(ValueError, match=match):
        cls(3, 2, **kwargs)


# ---------------------------------------------------------------- registry


@pytest.mark.parametrize("kind", KINDS)
def test_make_estimator_builds_each_kind(kind):
    est = make_estimator(kind, 6, 3, window=7, hidden_size=8)
    assert type(est) is ESTIMATORS[kind]
    assert (est.obs_dim, est.action_dim, est.window, est.hidden_size) == (6, 3, 7, 8)
    assert make_estimator(kind, 6, 3).window == 10


def test_make_estimator_unknown_kind_and_keyword():
    with pytest.raises(
        ValueError,
        match=r"'gp'.*\['ensemble', 'mc_dropout', 'reconstruction', 'rnd', 'world_model_ensemble'\]",
    ):
        make_estimator("gp", 6, 3)
    with pytest.raises(
        ValueError, match=r"does not accept \['num_members'\].*'dropout'.*'samples'"
    ):
        make_estimator("mc_dropout", 6, 3, num_members=5)
    with pytest.raises(ValueError, match=r"RNDUncertainty .*\['hidden', 'samples'\]"):
        make_estimator("rnd", 6, 3, hidden=8, samples=3)
    assert issubclass(ESTIMATORS["ensemble"], EnsembleUncertainty)
    assert ESTIMATORS["reconstruction"] is ReconstructionUncertainty


# ---------------------------------------------------------------- in vs out of distribution


def _linear_system(num: int, length: int, generator: torch.Generator):
    """s_{t+1} = 0.9 s_t + 0.1 a_t + noise, a ~ U[-1, 1], s_0 ~ U[-1, 1]: states stay in [-1, 1]."""
    s = torch.rand(num, 2, generator=generator) * 2 - 1
    action = torch.rand(num, length, 2, generator=generator) * 2 - 1
    obs = []
    for t in range(length):
        obs.append(s)
        s = 0.9 * s + 0.1 * action[:, t] + 0.01 * torch.randn(num, 2, generator=generator)
    return torch.stack(obs, 1), action


@pytest.mark.parametrize(  # the ensemble of world models (11 s) in make test-all
    "kind",
    [pytest.param(k, marks=pytest.mark.slow) if k == "world_model_ensemble" else k for k in KINDS],
)
def test_u_is_higher_out_of_distribution(kind):
    generator = torch.Generator().manual_seed(0)
    obs, action = _linear_system(32, 30, generator)
    held_obs, held_action = _linear_system(32, 30, generator)
    torch.manual_seed(0)
    est = make_estimator(kind, 2, 2, window=5, hidden_size=32)
    est.fit_normalization(obs, action)
    optimizer = torch.optim.Adam(est.parameters(), lr=3e-3)
    for _ in range(200):
        loss = est.loss(obs, action)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    sigma = est.input_norm.scale[:2]
    with torch.no_grad():
        u_in = _seeded_score(est, held_obs, held_action).mean()
        u_shifted = _seeded_score(est, held_obs + 5 * sigma, held_action).mean()
        u_big_action = _seeded_score(est, held_obs, 3 * held_action).mean()
    assert u_shifted > 2 * u_in, (kind, u_in, u_shifted)
    assert u_big_action > 2 * u_in, (kind, u_in, u_big_action)


@pytest.mark.parametrize("kind", NEW_KINDS)
def test_fit_uncertainty_trains_each_estimator(kind):
    generator = torch.Generator().manual_seed(1)
    obs, action = _linear_system(8, 25, generator)
    buffer = make_sequence_buffer(200, slice_len=6, num_slices=4)
    traj = torch.arange(8).repeat_interleave(25)
    buffer.extend(
        TensorDict(
            {
                "observation": obs.reshape(-1, 2),
                "action": action.reshape(-1, 2),
                ("collector", "traj_ids"): traj,
            },
            [200],
        )
    )
    torch.manual_seed(0)
    est = make_estimator(kind, 2, 2, window=4, **SMALL[kind])
    result = fit_uncertainty(est, buffer, steps=30, eval_every=10, progress=False)
    assert result.steps == 30 and torch.isfinite(torch.tensor(result.best_val_loss))
    assert bool(est.input_norm.fitted)


# ---------------------------------------------------------------- ensemble


def test_ensemble_equals_separately_evaluated_members():
    est = _est("ensemble")
    obs, action = torch.randn(4, 11, 3), torch.randn(4, 11, 2)
    x = est.input_norm.normalize(torch.cat([obs, action], -1))
    preds = []
    for e in range(est.num_members):
        h = x
        for i, (weight, bias) in enumerate(zip(est.weights, est.biases, strict=True)):
            h = F.linear(h, weight[e].t(), bias[e, 0])
            h = torch.relu(h) if i < len(est.weights) - 1 else h
        preds.append(h)
    preds = torch.stack(preds)  # [E, 4, 11, N]
    d = ((preds - preds.mean(0)) ** 2).mean(0).mean(-1)  # population variance, mean over N
    reference = torch.stack([d[:, t : t + 4].mean(-1) for t in range(8)], -1)
    torch.testing.assert_close(est.score(obs, action), reference, atol=1e-5, rtol=1e-5)
    with torch.no_grad():
        torch.testing.assert_close(est.score(obs, action), reference, atol=1e-5, rtol=1e-5)


def test_ensemble_loss_is_a_bootstrap_per_member():
    est = _est("ensemble")
    obs, action = torch.randn(3, 6, 3), torch.randn(3, 6, 2)
    torch.manual_seed(11)
    loss = est.loss(obs, action)
    torch.manual_seed(11)
    index = torch.randint(15, (3, 15))  # P = 3 sequences x 5 pairs
    assert not all(torch.equal(index[0], index[e]) for e in range(1, 3))
    x = est.input_norm.normalize(torch.cat([obs, action], -1))
    inputs = x[:, :-1].reshape(-1, 5)
    targets = (x[:, 1:, :3] - x[:, :-1, :3]).reshape(-1, 3)
    reference = torch.stack(
        [
            ((est.predict_deltas(inputs)[e][index[e]] - targets[index[e]]) ** 2).mean()
            for e in range(3)
        ]
    ).mean()
    torch.testing.assert_close(loss, reference)


def test_identical_members_drift_apart_under_their_bootstraps():
    est = _est("ensemble")
    with torch.no_grad():
        for p in (*est.weights, *est.biases):
            p.copy_(p[:1].expand_as(p))  # every member starts as member 0
    obs, action = torch.randn(4, 8, 3), torch.randn(4, 8, 2)
    assert est.score(obs, action).max() < 1e-10  # identical members agree (to rounding)
    optimizer = torch.optim.SGD(est.parameters(), lr=0.05)
    for _ in range(5):
        loss = est.loss(obs, action)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    first = est.weights[0]
    assert (first[1] - first[0]).abs().max() > 1e-3
    assert (first[2] - first[1]).abs().max() > 1e-3
    assert est.score(obs, action).min() > 1e-8


# ---------------------------------------------------------------- MC dropout


def test_mc_dropout_equals_explicitly_masked_passes():
    est = _est("mc_dropout")
    obs, action = torch.randn(2, 7, 3), torch.randn(2, 7, 2)
    torch.manual_seed(4)
    u = est.score(obs, action)
    torch.manual_seed(4)
    keep = 1 - est.dropout
    masks = torch.bernoulli(torch.full((2, est.samples, 1, est.hidden_size), keep)) / keep
    x = est.input_norm.normalize(torch.cat([obs, action], -1))
    preds = []
    for k in range(est.samples):
        h = torch.relu(est.hidden1(x)) * masks[0, k, 0]
        h = torch.relu(est.hidden2(h)) * masks[1, k, 0]
        preds.append(est.head(h))
    preds = torch.stack(preds)
    d = preds.var(0, correction=0).mean(-1)
    reference = torch.stack([d[:, t : t + 4].mean(-1) for t in range(4)], -1)
    torch.testing.assert_close(u, reference, atol=1e-5, rtol=1e-5)


def test_mc_dropout_masks_are_shared_within_a_call_and_redrawn_between_calls():
    est = _est("mc_dropout")
    obs, action = torch.randn(1, 8, 3), torch.randn(1, 8, 2)
    u = est.score(obs.expand(3, 8, 3), action.expand(3, 8, 2))
    assert torch.equal(u[0], u[1]) and torch.equal(u[0], u[2])  # common random numbers
    assert not torch.equal(est.score(obs, action)[0], u[0])


def test_mc_dropout_loss_uses_dropout():
    est = _est("mc_dropout")
    obs, action = torch.randn(2, 8, 3), torch.randn(2, 8, 2)
    assert est.loss(obs, action) != est.loss(obs, action)


# ---------------------------------------------------------------- RND


def test_rnd_target_is_frozen_and_predictor_trains():
    est = _est("rnd")
    target = {k: v.clone() for k, v in est.target.state_dict().items()}
    predictor = {k: v.clone() for k, v in est.predictor.state_dict().items()}
    assert set(target) and all(f"target.{k}" in est.state_dict() for k in target)
    # All parameters, frozen ones included, with weight decay: the target still must not move.
    optimizer = torch.optim.Adam(est.parameters(), lr=1e-2, weight_decay=0.1)
    obs, action = torch.randn(4, 10, 3), torch.randn(4, 10, 2)
    first = est.loss(obs, action).item()
    for _ in range(20):
        loss = est.loss(obs, action)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss.item() < first
    assert all(torch.equal(v, est.target.state_dict()[k]) for k, v in target.items())
    assert any(not torch.equal(v, est.predictor.state_dict()[k]) for k, v in predictor.items())


def test_rnd_loss_is_mean_squared_u():
    est = _est("rnd")
    obs, action = torch.randn(2, 9, 3), torch.randn(2, 9, 2)
    torch.testing.assert_close(est.loss(obs, action), est.score(obs, action).pow(2).mean())


# ---------------------------------------------------------------- planning


@pytest.mark.parametrize("kind", KINDS)
def test_estimator_inside_planning_model(kind):
    torch.manual_seed(0)
    model = fitted(LSTMWorldModel(6, 3, window=10))
    est = fitted(make_estimator(kind, 6, 3, window=10, **SMALL[kind]))

    def cost(obs, action, next_obs):
        return next_obs.pow(2).sum(-1) + 0.1 * action.pow(2).sum(-1)

    planning = PlanningModel(model, cost, uncertainty=est)
    actions = (torch.rand(7, 5, 3) * 2 - 1).requires_grad_()
    pred = planning(torch.rand(10, 6), torch.rand(10, 3), torch.rand(6), actions)
    assert pred.uncertainty.shape == (7, 5)
    assert torch.isfinite(pred.uncertainty).all()
    pred.uncertainty.sum().backward()
    assert torch.isfinite(actions.grad).all() and actions.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", KINDS)
def test_window_local_estimators_score_rows_independently(kind):
    """``window_local`` lets planners score candidates in row blocks: for those kinds, rows
    scored in two calls equal the rows scored in one; MC dropout (per-call masks) is not one."""
    est = _est(kind)
    assert est.window_local == (kind != "mc_dropout")
    if not est.window_local:
        return
    obs, action = torch.randn(6, 9, 3), torch.randn(6, 9, 2)
    with torch.no_grad():
        whole = est.score(obs, action)
        parts = torch.cat([est.score(obs[:2], action[:2]), est.score(obs[2:], action[2:])])
    torch.testing.assert_close(parts, whole)


class _PerStepScores(ReconstructionUncertainty):
    """An estimator of one's own with a bug: one u per step, not per window."""

    def score_sequence(self, x):
        return x.abs().sum(-1)


def test_an_estimator_returning_the_wrong_shape_is_one_clear_error_everywhere():
    est = _PerStepScores(3, 2, window=4)
    message = (
        r"^_PerStepScores\.score_sequence returned \({}\) for sequences \({}\); expected \({}\): "
        r"one u per window of 4 steps\.$"
    )
    with pytest.raises(ValueError, match=message.format("2, 10", "2, 10, 5", "2, 7")):
        est.score(torch.zeros(2, 10, 3), torch.zeros(2, 10, 2))
    with pytest.raises(ValueError, match=message.format("6, 4", "6, 4, 5", "6, 1")):
        est.score_windows(torch.zeros(6, 4, 5))
    world = fitted(LSTMWorldModel(3, 2, window=4))
    model = PlanningModel(world, lambda o, a, n: n.pow(2).sum(-1), uncertainty=fitted(est))
    with pytest.raises(ValueError, match=r"^_PerStepScores\.score_sequence returned \(3, 8\)"):
        model(torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(3), torch.zeros(3, 5, 2))
