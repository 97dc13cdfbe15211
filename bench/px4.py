"""Real PX4 v1.16.0 SITL in the loop at 50 Hz on this machine: does the whole system keep real time?

``neso up --vehicle px4`` (PX4 SITL, the world as its simulator in lockstep, the gateway, source, estimator,
controller, recorder and the dashboard — no browser page), flown as an operator does (PX4's "Ready for takeoff",
offboard, arm, the controller's take-off) to a hover at 1 m; then, for the measured span: the world's time against
the wall clock (its real-time factor; PX4 steps in lockstep with it), the setpoints the source missed (its health's
``deadline_misses``: no setpoint for a sample by the next one) and the setpoints that arrived. The goal: real time and
0 misses in 60 s. Skipped with one line when PX4 is not built (``make px4``).
"""
from __future__ import annotations

import os
import tempfile
import threading
import time

from runtime.client import command
from runtime.schema import HealthMsg, Keys, SetpointMsg, TruthMsg
from tests.busutil import free_port, neso, session, stop, wait_for
from runtime.bus import BusConfig

COLUMNS = ("PX4 SITL in the loop, 50 Hz, hovering", "span s", "world / wall", "setpoints", "missed", "notes")


def fly(span_s: float, *, dashboard: bool = True) -> dict:
    """One flight; the figures of the measured ``span_s`` (after the take-off and 3 s of hover)."""
    from sim.px4_sitl import px4_home
    from cli.paper_px4 import free_px4_instance

    hub = f"tcp/127.0.0.1:{free_port()}"
    keys = Keys("uav1")
    got: dict[str, list] = {"truth": [], "setpoint": [], "misses": []}
    lock = threading.Lock()

    def keep(kind, value) -> None:
        with lock:
            got[kind].append(value)

    home = tempfile.mkdtemp(prefix="neso-bench-px4-")
    env = dict(os.environ, HOME=home, NESO_PX4_HOME=str(px4_home()))  # MAVSDK's cache in a HOME of its own
    args = ["up", "--vehicle", "px4", "--px4-instance", str(free_px4_instance()), "--hub", hub, "--no-trainer",
            "--recordings-dir", os.path.join(home, "recordings")]
    args += ["--dashboard-port", str(free_port())] if dashboard else ["--no-dashboard"]
    lines: list[str] = []
    with session(BusConfig(connect=(hub,))) as s:
        s.declare_subscriber(keys.topic("truth"), lambda smp: keep(
            "truth", (time.monotonic(), TruthMsg.from_bytes(smp.payload.to_bytes()))))
        s.declare_subscriber(keys.topic("setpoint"), lambda smp: keep(
            "setpoint", (time.monotonic(), SetpointMsg.from_bytes(smp.payload.to_bytes()).seq)))
        s.declare_subscriber(keys.health("source"), lambda smp: keep(
            "misses", (time.monotonic(), HealthMsg.from_bytes(smp.payload.to_bytes()).counters.get("deadline_misses", 0.0))))
        proc = neso(*args, env=env)
        threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()

        def cmd(service: str, name: str) -> bool:
            return command(s, keys, service, name, {}, timeout_s=8.0).ok
        try:
            wait_for("PX4 ready for takeoff", lambda: any("Ready for takeoff" in line for line in lines), 90)
            wait_for("offboard", lambda: cmd("px4_gateway", "offboard_start"), 30, 1.0)
            wait_for("armed", lambda: cmd("px4_gateway", "arm"), 60, 1.0)
            assert cmd("controller", "arm") and cmd("controller", "takeoff")
            wait_for("airborne", lambda: got["truth"] and got["truth"][-1][1].pos_enu_m[2] > 0.9, 30)
            time.sleep(3.0)
            t0 = time.monotonic()
            time.sleep(span_s)
            t1 = time.monotonic()
        finally:
            stop(proc, timeout_s=20)
    with lock:
        truth = [(w, m.t_s) for w, m in got["truth"] if t0 <= w <= t1]
        setpoints = [seq for w, seq in got["setpoint"] if t0 <= w <= t1]
        misses = [m for w, m in got["misses"] if t0 - 1.5 <= w <= t1 + 1.5]
    world_x = (truth[-1][1] - truth[0][1]) / (truth[-1][0] - truth[0][0])
    return {"span_s": round(t1 - t0, 1), "world_x_real_time": round(world_x, 3), "setpoints": len(setpoints),
            "expected": round((t1 - t0) * 50.0), "missed": int(misses[-1] - misses[0]) if len(misses) > 1 else -1,
            "dashboard": dashboard}


def px4_rows(quick: bool = False, results: dict | None = None) -> list[tuple]:
    """One flight with the dashboard: 60 s measured (``quick``: 20 s)."""
    from sim.px4_sitl import missing_px4

    if missing_px4():
        return [("not measured", "", "", "", "", missing_px4())]
    r = fly(20.0 if quick else 60.0)
    if results is not None:
        results["px4_sitl_loop"] = r
    note = ("goal met: real time, 0 misses" if abs(r["world_x_real_time"] - 1.0) < 0.01 and r["missed"] == 0
            else "goal: real time, 0 misses")
    return [("source, estimator, controller, gateway, recorder, dashboard (no page)", f"{r['span_s']:g}",
             f"{r['world_x_real_time']:.3f}", f"{r['setpoints']} of {r['expected']}", str(r["missed"]), note)]


if __name__ == "__main__":
    import sys

    from bench.table import print_table, write_results

    found: dict = {}
    print_table(COLUMNS, px4_rows("--quick" in sys.argv, found))
    write_results(found)
