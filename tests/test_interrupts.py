"""``redeliver_dropped_interrupts``: a Ctrl-C that lands in a finaliser still stops the run."""

from __future__ import annotations

import signal
import sys
import time

import pytest

from torchrl_recon.runs.interrupts import RETRY_S, redeliver_dropped_interrupts


@pytest.fixture(autouse=True)
def _ctrl_c_raises_keyboard_interrupt():
    """SIGINT raises ``KeyboardInterrupt`` here, as in the CLI: a library may have put a handler
    of its own on it in this worker (TorchRL's ``LazyMemmapStorage`` with a temporary folder
    installs a cleanup handler that restores the one before it and signals again), and then a
    drop is not the CLI's case; the first test failed so, once, after another test's storage."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


class _RaisesWhenFinalised:
    def __init__(self, error: type[BaseException]) -> None:
        self.error = error

    def __del__(self) -> None:
        raise self.error


def _drop(error: type[BaseException]) -> None:
    """Python drops (prints as "Exception ignored in") what a finaliser raises."""
    finalised = _RaisesWhenFinalised(error)
    del finalised


def _wait(seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        time.sleep(0.005)


def test_a_dropped_keyboard_interrupt_is_raised_again_in_the_main_thread():
    with pytest.raises(KeyboardInterrupt), redeliver_dropped_interrupts():
        _drop(KeyboardInterrupt)
        _wait(100 * RETRY_S)  # without the redelivery this returns: the run would go on


def test_other_unraisable_errors_go_to_the_hook_there_was_before(monkeypatch):
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    with redeliver_dropped_interrupts():
        assert sys.unraisablehook is not seen.append
        _drop(ValueError)
    assert sys.unraisablehook == seen.append
    assert [type(u.exc_value) for u in seen] == [ValueError]


def test_a_redelivery_not_yet_made_is_cancelled_on_leaving():
    with redeliver_dropped_interrupts():
        _drop(KeyboardInterrupt)
    _wait(5 * RETRY_S)  # a KeyboardInterrupt here would fail the test
