"""Population fits: R members trained as one batch equal R separate fits."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.fitting import fit_population, fit_uncertainty, fit_world_model
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty

N, M = 3, 2
FIT = dict(steps=12, eval_every=3, val_batches=2, progress=False)


def _buffer(seed: int, slice_len: int = 8) -> object:
    """A damped linear system driven by random actions (4 trajectories of 30 steps)."""
    g = torch.Generator().manual_seed(seed)
    act = torch.rand(4, 30, M, generator=g) * 2 - 1
    obs = torch.empty(4, 31, N)
    obs[:, 0] = torch.randn(4, N, generator=g)
    for t in range(30):
        obs[:, t + 1] = 0.9 * obs[:, t] + 0.3 * torch.cat([act[:, t], act[:, t, :1]], -1)
    data = TensorDict(
        {
            "observation": obs[:, :-1],
            "action": act,
            ("next", "observation"): obs[:, 1:],
            ("collector", "traj_ids"): torch.arange(4)[:, None].expand(4, 30),
        },
        [4, 30],
    ).reshape(-1)
    rb = make_sequence_buffer(200, slice_len=slice_len, num_slices=4)
    rb.extend(data)
    return rb


def _world(seed: int) -> LSTMWorldModel:
    torch.manual_seed(100 + seed)
    return LSTMWorldModel(N, M, window=4, hidden_size=8, dense_size=8)


def _estimator(seed: int) -> ReconstructionUncertainty:
    torch.manual_seed(200 + seed)
    return ReconstructionUncertainty(N, M, window=4, hidden_size=8)


def _same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(
        torch.equal(x, y)
        for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True)
    )


@pytest.mark.parametrize("kind", ["world_model", "uncertainty"])
def test_one_member_is_bitwise_the_single_fit(kind):
    make, fit = (
        (_world, fit_world_model) if kind == "world_model" else (_estimator, fit_uncertainty)
    )
    ref_model, pop_model = make(0), make(0)
    kwargs = dict(FIT, weight_decay=1e-3, clip_norm=0.5, patience=2)
    ref = fit(ref_model, _buffer(0), val_buffer=_buffer(1), seed=7, **kwargs)
    (got,) = fit_population([pop_model], _buffer(0), val_buffers=[_buffer(1)], seeds=[7], **kwargs)
    assert got == ref
    assert _same(pop_model, ref_model)


@pytest.mark.parametrize("kind", ["world_model", "uncertainty"])
def test_members_follow_their_separate_fits(kind):
    """Own init, own data order (seed) and own buffer per member; clip_norm per member."""
    make, fit = (
        (_world, fit_world_model) if kind == "world_model" else (_estimator, fit_uncertainty)
    )
    seeds = [3, 4, 5]
    buffers = [_buffer(0), _buffer(0), _buffer(2)]  # two arms' data in one fit
    kwargs = dict(FIT, clip_norm=0.2, patience=None)
    refs, ref_models = [], []
    for i, seed in enumerate(seeds):
        ref_models.append(make(i))
        refs.append(fit(ref_models[-1], buffers[i], val_buffer=_buffer(9), seed=seed, **kwargs))
    models = [make(i) for i in range(3)]
    results = fit_population(models, buffers, val_buffers=_buffer(9), seeds=seeds, **kwargs)
    for got, ref, model, ref_model in zip(results, refs, models, ref_models, strict=True):
        assert got.steps == ref.steps == 12
        for a, b in zip(got.history, ref.history, strict=True):
            assert a["val_loss"] == pytest.approx(b["val_loss"], rel=1e-4, abs=1e-6)
        torch.testing.assert_close(model.state_dict(), ref_model.state_dict(), rtol=1e-3, atol=1e-4)
    assert len({r.best_val_loss for r in results}) == 3  # the members differ


def test_each_member_stops_on_its_own_and_keeps_its_best_weights():
    seeds = [0, 1]
    models = [_world(0), _world(1)]
    refs = []
    # member 0 with patience 1 on a noisy tiny fit stops early; compare with the separate fits.
    kwargs = dict(steps=30, eval_every=2, val_batches=1, progress=False, lr=3e-2, patience=1)
    for i, seed in enumerate(seeds):
        ref_model = _world(i)
        refs.append((fit_world_model(ref_model, _buffer(i), seed=seed, **kwargs), ref_model))
    results = fit_population(models, [_buffer(0), _buffer(1)], seeds=seeds, **kwargs)
    for got, (ref, ref_model), model in zip(results, refs, models, strict=True):
        assert got.steps == ref.steps
        assert [h["step"] for h in got.history] == [h["step"] for h in ref.history]
        assert got.best_val_loss == pytest.approx(ref.best_val_loss, rel=1e-4)
        best = min(h["val_loss"] for h in got.history)
        assert got.best_val_loss == best
        torch.testing.assert_close(model.state_dict(), ref_model.state_dict(), rtol=1e-3, atol=1e-4)
    assert len({r.steps for r in results}) == 2, [r.steps for r in results]  # stopped apart


def test_population_fit_errors_name_what_to_fix():
    rb = _buffer(0)
    with pytest.raises(ValueError, match=r"seeds has 1 entries; expected one per member \(2\)"):
        fit_population([_world(0), _world(1)], rb, seeds=[0], **FIT)
    with pytest.raises(ValueError, match="buffers has 1 entries"):
        fit_population([_world(0), _world(1)], [rb], **FIT)
    with pytest.raises(ValueError, match="one shape"):
        fit_population([_world(0), _world(1)], [rb, _buffer(1, slice_len=9)], **FIT)
    with pytest.raises(ValueError, match="share one config"):
        fit_population([_world(0), LSTMWorldModel(N, M, window=4)], rb, **FIT)
    stacked = LSTMWorldModel(N, M, window=4, num_members=2)
    with pytest.raises(ValueError, match=r"fits one model; this one has num_members=2"):
        fit_world_model(stacked, rb, **FIT)
    with pytest.raises(ValueError, match=r"models \[1\] hold several .* split\(\)"):
        fit_population([_world(0), stacked], rb, fit_normalization=False, **FIT)
    assert math.isfinite(fit_population([_world(0)], rb, **FIT)[0].best_val_loss)


def test_shared_sampling_is_statistically_the_separate_fits():
    """One sample per step split among the members: same-init members still see other data."""
    kwargs = dict(steps=30, eval_every=10, val_batches=2, progress=False, patience=None)
    refs = [
        fit_world_model(_world(0), _buffer(0), val_buffer=_buffer(9), seed=s, **kwargs)
        for s in range(4)
    ]
    models = [_world(0) for _ in range(4)]
    results = fit_population(
        models, _buffer(0), val_buffers=_buffer(9), seeds=range(4), shared_sampling=True, **kwargs
    )
    assert all(r.steps == 30 for r in results)
    weights = [m.lstm.weight_hh_l0 for m in models]
    assert all(not torch.equal(weights[0], w) for w in weights[1:])  # other batches, other fits
    shared = torch.tensor([r.best_val_loss for r in results])
    separate = torch.tensor([r.best_val_loss for r in refs])
    spread = max(shared.std(), separate.std()) + 1e-3
    assert (shared.mean() - separate.mean()).abs() <= 3 * spread, (shared, separate)
    assert all(r.best_val_loss <= r.history[0]["val_loss"] for r in results)


def test_shared_sampling_follows_each_member_in_any_order():
    """Members sharing a buffer draw one sample seeded by the first of them, whatever the order
    of the members: a member's fit is the same with its buffer's members interleaved with
    another buffer's, and with members that stopped early (patience 1) among them."""
    a, b = _buffer(0), _buffer(1)
    kwargs = dict(steps=24, eval_every=3, val_batches=2, progress=False, patience=1)

    def fit(order: list[int]) -> dict[int, float]:
        buffers = [a, a, b, b]
        models = [_world(i) for i in order]
        results = fit_population(
            models,
            [buffers[i] for i in order],
            seeds=[10 + i for i in order],
            shared_sampling=True,
            **kwargs,
        )
        return {i: r.best_val_loss for i, r in zip(order, results, strict=True)}

    grouped, interleaved = fit([0, 1, 2, 3]), fit([0, 2, 1, 3])
    assert interleaved == pytest.approx(grouped, rel=1e-6, abs=0)
    assert len(set(grouped.values())) == 4


