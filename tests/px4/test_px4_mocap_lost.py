"""Motion capture lost with real PX4 v1.16.0 SITL (`neso cmd source lose_tracking`, on the tier's shared flight, tests in
file order): the gateway tells PX4 the external vision failed (ODOMETRY quality -1, which EKF2 does not fuse with
EKF2_EV_QMIN 1) until states come back, and flies the vehicle level meanwhile. Lost for about 0.5 s of the gateway's
clock (the wall's), less than its 1 s without setpoints (flown again if a stall of the machine made it longer): PX4
told within the gateway's pose_lost_after_s (0.3 s) and again when tracked, over the span the gateway went without
states; PX4's own log shows it heard so in its time (lockstep: the world's) before EKF2 would have stopped the vision
by itself; and the flight goes on: no crash, in the air, in offboard, back at its hover, one recording through it all.
That loss is held on the wall clock, not the world's: a loaded machine slows the world in lockstep with PX4, and half
a second of the world's time once lasted 1.26 s for the gateway, whose failsafe then rightly held and landed (loaded
run 67); held on the wall clock, a 0.95 s stall of the world's process made 0.55 s last 1.53 s (quiet run 29), and
one of 0.80 s after the loss made the gateway tell PX4 of a second one (quiet run 31): flown again then.
How often the watchdog tells PX4 on the wall clock (50 Hz, quiet or loaded) is measured in ``make bench``
(:mod:`bench.gateway`). Lost longer than the gateway's 1 s without setpoints
(``stale_max_s``: the loop has no states to answer), its failsafe takes over: PX4's Hold, then its Land, disarmed,
no crash. (A 1 s loss sits on that boundary: it landed.) What PX4 says meanwhile is printed."""
from __future__ import annotations

import time

import numpy as np

from runtime.schema import HealthMsg
from services.px4_gateway import GatewayConfig
from tests.busutil import wait_for

GATEWAY = GatewayConfig()  # its watchdog sends the last pose, quality -1, once per tick while lost
# PX4 v1.16's EKF2 stops fusing external vision by itself when no sample has come for 2 × EV_MAX_INTERVAL (200 ms) of
# its time (ev_control.cpp, "vision data stopped"; common.h)
EKF2_VISION_STOPPED_S = 2 * 0.2
# the loss that must not end the flight is flown again (after the failsafe's landing, if any) when a stall of the
# machine made it last the gateway's failsafe second, or made a loss of its own: at most this many times
ATTEMPTS = 3


def px4_heard(flight) -> tuple[int, float, float]:
    """What PX4 heard of the last loss, in its time (s; lockstep: the world's), from its newest ULog's external
    vision (vehicle_visual_odometry, ``timestamp``: on arrival, as a repeated pose carries its old capture time):
    (failed samples logged, the last tracked one → the first failed one, the longest interval from that one to
    the first tracked one after). Logged, not sent: two samples within one cycle of PX4's logger are logged once
    (the gateway's 10 failed poses, 8 logged, up to 40 ms apart, on a quiet machine)."""
    from pyulog import ULog

    data = ULog(str(flight.newest_ulog()), ["vehicle_visual_odometry"]).data_list[0].data
    t_s, failed = data["timestamp"] / 1e6, np.flatnonzero(data["quality"].astype(int) < 0)
    breaks = np.flatnonzero(np.diff(failed) > 1)
    run = failed[failed > failed[breaks[-1]]] if breaks.size else failed
    assert run.size, "PX4 logged no failed external-vision sample"
    return run.size, t_s[run[0]] - t_s[run[0] - 1], float(np.diff(t_s[run[0]:run[-1] + 2]).max())


def gateway_counts(health: list[HealthMsg]) -> tuple[int, int]:
    """(failed poses sent, watchdog ticks late) in the gateway's newest health report."""
    status = health[-1].status
    return (int(status.split("mocap failed sent ")[1].split(",")[0]),
            int(status.split("watchdog late ")[1].split()[0].rstrip(",")))


def lose(flight, seconds: float, then_s: float) -> tuple[float, list[str]]:
    """Motion capture lost for ``seconds`` of the world's time, then ``then_s`` more of it; (the world's time it
    was lost at, what the processes said since)."""
    before = len(flight.output)
    lost_world_s = flight.probe.get("truth")[-1].t_s
    reply = flight.cmd("source", "lose_tracking", duration_s=seconds)
    assert reply.ok, reply
    wait_for("the world on", lambda: flight.probe.get("truth")[-1].t_s > lost_world_s + seconds + then_s, 60)
    return lost_world_s, flight.output[before:]


