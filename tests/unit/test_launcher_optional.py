"""The supervisor gives up on a crashing optional process alone, never restarts one that refused its
configuration, starts a process niced, and gives each its own grace at a stop."""
from __future__ import annotations

import os
import sys
import time

from runtime.launcher import ProcessSpec, Supervisor


def _poll_until(sup: Supervisor, done, timeout_s: float = 10.0) -> None:
    """Poll ``sup`` until ``done()`` (at most ``timeout_s``), then 20 times more: nothing further may happen."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        sup.poll()
        time.sleep(0.02)
    for _ in range(20):
        sup.poll()


def test_a_crashing_optional_process_is_given_up_on_alone_and_nice_applies_from_the_start():
    lines: list[str] = []
    sup = Supervisor([ProcessSpec("loop", (sys.executable, "-c", "import time; time.sleep(30)")),
                      ProcessSpec("page", (sys.executable, "-c", "raise SystemExit(3)"), essential=False),
                      ProcessSpec("niced", (sys.executable, "-c", "import time; time.sleep(30)"), essential=False, nice=7)],
                     restart_delay_s=0.01, max_restarts=2, stop_timeout_s=2.0, echo=lines.append)
    sup.start()
    try:
        assert os.getpriority(os.PRIO_PROCESS, sup.procs["niced"].pid) == min(19, os.getpriority(os.PRIO_PROCESS, 0) + 7)
        _poll_until(sup, lambda: any("giving up on it" in line for line in lines))
        assert any("giving up on it (not essential" in line for line in lines), lines
        assert not sup.finished.is_set() and sup.exit_code == 0
        assert sup.procs["loop"].poll() is None  # the essential one runs on
    finally:
        sup.stop()


def test_a_process_that_refuses_its_configuration_is_not_restarted():
    lines: list[str] = []
    refuse = "import sys; print('error: network missing'); sys.exit(2)"
    sup = Supervisor([ProcessSpec("loop", (sys.executable, "-c", "import time; time.sleep(30)")),
                      ProcessSpec("page", (sys.executable, "-c", refuse), essential=False)],
                     restart_delay_s=0.01, max_restarts=5, stop_timeout_s=2.0, echo=lines.append)
    sup.start()
    try:
        _poll_until(sup, lambda: any("not restarting" in line for line in lines))
        assert sup.restarts["page"] > sup.max_restarts and not any("restarting (restart" in line for line in lines), lines
        assert any("page exited with 2: it refused its configuration" in line and "the others go on" in line
                   for line in lines), lines
        assert not sup.finished.is_set() and sup.procs["loop"].poll() is None
    finally:
        sup.stop()

    lines.clear()
    essential = Supervisor([ProcessSpec("estimator", (sys.executable, "-c", refuse))], restart_delay_s=0.01,
                           echo=lines.append)
    essential.start()
    try:
        # its output is echoed by a thread of its own: wait for that line too
        _poll_until(essential, lambda: essential.finished.is_set() and any("network missing" in line for line in lines))
    finally:
        essential.stop()
    assert essential.finished.is_set() and essential.exit_code == 2, lines  # the run ends at once, with its code
    assert sum("error: network missing" in line for line in lines) == 1, lines


def test_each_process_gets_its_own_grace_at_a_stop():
    slow_exit = ("import signal, sys, time; signal.signal(signal.SIGTERM, lambda *_: (time.sleep(1.5), sys.exit(0))); "
                 "print('ready', flush=True); time.sleep(30)")
    lines: list[str] = []
    sup = Supervisor([ProcessSpec("writer", (sys.executable, "-c", slow_exit), stop_timeout_s=10.0),
                      ProcessSpec("other", (sys.executable, "-c", slow_exit))],
                     stop_timeout_s=0.3, echo=lines.append)
    sup.start()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and sum("ready" in line for line in lines) < 2:
        time.sleep(0.02)
    sup.stop()
    assert sup.procs["writer"].returncode == 0, lines  # its 1.5 s to finish were granted
    assert sup.procs["other"].returncode == -9 and any("other (pid" in line and "did not stop in 0.3 s" in line
                                                       for line in lines), lines
