from __future__ import annotations

import copy
import logging
import math
import re

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.collectors import Collector
from torchrl.objectives import LossModule
from torchrl.record.loggers import CSVLogger
from torchrl.trainers import ReplayBufferTrainer, Trainer

from torchrl_recon.data import load_buffer, make_sequence_buffer, save_buffer, split_by_trajectory
from torchrl_recon.envs import make_env
from torchrl_recon.fitting import (
    fit_population,
    fit_uncertainty,
    fit_world_model,
    load_checkpoint,
    load_modules,
    save_checkpoint,
    train_loss_module,
)
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss

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
    assert [h["step"] for h in result.history] == [25, 50, 75, 100]
    val_losses = [h["val_loss"] for h in result.history]
    assert result.best_val_loss == min(val_losses)
    assert result.best_val_loss < val_losses[0]
    rows = (tmp_path / "fit" / "scalars" / "uncertainty" / "val_loss.csv").read_text().split()
    assert [int(row.split(",")[0]) for row in rows] == [25, 50, 75, 100]
    logged = [float(row.split(",")[1]) for row in rows]
    assert logged == pytest.approx(val_losses)
    best_step = result.history[val_losses.index(min(val_losses))]["step"]
    extra = load_checkpoint(
        ckpt, {"uncertainty": ReconstructionUncertainty(3, 2, window=4, hidden_size=16)}
    )
    assert extra == {"step": best_step, "val_loss": pytest.approx(result.best_val_loss)}
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


@pytest.mark.parametrize(  # the same Trainer plumbing: the estimator's loss in make test-all
    "which", ["world_model", pytest.param("uncertainty", marks=pytest.mark.slow)]
)
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


class _LinearLoss(LossModule):
    """loss = mean(w * x): with x = 1 the gradient is 1 at every step, so each Adam step moves w
    by exactly lr_t g / (|g| + eps) and the result of training can be computed by hand."""

    def __init__(self, w0: float) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.tensor([w0], dtype=torch.float64))

    def forward(self, td: TensorDict) -> TensorDict:
        x = td["x"].to(torch.float64)
        value = (self.w * x).sum(-1).mean()
        # not a loss: a diagnostic that must not be optimised (its gradient would flip the sign)
        return TensorDict({"loss_linear": value, "diagnostic": -1000.0 * value}, [])


