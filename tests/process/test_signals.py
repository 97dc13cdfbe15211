"""Ctrl-C reaches a service however the kernel delivers it and whatever the main thread is doing: a process-directed
SIGINT goes to any thread that does not block it — often one of Zenoh's native threads — and Python runs the
handler only when the main thread runs, between two of its bytecodes. A node waiting without a timeout must still
stop promptly (a recorder once ignored Ctrl-C until the launcher's SIGKILL 12 s later), and so must one whose main
thread holds its stop event's lock when the signal lands — inside that event's wait, or inside a first handler's
``Event.set`` when the launcher's SIGTERM follows Ctrl-C (the recorder and the source then hung for good:
`test_live_flight.py`'s Ctrl-C test on a loaded machine; runtime/signals.py)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.busutil import REPO, free_port, hub

SERVICE = r"""
import os, signal, sys, threading, time
from runtime.node import Node, run_node
from tests.busutil import peer

def main(node):
    print("waiting", flush=True)
    if sys.argv[2] == "another thread":
        threading.Thread(target=time.sleep, args=(60,), daemon=True).start()  # a thread that takes signals
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # the main thread never does, as when Zenoh's do
    elif sys.argv[2] == "holding the stop event's lock":
        with node._stop._cond:  # as inside the event's wait once it woke: the handler runs here
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.3)
    else:  # "a second signal inside the first handler": the launcher's SIGTERM while Ctrl-C's handler runs
        def tracer(frame, event, arg):
            if event == "call" and frame.f_code.co_name == "notify_all":  # inside Event.set, holding its lock
                sys.settrace(None)
                os.kill(os.getpid(), signal.SIGTERM)
        sys.settrace(tracer)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.3)
    node.wait()
    print("stopped", flush=True)

sys.exit(run_node(Node("recorder", vehicle="uav1", bus=peer(sys.argv[1])), main))
"""


@pytest.mark.parametrize("how", ["another thread", "holding the stop event's lock",
                                 "a second signal inside the first handler"])
def test_a_signal_stops_a_waiting_node_within_a_second_however_it_lands(how):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint):
        proc = subprocess.Popen([sys.executable, "-c", SERVICE, endpoint, how], cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        try:
            lines = []
            while not lines or lines[-1] != "waiting":
                line = proc.stdout.readline()
                assert line, "".join(lines)
                lines.append(line.strip())
            sent = time.monotonic()
            if how == "another thread":
                os.kill(proc.pid, signal.SIGINT)
            code = proc.wait(timeout=5.0)
            took = time.monotonic() - sent
            print(f"\nstopped {took:.2f} s after SIGINT")
            assert code == 0 and proc.stdout.read().strip() == "stopped" and took < 1.0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
