"""viser's message buffers made safe for updates from threads other than its event loop.

viser (1.1.1, pinned) wakes a page's sender through an ``asyncio.Event``, and ``push()`` calls that
event's ``set()`` directly from whichever thread changed a GUI element — here the UI loop and the
bus-reply workers — besides scheduling it on the loop. ``asyncio.Event`` is not thread-safe: a
``set()`` that lands between the sender's ``if self._value`` and its ``self._waiters.append(fut)``
(inside ``Event.wait``) marks the event set without waking anyone, and every later ``set()`` is a
no-op because the value is already true, so that page's sender waits forever while new pages
work. That is a page that freezes for good while the flight and the dashboard go on — what two CI
runs showed (stops 20 and 21, a page frozen for over a minute on a loaded host).

:func:`install` gives each new buffer a :class:`LoopEvent`, whose ``set()`` from another thread is
only posted to the loop, so the event's state is touched by the loop's thread alone.
"""
from __future__ import annotations

import asyncio
import dataclasses

_INSTALLED = False


class LoopEvent(asyncio.Event):
    """An ``asyncio.Event`` of ``loop`` whose ``set()`` may be called from any thread: off the loop
    it is posted with ``call_soon_threadsafe`` (and dropped once the loop is closed: nobody waits)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__()
        self._owner_loop = loop

    def set(self) -> None:
        try:
            on_loop = asyncio.get_running_loop() is self._owner_loop
        except RuntimeError:  # no loop runs in this thread
            on_loop = False
        if on_loop:
            super().set()
            return
        try:
            self._owner_loop.call_soon_threadsafe(super().set)
        except RuntimeError:  # the loop is closed (the server stopped)
            pass


def install() -> None:
    """Give every viser message buffer created from now on a :class:`LoopEvent` (idempotent)."""
    global _INSTALLED
    if _INSTALLED:
        return
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    if "message_event" not in {f.name for f in dataclasses.fields(AsyncMessageBuffer)}:
        raise RuntimeError("viser's AsyncMessageBuffer has no message_event any more: "
                           "check dashboard/viser_threads.py against the installed viser")
    original_init = AsyncMessageBuffer.__init__

    def __init__(self, *args, **kwargs) -> None:
        original_init(self, *args, **kwargs)
        self.message_event = LoopEvent(self.event_loop)

    AsyncMessageBuffer.__init__ = __init__
    _INSTALLED = True
