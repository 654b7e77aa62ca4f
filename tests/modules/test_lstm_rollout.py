from __future__ import annotations

import pytest
import torch

from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.modules._lstm_rollout import (
    LSTMRollout,
    recorded_rollout,
    rollout,
    rollout_inplace,
)
from torchrl_recon.planners.gradient import frozen


def _frozen_model(activation: str = "relu", dtype=torch.float32) -> LSTMWorldModel:
    torch.manual_seed(0)
    model = LSTMWorldModel(5, 3, hidden_size=8, dense_size=7, activation=activation)
    model.fit_normalization(torch.randn(50, 5) * 20 + 50, torch.rand(50, 3), torch.randn(50, 5))
    return model.to(dtype).requires_grad_(False)


def _inputs(rows: int, horizon: int, dtype=torch.float32) -> tuple[torch.Tensor, ...]:
    torch.manual_seed(1)
    return tuple(
        x.to(dtype).requires_grad_(True)
        for x in (
            torch.randn(rows, 5) * 20 + 50,
            torch.randn(rows, 8),
            torch.randn(rows, 8),
            torch.rand(rows, horizon, 3) * 2 - 1,
        )
    )


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu"])
@pytest.mark.parametrize(("rows", "horizon"), [(16, 40), (1, 3), (3, 1)])
@pytest.mark.parametrize("weights_need_grad", [False, True])
def test_fused_rollout_is_bitwise_the_recorded_graph(activation, rows, horizon, weights_need_grad):
    """Same states and same gradients, bit for bit: plans and training do not change."""
    model = _frozen_model(activation).requires_grad_(weights_need_grad)
    params = list(model.parameters()) if weights_need_grad else []
    s0, h0, c0, actions = _inputs(rows, horizon)
    weight = torch.randn(rows, horizon, 5)
    inputs = (s0, h0, c0, actions, *params)
    recorded = recorded_rollout(s0, h0, c0, actions, activation, *model._folded_weights())
    fused = LSTMRollout.apply(s0, h0, c0, actions, activation, *model._folded_weights())
    assert torch.equal(recorded, fused)
    grads_recorded = torch.autograd.grad((recorded * weight).square().sum(), inputs)
    grads_fused = torch.autograd.grad((fused * weight).square().sum(), inputs)
    names = ["s0", "h0", "c0", "actions", *(n for n, _ in model.named_parameters())][: len(inputs)]
    for name, a, b in zip(names, grads_recorded, grads_fused, strict=True):
        assert torch.equal(a, b), f"{name}: max diff {(a - b).abs().max().item()}"


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu"])
def test_fused_rollout_passes_gradcheck(activation):
    """The hand-written derivatives against finite differences (float64), weights included."""
    model = _frozen_model(activation, torch.float64)
    weights = tuple(w.detach().requires_grad_(True) for w in model._folded_weights())
    inputs = (*_inputs(2, 4, torch.float64), *weights)
    assert torch.autograd.gradcheck(
        lambda s, h, c, a, *w: LSTMRollout.apply(s, h, c, a, activation, *w), inputs
    )


@pytest.mark.parametrize("activation", ["relu", pytest.param("tanh", marks=pytest.mark.slow)])
def test_a_populations_fused_rollout_passes_gradcheck(activation):
    """The member path (one sigmoid over the gates, one weight-gradient matmul after the loop)
    against finite differences (float64), two members apart, weights included."""
    torch.manual_seed(3)
    members = [_frozen_model(activation, torch.float64) for _ in range(2)]
    for k, member in enumerate(members):  # members apart
        member.lstm.weight_hh_l0.data.add_(0.1 * k)
    folded = (m._folded_weights() for m in members)
    stacked = [torch.stack(ws) for ws in zip(*folded, strict=True)]
    weights = tuple(w.detach().requires_grad_(True) for w in stacked)
    inputs = tuple(
        torch.stack([x.detach(), x.detach() * 0.5]).requires_grad_(True)
        for x in _inputs(2, 4, torch.float64)
    )
    assert torch.autograd.gradcheck(
        lambda s, h, c, a, *w: LSTMRollout.apply(s, h, c, a, activation, *w), (*inputs, *weights)
    )


