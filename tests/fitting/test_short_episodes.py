"""Training on episodes shorter than a slice: padded slices, masks, and losses that ignore padding."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from tests.normalized import fitted
from torchrl_recon.data import (
    MASK_KEY,
    TRAJ_KEY,
    long_trajectories,
    make_sequence_buffer,
    needs_padding,
    sequence_buffers,
)
from torchrl_recon.fitting import fit_population, fit_uncertainty, fit_world_model
from torchrl_recon.fitting.online import FitSchedule, fit_models
from torchrl_recon.modules import (
    EnsembleUncertainty,
    LSTMWorldModel,
    ReconstructionUncertainty,
    RNDUncertainty,
)
from torchrl_recon.modules.padding import check_prefix_mask, start_at_rest
from torchrl_recon.objectives import UncertaintyLoss, WorldModelPredictionLoss, as_sequences

N, M, WINDOW, SLICE = 3, 1, 4, 8


def episodes(lengths: list[int], seed: int = 0) -> TensorDict:
    """Flat transitions of episodes of the given lengths, one trajectory id each."""
    g = torch.Generator().manual_seed(seed)
    total = sum(lengths)
    obs = torch.randn(total, N, generator=g)
    ids = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    return TensorDict(
        {
            "observation": obs,
            "action": torch.rand(total, M, generator=g) * 2 - 1,
            ("next", "observation"): obs + 0.1 * torch.randn(total, N, generator=g),
            TRAJ_KEY: ids,
        },
        [total],
    )


def padded_batch(lengths: list[int], num_slices: int = 16, seed: int = 0) -> TensorDict:
    data = episodes(lengths, seed)
    rb = make_sequence_buffer(len(data), slice_len=SLICE, num_slices=num_slices, pad_short=True)
    rb.extend(data)
    torch.manual_seed(seed)
    return rb.sample()


def disturb_padding(batch: TensorDict) -> TensorDict:
    """A copy of ``batch`` whose padded steps hold other (large) values."""
    out = batch.clone()
    pad = ~out.get(MASK_KEY)
    for key in ("observation", "action", ("next", "observation")):
        x = out.get(key)
        x[pad] = 1e3 + torch.randn_like(x[pad])
    return out


SHORT = [[1, 2, 3], [2, 5, 7], [3, 3, 12, 2], [4, 9, 1, 6]]


@pytest.mark.parametrize("lengths", SHORT)
def test_padded_slices_mark_real_steps_as_a_prefix(lengths):
    batch = padded_batch(lengths)
    seqs = as_sequences(batch, SLICE)
    mask = seqs.get(MASK_KEY)
    ids = seqs.get(TRAJ_KEY)
    real = mask.sum(-1)
    check_prefix_mask(mask, mask.shape)  # real steps first, then padding
    for row in range(mask.shape[0]):
        n = min(lengths[int(ids[row, 0])], SLICE)
        assert int(real[row]) == n
        # padding repeats the last real step (nothing from another episode)
        assert (ids[row] == ids[row, 0]).all()
        last = seqs["observation"][row, n - 1]
        assert torch.equal(seqs["observation"][row, n:], last.expand(SLICE - n, N))


def test_without_short_episodes_a_padded_buffer_writes_no_mask_and_a_plain_one_never_does():
    long = episodes([10, 12])
    for pad in (True, False):
        rb = make_sequence_buffer(30, slice_len=SLICE, num_slices=4, pad_short=pad)
        rb.extend(long)
        assert MASK_KEY not in rb.sample().keys(True)


@pytest.mark.parametrize("mode", ["multi_step", "one_step"])
@pytest.mark.parametrize("lengths", SHORT)
def test_world_model_loss_ignores_padding(mode, lengths):
    torch.manual_seed(0)
    model = LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8)
    data = episodes(lengths)
    model.fit_normalization(data["observation"], data["action"], data["next", "observation"])
    loss = WorldModelPredictionLoss(model, mode=mode, slice_len=SLICE)
    batch = padded_batch(lengths)
    value = loss(batch)["loss_world_model"]
    assert torch.isfinite(value)
    assert torch.equal(loss(disturb_padding(batch))["loss_world_model"], value)
    value.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize(
    "make",
    [
        lambda: ReconstructionUncertainty(N, M, window=WINDOW),
        lambda: RNDUncertainty(N, M, window=WINDOW),
    ],
)
@pytest.mark.parametrize("lengths", SHORT)
def test_uncertainty_loss_ignores_padding(make, lengths):
    torch.manual_seed(0)
    estimator = make()
    data = episodes(lengths)
    estimator.fit_normalization(data["observation"], data["action"])
    loss = UncertaintyLoss(estimator, slice_len=SLICE)
    batch = padded_batch(lengths)
    value = loss(batch)["loss_uncertainty"]
    assert torch.isfinite(value)
    assert torch.equal(loss(disturb_padding(batch))["loss_uncertainty"], value)


def test_an_all_real_mask_gives_the_unmasked_losses():
    torch.manual_seed(0)
    data = episodes([12, 15, 11])
    rb = make_sequence_buffer(len(data), slice_len=SLICE, num_slices=6)
    rb.extend(data)
    batch = rb.sample()
    masked = batch.clone()
    masked.set(MASK_KEY, torch.ones(len(batch), dtype=torch.bool))
    model = fitted(LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8))
    ae = fitted(ReconstructionUncertainty(N, M, window=WINDOW))  # (unfitted: a loss warns)
    for mode in ("multi_step", "one_step"):
        loss = WorldModelPredictionLoss(model, mode=mode, slice_len=SLICE)
        torch.testing.assert_close(loss(masked), loss(batch))
    loss = UncertaintyLoss(ae, slice_len=SLICE)
    torch.testing.assert_close(loss(masked), loss(batch))


def test_a_two_step_episode_is_predicted_from_a_context_at_rest():
    """The multi-step loss of an episode shorter than the warm-up: the context before its start
    is its first observation and the zero action (MPCPolicy(warmup="plan")'s convention)."""
    torch.manual_seed(0)
    model = fitted(LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8))
    data = episodes([2])
    seq = data.unsqueeze(0)  # [1, 2]
    pad = SLICE - 2
    batch = torch.cat([seq, seq[:, -1:].expand(1, pad)], 1).reshape(-1)
    batch.set(MASK_KEY, torch.arange(SLICE) < 2)
    got = WorldModelPredictionLoss(model, slice_len=SLICE)(batch)["loss_world_model"]
    s0, s1 = data["observation"][0], data["observation"][1]
    ctx_obs = torch.stack([s0] * (WINDOW - 1) + [s0])[None]
    ctx_act = torch.cat([torch.zeros(WINDOW - 1, M), data["action"][:1]])[None]
    pred = model.imagine(ctx_obs, ctx_act, s1[None], data["action"][1:2].view(1, 1, 1, M))[0, 0, 0]
    want = ((pred - data["next", "observation"][1]) / model.obs_norm.scale).pow(2).mean()
    torch.testing.assert_close(got, want)


