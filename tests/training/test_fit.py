from __future__ import annotations

import logging

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.record.loggers import CSVLogger
from torchrl.trainers import ReplayBufferTrainer, Trainer

from torchrl_recon.data import load_buffer, make_sequence_buffer, save_buffer, split_by_trajectory
from torchrl_recon.envs import make_env
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss
from torchrl_recon.training import (
    fit_uncertainty,
    fit_world_model,
    load_checkpoint,
    load_modules,
    save_checkpoint,
    train_loss_module,
)

logging.getLogger("torchrl").setLevel(logging.WARNING)


def _synthetic(n_traj: int = 6, length: int = 40) -> TensorDict:
    """A damped linear system driven by random actions, as flat transitions with trajectory ids."""
    g = torch.Generator().manual_seed(0)
    obs, act, nxt, ids = [], [], [], []
    for i in range(n_traj):
        s = torch.randn(3, generator=g)
        for _ in range(length):
            a = torch.rand(2, generator=g) * 2 - 1
            s2 = 0.9 * s + 0.3 * torch.cat([a, a[:1]])
            obs.append(s), act.append(a), nxt.append(s2), ids.append(i)
            s = s2
    return TensorDict(
        {
            "observation": torch.stack(obs),
            "action": torch.stack(act),
            ("next", "observation"): torch.stack(nxt),
            ("collector", "traj_ids"): torch.tensor(ids),
        },
        [len(ids)],
    )


def _buffers(slice_len: int = 12):
    train, val = split_by_trajectory(_synthetic(), 0.34, seed=0)
    rb, vrb = (
        make_sequence_buffer(1000, slice_len=slice_len, num_slices=8),
        make_sequence_buffer(1000, slice_len=slice_len, num_slices=8),
    )
    rb.extend(train), vrb.extend(val)
    return rb, vrb


def test_fit_world_model_reduces_validation_loss_and_is_reproducible(tmp_path):
    rb, vrb = _buffers()
    results = []
    for _ in range(2):
        torch.manual_seed(1)
        model = LSTMWorldModel(3, 2, window=4, hidden_size=16, dense_size=16)
        results.append(
            fit_world_model(
                model, rb, val_buffer=vrb, steps=150, eval_every=50, progress=False, seed=3
            )
        )
    first, second = results
    assert first.history[-1]["val_loss"] < first.history[0]["val_loss"]
    assert [h["val_loss"] for h in first.history] == [h["val_loss"] for h in second.history]


def test_fit_uncertainty_logs_and_checkpoints(tmp_path):
    rb, vrb = _buffers()
    ae = ReconstructionUncertainty(3, 2, window=4, hidden_size=16)
    logger = CSVLogger("fit", log_dir=str(tmp_path))
    ckpt = tmp_path / "ae.pt"
    result = fit_uncertainty(
        ae,
        rb,
        val_buffer=vrb,
        steps=100,
        eval_every=25,
        progress=False,
        logger=logger,
        checkpoint_path=ckpt,
    )
    assert result.best_val_loss < result.history[0]["val_loss"] or len(result.history) == 1
    assert (tmp_path / "fit" / "scalars" / "uncertainty" / "val_loss.csv").exists() or list(
        tmp_path.rglob("*val_loss*")
    )
    loaded = load_modules(ckpt)["uncertainty"]
    x = torch.randn(2, 9, 3), torch.randn(2, 9, 2)
    torch.testing.assert_close(loaded.score(*x), ae.score(*x))


def test_early_stopping_stops_before_steps():
    rb, vrb = _buffers()
    ae = ReconstructionUncertainty(3, 2, window=4, hidden_size=16)
    result = fit_uncertainty(
        ae,
        rb,
        val_buffer=vrb,
        steps=5000,
        eval_every=5,
        patience=2,
        lr=1e-1,
        lr_decay=False,
        progress=False,
    )
    assert result.steps < 5000


def test_non_finite_training_stops_clearly_and_keeps_the_last_good_checkpoint(tmp_path):
    rb, vrb = _buffers()
    model = LSTMWorldModel(3, 2, window=4, hidden_size=16, dense_size=16)
    ckpt = tmp_path / "wm.pt"
    fit_world_model(
        model, rb, val_buffer=vrb, steps=20, eval_every=10, progress=False, checkpoint_path=ckpt
    )
    good = {k: v.clone() for k, v in model.state_dict().items()}

    def explode(
        module, inputs, output
    ):  # the LSTM starts returning inf: the loss becomes non-finite
        out, (h, c) = output
        return out, (h * float("inf"), c)

    handle = model.lstm.register_forward_hook(explode)
    with pytest.raises(FloatingPointError, match="last good checkpoint"):
        fit_world_model(
            model,
            rb,
            val_buffer=vrb,
            fit_normalization=False,
            steps=20,
            eval_every=10,
            progress=False,
            checkpoint_path=ckpt,
        )
    handle.remove()
    restored = load_modules(ckpt)["world_model"]
    for key, value in restored.state_dict().items():
        assert torch.isfinite(value).all()
        torch.testing.assert_close(value, good[key])
    for key, value in model.state_dict().items():  # the model in memory is back to its best weights
        torch.testing.assert_close(value, good[key])


