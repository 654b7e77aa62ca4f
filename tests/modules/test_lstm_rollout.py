from __future__ import annotations

import pytest
import torch

from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.modules._lstm_rollout import LSTMRollout
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
def test_fused_rollout_is_bitwise_the_recorded_graph(activation, rows, horizon):
    """Same states and same gradients, bit for bit: plans do not change with the fast path."""
    model = _frozen_model(activation)
    s0, h0, c0, actions = _inputs(rows, horizon)
    weight = torch.randn(rows, horizon, 5)
    recorded = model._rollout_autograd(s0, h0, c0, actions)
    fused = LSTMRollout.apply(s0, h0, c0, actions, model._folded_weights(), activation)
    assert torch.equal(recorded, fused)
    grads_recorded = torch.autograd.grad((recorded * weight).square().sum(), (s0, h0, c0, actions))
    grads_fused = torch.autograd.grad((fused * weight).square().sum(), (s0, h0, c0, actions))
    for name, a, b in zip(("s0", "h0", "c0", "actions"), grads_recorded, grads_fused, strict=True):
        assert torch.equal(a, b), f"{name}: max diff {(a - b).abs().max().item()}"


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu"])
def test_fused_rollout_passes_gradcheck(activation):
    """The hand-written derivatives against finite differences (float64)."""
    model = _frozen_model(activation, torch.float64)
    weights = model._folded_weights()
    inputs = _inputs(2, 4, torch.float64)
    assert torch.autograd.gradcheck(
        lambda s, h, c, a: LSTMRollout.apply(s, h, c, a, weights, activation), inputs
    )


def test_imagine_takes_the_fused_rollout_only_when_the_weights_are_frozen():
    model = _frozen_model().requires_grad_(True)
    context = torch.randn(2, 10, 5) * 20 + 50, torch.rand(2, 10, 3), torch.randn(2, 5) * 20 + 50
    actions = torch.rand(2, 4, 6, 3, requires_grad=True)
    trained = model.imagine(*context, actions)
    assert not _reaches(trained.grad_fn, "LSTMRolloutBackward")  # the weights need gradients
    trained.sum().backward()
    assert model.lstm.weight_hh_l0.grad.abs().sum() > 0
    with frozen(model):
        planned = model.imagine(*context, actions)
    assert _reaches(planned.grad_fn, "LSTMRolloutBackward")
    assert torch.equal(planned, trained)


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
