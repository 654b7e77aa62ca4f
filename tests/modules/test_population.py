"""Members: one member is bitwise the single model; R members equal R single models."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from torchrl_recon.fitting import load_checkpoint, load_modules, save_checkpoint
from torchrl_recon.modules import (
    LSTMWorldModel,
    ReconstructionPopulation,
    ReconstructionUncertainty,
    WorldModelPopulation,
)

N, M, T = 6, 3, 4
SIZES = dict(window=T, hidden_size=8, dense_size=8)


def _fit_norm(model, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    s, a = torch.randn(60, N, generator=g) * (seed + 1), torch.rand(60, M, generator=g)
    if isinstance(model, LSTMWorldModel):
        model.fit_normalization(s, a, s + torch.randn(60, N, generator=g))
    else:
        model.fit_normalization(s, a)


def _world_models(count: int) -> list[LSTMWorldModel]:
    torch.manual_seed(0)
    models = [LSTMWorldModel(N, M, **SIZES) for _ in range(count)]
    for i, m in enumerate(models):
        _fit_norm(m, i)
    return models


def _inputs(members: int, seed: int = 5):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(members, 2, T, N, generator=g),
        torch.randn(members, 2, T, M, generator=g),
        torch.randn(members, 2, N, generator=g),
        torch.rand(members, 2, 3, 7, M, generator=g, requires_grad=True),
    )


def test_one_member_is_bitwise_the_single_model():
    torch.manual_seed(3)
    single = LSTMWorldModel(N, M, **SIZES)
    torch.manual_seed(3)
    pop = LSTMWorldModel(N, M, num_members=1, **SIZES)
    for (key, a), b in zip(single.state_dict().items(), pop.state_dict().values(), strict=True):
        assert torch.equal(a, b[0]), f"{key} initialised differently"
    _fit_norm(single, 0)
    pop.load_member(0, single)
    ctx_s, ctx_a, s0, actions = _inputs(1)
    got = pop.imagine(ctx_s, ctx_a, s0, actions)
    got.square().sum().backward()
    pop_grads = [p.grad[0].clone() for p in pop.parameters()]
    action_grad, actions.grad = actions.grad.clone(), None
    want = single.imagine(ctx_s[0], ctx_a[0], s0[0], actions[0])
    want.square().sum().backward()
    assert torch.equal(got[0], want)
    assert torch.equal(action_grad, actions.grad)
    for a, b in zip(pop_grads, single.parameters(), strict=True):
        assert torch.equal(a, b.grad)
    with torch.no_grad():  # the in-place no-grad path
        want = single.imagine(ctx_s[0], ctx_a[0], s0[0], actions[0])
        assert torch.equal(pop.imagine(ctx_s, ctx_a, s0, actions)[0], want)
    obs, act = torch.randn(1, 3, 9, N), torch.randn(1, 3, 9, M)
    assert torch.equal(pop.predict_delta(obs, act)[0], single.predict_delta(obs[0], act[0]))
    (s1, (h1, _)), (s2, (h2, _)) = (
        pop.step(obs[:, :, 0], act[:, :, 0]),
        single.step(obs[0, :, 0], act[0, :, 0]),
    )
    assert torch.equal(s1[0], s2) and torch.equal(h1[0], h2)


def test_members_equal_separate_models_outputs_and_gradients():
    models = _world_models(3)
    pop = LSTMWorldModel.from_members(models)
    ctx_s, ctx_a, s0, actions = _inputs(3)
    got = pop.imagine(ctx_s, ctx_a, s0, actions)
    got.square().sum().backward()
    grad, actions.grad = actions.grad.clone(), None
    want = torch.stack(
        [m.imagine(*(x[i] for x in (ctx_s, ctx_a, s0, actions))) for i, m in enumerate(models)]
    )
    want.square().sum().backward()
    torch.testing.assert_close(got, want)
    torch.testing.assert_close(grad, actions.grad)
    names = dict(pop.named_parameters())
    for i, m in enumerate(models):
        for key, p in m.named_parameters():
            torch.testing.assert_close(names[key].grad[i], p.grad, rtol=1e-4, atol=1e-5)
    # the engine's recorded reference and the no-grad path agree with the fused node
    state = pop.warmup(ctx_s, ctx_a)
    flat = actions[:, :, 0]
    recorded = pop.rollout(s0, flat, state, recorded=True)
    torch.testing.assert_close(pop.rollout(s0, flat, state), recorded)
    with torch.no_grad():
        torch.testing.assert_close(pop.rollout(s0, flat, state), recorded)
    obs, act = torch.randn(3, 2, 9, N), torch.randn(3, 2, 9, M)
    torch.testing.assert_close(
        pop.predict_delta(obs, act),
        torch.stack([m.predict_delta(obs[i], act[i]) for i, m in enumerate(models)]),
    )
    s1, (h1, c1) = pop.step(obs[:, :, 0], act[:, :, 0], state)
    for i, m in enumerate(models):
        s2, (h2, c2) = m.step(obs[i, :, 0], act[i, :, 0], (state[0][i], state[1][i]))
        torch.testing.assert_close(s1[i], s2)
        torch.testing.assert_close(c1[i], c2)


def test_split_and_stack_round_trip_and_checkpoint(tmp_path):
    models = _world_models(3)
    pop = LSTMWorldModel.from_members(models)
    back = pop.split()
    for a, b in zip(back, models, strict=True):
        assert a.config() == b.config()
        for (key, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
            assert torch.equal(x, y), key
    again = LSTMWorldModel.from_members(back)
    for key, value in pop.state_dict().items():
        assert torch.equal(value, again.state_dict()[key]), key
    save_checkpoint(tmp_path / "pop.pt", {"world_model": pop})
    loaded = load_modules(tmp_path / "pop.pt")["world_model"]
    assert isinstance(loaded, LSTMWorldModel) and loaded.num_members == 3
    assert torch.equal(loaded.lstm.weight_ih_l0, pop.lstm.weight_ih_l0)
    with pytest.raises(ValueError, match="share one config"):
        LSTMWorldModel.from_members([models[0], LSTMWorldModel(N, M, window=T)])
    with pytest.raises(ValueError, match="member dim first"):
        pop.warmup(torch.zeros(2, T, N), torch.zeros(2, T, M))


def test_single_model_state_dict_layout_is_unchanged():
    """A checkpoint written before populations holds exactly these entries and still loads."""
    model = LSTMWorldModel(N, M, **SIZES)
    shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert shapes == {
        "lstm.weight_ih_l0": (32, N + M),
        "lstm.weight_hh_l0": (32, 8),
        "lstm.bias_ih_l0": (32,),
        "lstm.bias_hh_l0": (32,),
        "dense.weight": (8, 8),
        "dense.bias": (8,),
        "head.weight": (N, 8),
        "head.bias": (N,),
        **{
            f"{n}_norm.{s}": (d,)
            for n, d in (("obs", N), ("action", M), ("delta", N))
            for s in ("loc", "scale")
        },
        **{f"{n}_norm.fitted": () for n in ("obs", "action", "delta")},
    }


def test_reconstruction_population():
    torch.manual_seed(0)
    estimators = [ReconstructionUncertainty(N, M, window=T, hidden_size=8) for _ in range(3)]
    for i, e in enumerate(estimators):
        _fit_norm(e, i)
    pop = ReconstructionPopulation.from_members(estimators)
    obs, act = torch.randn(3, 2, 9, N), torch.randn(3, 2, 9, M)
    want = torch.stack([e.score(obs[i], act[i]) for i, e in enumerate(estimators)])
    torch.testing.assert_close(pop.score(obs, act), want)
    torch.testing.assert_close(pop.loss(obs, act), want.flatten(1).mean(1))
    one = ReconstructionPopulation.from_members(estimators[:1])
    assert torch.equal(one.score(obs[:1], act[:1])[0], want[0])
    with torch.no_grad():
        assert torch.equal(one.score(obs[:1], act[:1])[0], estimators[0].score(obs[0], act[0]))
    for a, b in zip(pop.split(), estimators, strict=True):
        for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
            assert torch.equal(x, y)


def test_predict_window_deltas_is_predict_delta_on_each_window():
    pop = LSTMWorldModel.from_members(_world_models(3))
    obs = torch.randn(3, 2, 11, N, requires_grad=True)
    act = torch.randn(3, 2, 11, M)
    got = pop.predict_window_deltas(obs, act, T)
    assert got.shape == (3, 2, 11 - T + 1, N)
    windows = [
        pop.predict_delta(obs[:, :, w : w + T], act[:, :, w : w + T])[:, :, -1]
        for w in range(11 - T + 1)
    ]
    want = torch.stack(windows, 2)
    torch.testing.assert_close(got, want)
    (grad,) = torch.autograd.grad(got.square().sum(), obs)
    (want_grad,) = torch.autograd.grad(want.square().sum(), obs)
    torch.testing.assert_close(grad, want_grad)
    with pytest.raises(ValueError, match="at least window=12 steps"):
        pop.predict_window_deltas(obs, act, 12)
    with pytest.raises(ValueError, match="window must be an int >= 1, got 0"):
        pop.predict_window_deltas(obs, act, 0)


def test_members_keep_the_single_models_names_and_order():
    """R members hold the single model's entries with the member dim first, parameters in the
    same order (what the optimizer and per-member clipping see)."""
    single = LSTMWorldModel(N, M, **SIZES)
    models = LSTMWorldModel(N, M, num_members=3, **SIZES)
    assert WorldModelPopulation is LSTMWorldModel  # the former name
    assert [k for k, _ in models.named_parameters()] == [k for k, _ in single.named_parameters()]
    assert {k: v.shape for k, v in models.state_dict().items()} == {
        k: (3, *v.shape) for k, v in single.state_dict().items()
    }
    assert models.config() == {**single.config(), "num_members": 3}
    assert "num_members" not in single.config()  # single checkpoints compare as before


def test_checkpoints_written_before_the_member_dim_still_load():
    """The fixture was written by the code before populations became ``num_members``: stacked
    entries named ``lstm_weight_ih_l0`` and class ``WorldModelPopulation``; outputs saved with it."""
    path = Path(__file__).with_name("checkpoints_before_member_dim.pt")
    saved = torch.load(path, weights_only=True)
    loaded = load_modules(path)
    for name, module in loaded.items():
        values = saved["modules"][name]["state_dict"].values()
        assert len(values) == len(module.state_dict())
        for a, b in zip(module.state_dict().values(), values, strict=True):
            assert torch.equal(a, b), name
    pop, aes, ens = loaded["population"], loaded["autoencoders"], loaded["ensemble"]
    assert type(pop) is LSTMWorldModel and pop.num_members == 2
    x, out = saved["extra"]["inputs"], saved["extra"]
    with torch.no_grad():
        assert torch.equal(
            pop.imagine(x["ctx_s"], x["ctx_a"], x["s0"], x["actions"]), out["population_imagine"]
        )
        assert torch.equal(pop.predict_delta(x["obs"], x["act"]), out["population_predict_delta"])
        assert torch.equal(aes.score(x["obs"], x["act"]), out["autoencoders_score"])
        assert torch.equal(ens.score(x["obs"][0], x["act"][0]), out["ensemble_score"])
    fresh = LSTMWorldModel(**saved["modules"]["population"]["config"])
    load_checkpoint(path, {"population": fresh})  # into an existing module of the new class
    assert torch.equal(fresh.head.weight, pop.head.weight)


def test_one_model_has_no_member_dim():
    model, models = LSTMWorldModel(N, M, **SIZES), LSTMWorldModel(N, M, num_members=2, **SIZES)
    with pytest.raises(ValueError, match=r"is one model \(num_members=None\)"):
        model.split()
    with pytest.raises(ValueError, match="needs at least one single LSTMWorldModel"):
        LSTMWorldModel.from_members([models])
    with pytest.raises(ValueError, match="fit_normalization fits one model"):
        models.fit_normalization(torch.randn(5, N), torch.randn(5, M), torch.randn(5, N))
    with pytest.raises(ValueError, match="differs from the members'"):
        models.load_member(0, LSTMWorldModel(N, M, window=T))
    with pytest.raises(ValueError, match=r"expected \[\*B, H, 3\] with \*B = \(2,\)"):
        model.rollout(torch.zeros(2, N), torch.zeros(3, 5, M), (torch.zeros(2, 8),) * 2)
    with pytest.raises(ValueError, match=r"expected \[R, \*B, H, 3\] with \[R, \*B\] = \(2, 2\)"):
        models.rollout(torch.zeros(2, 2, N), torch.zeros(2, 3, 5, M), (torch.zeros(2, 2, 8),) * 2)


def test_a_single_models_window_deltas_are_its_one_member_populations():
    (model,) = _world_models(1)
    obs, act = torch.randn(2, 11, N), torch.randn(2, 11, M)
    got = model.predict_window_deltas(obs, act, T)
    one = LSTMWorldModel.from_members([model])
    assert torch.equal(got, one.predict_window_deltas(obs[None], act[None], T)[0])
    want = torch.stack(
        [
            model.predict_delta(obs[:, w : w + T], act[:, w : w + T])[:, -1]
            for w in range(11 - T + 1)
        ],
        1,
    )
    torch.testing.assert_close(got, want)
