from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

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
    loss = WorldModelPredictionLoss(LSTMWorldModel(3, 2, window=4), mode=mode, slice_len=8)
    flat = _batch()
    value = loss(flat)["loss_world_model"]
    assert value.ndim == 0 and torch.isfinite(value)
    torch.testing.assert_close(loss(flat.reshape(3, 8))["loss_world_model"], value)
    value.backward()
    assert loss.world_model.head.weight.grad.abs().sum() > 0


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
    ae = ReconstructionUncertainty(3, 2, window=4, hidden_size=8)
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
