"""viser's page sender woken from other threads (dashboard/viser_threads.py).

The hazard is one interleaving: a ``set()`` from another thread between ``Event.wait``'s check of
the value and its registering a waiter. It is forced here exactly (the foreign ``set()`` runs while
``wait`` creates its future), so the test does not depend on luck with the GIL."""
from __future__ import annotations

import asyncio
import concurrent.futures
import threading

import pytest

from dashboard.viser_threads import LoopEvent
from tests.helpers import race_the_next_wait


@pytest.fixture
def loop():
    lp = asyncio.new_event_loop()
    thread = threading.Thread(target=lp.run_forever, daemon=True)
    thread.start()
    yield lp

    async def drain() -> None:  # a waiter the test gave up on ends here, not as a pending task at exit
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    asyncio.run_coroutine_threadsafe(drain(), lp).result(2.0)
    lp.call_soon_threadsafe(lp.stop)
    thread.join(2.0)
    lp.close()


def waits(loop, make_event) -> bool:
    """Whether a waiter hit by the race is woken, by that ``set()`` or a later one from another thread."""
    event = make_event(loop)
    ran = race_the_next_wait(loop, event, event.set)
    woke = asyncio.run_coroutine_threadsafe(event.wait(), loop)
    assert ran.wait(2.0), "the race did not run"
    try:
        woke.result(0.5)
        return True
    except concurrent.futures.TimeoutError:
        event.set()  # a later update, from another thread again
        try:
            woke.result(0.5)
            return True
        except concurrent.futures.TimeoutError:
            woke.cancel()
            return False


def test_a_plain_asyncio_event_set_from_another_thread_can_lose_its_waiter_for_good(loop):
    """What viser 1.1.1 does (the reason for the patch): the waiter is never woken again."""
    assert not waits(loop, lambda _lp: asyncio.Event())


def test_a_loop_event_set_from_another_thread_always_wakes_its_waiter(loop):
    assert waits(loop, LoopEvent)


def test_a_loop_event_set_on_its_loop_is_an_ordinary_set(loop):
    made = concurrent.futures.Future()

    def on_loop():
        event = LoopEvent(loop)
        event.set()
        made.set_result(event.is_set())
    loop.call_soon_threadsafe(on_loop)
    assert made.result(2.0) is True


def test_set_after_the_loop_closed_is_quiet():
    lp = asyncio.new_event_loop()
    event = LoopEvent(lp)
    lp.close()
    event.set()  # the server stopped: nothing to wake, no error
    assert not event.is_set()
