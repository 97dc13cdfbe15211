"""The dashboard's bus facade: a newer request about the same thing replaces the waiting one; commands all go."""
from __future__ import annotations

import threading

from dashboard.service import SUPERSEDED, BusFacade


def test_a_newer_change_replaces_the_waiting_one_and_none_overtakes():
    facade = BusFacade(session=None, timeout_s=2.0, workers=3)
    release, sent, replies = threading.Event(), [], {}
    done = threading.Semaphore(0)

    def change(value):
        def go():
            if value == 0:
                release.wait(5.0)  # the first one is on the wire while the operator keeps dragging
            sent.append(value)
            return True, f"sent {value}"
        return go

    def reply_for(value):
        def reply(ok, text):
            replies[value] = (ok, text)
            done.release()
        return reply

    key = ("set", "uav1", "estimator", ("lipschitz_bound",))
    for value in range(5):
        facade._submit(change(value), reply_for(value), key=key)
    release.set()
    for _ in range(5):
        assert done.acquire(timeout=5.0)
    facade.close()
    assert sent == [0, 4]  # the running one, then the newest; 1-3 never sent
    assert [replies[v] for v in (1, 2, 3)] == [(False, SUPERSEDED)] * 3
    assert replies[0] == (True, "sent 0") and replies[4] == (True, "sent 4")
    assert facade.superseded == 3


def test_commands_are_never_superseded():
    facade = BusFacade(session=None, timeout_s=2.0, workers=1)
    sent, done = [], threading.Semaphore(0)
    for name in ("arm", "takeoff", "hold", "abort"):
        facade._submit(lambda name=name: (sent.append(name), (True, name))[1], lambda ok, text: done.release())
    for _ in range(4):
        assert done.acquire(timeout=5.0)
    facade.close()
    assert sent == ["arm", "takeoff", "hold", "abort"]