def test_population_errors_are_each_members_multi_step_errors():
    """One batched rollout of all members gives each member's own ``multi_step_errors``."""
    from torchrl_recon.evaluation import multi_step_errors, population_multi_step_errors

    models = [_world(i) for i in range(3)]
    g = torch.Generator().manual_seed(0)
    td = TensorDict(
        {
            "observation": torch.randn(5, 12, N, generator=g),
            "action": torch.rand(5, 12, M, generator=g),
            ("next", "observation"): torch.randn(5, 12, N, generator=g),
        },
        [5, 12],
    )
    scale = torch.rand(N, generator=g) + 0.5
    together = population_multi_step_errors(
        LSTMWorldModel.from_members(models), td, window=4, scale=scale
    )
    assert together.shape == (3, 5, 8)
    for r, model in enumerate(models):
        alone = multi_step_errors(model, td, window=4, scale=scale)
        torch.testing.assert_close(together[r], alone, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="L > window=12"):
        population_multi_step_errors(LSTMWorldModel.from_members(models), td, window=12)


def test_fit_world_members_fits_each_member_as_its_own_fit():
    """fit_world_members on a stacked model: member r as fit_world_model(seed=seed + r) on a
    copy of it, up to float rounding; the result's loss is the members' mean."""
    from torchrl_recon.fitting import fit_world_members

    rb = _buffer(0)
    torch.manual_seed(0)
    stacked = LSTMWorldModel(N, M, window=4, hidden_size=8, dense_size=8, num_members=2)
    copies = stacked.split()
    result = fit_world_members(stacked, rb, seed=7, steps=12, eval_every=4, progress=False)
    singles = [
        fit_world_model(m, rb, seed=7 + r, steps=12, eval_every=4, progress=False)
        for r, m in enumerate(copies)
    ]
    for fitted, single in zip(stacked.split(), copies, strict=True):
        for a, b in zip(fitted.parameters(), single.parameters(), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    mean = sum(s.best_val_loss for s in singles) / 2
    assert result.best_val_loss == pytest.approx(mean, rel=1e-4)
    with pytest.raises(ValueError, match="num_members"):
        fit_world_members(copies[0], rb, steps=2, progress=False)