def test_start_at_rest_leaves_long_rows_alone():
    mask = torch.tensor([[True] * 6, [True] * 5 + [False], [True] * 2 + [False] * 4])
    x = torch.arange(18.0).view(3, 6, 1)
    new_mask, (y,) = start_at_rest(mask, 5, x)
    assert torch.equal(y[:2], x[:2]) and torch.equal(new_mask[:2], mask[:2])
    assert y[2].flatten().tolist() == [12.0, 12.0, 12.0, 12.0, 13.0, 14.0]
    assert new_mask[2].tolist() == [False, False, False, True, True, False]


def test_estimators_without_a_masked_loss_refuse_padded_batches():
    estimator = EnsembleUncertainty(N, M, window=WINDOW, num_members=2)
    with pytest.raises(ValueError, match="EnsembleUncertainty cannot train on padded slices"):
        UncertaintyLoss(estimator, slice_len=SLICE)(padded_batch([2, 3]))


def test_a_bad_mask_is_one_clear_error():
    with pytest.raises(ValueError, match="real step after a padded one"):
        check_prefix_mask(torch.tensor([[True, False, True]]), torch.Size([1, 3]))
    with pytest.raises(ValueError, match="expected \\(2, 3\\)"):
        check_prefix_mask(torch.ones(3, 2, dtype=torch.bool), torch.Size([2, 3]))


def test_padding_needs_trajectory_sampling():
    with pytest.raises(ValueError, match="sampling='trajectory'"):
        make_sequence_buffer(10, slice_len=4, num_slices=2, sampling="step", pad_short=True)


def ended(data: TensorDict, last_ends: bool = True) -> TensorDict:
    """``data`` with ``("next", "done")`` at each episode's last step (the last episode's
    only with ``last_ends``: else it is a piece cut short by the end of a collection)."""
    ids = data[TRAJ_KEY]
    done = torch.cat([ids[1:] != ids[:-1], torch.tensor([last_ends])])
    data["next", "done"] = done.unsqueeze(-1)
    return data


def test_needs_padding_only_where_a_strict_sampler_finds_no_slice():
    """Without ends recorded (or with the rule before 2026-11-29), a part pads only when it
    holds no full window."""
    short, mixed = episodes([3, 4, 2]), episodes([3, 9, 2])
    assert long_trajectories(mixed, SLICE) == 1
    assert needs_padding(SLICE, short) and not needs_padding(SLICE, mixed)
    assert needs_padding(SLICE, mixed, short)
    legacy = "pad_if_no_window"
    assert not needs_padding(SLICE, ended(episodes([3, 9, 2])), short_episodes=legacy)