def lose_on_the_wall_clock(flight, wall_s: float, then_s: float) -> tuple[float, list[str]]:
    """Motion capture lost for ``wall_s`` of the wall clock (the command that ends it sent then: the world's 20 ms
    later, no state), then ``then_s`` more of the world's time; (the world's time it was lost at, what the processes
    said since)."""
    before = len(flight.output)
    lost_world_s = flight.probe.get("truth")[-1].t_s
    reply = flight.cmd("source", "lose_tracking", duration_s=3.0)  # at most 3 s, should the second command not come
    assert reply.ok, reply
    time.sleep(wall_s)
    reply = flight.cmd("source", "lose_tracking", duration_s=0.02)  # a loss commanded anew replaces the one running
    assert reply.ok, reply
    found_world_s = flight.probe.get("truth")[-1].t_s
    wait_for("the world on", lambda: flight.probe.get("truth")[-1].t_s > found_world_s + then_s, 60)
    return lost_world_s, flight.output[before:]


def recorded_spans(directory) -> dict[str, tuple[float, float]]:
    """Each recording in ``directory``: the world's time (s) of its first and last state."""
    from recordings.catalog import recordings_in
    from recordings.reader import read_recording

    spans = {}
    for path in recordings_in(directory):
        t_s = read_recording(path).channel("state").columns.get("t_s")
        if t_s is not None and len(t_s):
            spans[path.name] = (float(t_s[0]), float(t_s[-1]))
    return spans


def modes_since(flight, stamp_s: float) -> list[tuple[bool, str]]:
    """(armed, PX4's mode) as the gateway reported them after ``stamp_s``, each change once."""
    modes: list[tuple[bool, str]] = []
    for t in flight.probe.get("telemetry"):
        if t.stamp_s > stamp_s and (not modes or modes[-1] != (t.armed, t.flight_mode)):
            modes.append((t.armed, t.flight_mode))
    return modes


