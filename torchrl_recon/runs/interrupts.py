"""Ctrl-C that stops a run every time, not only where Python can raise it.

A SIGINT (or the CLI's SIGTERM) raises ``KeyboardInterrupt`` wherever the main thread is. When
that is a finaliser or a weakref callback run by the garbage collector, Python cannot raise it
there: it prints "Exception ignored in ..." and drops it, and the run goes on to its end (2 of
25 interrupted smoke runs, measured). Inside :func:`redeliver_dropped_interrupts` a dropped
``KeyboardInterrupt`` is raised again in the main thread, so the run stops as a Ctrl-C should.
"""

from __future__ import annotations

import _thread
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

RETRY_S = 0.05
"""How long after a dropped ``KeyboardInterrupt`` it is raised again (time to leave the
finaliser)."""


def _interrupting_signal() -> signal.Signals | None:
    """The signal that raises ``KeyboardInterrupt`` here: SIGINT, or SIGTERM where SIGINT is
    ignored (a background job) and SIGTERM interrupts (the CLI's setting); None if neither."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(signum) is signal.default_int_handler:
            return signum
    return None


@contextmanager
def redeliver_dropped_interrupts() -> Iterator[None]:
    """While inside, a ``KeyboardInterrupt`` that Python drops (raised in a finaliser or
    weakref callback) is raised again in the main thread :data:`RETRY_S` later instead of
    printed (should it land in a finaliser again, once more); other unraisable exceptions go
    to the hook there was before. On leaving, that hook is back and a redelivery not yet
    made is cancelled.

    Examples:
        >>> with redeliver_dropped_interrupts():
        ...     sys.unraisablehook is not sys.__unraisablehook__
        True
    """
    before = sys.unraisablehook
    pending: list[threading.Timer] = []

    def hook(unraisable: Any) -> None:
        signum = _interrupting_signal()
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and signum is not None:
            # a moment later, from another thread: raised now, inside the finaliser (or this
            # hook), it would be dropped again
            later = threading.Timer(RETRY_S, _thread.interrupt_main, args=(signum,))
            later.daemon = True
            pending.append(later)
            later.start()
            return
        before(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = before
        for later in pending:
            later.cancel()
