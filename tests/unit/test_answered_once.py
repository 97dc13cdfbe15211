"""A command is done once per request id, however often the client repeats its query."""
from __future__ import annotations

import threading
import time

import pytest

from runtime.node import AnsweredOnce


def test_a_repeat_gets_the_first_answer_and_does_nothing_again():
    once, calls = AnsweredOnce(), []

    def rollback():
        calls.append(1)
        return True, f"rolled back ({len(calls)})"

    assert once.run("r1", rollback) == (True, "rolled back (1)")
    assert once.run("r1", rollback) == (True, "rolled back (1)")
    assert once.run("r2", rollback) == (True, "rolled back (2)")
    assert len(calls) == 2


def test_a_repeat_while_the_first_still_runs_gets_no_answer_then_the_first_one():
    once, calls, release = AnsweredOnce(), [], threading.Event()

    def slow_ack():
        calls.append(1)
        release.wait(5.0)
        return True, "accepted by the vehicle"

    first = threading.Thread(target=once.run, args=("arm-1", slow_ack))
    first.start()
    time.sleep(0.05)
    assert once.run("arm-1", slow_ack, wait_s=0.01) is None  # still running: no answer, not run again
    release.set()
    first.join(5.0)
    assert once.run("arm-1", slow_ack) == (True, "accepted by the vehicle")
    assert len(calls) == 1


def test_a_failing_command_is_answered_as_failed_once_and_old_answers_are_forgotten():
    once = AnsweredOnce(keep=2)

    def boom():
        raise RuntimeError("bug")

    with pytest.raises(RuntimeError, match="bug"):  # the caller (Node) logs it as an event
        once.run("x", boom)
    assert once.run("x", lambda: (True, "not run")) == (False, "command failed (see events)")
    once.run("a", lambda: (True, "a"))
    once.run("b", lambda: (True, "b"))
    assert once.run("x", lambda: (True, "run again: forgotten")) == (True, "run again: forgotten")
