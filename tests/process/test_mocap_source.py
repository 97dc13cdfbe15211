"""The motion-capture source runs against the `motioncapture` library's mock backend and reports what it sees."""
from __future__ import annotations

from runtime.schema import HealthMsg, Keys
from tests.busutil import free_port, hub, neso, stop


def test_mocap_source_connects_through_the_library_and_says_the_rigid_body_is_missing():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint) as s:
        got: list[HealthMsg] = []
        sub = s.declare_subscriber(Keys("uav1").health("source"),
                                   lambda sample: got.append(HealthMsg.from_bytes(sample.payload.to_bytes())))
        proc = neso("run", "source", "--backend", "mocap", "--mocap-type", "mock", "--rigid-body", "cf7",
                    "--connect", endpoint)
        import time

        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not any("frames" in h.status for h in got[1:]):
            time.sleep(0.1)
        out = stop(proc)
        sub.undeclare()
    assert proc.returncode == 0, out
    status = [h.status for h in got if "frames" in h.status][-1]
    assert "rigid body 'cf7' not seen yet" in status and int(status.split(": ")[1].split()[0]) > 10, status
