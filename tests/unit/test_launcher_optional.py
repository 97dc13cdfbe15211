"""The supervisor gives up on a crashing optional process alone, and starts a process niced."""
from __future__ import annotations

import os
import sys
import time

from runtime.launcher import ProcessSpec, Supervisor


def test_a_crashing_optional_process_is_given_up_on_alone_and_nice_applies_from_the_start():
    lines: list[str] = []
    sup = Supervisor([ProcessSpec("loop", (sys.executable, "-c", "import time; time.sleep(30)")),
                      ProcessSpec("page", (sys.executable, "-c", "raise SystemExit(3)"), essential=False),
                      ProcessSpec("niced", (sys.executable, "-c", "import time; time.sleep(30)"), essential=False, nice=7)],
                     restart_delay_s=0.01, max_restarts=2, stop_timeout_s=2.0, echo=lines.append)
    sup.start()
    try:
        assert os.getpriority(os.PRIO_PROCESS, sup.procs["niced"].pid) == min(19, os.getpriority(os.PRIO_PROCESS, 0) + 7)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not any("giving up on it" in line for line in lines):
            sup.poll()
            time.sleep(0.02)
        for _ in range(20):
            sup.poll()
        assert any("giving up on it (not essential" in line for line in lines), lines
        assert not sup.finished.is_set() and sup.exit_code == 0
        assert sup.procs["loop"].poll() is None  # the essential one runs on
    finally:
        sup.stop()
