"""``python -m bench``: the method's and the simulator's speed, side by side in one run.

Rows: simulator speed as a multiple of real time (hover, 20 s); the estimator + controller
tick; network inference at batch 1; the estimator's and the controller's step objects per sample as
the services run them (:mod:`bench.steps`); and the whole ``neso experiment paper`` pipeline
(``--trials 5``, all flights and trainings), which the issue wants under 3 min (target 60 s).
Then the bus: end-to-end latency of ``neso up`` at 50 and 500 Hz against bare Zenoh and UDP
ping-pongs (:mod:`bench.bus_latency`, ~3.5 min: 60 s flights, 15 s of round trips per floor).
Then the hot path (:mod:`bench.hotpath`, ~12 min; ``"bus"`` and ``"fleet"`` in ``out/bench.json``): a bare
Zenoh chain with the pipeline's three hops beside the 500 Hz pipeline (isolation off and on), 50 Hz alone and
with the dashboard and 3 Chromium pages (isolation off and on), and fleets of 1, 2, 4 and 8 vehicles.
Then Zenoh's transport choices for the loop — defaults, ``--priorities``, ``--low-latency`` — in rotated rounds
beside the bare chain (:mod:`bench.transport`, ~8 min; ``bus.transport``).
Then the secure bus (:mod:`bench.secure`, ~5 min): Zenoh ping-pong plain, over mutual TLS, with the
ACL, and routed through a secure hub; the pipeline plain beside ``--secure``; at 500 and 50 Hz, two
rotated rounds each; also into ``out/bench.json`` (``"secure"``).
Then recording (:mod:`bench.recording`, ~85 s): loop latency at 50 Hz with the recorder off beside on,
the recorder's writer cost, and ``.rrd`` → training set for a 60 s flight.
Then a flood of malformed payloads in the real-time loop, quiet beside flooded 1 s windows: deadlines missed, estimate
latency, each process's CPU and the CPU a rejected payload costs (:mod:`bench.flood`, ~35 s; ``"flood"``).
Then the TDR loop (:mod:`bench.tdr`, ~50 s): a 30 s recording → trained, certified, promoted network.
Then the PX4 gateway: setpoint on the bus → SET_ATTITUDE_TARGET at a MAVLink vehicle, p50/p99, and its
watchdog with the motion capture lost (the failed poses' interval at the vehicle, quiet beside every core busy)
(:mod:`bench.gateway`, ~40 s).
Then real PX4 v1.16.0 SITL in the loop with the dashboard, hovering: the world's real-time factor and the setpoints
missed in 60 s (:mod:`bench.px4`, ~100 s).
Then motion capture over NatNet: a frame leaving the simulated Motive → the state on the bus, at 120 and 360 Hz
frames, p50/p99 (:mod:`bench.natnet`, ~20 s).
Then the dashboard's cost to the loop and bus → DOM latency (:mod:`bench.dashboard`, ~90 s).
Then importing PX4 logs: the shared CubeOrange log and a 20-minute log (:mod:`bench.px4_import`, ~40 s).
Then the stability certificates: max certified L_N of each method over a gain grid, the cost of
``best_certificate`` cold and cached, and each bound against a simulated worst case (:mod:`bench.certificate`, ~1 min).
Then the real-flight benchmark (:mod:`bench.nanobench`, ~2 min; ~1 min ``--quick`` at 30 epochs): NanoBench Crazyflie
flights shipped in ``tests/data/nanobench/`` — the z residual's R² on held-out flights of the certified recipe, the
paper recipe, the best linear map in the bound and the mean, the learned slopes near the ground, and the neural ESO's
composite estimate against the ESO alone, replayed (``"nanobench"`` in ``out/bench.json``).
Pass ``--quick`` (``make bench-quick``) for a subset a user runs in under 5 minutes: the core rows without the
paper pipeline, the bus latency, the flood, the gateway, PX4 SITL in the loop, NatNet, PX4 log import, the certificates and NanoBench,
each shortened; the rest is listed as not run. Every run ends with a table of each section's wall time
(``"section_wall_s"`` in ``out/bench.json``).

Every table is also written to ``out/bench.json`` as it is printed (``{"tables": [{"columns",
"rows"}], "simulator_x_real_time": {...}}``), so a run cut short keeps what it measured.
"""
from __future__ import annotations