def _ones_buffer():
    rb = make_sequence_buffer(100, slice_len=2, num_slices=2)
    rb.extend(
        TensorDict(
            {"x": torch.ones(20, 1), ("collector", "traj_ids"): torch.arange(20) // 10}, [20]
        )
    )
    return rb


ADAM_EPS = 1e-8


def _train_linear(w0: float = 1.0, **kwargs) -> tuple[float, float]:
    loss = _LinearLoss(w0)
    kwargs = {"eval_every": kwargs.get("steps", 1), "progress": False, **kwargs}
    result = train_loss_module(loss, _ones_buffer(), **kwargs)
    return float(loss.w.detach()), result.best_val_loss


def test_learning_rate_follows_a_cosine_from_lr_to_lr_over_20():
    steps, lr = 40, 0.01
    eta_min = lr / 20
    rates = [
        eta_min + (lr - eta_min) * (1 + math.cos(math.pi * t / steps)) / 2 for t in range(steps)
    ]
    w, best = _train_linear(steps=steps, lr=lr)
    expected = 1.0 - sum(rates) / (1 + ADAM_EPS)
    assert w == pytest.approx(expected, rel=1e-9)
    assert best == pytest.approx(expected, rel=1e-9)  # the final weights are the best ones
    w, _ = _train_linear(steps=steps, lr=lr, lr_decay=False)
    assert w == pytest.approx(1.0 - steps * lr / (1 + ADAM_EPS), rel=1e-9)


def test_clip_norm_clips_the_gradient_before_the_adam_step():
    lr = 0.1
    # Adam is blind to the gradient's scale except through eps: clipping |g| = 1 to 1e-10
    # shrinks the first step from lr to lr * 1e-10 / (1e-10 + eps), about lr / 101.
    w, _ = _train_linear(steps=1, lr=lr, clip_norm=1e-10)
    clipped = 1e-10 / (1.0 + 1e-6)  # torch's clip coefficient max_norm / (norm + 1e-6)
    assert w == pytest.approx(1.0 - lr * clipped / (clipped + ADAM_EPS), rel=1e-9)
    for clip_norm in (None, 10.0):  # no clipping, or a gradient already below the limit
        w, _ = _train_linear(steps=1, lr=lr, clip_norm=clip_norm)
        assert w == pytest.approx(1.0 - lr / (1 + ADAM_EPS), rel=1e-9)


def test_weight_decay_adds_the_l2_gradient():
    lr = 0.1
    # g = 1 + weight_decay * w = 1 + 1.0 * (-2) = -1: the step goes up instead of down
    w, _ = _train_linear(w0=-2.0, steps=1, lr=lr, weight_decay=1.0)
    assert w == pytest.approx(-2.0 + lr / (1 + ADAM_EPS), rel=1e-9)
    w, _ = _train_linear(w0=-2.0, steps=1, lr=lr)
    assert w == pytest.approx(-2.0 - lr / (1 + ADAM_EPS), rel=1e-9)


def test_best_weights_are_restored_at_the_end():
    """Train on x = 1 and validate on x = -1: every step lowers w and so raises the validation
    loss -w; the weights of the first evaluation are the best and are restored."""
    loss = _LinearLoss(1.0)
    rb = make_sequence_buffer(100, slice_len=2, num_slices=2)
    val = make_sequence_buffer(100, slice_len=2, num_slices=2)
    rb.extend(
        TensorDict(
            {"x": torch.ones(20, 1), ("collector", "traj_ids"): torch.arange(20) // 10}, [20]
        )
    )
    val.extend(
        TensorDict(
            {"x": -torch.ones(20, 1), ("collector", "traj_ids"): torch.arange(20) // 10}, [20]
        )
    )
    result = train_loss_module(
        loss,
        rb,
        val_buffer=val,
        steps=30,
        lr=0.1,
        lr_decay=False,
        eval_every=10,
        patience=None,
        progress=False,
    )
    assert [h["step"] for h in result.history] == [10, 20, 30]
    w_at_10 = 1.0 - 10 * 0.1 / (1 + ADAM_EPS)
    assert float(loss.w.detach()) == pytest.approx(w_at_10, rel=1e-9)
    assert result.best_val_loss == pytest.approx(-w_at_10, rel=1e-9)


def test_a_users_loss_that_turns_nan_stops_the_fit_at_its_best_weights():
    """A loss module that returns NaN without raising (a user's, unlike the library's, which
    check their own loss): the one loop checks every member's loss, so one model's fit stops
    at that step with one sentence and its best weights back, as a member's does."""
    loss = _LinearLoss(1.0)
    calls = [0]

    def nan_from_the_7th_step(module, inputs, output):
        calls[0] += 1
        return output.apply(lambda v: v * math.nan) if calls[0] > 6 + 2 else output

    handle = loss.register_forward_hook(nan_from_the_7th_step)  # 6 steps, 2 validations
    fit = dict(steps=20, eval_every=3, val_batches=1, lr=0.1, lr_decay=False, progress=False)
    with pytest.raises(FloatingPointError) as info:
        train_loss_module(loss, _ones_buffer(), **fit)
    handle.remove()
    assert str(info.value) == (
        "Training stopped at step 7: the loss is not finite; check the data and the learning rate."
    )
    assert float(loss.w.detach()) == pytest.approx(1.0 - 6 * 0.1 / (1 + ADAM_EPS), rel=1e-6)


if __name__ == "__main__":
    pytest.main([__file__, "-q"])


@pytest.mark.parametrize(
    ("setting", "error", "message"),
    [
        ({"patience": 0}, ValueError, "patience must be an int >= 1, got 0."),
        ({"patience": -1}, ValueError, "patience must be an int >= 1, got -1."),
        ({"lr": -1.0}, ValueError, "lr must be a finite number > 0, got -1.0."),
        ({"lr": float("nan")}, ValueError, "lr must be a finite number > 0, got nan."),
        (
            {"weight_decay": -0.1},
            ValueError,
            "weight_decay must be a finite number >= 0, got -0.1.",
        ),
        ({"clip_norm": 0.0}, ValueError, "clip_norm must be a finite number > 0, got 0.0."),
        (
            {"clip_norm": float("inf")},
            ValueError,
            "clip_norm must be a finite number > 0, got inf.",
        ),
        ({"lr": "1e-3"}, TypeError, "lr must be a number, got '1e-3'."),
        ({"seed": "a"}, TypeError, "seed must be an int, got 'a'."),
        (
            {"stepz": 3},
            TypeError,
            "got an unexpected keyword argument 'stepz'; the keywords are train_loss_module's.",
        ),
    ],
)
def test_a_fit_setting_out_of_range_is_refused_before_any_step(setting, error, message):
    rb, _ = _buffers()
    model = LSTMWorldModel(3, 2, window=4)
    before = copy.deepcopy(model.state_dict())
    with pytest.raises(error, match=f"^{re.escape(message)}$"):
        fit_world_model(model, rb, steps=2, progress=False, **setting)
    for key, value in model.state_dict().items():  # nothing fitted, not even the normalisation
        assert torch.equal(value, before[key]), key


def test_the_estimators_fit_checks_its_settings_before_its_normalisation():
    rb, _ = _buffers()
    estimator = ReconstructionUncertainty(3, 2, window=4)
    with pytest.raises(ValueError, match=r"^lr must be a finite number > 0, got 0\.0\.$"):
        fit_uncertainty(estimator, rb, steps=2, lr=0.0, progress=False)
    assert not estimator.input_norm.fitted


def test_a_population_fit_refuses_the_same_settings_and_seeds_that_are_not_ints():
    rb, _ = _buffers()
    models = [LSTMWorldModel(3, 2, window=4) for _ in range(2)]
    with pytest.raises(ValueError, match=r"^patience must be an int >= 1, got 0\.$"):
        fit_population(models, rb, steps=2, patience=0, progress=False)
    with pytest.raises(TypeError, match=r"^seeds must be ints, got \[0, 1\.5\]\.$"):
        fit_population(models, rb, seeds=[0, 1.5], steps=2, progress=False)
    results = fit_population(models, rb, seeds=[np.int64(3), 4], steps=2, progress=False)
    assert [r.steps for r in results] == [2, 2]
