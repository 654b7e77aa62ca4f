"""Replay-buffer helpers: whole-episode splits and windows that never cross an episode end."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_recon.data import (
    GatherTensorStorage,
    buffer_contents,
    cut_sequences,
    load_buffer,
    make_sequence_buffer,
    save_buffer,
    split_by_trajectory,
)
from torchrl_recon.data.buffers import TRAJ_KEY

LENGTHS = (9, 14, 6, 21, 11, 7, 16, 8, 12, 10)  # episode lengths, all different


def _episodes(lengths=LENGTHS) -> TensorDict:
    """Flat transitions of consecutive episodes: trajectory id and the time step inside it."""
    ids = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    t = torch.cat([torch.arange(n) for n in lengths])
    return TensorDict(
        {"t": t, "observation": torch.randn(len(ids), 2), ("collector", "traj_ids"): ids},
        [len(ids)],
    )


def test_split_by_trajectory_keeps_whole_episodes_together():
    data = _episodes()
    train, val = split_by_trajectory(data, 0.3, seed=0)
    train_ids = set(train["collector", "traj_ids"].tolist())
    val_ids = set(val["collector", "traj_ids"].tolist())
    assert train_ids.isdisjoint(val_ids) and train_ids | val_ids == set(range(len(LENGTHS)))
    assert len(val_ids) == 3  # round(0.3 * 10) whole episodes
    for part, ids in ((train, train_ids), (val, val_ids)):
        assert len(part) == sum(LENGTHS[i] for i in ids)  # every step of each episode
        for i in ids:  # in time order, as stored
            steps = part["t"][part["collector", "traj_ids"] == i]
            assert steps.tolist() == list(range(LENGTHS[i]))
    assert len(train) + len(val) == len(data)


def test_split_by_trajectory_depends_on_the_seed_only():
    data = _episodes()

    def val_ids(seed: int) -> set[int]:
        return set(split_by_trajectory(data, 0.3, seed=seed)[1]["collector", "traj_ids"].tolist())

    torch.manual_seed(0)
    first = val_ids(1)
    torch.manual_seed(123)  # the global RNG plays no part
    assert val_ids(1) == first
    assert len({frozenset(val_ids(seed)) for seed in range(6)}) > 1


def test_split_by_trajectory_takes_at_least_one_episode_and_checks_its_input():
    data = _episodes((5, 5, 5))
    assert (
        len(set(split_by_trajectory(data, 0.01, seed=0)[1]["collector", "traj_ids"].tolist())) == 1
    )
    train, val = split_by_trajectory(_episodes((4, 6)), 0.5, seed=0)  # two episodes: one each
    assert {len(train), len(val)} == {4, 6}
    for bad in (0.0, 1.0, -0.2, 1.5):
        with pytest.raises(ValueError, match=f"val_fraction must be in \\(0, 1\\), got {bad}"):
            split_by_trajectory(data, bad, seed=0)
    with pytest.raises(ValueError, match="at least 2 trajectories to split, got 1"):
        split_by_trajectory(_episodes((8,)), 0.5, seed=0)


def test_sampled_windows_never_cross_an_episode_end():
    slice_len, num_slices = 8, 16
    rb = make_sequence_buffer(1000, slice_len=slice_len, num_slices=num_slices)
    rb.extend(_episodes(LENGTHS + (3,)))  # one episode shorter than a window: never sampled
    torch.manual_seed(0)
    starts = set()
    for _ in range(30):
        batch = rb.sample()
        assert batch.shape == (slice_len * num_slices,)
        windows = batch.reshape(num_slices, slice_len)
        ids, t = windows["collector", "traj_ids"], windows["t"]
        assert (ids == ids[:, :1]).all()  # one episode per window
        assert (t[:, 1:] - t[:, :-1] == 1).all()  # consecutive steps of it
        assert (ids != len(LENGTHS)).all()
        starts |= {(int(i), int(s)) for i, s in zip(ids[:, 0], t[:, 0], strict=True)}
    # windows start anywhere an 8-step window fits, including at t = 0 and at the last fit
    assert (3, 0) in starts and (3, LENGTHS[3] - slice_len) in starts


def test_windows_follow_a_custom_trajectory_key():
    data = _episodes()
    data["run_id"] = data["collector", "traj_ids"]
    del data["collector"]
    rb = make_sequence_buffer(1000, slice_len=6, num_slices=32, traj_key="run_id")
    rb.extend(data)
    torch.manual_seed(0)
    windows = rb.sample().reshape(32, 6)
    assert (windows["run_id"] == windows["run_id"][:, :1]).all()
    assert (windows["t"][:, 1:] - windows["t"][:, :-1] == 1).all()


def test_make_sequence_buffer_checks_its_sizes():
    rb = make_sequence_buffer(50, slice_len=4, num_slices=3)
    assert rb.sampler.slice_len == 4 and rb._batch_size == 12
    rb = make_sequence_buffer(1, slice_len=1, num_slices=1)  # the smallest allowed
    rb.extend(_episodes((1,)))
    assert rb.sample().shape == (1,)
    for kwargs in (
        {"max_size": 0, "slice_len": 4, "num_slices": 3},
        {"max_size": 50, "slice_len": 0, "num_slices": 3},
        {"max_size": 50, "slice_len": 4, "num_slices": 0},
    ):
        with pytest.raises(ValueError, match="must be >= 1"):
            make_sequence_buffer(kwargs.pop("max_size"), **kwargs)


def test_buffer_contents_returns_everything_and_refuses_an_empty_buffer():
    rb = make_sequence_buffer(100, slice_len=2, num_slices=1)
    with pytest.raises(ValueError, match="^The replay buffer is empty; collect data"):
        buffer_contents(rb)
    data = _episodes((4, 6))
    rb.extend(data)
    torch.testing.assert_close(buffer_contents(rb)["observation"], data["observation"])


def test_cut_sequences_stays_inside_each_episode():
    data = _episodes((9, 4, 2, 8))
    cut = cut_sequences(data, 4)
    assert cut.shape == (2 + 1 + 0 + 2, 4)
    assert cut["collector", "traj_ids"][:, 0].tolist() == [0, 0, 1, 3, 3]
    assert cut["t"].tolist() == [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 2, 3]] + [
        [0, 1, 2, 3],
        [4, 5, 6, 7],
    ]
    assert cut_sequences(data, 1)["t"].shape == (len(data), 1)
    with pytest.raises(ValueError, match="length must be >= 1, got 0"):
        cut_sequences(data, 0)
    with pytest.raises(ValueError, match="No trajectory has 10 steps"):
        cut_sequences(data, 10)
    shuffled = data[torch.tensor([0, 9, 1, 2, 3, 4, 5, 6, 7, 8])]
    with pytest.raises(ValueError, match="Trajectory 0 is not contiguous"):
        cut_sequences(shuffled, 2)


def test_saved_buffer_with_a_pickle_is_refused(tmp_path):
    rb = make_sequence_buffer(100, slice_len=2, num_slices=1)
    rb.extend(_episodes((4, 6)))
    save_buffer(rb, tmp_path / "rb")
    (tmp_path / "rb" / "prefetch.pkl").write_bytes(b"not loaded")
    with pytest.raises(
        ValueError, match=f"^{tmp_path / 'rb' / 'prefetch.pkl'}: a pickle .*; refusing"
    ):
        load_buffer(make_sequence_buffer(100, slice_len=2, num_slices=1), tmp_path / "rb")


def test_save_and_load_round_trip_without_a_pickle(tmp_path):
    rb = make_sequence_buffer(100, slice_len=2, num_slices=1)
    data = _episodes((4, 6))
    rb.extend(data)
    target = tmp_path / "nested" / "rb"  # parents are created
    save_buffer(rb, target)
    save_buffer(rb, target)  # saving again over it is fine
    assert (target / "storage").is_dir() and not (target / "prefetch.pkl").exists()
    restored = load_buffer(make_sequence_buffer(100, slice_len=2, num_slices=1), target)
    torch.testing.assert_close(restored[:]["observation"], data["observation"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="No saved replay buffer at .*empty"):
        load_buffer(make_sequence_buffer(10, slice_len=2, num_slices=1), tmp_path / "empty")


def test_buffers_that_prefetch_are_not_saved(tmp_path):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=2, prefetch=2)
    rb.extend(_episodes((4, 6)))
    with pytest.raises(
        ValueError,
        match=r"^save_buffer supports buffers without prefetch only \(prefetch state is pickled\)\.$",
    ):
        save_buffer(rb, tmp_path / "rb")
    assert not (tmp_path / "rb").exists()


def test_gather_storage_samples_the_rows_lazy_tensor_storage_would():
    """Same seed, same windows: the index_select gather changes the speed, not the rows."""
    data = _episodes()
    gather = make_sequence_buffer(500, slice_len=5, num_slices=6)
    plain = TensorDictReplayBuffer(
        storage=LazyTensorStorage(500),
        sampler=type(gather.sampler)(
            slice_len=5, strict_length=True, traj_key=("collector", "traj_ids")
        ),
        batch_size=30,
    )
    assert isinstance(gather.storage, GatherTensorStorage)
    for rb in (gather, plain):
        rb.extend(data)
    for seed in range(3):
        torch.manual_seed(seed)
        a = gather.sample()
        torch.manual_seed(seed)
        b = plain.sample()
        assert (a == b).all()
    storage, t = gather.storage, data["t"]
    rows = torch.tensor([4, 0, 4, len(data) - 1])
    assert (storage.get(rows)["t"] == t[rows]).all()
    assert (storage.get((rows,))["t"] == t[rows]).all()
    assert (storage.get(slice(2, 5))["t"] == t[2:5]).all()  # other indices: LazyTensorStorage's
    assert (storage.get(torch.tensor([-1]))["t"] == t[-1:]).all()
    with pytest.raises(IndexError):
        storage.get(torch.tensor([len(data)]))  # a row past the filled part is refused


def test_the_cached_trajectory_bounds_draw_torchrls_own_slices_and_follow_an_extend():
    """``cache_values=True`` reads the trajectory bounds once per extend: the same slices as
    TorchRL's uncached sampler under the same seed, and trajectories added later are drawn."""
    from torchrl.data import SliceSampler

    ids = torch.arange(60) // 12
    data = TensorDict({"x": torch.arange(60.0), TRAJ_KEY: ids}, [60])
    ours = make_sequence_buffer(200, slice_len=5, num_slices=4)
    plain = TensorDictReplayBuffer(
        storage=LazyTensorStorage(200),
        sampler=SliceSampler(slice_len=5, traj_key=TRAJ_KEY),
        batch_size=20,
    )
    assert ours.sampler.cache_values and not plain.sampler.cache_values
    for rb in (ours, plain):
        rb.extend(data)
    for _ in range(3):
        torch.manual_seed(1)
        a = ours.sample()["x"]
        torch.manual_seed(1)
        assert torch.equal(a, plain.sample()["x"])
    ours.extend(TensorDict({"x": torch.full((12,), -1.0), TRAJ_KEY: torch.full((12,), 9)}, [12]))
    torch.manual_seed(0)
    assert any((ours.sample()["x"] == -1).any() for _ in range(20))