def test_multi_step_training_is_bitwise_the_recorded_graph(monkeypatch):
    """A few Adam steps of the multi-step loss land on the same weights as with the reference."""
    from tensordict import TensorDict

    from torchrl_recon.modules import _lstm_rollout
    from torchrl_recon.objectives import WorldModelPredictionLoss

    class Recorded:  # in place of LSTMRollout: the rollout with every op recorded
        apply = staticmethod(recorded_rollout)

    torch.manual_seed(2)
    data = TensorDict(
        {
            "observation": torch.randn(4 * 20, 5) * 20 + 50,
            "action": torch.rand(4 * 20, 3),
            ("next", "observation"): torch.randn(4 * 20, 5) * 20 + 50,
        },
        [4 * 20],
    )
    trained = []
    for node in (LSTMRollout, Recorded):
        monkeypatch.setattr(_lstm_rollout, "LSTMRollout", node)
        model = _frozen_model().requires_grad_(True)
        model.window = 4
        loss = WorldModelPredictionLoss(model, slice_len=20)
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
        for _ in range(3):
            optimizer.zero_grad()
            loss(data)["loss_world_model"].backward()
            optimizer.step()
        trained.append(model.state_dict())
    assert trained[0]["lstm.weight_hh_l0"].ne(_frozen_model().lstm.weight_hh_l0).any()
    for name, value in trained[0].items():
        assert torch.equal(value, trained[1][name]), name


def test_imagine_differentiates_through_the_fused_rollout():
    model = _frozen_model().requires_grad_(True)
    context = torch.randn(2, 10, 5) * 20 + 50, torch.rand(2, 10, 3), torch.randn(2, 5) * 20 + 50
    actions = torch.rand(2, 4, 6, 3, requires_grad=True)
    trained = model.imagine(*context, actions)
    assert _reaches(trained.grad_fn, "LSTMRolloutBackward")
    trained.sum().backward()
    assert model.lstm.weight_hh_l0.grad.abs().sum() > 0 and actions.grad.abs().sum() > 0
    with frozen(model):
        planned = model.imagine(*context, actions)
    assert _reaches(planned.grad_fn, "LSTMRolloutBackward")
    assert torch.equal(planned, trained)


def test_rollout_picks_the_reference_or_an_accelerator_per_call():
    """One place picks: the reference when asked, the fused node when a gradient is needed, the
    in-place loop for one model without one, the reference for members without one."""
    model = _frozen_model()
    s0, h0, c0, actions = _inputs(3, 5)
    weights = model._folded_weights()
    fused = rollout(s0, h0, c0, actions, "relu", *weights)
    assert type(fused.grad_fn).__name__ == "LSTMRolloutBackward"
    reference = rollout(s0, h0, c0, actions, "relu", *weights, reference=True)
    assert type(reference.grad_fn).__name__ != "LSTMRolloutBackward"
    assert torch.equal(fused, reference)
    plain = [x.detach() for x in (s0, h0, c0, actions)]
    assert torch.equal(rollout(*plain, "relu", *weights), rollout_inplace(*plain, "relu", *weights))
    members = [x.expand(2, *x.shape) for x in plain]
    stacked = [w.expand(2, *w.shape) for w in weights]
    got = rollout(*members, "relu", *stacked)
    assert got.grad_fn is None
    assert torch.equal(got, recorded_rollout(*members, "relu", *stacked))


def test_double_backward_is_refused_not_wrong():
    model = _frozen_model()
    s0, h0, c0, actions = _inputs(2, 3)
    states = LSTMRollout.apply(s0, h0, c0, actions, "relu", *model._folded_weights())
    (grad,) = torch.autograd.grad(states.square().sum(), actions, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        grad.sum().backward()


def _reaches(fn, name: str, depth: int = 4) -> bool:
    if fn is None or depth < 0:
        return False
    if type(fn).__name__ == name:
        return True
    return any(_reaches(f, name, depth - 1) for f, _ in fn.next_functions)


def test_frozen_restores_requires_grad_after_an_error():
    model = _frozen_model().requires_grad_(True)
    model.head.bias.requires_grad_(False)
    with pytest.raises(RuntimeError, match="boom"), frozen(model):
        assert not any(p.requires_grad for p in model.parameters())
        raise RuntimeError("boom")
    assert not model.head.bias.requires_grad
    assert all(p.requires_grad for name, p in model.named_parameters() if name != "head.bias")


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
