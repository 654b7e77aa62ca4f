"""StepUniformSliceSampler: windows of one trajectory each, every window start equally likely."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.data import (
    StepUniformSliceSampler,
    load_buffer,
    make_sequence_buffer,
    save_buffer,
)
from torchrl_recon.experiments.run_dir import config_differences
from torchrl_recon.fitting import fit_world_model
from torchrl_recon.modules import LSTMWorldModel

TRAJ = ("collector", "traj_ids")


def _data(lengths: list[int]) -> TensorDict:
    ids = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    n = ids.numel()
    return TensorDict(
        {
            "observation": torch.randn(n, 2),
            "action": torch.randn(n, 1),
            ("next", "observation"): torch.randn(n, 2),
            "step": torch.arange(n),
            TRAJ: ids,
        },
        [n],
    )


def _windows(rb, slice_len: int) -> tuple[torch.Tensor, torch.Tensor]:
    sample = rb.sample()
    return sample["step"].view(-1, slice_len), sample[TRAJ].view(-1, slice_len)


def test_windows_are_contiguous_and_never_cross_a_trajectory():
    rb = make_sequence_buffer(400, slice_len=10, num_slices=64, sampling="step")
    rb.extend(_data([50, 12, 9, 100, 10]))
    assert isinstance(rb.sampler, StepUniformSliceSampler)
    for _ in range(20):
        steps, ids = _windows(rb, 10)
        assert steps.diff(dim=1).eq(1).all()
        assert ids.eq(ids[:, :1]).all()
        assert not ids.eq(2).any()  # 9 steps: shorter than a window, never drawn


def test_window_starts_are_uniform_over_steps_not_trajectories():
    # one long trajectory (161 window starts) and one short one (6 starts)
    lengths, slice_len = [200, 45], 40
    share = {}
    for sampling in ("step", "trajectory"):
        rb = make_sequence_buffer(300, slice_len=slice_len, num_slices=500, sampling=sampling)
        rb.extend(_data(lengths))
        torch.manual_seed(0)
        ids = torch.cat([_windows(rb, slice_len)[1][:, 0] for _ in range(40)])
        share[sampling] = ids.eq(1).float().mean().item()
    assert share["step"] == pytest.approx(6 / 167, abs=0.01)
    assert share["trajectory"] == pytest.approx(0.5, abs=0.03)


def test_every_window_start_is_drawn_about_equally_often():
    rb = make_sequence_buffer(100, slice_len=5, num_slices=1000, sampling="step")
    rb.extend(_data([30, 20, 14]))
    starts = rb.sampler.window_starts(rb.storage)
    assert starts.tolist() == [*range(0, 26), *range(30, 46), *range(50, 60)]
    torch.manual_seed(0)
    first = torch.cat([_windows(rb, 5)[0][:, 0] for _ in range(50)])
    counts = torch.bincount(first, minlength=64)[starts]
    expected = first.numel() / starts.numel()
    assert counts.sum() == first.numel()  # nothing outside the valid starts
    assert (counts - expected).abs().max() < 5 * expected**0.5  # within ~5 sigma


def test_same_seed_same_windows():
    rb = make_sequence_buffer(200, slice_len=8, num_slices=16, sampling="step")
    rb.extend(_data([60, 70, 40]))
    torch.manual_seed(3)
    a = _windows(rb, 8)[0]
    torch.manual_seed(3)
    b = _windows(rb, 8)[0]
    torch.manual_seed(4)
    c = _windows(rb, 8)[0]
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_bad_input_is_refused_with_a_clear_message():
    with pytest.raises(ValueError, match="sampling must be one of"):
        make_sequence_buffer(10, slice_len=2, num_slices=1, sampling="steps")
    with pytest.raises(ValueError, match="slice_len must be an int >= 1"):
        StepUniformSliceSampler(slice_len=0)
    rb = make_sequence_buffer(50, slice_len=20, num_slices=2, sampling="step")
    rb.extend(_data([10, 15]))
    with pytest.raises(RuntimeError, match="No trajectory in the buffer has slice_len = 20"):
        rb.sample()
    rb = make_sequence_buffer(50, slice_len=5, num_slices=2, sampling="step")
    rb.extend(TensorDict({"x": torch.arange(20.0)}, [20]))
    with pytest.raises(KeyError, match="trajectory ids under"):
        rb.sample()
    rb = make_sequence_buffer(50, slice_len=5, num_slices=2, sampling="step")
    rb.extend(_data([20]))
    with pytest.warns(UserWarning, match="conflicting batch_sizes"):  # TorchRL's, about 7
        with pytest.raises(ValueError, match="not a multiple of slice_len 5"):
            rb.sample(7)


def test_a_saved_buffer_samples_the_same_after_loading(tmp_path):
    rb = make_sequence_buffer(200, slice_len=8, num_slices=16, sampling="step")
    rb.extend(_data([60, 70, 40]))
    save_buffer(rb, tmp_path / "rb")
    loaded = load_buffer(
        make_sequence_buffer(200, slice_len=8, num_slices=16, sampling="step"), tmp_path / "rb"
    )
    torch.manual_seed(1)
    a = _windows(rb, 8)[0]
    torch.manual_seed(1)
    assert torch.equal(a, _windows(loaded, 8)[0])


def test_a_world_model_fits_on_step_uniform_windows():
    torch.manual_seed(0)
    rb = make_sequence_buffer(300, slice_len=8, num_slices=8, sampling="step")
    rb.extend(_data([120, 90, 30]))
    model = LSTMWorldModel(2, 1, window=4, hidden_size=8)
    result = fit_world_model(model, rb, steps=20, eval_every=10, progress=False)
    assert result.steps == 20 and torch.isfinite(torch.tensor(result.best_val_loss))


def test_a_run_made_before_the_key_existed_resumes_at_its_old_behaviour():
    old = {"training": {"slice_len": 40}}
    assert (
        config_differences(old, {"training": {"slice_len": 40, "window_sampling": "trajectory"}})
        == []
    )
    assert config_differences(old, {"training": {"slice_len": 40, "window_sampling": "step"}}) == [
        "training.window_sampling: (absent) -> 'step'"
    ]