import sys
import time
import timeit

import numpy as np

from bench.table import RESULTS, print_table, write_results


SIM_TARGET_X = 100.0  # the simulator must run at least this many times faster than real time


def _per_call_us(fn, number: int) -> float:
    return min(timeit.repeat(fn, number=number, repeat=5)) / number * 1e6


def bench_tick() -> tuple[float, float]:
    from neso.control import PositionController
    from neso.estimator import AppliedControl, NeuralESO, NeuralEsoConfig
    from neso.types import Reference, StateMeasurement
    from tests.helpers import random_network

    net = random_network(0, bound=1.0)
    est = NeuralESO(NeuralEsoConfig(), net)
    ctrl = PositionController()
    meas = StateMeasurement(0.0, np.array([0, 0, 1.0]), np.zeros(3), 0.0, 0.0, 0.0)
    est.reset(meas, 9.81)
    ref = Reference(pos_enu_m=np.array([0, 0, 1.0]))
    applied = AppliedControl(np.zeros(3), 9.81)

    def tick():
        e = est.update(meas, applied)
        ctrl.step(meas, ref, e.f_hat)

    return _per_call_us(tick, 2000), _per_call_us(lambda: net.predict(meas.pos_enu_m.repeat(2)[:5]), 20000)


def core_section(quick: bool) -> None:
    """The simulator's speed, the tick, inference, the step objects and (not ``quick``) the paper pipeline."""
    from sim.quadrotor import sim_speed_x_real_time

    rows = []
    speed_x = sim_speed_x_real_time(20.0)
    RESULTS["simulator_x_real_time"] = {"hover_s": 20.0, "x_real_time": round(speed_x, 1), "target_x": SIM_TARGET_X,
                                        "meets_target": speed_x >= SIM_TARGET_X}
    rows.append((f"simulator, hover 20 s (target ≥ {SIM_TARGET_X:.0f}×)",
                 f"{speed_x:.0f}× real time" + ("" if speed_x >= SIM_TARGET_X else "  BELOW TARGET")))
    tick_us, predict_us = bench_tick()
    rows.append(("estimator + controller tick (Neural-ESO)", f"{tick_us:.1f} µs"))
    rows.append(("network inference, batch 1 (5→20→25→10→1)", f"{predict_us:.1f} µs"))
    from bench.steps import step_rows

    steps: dict = {}
    for name, best, median, target in step_rows(steps):
        rows.append((f"{name} (500 Hz lemniscate, per sample; target {target})", f"{best} µs (median of 5: {median})"))
    RESULTS["steps_us"] = steps
    if not quick:
        from sim.experiments import PaperConfig, run_paper

        t0 = time.perf_counter()
        run = run_paper(PaperConfig(trials=5), log=lambda *_: None)
        total = time.perf_counter() - t0
        rows.append(("neso experiment paper --trials 5 (target < 60 s, limit 180 s)", f"{total:.1f} s"))
        for stage, secs in run.details["timing_s"].items():
            rows.append((f"  stage {stage}", f"{secs:.1f} s"))
    print_table(("benchmark", "result"), rows)


def bus_section(quick: bool) -> None:
    from bench.bus_latency import COLUMNS, FOOTNOTE, bus_latency_rows

    print_table(COLUMNS, bus_latency_rows(flight_s=10.0 if quick else 60.0, floor_s=3.0 if quick else 15.0))
    print(FOOTNOTE)


