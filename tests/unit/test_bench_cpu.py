"""bench.cpu: the CPU a benchmarked process spent, per sample of a loop."""
import subprocess
import sys
import threading

from bench.cpu import CpuWindow, cpu_s


def test_cpu_window_tells_a_busy_process_from_an_idle_one():
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    idle = subprocess.Popen(["sleep", "30"])
    try:
        start = threading.Event()
        window = CpuWindow(lambda: {"busy": busy.pid, "idle": idle.pid}, 1.0, start)
        start.set()
        per_sample = window.per_sample_us(rate_hz=1.0)  # one "sample" a second: µs of CPU per second
    finally:
        busy.kill(), idle.kill()
        busy.wait(), idle.wait()
    # a spinning process: whatever share the scheduler gives it (in `make test` it inherits the computing worker's
    # nice 10: 0.14 core measured beside a busy core and a flight), against next to nothing for a sleeping one
    assert per_sample["idle"] < 0.05e6
    assert per_sample["busy"] > 20 * max(per_sample["idle"], 1e3), per_sample


def test_a_window_that_never_starts_reports_nothing_and_a_gone_process_counts_zero():
    window = CpuWindow(lambda: {"x": 1}, 0.1, threading.Event(), start_timeout_s=0.1)
    assert window.per_sample_us(500.0) == {}
    gone = subprocess.Popen(["true"])
    gone.wait()
    assert cpu_s([gone.pid]) == 0.0