def test_an_episode_that_ended_short_beside_a_long_one_is_padded_and_drawn():
    """The default keeps an ended short episode (a strict sampler would leave it out: on
    InvertedDoublePendulum-v5 it drew 55 of 229 episodes); a piece cut short by the end of
    the collection alone is not padded (data without terminations sample as before)."""
    mixed = ended(episodes([3, 9, 2]))
    assert needs_padding(SLICE, mixed)
    assert not needs_padding(SLICE, ended(episodes([9, 10, 2]), last_ends=False))
    (rb,) = sequence_buffers((mixed,), slice_len=SLICE, num_slices=32)
    torch.manual_seed(0)
    batch = rb.sample()
    assert set(batch[TRAJ_KEY][batch.get(MASK_KEY)].tolist()) == {0, 1, 2}
    (strict,) = sequence_buffers(
        (mixed,), slice_len=SLICE, num_slices=32, short_episodes="pad_if_no_window"
    )
    assert set(strict.sample()[TRAJ_KEY].tolist()) == {1}
    with pytest.raises(ValueError, match="short_episodes must be one of"):
        needs_padding(SLICE, mixed, short_episodes="drop")
    with pytest.raises(ValueError, match="short_episodes must be one of"):
        FitSchedule(short_episodes="drop")


@pytest.mark.parametrize("lengths", [[2, 3, 5, 4, 3, 6], [1, 7, 3, 2, 5, 4]])
def test_fits_on_short_episodes_normalise_with_the_stored_steps_only(lengths):
    torch.manual_seed(0)
    data = episodes(lengths)
    rb = make_sequence_buffer(len(data), slice_len=SLICE, num_slices=4, pad_short=True)
    rb.extend(data)
    model = LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8)
    result = fit_world_model(model, rb, steps=6, eval_every=3, progress=False)
    assert result.steps == 6 and torch.isfinite(torch.tensor(result.best_val_loss))
    reference = LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8)
    reference.fit_normalization(data["observation"], data["action"], data["next", "observation"])
    for got, want in zip(model.norm_stats(), reference.norm_stats(), strict=True):
        torch.testing.assert_close(got, want)
    ae = ReconstructionUncertainty(N, M, window=WINDOW)
    fit_uncertainty(ae, rb, steps=4, eval_every=2, progress=False)
    ref_ae = ReconstructionUncertainty(N, M, window=WINDOW)
    ref_ae.fit_normalization(data["observation"], data["action"])
    torch.testing.assert_close(ae.input_norm.loc, ref_ae.input_norm.loc)
    torch.testing.assert_close(ae.input_norm.scale, ref_ae.input_norm.scale)


@pytest.mark.parametrize("shared_sampling", [False, True])
def test_population_fits_on_padded_buffers_match_their_single_fits(shared_sampling):
    data = episodes([2, 3, 5, 4, 3, 6, 2])
    rb = make_sequence_buffer(len(data), slice_len=SLICE, num_slices=4, pad_short=True)
    rb.extend(data)
    plain = make_sequence_buffer(len(data), slice_len=SLICE, num_slices=4)
    plain.extend(episodes([12, 14]))  # a member on unpadded data: its batches have no mask
    for make in (
        lambda: LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8),
        lambda: ReconstructionUncertainty(N, M, window=WINDOW, hidden_size=8),
    ):
        torch.manual_seed(0)
        models = [make() for _ in range(3)]
        results = fit_population(
            models,
            [rb, plain, rb],
            steps=4,
            eval_every=2,
            progress=False,
            shared_sampling=shared_sampling,
        )
        assert all(torch.isfinite(torch.tensor(r.best_val_loss)) for r in results)
    if not shared_sampling:  # member 0 is its own fit (up to float rounding)
        torch.manual_seed(0)
        single = LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8)
        torch.manual_seed(0)
        members = [LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8)] + [
            LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8) for _ in range(2)
        ]
        one = fit_world_model(single, rb, steps=4, eval_every=2, progress=False, seed=0)
        many = fit_population(members, [rb, plain, rb], steps=4, eval_every=2, progress=False)
        assert many[0].best_val_loss == pytest.approx(one.best_val_loss, rel=1e-4)


def test_online_fits_pad_when_a_split_has_no_long_episode():
    torch.manual_seed(0)
    data = episodes([3, 4, 2, 5, 3, 6, 2, 4, 3, 5])
    model = LSTMWorldModel(N, M, window=WINDOW, hidden_size=8, dense_size=8)
    ae = ReconstructionUncertainty(N, M, window=WINDOW)
    schedule = FitSchedule(steps=4, eval_every=2, slice_len=SLICE, num_slices=4, val_fraction=0.2)
    losses = fit_models(model, ae, data, schedule, seed=0, warm=False)
    assert set(losses) == {"world_model", "uncertainty"}
    assert all(torch.isfinite(torch.tensor(v)) for v in losses.values())
