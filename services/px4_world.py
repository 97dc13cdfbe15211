"""The simulator source with real PX4 SITL in the loop (``neso run source --link px4``): the world listens on
TCP ``--px4-port`` for PX4's simulator link (``sim.px4_link``) and is stepped by PX4's motor outputs
(``sim.px4_hil``); the source service publishes its states and truth as ever. The controller's setpoints reach
PX4 through the px4_gateway (MAVSDK offboard), motion capture reaches PX4's EKF2 the same way (the gateway's
ODOMETRY); the source only keeps the newest setpoint as the truth's reference."""
from __future__ import annotations

import threading

from sim.px4_hil import AutopilotInTheLoop, HilSensors
from sim.px4_link import Px4SimLink

REPORT_PERIOD_S = 10.0


def px4_in_the_loop(node, config, sim) -> AutopilotInTheLoop:
    """``sim`` (a :class:`sim.quadrotor.QuadrotorSim`) with PX4 SITL commanding its rotors; the link's
    connects, stalls and drops are logged and raised as events."""
    def report(level: str, line: str) -> None:
        node.log(line)
        node.event(level, line)

    link = Px4SimLink(config.px4_port, connect_log=report)
    node.log(f"PX4 simulator link listening on TCP 127.0.0.1:{config.px4_port} (PX4 SITL connects; lockstep)")
    world = AutopilotInTheLoop(sim, link.exchange, HilSensors(seed=config.seed))
    threading.Thread(target=_report, args=(node, world, link), name="px4-world-report", daemon=True).start()
    return world


def _report(node, world: AutopilotInTheLoop, link: Px4SimLink) -> None:
    """Every ``REPORT_PERIOD_S``: what PX4 answered and how often its motor outputs saturated in the air."""
    while not node.wait(REPORT_PERIOD_S):
        share = 100.0 * world.saturated / world.airborne if world.airborne else 0.0
        node.log(f"PX4 link: {world.exchanges} sensor exchanges answered, {world.unanswered} unanswered ({link.stalls} "
                 f"stalls, {link.stale} late answers skipped); in the air "
                 f"{world.airborne}, of them {world.saturated} ({share:.2f} %) with a motor output within 1 % of "
                 "0 or 1")
