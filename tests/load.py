"""Runs under load, on purpose: ``pytest -p tests.load`` (tests/README.md, "Under load").

- ``NESO_TEST_LOAD_CORES=k``: k busy processes (a Python loop each, nice 0) beside the run, started at its start and
  stopped at its end (with workers, by the controller only): "one core kept busy by another process" is k=1.
- ``NESO_TEST_LOAD_GIL=k``: k threads in each test process keeping its interpreter lock busy, the switch interval
  raised to 0.2 s: a test process that takes what it subscribed to late, as a loaded machine made it (the lockstep
  test once read its probe before the tail of the flight had reached it: 268 of 550 samples with k=3).
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading

_procs: list[subprocess.Popen] = []
_stop = threading.Event()


def _spin() -> None:
    while not _stop.is_set():
        sum(i * i for i in range(200_000))


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # the controller, or the only process
        for _ in range(int(os.environ.get("NESO_TEST_LOAD_CORES", "0"))):
            _procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
    threads = int(os.environ.get("NESO_TEST_LOAD_GIL", "0"))
    if threads:
        sys.setswitchinterval(0.2)
        for _ in range(threads):
            threading.Thread(target=_spin, name="load", daemon=True).start()


def pytest_unconfigure(config):
    _stop.set()
    for proc in _procs:
        proc.kill()
        proc.wait()