def test_checkpoint_round_trip_and_mismatch(tmp_path):
    model = LSTMWorldModel(3, 2, window=4)
    model.fit_normalization(torch.randn(20, 3), torch.randn(20, 2), torch.randn(20, 3))
    save_checkpoint(tmp_path / "m.pt", {"world_model": model}, extra={"seed": 1})
    other = LSTMWorldModel(3, 2, window=4)
    assert load_checkpoint(tmp_path / "m.pt", {"world_model": other}) == {"seed": 1}
    torch.testing.assert_close(other.obs_norm.loc, model.obs_norm.loc)
    with pytest.raises(ValueError, match="window"):
        load_checkpoint(tmp_path / "m.pt", {"world_model": LSTMWorldModel(3, 2, window=5)})
    with pytest.raises(ValueError, match="obs_dim"):
        load_checkpoint(tmp_path / "m.pt", {"world_model": LSTMWorldModel(4, 2, window=4)})
    with pytest.raises(ValueError, match="ReconstructionUncertainty"):
        load_checkpoint(tmp_path / "m.pt", {"world_model": ReconstructionUncertainty(3, 2)})
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_modules(tmp_path / "missing.pt")
    torch.save({"format": 99}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a torchrl_recon checkpoint"):
        load_modules(tmp_path / "bad.pt")


def test_buffer_save_load_round_trip(tmp_path):
    rb, _ = _buffers()
    save_buffer(rb, tmp_path / "rb")
    assert not (tmp_path / "rb" / "prefetch.pkl").exists()
    restored = load_buffer(make_sequence_buffer(1000, slice_len=12, num_slices=8), tmp_path / "rb")
    assert len(restored) == len(rb)
    torch.testing.assert_close(restored[:]["observation"], rb[:]["observation"])
    with pytest.raises(FileNotFoundError, match="No saved replay buffer"):
        load_buffer(make_sequence_buffer(10, slice_len=2, num_slices=1), tmp_path / "nothing")


def test_empty_buffer_is_a_clear_error():
    with pytest.raises(ValueError, match="empty"):
        fit_world_model(
            LSTMWorldModel(3, 2),
            make_sequence_buffer(10, slice_len=12, num_slices=1),
            progress=False,
        )


@pytest.mark.parametrize("which", ["world_model", "uncertainty"])
def test_losses_train_inside_torchrl_trainer(which):
    torch.manual_seed(0)
    env = make_env("industrial_benchmark", seed=0, max_episode_steps=100)
    first = env.rollout(200, break_when_any_done=False)
    if which == "world_model":
        module = LSTMWorldModel(6, 3, window=8)
        module.fit_normalization(
            first["observation"], first["action"], first["next", "observation"]
        )
        loss = WorldModelPredictionLoss(module, slice_len=16)
    else:
        module = ReconstructionUncertainty(6, 3, window=8)
        module.fit_normalization(first["observation"], first["action"])
        loss = UncertaintyLoss(module, slice_len=16)
    probe = first[:192].reshape(12, 16)
    with torch.no_grad():
        before = sum(v for k, v in loss(probe).items() if k.startswith("loss"))
    collector = Collector(env, policy=None, frames_per_batch=200, total_frames=1200)
    rb = make_sequence_buffer(2000, slice_len=16, num_slices=8)
    trainer = Trainer(
        collector=collector,
        total_frames=1200,
        frame_skip=1,
        optim_steps_per_batch=20,
        loss_module=loss,
        optimizer=torch.optim.Adam(module.parameters(), lr=3e-3),
        progress_bar=False,
        save_trainer_interval=0,
    )
    ReplayBufferTrainer(rb, flatten_tensordicts=True).register(trainer)
    trainer.train()
    with torch.no_grad():
        after = sum(v for k, v in loss(probe).items() if k.startswith("loss"))
    assert len(rb) == 1200
    assert after < before


def test_train_loss_module_argument_checks():
    rb, _ = _buffers()
    with pytest.raises(ValueError, match="steps"):
        train_loss_module(
            UncertaintyLoss(ReconstructionUncertainty(3, 2, window=4), slice_len=12), rb, steps=0
        )


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