def test_motion_capture_lost_shorter_than_the_gateways_second_is_told_to_px4_and_the_flight_goes_on(flight):
    health: list[HealthMsg] = []
    flight.s.declare_subscriber(flight.probe.keys.health("px4_gateway"),
                                lambda smp: health.append(HealthMsg.from_bytes(smp.payload.to_bytes())))
    for attempt in range(1, ATTEMPTS + 1):
        flight.airborne()
        time.sleep(3.0)
        sent_before, late_before = gateway_counts(health)
        lost_world_s, said = lose_on_the_wall_clock(flight, 0.45, 5.0)
        states = [m for m in flight.probe.get("state") if m.t_s > lost_world_s - 1.0]
        state_t = np.array([m.t_s for m in states])
        gap = int(np.argmax(np.diff(state_t)))  # the last tracked state before the loss, in ``states``
        # the loss on the wall clock: from the last tracked state to the next one (their stamps)
        wall_s = states[gap + 1].stamp_s - states[gap].stamp_s
        # losses the gateway saw besides the test's: a stall of the world's process (no states on the wall clock)
        others = int(np.sum(np.diff([m.stamp_s for m in states]) > GATEWAY.pose_lost_after_s)) - 1
        if wall_s < GATEWAY.stale_max_s and not others or attempt == ATTEMPTS:
            break
        # not the loss this test is about: a stall of the machine lengthened it past the gateway's second, whose
        # failsafe then rightly held and landed (quiet run 29: the world stood still 0.95 s in it), or made one more
        # (quiet run 31: 0.80 s, 3 s after it; the gateway told PX4 twice). Again, once landed if it landed
        print(f"\nattempt {attempt}: the loss lasted {wall_s:.2f} s on the wall, {others} more; "
              f"{[line.strip() for line in said if 'stood still' in line or 'failsafe' in line]}")
        if any("failsafe" in line for line in said):
            wait_for("PX4 disarmed after the failsafe's land", lambda: not flight.telemetry().armed, 60)
    wait_for("a health report after it", lambda: health and health[-1].stamp_s > time.monotonic() - 0.5, 5)
    told = [line for line in said if "PX4 told it failed" in line]
    back = [line for line in said if "motion capture back after" in line]
    px4 = [line for line in said if "vehicle says" in line]
    truth = [m for m in flight.probe.get("truth") if m.t_s > lost_world_s - 1.0]
    t_world = np.array([m.t_s for m in truth])
    pos = np.array([m.pos_enu_m for m in truth])
    at = pos[np.searchsorted(t_world, lost_world_s)]
    found_world_s = float(state_t[gap + 1])
    blind = np.linalg.norm(pos[(t_world > lost_world_s) & (t_world < found_world_s)] - at, axis=1).max()
    refs = {m.seq: np.array(m.pos_enu_m) for m in flight.probe.get("reference")}
    last_2_s = [np.linalg.norm(np.array(m.pos_enu_m) - refs[m.seq]) for m in truth
                if m.t_s > found_world_s + 3.0 and m.seq in refs]
    state_gaps = np.diff(state_t)
    sent, late = np.subtract(gateway_counts(health), (sent_before, late_before))
    modes = modes_since(flight, truth[0].stamp_s)
    heard, told_px4_s, kept_px4_s = px4_heard(flight)
    print(f"\nmotion capture lost {wall_s:.2f} s on the wall ({state_gaps.max():.2f} s of the world's time): gateway "
          f"{told[:1]} {back[:1]}; PX4 said {px4}; (armed, mode) {modes}; farthest from where it was lost: "
          f"{blind * 100:.1f} cm while lost; "
          f"hover error in the last 2 s at most {max(last_2_s) * 100:.1f} cm; {sent} failed poses sent "
          f"(watchdog ticks late meanwhile: {late}); PX4 logged {heard}, the first {told_px4_s * 1e3:.0f} ms of its "
          f"time after the last tracked pose, then at most {kept_px4_s * 1e3:.0f} ms apart")
    assert len(told) == 1 and len(back) == 1, said[-30:]
    assert np.sum(state_gaps > 0.05) == 1, "no state for one span, states every period before and after it"
    # the loss this test is about: told (after pose_lost_after_s), and shorter than the gateway's failsafe's second
    assert GATEWAY.pose_lost_after_s + 0.1 <= wall_s < GATEWAY.stale_max_s, \
        f"the test's loss lasted {wall_s:.2f} s, in each of {ATTEMPTS} attempts"
    gap_s = float(back[0].split("motion capture back after ")[1].split(" s")[0])
    assert abs(gap_s - wall_s) < 0.1, (gap_s, wall_s)  # the gateway saw that span, as the world made it
    lost_for_s = gap_s - GATEWAY.pose_lost_after_s  # told after pose_lost_after_s without a state, until one came
    assert 1 <= sent <= GATEWAY.watchdog_hz * lost_for_s + 2, (sent, lost_for_s)  # once a tick at most, no burst
    # PX4 heard it, in its time, before EKF2 would have stopped the vision by itself (the interval until tracked
    # again is asserted by the longer loss below)
    assert told_px4_s < EKF2_VISION_STOPPED_S, told_px4_s
    # the flight goes on
    assert not any(m.crashed for m in truth) and min(pos[:, 2]) > 0.5, "in the air throughout, no crash"
    assert modes == [(True, "offboard")], modes
    assert max(last_2_s) < 0.1, "back at its hover"
    # one recording through it all, read back from the recorder's own files (the open one read as a crash would
    # leave it): one file holds the world's second before the loss to 3 s after it, no file begins in that span.
    # Before: the recorder's 1 Hz status at the test's probe; quiet run 17 saw none of its ~7 (the recorder's log
    # shows it recording through the loss; not root-caused, likely the bus dropping the status, a lower priority than
    # the loop's streams, on its way to a busy test process)
    spans = recorded_spans(flight.recordings)
    through = [f for f, (first, last) in spans.items() if first <= lost_world_s - 1.0 and last >= lost_world_s + 3.0]
    begun = [f for f, (first, _) in spans.items() if lost_world_s - 1.0 < first <= lost_world_s + 3.0]
    assert len(through) == 1 and not begun, ("one recording, through the loss", lost_world_s, spans)


def test_lost_longer_than_the_gateways_second_without_setpoints_px4_holds_then_lands(flight):
    flight.airborne()
    lost_world_s, said = lose(flight, 1.5, 10.0)
    wait_for("PX4 disarmed after its land", lambda: not flight.telemetry().armed, 60)
    truth = [m for m in flight.probe.get("truth") if m.t_s > lost_world_s]
    modes = modes_since(flight, truth[0].stamp_s)
    heard, told_px4_s, kept_px4_s = px4_heard(flight)
    print(f"\nmotion capture lost 1.5 s: (armed, mode) {modes}; gateway {[line for line in said if 'failsafe' in line]}; "
          f"PX4 logged {heard} failed poses, the first {told_px4_s * 1e3:.0f} ms of its time after the last tracked "
          f"pose, then at most {kept_px4_s * 1e3:.0f} ms apart")
    # in PX4's time: told before EKF2 would have stopped the vision by itself, and never silent that long until
    # tracked again (the watchdog kept telling it through its failsafe's hold and land)
    assert told_px4_s < EKF2_VISION_STOPPED_S and kept_px4_s < EKF2_VISION_STOPPED_S, (told_px4_s, kept_px4_s)
    assert any("commanding hold" in line for line in said) and any("commanding land" in line for line in said)
    assert [m for _, m in modes][:3] == ["offboard", "hold", "land"] and modes[-1][0] is False, modes
    assert not any(m.crashed for m in truth) and truth[-1].on_ground, "landed, no crash"
