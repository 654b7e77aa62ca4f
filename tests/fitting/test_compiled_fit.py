"""Fits with ``compile=True``: their training steps under ``torch.compile``, the same fit up to
float rounding; refused up front where torch.compile cannot build its kernels.

``make test`` traces the steps with the ``aot_eager`` backend (Dynamo and AOTAutograd, forward
and backward, no C++ build: seconds); Inductor's own build of the same steps (tens of seconds
with a cold cache, as on a fresh machine) runs in ``make test-all``."""

from __future__ import annotations

import pytest
import torch

from tests.compilers import needs_cpp_compiler
from torchrl_recon.data import make_sequence_buffer
from torchrl_recon.devices import check_compile_support
from torchrl_recon.fitting import fit_population, fit_world_model
from torchrl_recon.fitting.fit import COMPILING
from torchrl_recon.modules import LSTMWorldModel

from .test_population_fit import FIT, M, N, _buffer


def _world(seed: int) -> LSTMWorldModel:
    torch.manual_seed(100 + seed)
    return LSTMWorldModel(N, M, window=4, hidden_size=8, dense_size=8)


def _close(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(
        torch.allclose(x, y, rtol=1e-4, atol=1e-6)
        for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True)
    )


@needs_cpp_compiler
def test_a_compiled_fit_is_the_eager_fit_up_to_rounding(compile_backend):
    rb = _buffer(0)
    eager, compiled = _world(0), _world(0)
    a = fit_world_model(eager, rb, seed=1, **FIT)
    b = fit_world_model(compiled, rb, seed=1, compile=True, **FIT)
    assert a.steps == b.steps
    assert b.best_val_loss == pytest.approx(a.best_val_loss, rel=1e-4)
    assert _close(eager, compiled)
    assert not _close(_world(0), compiled)  # it trained


@pytest.mark.slow  # 6 s of compiling; the one-model compiled fit stays
@needs_cpp_compiler
def test_a_compiled_population_fit_is_the_eager_one_up_to_rounding():
    rb = _buffer(0)
    eager, compiled = [_world(r) for r in range(2)], [_world(r) for r in range(2)]
    a = fit_population(eager, rb, shared_sampling=True, **FIT)
    b = fit_population(compiled, rb, shared_sampling=True, compile=True, **FIT)
    for x, y in zip(a, b, strict=True):
        assert y.best_val_loss == pytest.approx(x.best_val_loss, rel=1e-4)
    assert all(_close(x, y) for x, y in zip(eager, compiled, strict=True))


@needs_cpp_compiler
def test_a_compiled_fit_still_stops_on_non_finite_data(compile_backend):
    """NaN inputs: the eager fit's ValueError naming the key and its buffer row (the compiled
    step leaves the input checks out; its non-finite loss has the batch checked as eager)."""
    data = _buffer(0)[:]
    data["observation"][:] = float("nan")  # eager, the world model's input check refuses it
    rb = make_sequence_buffer(200, slice_len=8, num_slices=4)
    rb.extend(data)
    messages = []
    for compile in (False, True):  # the same error as eager: the input named
        named = r"^Training stopped at step 1: 'observation' in the replay buffer holds NaN or inf"
        with pytest.raises(ValueError, match=named) as info:
            fit_population(
                [_world(r) for r in range(2)], rb, fit_normalization=False, compile=compile, **FIT
            )
        messages.append(str(info.value))
        with pytest.raises(ValueError, match=named):
            fit_world_model(_world(0), rb, fit_normalization=False, compile=compile, **FIT)
    assert messages[0] == messages[1]
    diverging = FIT | {"lr": 1e30}  # finite inputs, a loss that blows up: as before
    with pytest.raises(FloatingPointError, match=r"member\(s\) \[0, 1\] is not finite"):
        fit_population([_world(r) for r in range(2)], _buffer(0), compile=True, **diverging)


def test_compile_without_a_cpp_compiler_is_refused_before_any_step(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler++")
    model, untouched = _world(0), _world(0)
    with pytest.raises(RuntimeError, match="'no-such-compiler\\+\\+' is not on PATH"):
        fit_world_model(model, _buffer(0), compile=True, **FIT)  # normalisation untouched too
    assert all(
        torch.equal(x, y)
        for x, y in zip(model.state_dict().values(), untouched.state_dict().values(), strict=True)
    )
    with pytest.raises(RuntimeError, match="not on PATH"):
        fit_population([model, untouched], _buffer(0), compile=True, **FIT)
    check_compile_support("cuda")  # nothing to check off the CPU


# In make test-all: each compiles a fit of its own (tens of seconds with a cold Inductor cache,
# as on a fresh machine); the compiled fits of make test are the two tests above.
@pytest.mark.slow
@needs_cpp_compiler
@pytest.mark.parametrize("population", [False, True])
def test_a_compiled_fits_progress_bar_says_the_first_step_compiles(population, capsys):
    """The cold compile takes tens of seconds on a CPU with the bar at 0: the bar says why."""
    fit = FIT | {"progress": True}
    if population:
        fit_population([_world(r) for r in range(2)], _buffer(0), compile=True, **fit)
    else:
        fit_world_model(_world(0), _buffer(0), seed=1, compile=True, **fit)
    assert COMPILING in capsys.readouterr().err
    fit_world_model(_world(0), _buffer(0), seed=1, **fit)  # eager: no such note
    assert COMPILING not in capsys.readouterr().err
