from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from tests.normalized import fitted
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss


def _batch(n: int = 24) -> TensorDict:
    torch.manual_seed(0)
    obs = torch.randn(n, 3)
    return TensorDict(
        {"observation": obs, "action": torch.randn(n, 2), ("next", "observation"): obs + 0.1}, [n]
    )


@pytest.mark.parametrize("mode", ["multi_step", "one_step"])
def test_world_model_loss_flat_and_2d_batches_agree(mode):
    loss = WorldModelPredictionLoss(fitted(LSTMWorldModel(3, 2, window=4)), mode=mode, slice_len=8)
    flat = _batch()
    value = loss(flat)["loss_world_model"]
    assert value.ndim == 0 and torch.isfinite(value)
    torch.testing.assert_close(loss(flat.reshape(3, 8))["loss_world_model"], value)
    value.backward()
    assert loss.world_model.head.weight.grad.abs().sum() > 0


def _constant_delta_model(window: int = 4) -> LSTMWorldModel:
    """A world model whose normalised Δs prediction is the constant ``B`` (head weight 0), with
    known statistics: obs scale S_OBS, Δs loc L_D and scale S_D."""
    model = LSTMWorldModel(3, 2, window=window, hidden_size=8, dense_size=8)
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.copy_(B)
        model.obs_norm.scale.copy_(S_OBS)
        model.delta_norm.loc.copy_(L_D)
        model.delta_norm.scale.copy_(S_D)
        for norm in (model.obs_norm, model.action_norm, model.delta_norm):
            norm.fitted.fill_(True)  # statistics set by hand
    return model


B = torch.tensor([0.5, -1.0, 2.0])
S_OBS = torch.tensor([2.0, 0.5, 1.0])
L_D = torch.tensor([0.1, 0.0, -0.2])
S_D = torch.tensor([0.5, 2.0, 1.0])


def test_one_step_loss_equals_a_hand_computation():
    td = _batch()
    value = WorldModelPredictionLoss(_constant_delta_model(), mode="one_step", slice_len=8)(td)
    obs, nxt = td["observation"].tolist(), td["next", "observation"].tolist()
    errors = [
        (float(B[j]) - ((nxt[i][j] - obs[i][j]) - float(L_D[j])) / float(S_D[j])) ** 2
        for i in range(len(obs))
        for j in range(3)
    ]
    assert value["loss_world_model"].item() == pytest.approx(sum(errors) / len(errors), rel=1e-5)


def test_multi_step_loss_equals_a_hand_computation():
    """Warm up on steps 0..3 of each sequence of 8, then predict s_5..s_8 from the real s_4 by
    adding the constant raw Δs = B S_D + L_D each step; squared error in obs-scale units."""
    window, length = 4, 8
    td = _batch()
    value = WorldModelPredictionLoss(_constant_delta_model(window), slice_len=length)(td)
    obs, nxt = td["observation"].tolist(), td["next", "observation"].tolist()
    delta = (B * S_D + L_D).tolist()
    errors = []
    for start in range(0, len(obs), length):
        s = obs[start + window]
        for k in range(length - window):
            s = [s[j] + delta[j] for j in range(3)]
            target = nxt[start + window + k]
            errors += [((s[j] - target[j]) / float(S_OBS[j])) ** 2 for j in range(3)]
    assert value["loss_world_model"].item() == pytest.approx(sum(errors) / len(errors), rel=1e-5)


def test_flat_batch_needs_slice_len():
    with pytest.raises(ValueError, match="slice_len"):
        WorldModelPredictionLoss(LSTMWorldModel(3, 2, window=4))(_batch())
    with pytest.raises(ValueError, match="slices of 5"):
        WorldModelPredictionLoss(LSTMWorldModel(3, 2, window=4), slice_len=5)(_batch())


def test_multi_step_needs_sequences_longer_than_window():
    with pytest.raises(ValueError, match="longer than window=8"):
        WorldModelPredictionLoss(LSTMWorldModel(3, 2, window=8), slice_len=8)(_batch())


def test_bad_mode():
    with pytest.raises(ValueError, match="mode"):
        WorldModelPredictionLoss(LSTMWorldModel(3, 2), mode="teacher")


def test_uncertainty_loss_is_mean_u():
    ae = fitted(ReconstructionUncertainty(3, 2, window=4, hidden_size=8))
    td = _batch()
    value = UncertaintyLoss(ae, slice_len=8)(td)["loss_uncertainty"]
    seq = td.reshape(3, 8)
    torch.testing.assert_close(value, ae.score(seq["observation"], seq["action"]).mean())


def test_non_finite_loss_is_a_clear_error():
    model = LSTMWorldModel(3, 2, window=4)
    with torch.no_grad():
        model.head.bias.fill_(float("inf"))
    with pytest.raises(FloatingPointError, match="world-model loss"):
        WorldModelPredictionLoss(model, mode="one_step", slice_len=8)(_batch())


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
