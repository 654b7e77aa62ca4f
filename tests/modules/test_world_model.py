from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.modules import LinearDeltaModel, LSTMWorldModel


def _model(window: int = 4) -> LSTMWorldModel:
    torch.manual_seed(0)
    model = LSTMWorldModel(3, 2, hidden_size=8, dense_size=8, window=window)
    model.fit_normalization(
        torch.randn(50, 3) * 2 + 1, torch.rand(50, 2), torch.randn(50, 3) * 2 + 1.5
    )
    return model


@pytest.mark.parametrize("batch", [(), (2,), (2, 3)])
def test_imagine_shapes(batch):
    model = _model()
    states = model.imagine(
        torch.randn(*batch, 4, 3),
        torch.randn(*batch, 4, 2),
        torch.randn(*batch, 3),
        torch.rand(*batch, 5, 7, 2),
    )
    assert states.shape == (*batch, 5, 7, 3)


def test_imagine_equals_teacher_forced_recursion():
    model = _model()
    ctx_s, ctx_a, s0, acts = (
        torch.randn(4, 3),
        torch.randn(4, 2),
        torch.randn(3),
        torch.rand(2, 5, 2),
    )
    states = model.imagine(ctx_s, ctx_a, s0, acts)
    for k in range(2):
        obs, act = torch.cat([ctx_s, s0[None]]), torch.cat([ctx_a, acts[k, :1]])
        for t in range(5):
            delta = model.delta_norm.denormalize(model.predict_delta(obs, act))[-1]
            torch.testing.assert_close(states[k, t], obs[-1] + delta, atol=1e-5, rtol=1e-5)
            obs = torch.cat([obs, (obs[-1] + delta)[None]])
            act = torch.cat([act, acts[k, t + 1 : t + 2]])


def test_context_longer_than_window_uses_last_window_steps():
    model = _model(window=4)
    ctx_s, ctx_a, s0, acts = (
        torch.randn(9, 3),
        torch.randn(9, 2),
        torch.randn(3),
        torch.rand(2, 5, 2),
    )
    torch.testing.assert_close(
        model.imagine(ctx_s, ctx_a, s0, acts), model.imagine(ctx_s[-4:], ctx_a[-4:], s0, acts)
    )


def test_precomputed_warmup_state_gives_the_same_rollout():
    model = _model()
    ctx_s, ctx_a, s0, acts = (
        torch.randn(2, 4, 3),
        torch.randn(2, 4, 2),
        torch.randn(2, 3),
        torch.rand(2, 5, 6, 2),
    )
    state = model.warmup(ctx_s, ctx_a)
    torch.testing.assert_close(
        model.imagine(ctx_s, ctx_a, s0, acts, state=state), model.imagine(ctx_s, ctx_a, s0, acts)
    )


def test_gradients_reach_actions_and_parameters():
    model = _model()
    acts = torch.rand(1, 3, 6, 2, requires_grad=True)
    states = model.imagine(torch.randn(1, 4, 3), torch.randn(1, 4, 2), torch.randn(1, 3), acts)
    states.sum().backward()
    assert acts.grad is not None and acts.grad.abs().sum() > 0
    assert model.lstm.weight_hh_l0.grad.abs().sum() > 0


def test_forward_writes_predicted_next_observation():
    model = _model()
    td = TensorDict({"observation": torch.randn(2, 6, 3), "action": torch.randn(2, 6, 2)}, [2, 6])
    out = model(td)
    assert out["next", "predicted_observation"].shape == (2, 6, 3)
    assert model.in_keys == ["observation", "action"]


def test_normalization_is_in_state_dict():
    keys = _model().state_dict().keys()
    assert {"obs_norm.loc", "obs_norm.scale", "delta_norm.scale", "action_norm.loc"} <= set(keys)


