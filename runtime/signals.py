"""Ctrl-C and SIGTERM as a flag: the handler only records that a signal came; the code that waits polls for it.

A Python signal handler runs in the main thread between two bytecodes of whatever it interrupted. A handler that
takes a lock — ``threading.Event.set`` takes the event's own — deadlocks when the code it interrupted holds that
lock: the main thread inside the same event's ``wait``, or inside a first handler's ``set`` when a second signal
lands. That second signal is the usual case, not a corner: Ctrl-C reaches every process of ``neso up``'s group and
the launcher's SIGTERM follows within milliseconds. Seen (py-spy) as a recorder and a source whose main threads sat
for good in ``Event.set`` → handler → ``Event.set``, and a ``neso up`` that waited out the recorder's 12 s grace
(``tests/process/test_live_flight.py``'s Ctrl-C test, on a loaded machine). Storing an attribute takes no lock.
"""
from __future__ import annotations

import signal
import time

POLL_S = 0.1  # how soon a waiter sees the flag (the main thread must run anyway for Python to call the handler)


class Signalled:
    """``install()`` makes SIGINT and SIGTERM set :attr:`signum`; ``bool(flag)``, :meth:`is_set` and :meth:`wait`
    read it (an Event's interface, so it can stand where a stop event is expected)."""

    def __init__(self) -> None:
        self.signum = 0

    def install(self, signals=(signal.SIGINT, signal.SIGTERM)) -> "Signalled":
        for sig in signals:
            signal.signal(sig, self._handler)
        return self

    def _handler(self, signum, _frame) -> None:
        self.signum = signum  # nothing else: no lock, nothing that could wait for what it interrupted

    def __bool__(self) -> bool:
        return self.signum != 0

    def is_set(self) -> bool:
        return self.signum != 0

    def wait(self, timeout_s: float | None = None, *, also=None) -> bool:
        """Until a signal came (True), ``also()`` is true (True) or ``timeout_s`` passed (False)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not (self.signum or (also is not None and also())):
            left = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
            if left <= 0:
                return False
            time.sleep(left)
        return True
