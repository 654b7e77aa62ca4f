"""NaN or inf in the data: one line naming the key and its first row, before any fit, at a
refit, where a Trainer's hooks first see a batch; a diverged loss's message ends in one stop."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.fitting import fit_population, fit_uncertainty, fit_world_model
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty, unfitted_normalizers
from torchrl_recon.trainers import FitNormalization, IterationCollector, LogIteration
from torchrl_recon.trainers.collector import check_batch

FIT = dict(steps=4, eval_every=2, progress=False)


def _data(bad_key=None, row: int = 13, value: float = float("nan")) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(40, 3, generator=g)
    td = TensorDict(
        {
            "observation": obs,
            "action": torch.rand(40, 2, generator=g),
            ("next", "observation"): 0.9 * obs,
            ("next", "reward"): torch.zeros(40, 1),
            ("next", "done"): (torch.arange(40) % 20 == 19)[:, None],
            ("collector", "traj_ids"): torch.arange(40) // 20,
        },
        [40],
    )
    if bad_key is not None:
        td[bad_key][row, 1 if td[bad_key].shape[-1] > 1 else 0] = value
    return td


def _buffer(data: TensorDict):
    rb = make_sequence_buffer(100, slice_len=8, num_slices=4)
    rb.extend(data)
    return rb


def _world() -> LSTMWorldModel:
    return LSTMWorldModel(3, 2, window=4, hidden_size=8, dense_size=8)


@pytest.mark.parametrize(
    "key, shown",
    [
        ("observation", "'observation'"),
        ("action", "'action'"),
        (("next", "observation"), r"\('next', 'observation'\)"),
    ],
)
def test_a_first_fit_names_the_key_and_row_and_fits_nothing(key, shown):
    model = _world()
    with pytest.raises(ValueError) as info:
        fit_world_model(model, _buffer(_data(key)), **FIT)
    message = str(info.value)
    assert message.startswith(f"{key!r} in the replay buffer holds NaN or inf (first at row 13")
    assert "\n" not in message and "clean the data first" in message
    assert unfitted_normalizers(model) == ["obs_norm", "action_norm", "delta_norm"]  # untouched
    if key != ("next", "observation"):  # an estimator reads no next observation
        with pytest.raises(ValueError, match=rf"^{shown} in the replay buffer holds NaN or inf"):
            fit_uncertainty(ReconstructionUncertainty(3, 2, window=4), _buffer(_data(key)), **FIT)
        with pytest.raises(ValueError, match=rf"^{shown} in the replay buffer holds NaN or inf"):
            fit_population([_world(), _world()], _buffer(_data(key)), **FIT)
    else:  # the estimator's fit does not read it: it runs
        fit_uncertainty(ReconstructionUncertainty(3, 2, window=4), _buffer(_data(key)), **FIT)


def test_inf_is_named_as_nan_is():
    with pytest.raises(ValueError, match=r"^'action' in the replay buffer holds NaN or inf"):
        fit_world_model(_world(), _buffer(_data("action", value=float("inf"))), **FIT)


@pytest.mark.parametrize("key", ["observation", "action"])
def test_a_refit_on_bad_data_names_the_key_and_the_buffer_row_in_one_sentence(key):
    model = _world()
    fit_world_model(model, _buffer(_data()), **FIT)
    bad = _data()
    bad[key][:] = float("nan")  # every sampled row: the first step meets it
    with pytest.raises(ValueError) as info:
        fit_world_model(model, _buffer(bad), fit_normalization=False, **FIT)
    message = str(info.value)
    assert message.startswith(f"Training stopped at step 1: {key!r} in the replay buffer holds NaN")
    assert ".." not in message and message.endswith(".")


def test_a_loss_that_diverges_on_finite_data_ends_in_one_full_stop():
    model = _world()
    rb = _buffer(_data())
    fit_world_model(model, rb, **FIT)

    def explode(module, inputs, output):  # the LSTM's state turns inf: the loss is not finite
        out, (h, c) = output
        return out, (h * float("inf"), c)

    handle = model.lstm.register_forward_hook(explode)
    try:
        with pytest.raises(FloatingPointError) as info:
            fit_world_model(model, rb, fit_normalization=False, **FIT)
    finally:
        handle.remove()
    message = str(info.value)
    assert message.startswith("Training stopped at step 1: world-model loss is ")
    assert message.endswith("check the data and the learning rate.") and ".." not in message


def test_the_estimators_own_fit_names_the_argument_and_index():
    obs = torch.randn(10, 3)
    obs[4, 2] = float("nan")
    with pytest.raises(ValueError, match=r"^obs contains NaN or inf \(first at index \[4, 2\]\)"):
        ReconstructionUncertainty(3, 2, window=4).fit_normalization(obs, torch.rand(10, 2))
    with pytest.raises(ValueError, match=r"^obs \(10, 3\) and action \(9, 2\) disagree"):
        ReconstructionUncertainty(3, 2, window=4).fit_normalization(
            torch.rand(10, 3), torch.rand(9, 2)
        )


def test_fit_normalization_hook_names_the_key_and_the_batch_index():
    batch = _data(("next", "observation"), row=13).reshape(2, 20)  # [envs, steps]
    world = _world()
    with pytest.raises(
        ValueError,
        match=r"^\('next', 'observation'\) in the collected batch holds NaN or inf \(first at row \[0, 13\], feature 1\)",
    ):
        FitNormalization(world)(batch)
    assert unfitted_normalizers(world)


def test_a_nan_reward_is_refused_where_the_online_hooks_first_see_the_batch():
    batch = _data(("next", "reward"), row=7)
    match = r"^\('next', 'reward'\) in the collected batch holds NaN or inf \(first at row 7, feature 0\); the env returned it"
    with pytest.raises(ValueError, match=match):
        check_batch(batch)
    with pytest.raises(ValueError, match=match):
        LogIteration(_world(), slice_len=8).before_fit(batch)


def test_the_online_collector_refuses_a_batch_with_a_nan_reward_before_the_trainer_sees_it():
    class NaNRewards(IterationCollector):  # an online collector whose env returns a NaN reward
        def collect_iteration(self, iteration: int) -> TensorDict:
            self.batch_info = dict(iteration=iteration, policy="random")
            return _data(("next", "reward"), row=3)

    collector = NaNRewards(iterations=0, steps_per_iteration=20, random_steps=40)
    with pytest.raises(ValueError, match=r"^\('next', 'reward'\) in iteration 0's batch holds NaN"):
        next(iter(collector))
