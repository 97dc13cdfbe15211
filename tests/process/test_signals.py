"""Ctrl-C reaches a service however the kernel delivers it: a process-directed SIGINT goes to any thread that does
not block it — often one of Zenoh's native threads — and Python runs the handler only when the main thread runs. A
node waiting without a timeout must still stop promptly (a recorder once ignored Ctrl-C until the launcher's
SIGKILL 12 s later: `test_live_flight.py`'s Ctrl-C test, intermittently)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from tests.busutil import REPO, free_port, hub

SERVICE = r"""
import signal, sys, threading, time
from runtime.node import Node, run_node
from tests.busutil import peer

def main(node):
    threading.Thread(target=time.sleep, args=(60,), daemon=True).start()  # a thread that takes signals
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # the main thread never does, as when Zenoh's do
    print("waiting", flush=True)
    node.wait()
    print("stopped", flush=True)

sys.exit(run_node(Node("recorder", vehicle="uav1", bus=peer(sys.argv[1])), main))
"""


def test_a_sigint_delivered_to_another_thread_stops_a_waiting_node_within_a_second():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint):
        proc = subprocess.Popen([sys.executable, "-c", SERVICE, endpoint], cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        try:
            lines = []
            while not lines or lines[-1] != "waiting":
                line = proc.stdout.readline()
                assert line, "".join(lines)
                lines.append(line.strip())
            sent = time.monotonic()
            os.kill(proc.pid, signal.SIGINT)
            code = proc.wait(timeout=5.0)
            took = time.monotonic() - sent
            print(f"\nstopped {took:.2f} s after SIGINT")
            assert code == 0 and proc.stdout.read().strip() == "stopped" and took < 1.0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
