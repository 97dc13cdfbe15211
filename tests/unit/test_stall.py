"""runtime/stall.py: a loop that stood still is reported with where it stood, or that nothing ran."""
from __future__ import annotations

import threading
import time

from runtime.stall import LateWake, StallWatch


def _stuck_until_noted(watch: StallWatch) -> None:
    """Stands still (as a loop blocked on a lock or a socket would) until the watch has noted where."""
    deadline = time.monotonic() + 30.0
    while watch.noted is None and time.monotonic() < deadline:
        time.sleep(0.01)


def test_a_loop_that_stood_still_is_reported_once_with_the_function_it_stood_in():
    started = time.monotonic()
    watch = StallWatch(0.05)
    try:
        _stuck_until_noted(watch)
        stood = watch.beat()
        assert stood is not None and stood[0] >= 0.05 and stood[0] <= time.monotonic() - started, stood
        assert stood[1].startswith("_stuck_until_noted (test_stall.py:"), stood[1]
        assert "test_a_loop_that_stood_still" in stood[1], "the frames that called it follow"
        assert watch.noted is None, "reported once"
    finally:
        watch.close()


def test_a_beat_within_the_threshold_is_no_stall_and_a_process_without_cpu_is_said_to_be_one():
    now = [100.0]
    watch = StallWatch(0.5, clock=lambda: now[0])
    watch.close()  # the watch beside it does not run: as in a process that got no CPU at all
    now[0] += 0.4
    assert watch.beat() is None
    now[0] += 2.0
    assert watch.beat() == (2.0, "unknown: the watch beside it did not run either (the process had no CPU)")


def _says_no_cpu_after_the_hold(watch: StallWatch) -> None:
    """Once the watch has noted the 2 s hold (its fake clock moved), the loop's beat reports it as no CPU."""
    try:
        _stuck_until_noted(watch)
        assert watch.beat() == (2.0, "unknown: the process had no CPU (the watch beside it woke 1.88 s late too)")
    finally:
        watch.close()


def test_a_watch_that_woke_as_late_as_the_loop_says_the_process_had_no_cpu_not_where_the_loop_is_now():
    """After SIGCONT the watch may run before the loop does: the loop then stands in its period's wait, which is
    not where it stood (the process was stopped). The watch's own lateness tells the two apart."""
    now = [100.0]
    watch = StallWatch(0.5, clock=lambda: now[0])
    now[0] += 2.0  # the watch and the loop both held for 2 s
    _says_no_cpu_after_the_hold(watch)


def test_a_watch_whose_thread_started_only_after_the_hold_still_says_the_process_had_no_cpu(monkeypatch):
    """The watch's thread may first run after the process was held (loaded run 42: the test above named its own
    frame): its lateness counts from the watch's creation, not from its thread's first instant."""
    started, start = threading.Event(), threading.Thread.start

    def start_once_released(thread):
        run = thread.run
        thread.run = lambda: (started.wait(), run())
        start(thread)

    now = [100.0]
    with monkeypatch.context() as m:
        m.setattr(threading.Thread, "start", start_once_released)
        watch = StallWatch(0.5, clock=lambda: now[0])
    now[0] += 2.0  # held before the watch's thread ever ran
    started.set()
    _says_no_cpu_after_the_hold(watch)


def test_a_watchdog_that_woke_late_judges_at_its_next_wake_not_this_one():
    """The controller's watchdog (services/controller.py): a wake over two periods late skips its judgement once,
    so an estimate queued behind the process's stop is answered before the local ESO is blamed on the estimator."""
    wakes = LateWake(0.02, now_s=0.0)
    assert [wakes.may_judge(t) for t in (0.02, 0.04, 0.061)] == [True, True, True], "on time (and a hair late)"
    assert not wakes.may_judge(3.0), "2.9 s late: the process had no CPU"
    assert wakes.may_judge(3.02), "the next wake judges"
    assert [wakes.may_judge(t) for t in (6.0, 9.0, 12.0)] == [False, True, False], \
        "starved at every wake, it still judges every other one: a dead estimator is still found"