@pytest.mark.parametrize(
    "args, match",
    [
        (
            (torch.randn(4, 5), torch.randn(4, 2), torch.randn(3), torch.rand(2, 5, 2)),
            "context_obs",
        ),
        ((torch.randn(2, 3), torch.randn(2, 2), torch.randn(3), torch.rand(2, 5, 2)), "window=4"),
        ((torch.randn(4, 3), torch.randn(4, 2), torch.randn(3), torch.rand(5, 2)), "actions"),
        (
            (
                torch.randn(4, 3),
                torch.randn(4, 2),
                torch.tensor([0.0, float("nan"), 0.0]),
                torch.rand(2, 5, 2),
            ),
            "NaN",
        ),
        (
            (torch.randn(2, 4, 3), torch.randn(2, 4, 2), torch.randn(2, 3), torch.rand(3, 2, 5, 2)),
            "actions",
        ),
    ],
)
def test_bad_input_is_a_clear_error(args, match):
    with pytest.raises(ValueError, match=match):
        _model().imagine(*args)


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="window"):
        LSTMWorldModel(3, 2, window=0)
    with pytest.raises(ValueError, match="activation"):
        LSTMWorldModel(3, 2, activation="swish")


def test_linear_baseline_recovers_linear_dynamics():
    torch.manual_seed(0)
    s, a = torch.randn(200, 2), torch.randn(200, 1)
    next_s = s + 0.1 * s @ torch.tensor([[0.0, 1.0], [-1.0, 0.0]]) + 0.5 * a
    model = LinearDeltaModel(2, 1)
    model.fit(s, a, next_s)
    pred = model.imagine(s[None, :1], a[None, :1], s[:1], a[None, None, :3].expand(1, 1, 3, 1))
    assert pred.shape == (1, 1, 3, 2)
    torch.testing.assert_close(pred[0, 0, 0], next_s[0], atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu"])
def test_inplace_and_autograd_rollouts_agree(activation):
    torch.manual_seed(0)
    model = LSTMWorldModel(6, 3, window=5, activation=activation)
    model.fit_normalization(torch.randn(100, 6) * 3, torch.rand(100, 3), torch.randn(100, 6))
    args = torch.randn(2, 5, 6), torch.rand(2, 5, 3), torch.randn(2, 6), torch.rand(2, 20, 15, 3)
    with torch.no_grad():
        fast = model.imagine(*args)  # in-place path
    slow = model.imagine(*args)  # autograd path (parameters require grad)
    assert slow.requires_grad and not fast.requires_grad
    torch.testing.assert_close(fast, slow.detach(), atol=1e-4, rtol=1e-4)


def test_step_by_step_prediction_equals_the_rollout():
    """``step`` (nn.LSTM once per step) and ``rollout`` (the fused loop) predict the same states."""
    model = _model()
    ctx_s, ctx_a, s0, acts = (
        torch.randn(2, 4, 3),
        torch.randn(2, 4, 2),
        torch.randn(2, 3),
        torch.rand(2, 6, 2),
    )
    state = model.warmup(ctx_s, ctx_a)
    with torch.no_grad():
        rolled = model.rollout(s0, acts, state)
        s, stepped = s0, []
        for t in range(6):
            s, state = model.step(s, acts[:, t], state)
            stepped.append(s)
    torch.testing.assert_close(torch.stack(stepped, 1), rolled, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(rolled, model.imagine(ctx_s, ctx_a, s0, acts[:, None])[:, 0])


def test_recorded_rollout_is_the_reference_of_the_fused_one():
    model = _model()
    ctx_s, ctx_a = torch.randn(3, 4, 3), torch.randn(3, 4, 2)
    s0, acts = torch.randn(3, 3), torch.rand(3, 5, 2)
    results = []
    for recorded in (True, False):
        model.zero_grad()
        states = model.rollout(s0, acts, model.warmup(ctx_s, ctx_a), recorded=recorded)
        states.square().sum().backward()
        results.append((states.detach(), [p.grad.clone() for p in model.parameters()]))
    assert torch.equal(results[0][0], results[1][0])
    assert all(torch.equal(a, b) for a, b in zip(results[0][1], results[1][1], strict=True))


def test_step_and_rollout_reject_mismatched_batches():
    model = _model()
    with pytest.raises(ValueError, match="disagree on batch dims"):
        model.step(torch.zeros(2, 3), torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"expected \[\*B, H, 2\] with \*B = \(2,\)"):
        model.rollout(
            torch.zeros(2, 3),
            torch.zeros(3, 5, 2),
            model.warmup(torch.zeros(2, 4, 3), torch.zeros(2, 4, 2)),
        )


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
