"""``fit_population(cuda_graph=True)`` on the CPU: the captured step's own logic, without a graph.

A CUDA graph needs a GPU (``tests/test_device.py`` captures one there). Off CUDA,
:class:`~torchrl_recon.fitting.fit_graph.CapturedStep` runs its step eagerly, so with the
device check lifted the graph-mode loop runs here as it does on a GPU around the capture: the
whole step in one call (backward and Adam before the loss check), Adam with a tensor learning
rate, the stopped members restored by a mask inside the step. These tests pin that loop to the
eager fit, and check that the step asks nothing of the host (a host read fails a capture).
"""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torch.utils._python_dispatch import TorchDispatchMode

import torchrl_recon.fitting.fit as fit_module
import torchrl_recon.modules.checks as checks
from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.fitting import fit_population
from torchrl_recon.fitting.fit_graph import (
    CapturedStep,
    capturable_adam,
    check_cuda_graph,
    restore_frozen,
)
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty

# ATen ops that read a tensor's value on the host (item, bool(), nonzero's size) or copy a
# host value into a new tensor (torch.tensor(...): a host-to-device copy on a GPU).
HOST_SYNC_OPS = {
    "aten._local_scalar_dense.default",
    "aten.item.default",
    "aten.is_nonzero.default",
    "aten.nonzero.default",
    "aten.equal.default",
    "aten.lift_fresh.default",
}


class HostSyncs(TorchDispatchMode):
    """Records every op of :data:`HOST_SYNC_OPS` run inside it."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if str(func) in HOST_SYNC_OPS:
            self.seen.append(str(func))
        return func(*args, **(kwargs or {}))


def _buffer(steps: int = 120, episode: int = 30, pad_short: bool = False):
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(steps, 2, generator=g).cumsum(0)
    rb = make_sequence_buffer(2 * steps, slice_len=8, num_slices=4, pad_short=pad_short)
    rb.extend(
        TensorDict(
            {
                "observation": obs,
                "action": torch.rand(steps, 1, generator=g) * 2 - 1,
                ("next", "observation"): obs + 0.1,
                ("collector", "traj_ids"): torch.arange(steps) // episode,
            },
            [steps],
        )
    )
    return rb


def _models(kind: str, count: int) -> list:
    torch.manual_seed(0)
    if kind == "world":
        return [LSTMWorldModel(2, 1, window=4, hidden_size=8, dense_size=8) for _ in range(count)]
    return [ReconstructionUncertainty(2, 1, window=4) for _ in range(count)]


@pytest.fixture
def graph_off_cuda(monkeypatch):
    """Let ``cuda_graph=True`` run on the CPU (its step eager there, see the module docstring)."""
    monkeypatch.setattr(fit_module, "check_cuda_graph", lambda *args: None)


@pytest.mark.parametrize("shared", [False, True], ids=["own-samples", "shared-sampling"])
@pytest.mark.parametrize("kind", ["world", "uncertainty"])
def test_graph_mode_fit_is_the_eager_fit(graph_off_cuda, kind, shared):
    """Same stops, same best losses and weights within float32 rounding (a tensor learning rate
    rounds as float32), with members stopping at different steps (lr 0.05, patience 1)."""
    fit = dict(steps=40, eval_every=2, patience=1, lr=0.05, progress=False, shared_sampling=shared)
    models = _models(kind, 3)
    eager, graphed = copy.deepcopy(models), copy.deepcopy(models)
    a = fit_population(eager, _buffer(), **fit)
    b = fit_population(graphed, _buffer(), cuda_graph=True, **fit)
    assert [r.steps for r in b] == [r.steps for r in a]
    assert len({r.steps for r in a}) > 1 or min(r.steps for r in a) < 40, "no member stopped"
    for x, y in zip(a, b, strict=True):
        assert y.best_val_loss == pytest.approx(x.best_val_loss, rel=1e-5)
    for m, n in zip(eager, graphed, strict=True):
        for (key, p), q in zip(m.state_dict().items(), n.state_dict().values(), strict=True):
            torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6, msg=key)


def test_one_model_in_graph_mode_is_its_eager_fit(graph_off_cuda):
    """R = 1: the single model's loss module inside the step."""
    fit = dict(steps=12, eval_every=4, progress=False)
    models = _models("world", 1)
    eager, graphed = copy.deepcopy(models), copy.deepcopy(models)
    a = fit_population(eager, _buffer(), **fit)[0]
    b = fit_population(graphed, _buffer(), cuda_graph=True, **fit)[0]
    assert b.best_val_loss == pytest.approx(a.best_val_loss, rel=1e-5)