def hotpath_section(quick: bool) -> None:
    """The hot path, subscriber handlers and Zenoh's transport choices (``"bus"``, ``"fleet"``)."""
    from bench.handlers import COLUMNS as HANDLER_COLUMNS, handler_rows
    from bench.hotpath import COLUMNS as HOTPATH_COLUMNS, hotpath_rows
    from bench.transport import COLUMNS as TRANSPORT_COLUMNS, transport_rows

    hot: dict = {}
    print_table(HOTPATH_COLUMNS, hotpath_rows(10.0 if quick else 60.0, hot, fleet_s=10.0 if quick else 30.0))
    print(flush=True)
    print_table(HANDLER_COLUMNS, handler_rows(10.0 if quick else 20.0, hot))  # into hot["bus"]
    print(flush=True)
    print_table(TRANSPORT_COLUMNS, transport_rows(10.0 if quick else 20.0, 1 if quick else 3, hot))  # hot["bus"]
    write_results(hot)


def secure_section(quick: bool) -> None:
    from bench.secure import COLUMNS, record, secure_rows

    found: dict = {}
    print_table(COLUMNS, secure_rows(flight_s=6.0 if quick else 15.0, floor_s=3.0 if quick else 6.0,
                                     rounds=1 if quick else 2, results=found))
    record("secure", found)


def recording_section(quick: bool) -> None:
    from bench.recording import COLUMNS, recording_rows

    print_table(COLUMNS, recording_rows(quick))


def flood_section(quick: bool) -> None:
    from bench.flood import print_flood

    print_flood(quick)


def tdr_section(quick: bool) -> None:
    from bench.tdr import COLUMNS, tdr_rows

    print_table(COLUMNS, tdr_rows(quick))


def gateway_section(quick: bool) -> None:
    from bench.gateway import COLUMNS, gateway_rows

    print_table(COLUMNS, gateway_rows(duration_s=5.0 if quick else 20.0))


def px4_section(quick: bool) -> None:
    from bench.px4 import COLUMNS, px4_rows

    found: dict = {}
    print_table(COLUMNS, px4_rows(quick, found))
    write_results(found)


def natnet_section(quick: bool) -> None:
    from bench.natnet import COLUMNS, natnet_rows

    print_table(COLUMNS, natnet_rows(duration_s=2.0 if quick else 4.0))


def dashboard_section(quick: bool) -> None:
    from bench.dashboard import COLUMNS, dashboard_rows

    print_table(COLUMNS, dashboard_rows(flight_s=6.0 if quick else 12.0))


def px4_import_section(quick: bool) -> None:
    from bench.px4_import import COLUMNS, px4_import_rows

    print_table(COLUMNS, px4_import_rows(quick))


def certificate_section(quick: bool) -> None:
    from bench.certificate import print_tables

    print_tables(print_table)


def nanobench_section(quick: bool) -> None:
    from bench.nanobench import nanobench_rows

    nanobench_rows(quick, print_table)


# (name, what it measures, in --quick) in the order they run
SECTIONS = (
    ("core", core_section, True),
    ("bus latency", bus_section, True),
    ("hot path, handlers, transport", hotpath_section, False),
    ("secure bus", secure_section, False),
    ("recording", recording_section, False),
    ("flood", flood_section, True),
    ("TDR loop", tdr_section, False),
    ("PX4 gateway", gateway_section, True),
    ("PX4 SITL in the loop", px4_section, True),
    ("NatNet", natnet_section, True),
    ("dashboard", dashboard_section, False),
    ("PX4 log import", px4_import_section, True),
    ("certificates", certificate_section, True),
    ("NanoBench real flights", nanobench_section, True),
)


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    spent = []
    for name, section, in_quick in SECTIONS:
        if quick and not in_quick:
            spent.append((name, "not run (--quick)"))
            continue
        t0 = time.perf_counter()
        section(quick)
        print(flush=True)
        spent.append((name, f"{time.perf_counter() - t0:.0f} s"))
    print_table(("section" + (" (--quick)" if quick else ""), "wall time"), spent)
    RESULTS["section_wall_s"] = {name: took for name, took in spent}
    write_results()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
