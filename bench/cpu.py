"""CPU time of benchmarked processes, from ``/proc`` (Linux)."""
from __future__ import annotations

import os
from typing import Iterable


def cpu_s(pids: Iterable[int]) -> float:
    """User + system CPU seconds so far of ``pids``, summed (a process that is gone counts 0)."""
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            pass
    return total