@pytest.mark.parametrize(
    "kind, count, pad_short",
    [("world", 3, False), ("world", 3, True), ("world", 1, False), ("uncertainty", 3, True)],
)
def test_the_captured_step_never_reads_a_tensor_on_the_host(
    graph_off_cuda, monkeypatch, kind, count, pad_short
):
    """The step as it is captured (value checks off, as while capturing) runs no op that reads
    a value on the host: forward, the hand-written LSTM backward, the per-member clip and the
    stopped members' restore. The optimiser here is SGD: on a GPU the step's Adam is torch's
    ``capturable`` one, and the CPU's non-capturable Adam reads its step count on the host."""
    # the parts ask checks.in_graph(), which asks this: one patch turns every value check off
    monkeypatch.setattr(checks, "capturing_cuda_graph", lambda: True)
    monkeypatch.setattr(
        fit_module,
        "capturable_adam",
        lambda params, lr, weight_decay: torch.optim.SGD(params, lr=lr),
    )
    probes: list[HostSyncs] = []

    class Probed(CapturedStep):
        def __call__(self, inputs):
            probes.append(HostSyncs())
            with probes[-1]:
                return super().__call__(inputs)

    monkeypatch.setattr(fit_module, "CapturedStep", Probed)
    rb = _buffer(episode=6, pad_short=True) if pad_short else _buffer()
    fit_population(_models(kind, count), rb, steps=3, eval_every=3, progress=False, cuda_graph=True)
    assert len(probes) == 3
    assert [p.seen for p in probes] == [[], [], []]


def test_the_probe_sees_a_host_read():
    """The probe above can fail: a value check reads the host."""
    with HostSyncs() as probe:
        checks.check_finite("x", torch.zeros(3))
    assert probe.seen


def test_a_scheduler_writes_the_captured_learning_rate_in_place():
    """The graph reads the learning-rate tensor Adam was built with: the schedule must change
    that tensor, not put a new one in its place, and follow the float schedule."""
    p = torch.nn.Parameter(torch.zeros(2))
    optimizer = capturable_adam([p], 1e-2, 0.0)
    lr = optimizer.param_groups[0]["lr"]
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, 10, eta_min=5e-4)
    floats = torch.optim.lr_scheduler.CosineAnnealingLR(
        torch.optim.Adam([torch.nn.Parameter(torch.zeros(2))], lr=1e-2), 10, eta_min=5e-4
    )
    for _ in range(5):
        p.grad = torch.ones(2)
        optimizer.step()
        schedule.step()
        floats.optimizer.step()
        floats.step()
    assert optimizer.param_groups[0]["lr"] is lr
    assert float(lr) == pytest.approx(floats.get_last_lr()[0], rel=1e-6)
    assert float(lr) < 1e-2


def test_restore_frozen_is_the_indexed_restore():
    state = {"w": torch.randn(4, 3, 2), "fitted": torch.tensor([True, False, True, False])}
    best = {"w": torch.randn(4, 3, 2), "fitted": torch.tensor([False, True, False, True])}
    expected = {k: v.clone() for k, v in state.items()}
    for k in expected:
        expected[k][[1, 3]] = best[k][[1, 3]]
    restore_frozen(state, best, torch.tensor([False, True, False, True]))
    for k, v in expected.items():
        assert torch.equal(state[k], v), k


def test_cuda_graph_is_refused_off_cuda_and_beside_compile():
    with pytest.raises(ValueError, match="must be on a CUDA device, got cpu"):
        fit_population(_models("world", 2), _buffer(), steps=2, progress=False, cuda_graph=True)
    with pytest.raises(TypeError, match="cuda_graph must be True or False, got 'yes'"):
        fit_population(_models("world", 2), _buffer(), steps=2, progress=False, cuda_graph="yes")
    with pytest.raises(ValueError, match="pick one"):
        check_cuda_graph(True, torch.device("cuda"), compile=True)
    check_cuda_graph(True, torch.device("cuda", 1), compile=False)
    check_cuda_graph(False, torch.device("cpu"), compile=True)


def test_a_captured_step_off_cuda_runs_eagerly_every_call():
    calls = []
    step = CapturedStep(lambda td: calls.append(1) or td["x"].sum(), torch.device("cpu"))
    for value in (1.0, 2.0, 3.0):
        assert float(step(TensorDict(x=torch.full((2,), value)))) == 2 * value
    assert len(calls) == 3 and step.graph is None and step.replays == 0


def test_graph_mode_makes_its_tensors_where_the_models_are(graph_off_cuda):
    """Under ``torch.device("meta")`` a tensor made without the models' device (the frozen
    mask, Adam's learning rate) would be a meta tensor: the fit would fail or change."""
    fit = dict(steps=8, eval_every=2, patience=1, lr=0.05, progress=False, shared_sampling=True)
    plain, under_meta = _models("world", 3), _models("world", 3)
    buffers = _buffer(), _buffer()
    a = fit_population(plain, buffers[0], cuda_graph=True, **fit)
    with torch.device("meta"):
        b = fit_population(under_meta, buffers[1], cuda_graph=True, **fit)
    assert [r.history for r in b] == [r.history for r in a]
    for m, n in zip(plain, under_meta, strict=True):
        for p, q in zip(m.parameters(), n.parameters(), strict=True):
            assert q.device.type == "cpu" and torch.equal(p, q)
