"""Mission: a continuous reference from operator commands, and the operations the controller needs."""
from __future__ import annotations

import numpy as np
import pytest

from flight.mission import COMMANDS, Mission, MissionConfig


def flying(name: str = "takeoff", t_s: float = 0.0) -> Mission:
    mission = Mission(MissionConfig())
    mission.start(name, t_s, np.array([0.0, 0.0, 0.05]))
    return mission


def test_a_command_starts_from_the_reference_not_the_vehicle():
    mission = flying("takeoff")
    ref = mission.reference(1.0)
    mission.start("hover", 1.0, np.array([5.0, 5.0, 5.0]))  # a vehicle far from its reference
    np.testing.assert_allclose(mission.reference(1.5).pos_enu_m, ref.pos_enu_m)
    assert mission.segment == "hover"


def test_hold_freezes_the_reference_at_the_measured_position():
    mission = flying("lemniscate")
    mission.reference(4.0)
    measured = np.array([0.3, -0.2, 0.27])
    assert mission.hold(4.0, measured)
    for t_s in (4.0, 10.0, 100.0):
        ref = mission.reference(t_s)
        np.testing.assert_array_equal(ref.pos_enu_m, measured)
        np.testing.assert_array_equal(ref.vel_enu_mps, np.zeros(3))
    assert mission.segment == "hold"


def test_abort_lands_from_the_measured_position():
    mission = flying("takeoff")
    mission.reference(2.0)
    measured = np.array([0.1, 0.1, 0.6])
    assert mission.abort(2.0, measured)
    np.testing.assert_allclose(mission.reference(2.0).pos_enu_m, measured)
    assert mission.segment == "land"
    assert mission.reference(2.0 + 0.6 / MissionConfig().land_speed_mps + 0.5).pos_enu_m[2] < 0.0
    assert mission.landed(0.03)
    assert mission.idle and mission.reference(30.0) is None


def test_hold_and_abort_do_nothing_on_the_ground():
    mission = Mission(MissionConfig())
    assert not mission.hold(0.0, np.zeros(3)) and not mission.abort(0.0, np.zeros(3))
    assert mission.idle and mission.reference(1.0) is None


def test_an_unknown_command_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="lemniscate"):
        Mission().start("loop", 0.0, np.zeros(3))
    assert "hold" not in COMMANDS  # hold/abort are operations, not missions


@pytest.mark.parametrize("start_z", [0.05, 0.3, 0.45, 1.0, 2.0])
def test_every_segments_z_reference_stays_inside_its_bounds_and_the_certificates_envelope(start_z):
    """What the stability certificate states its |e_z| bound for: each segment's z speed, acceleration and jerk
    (flight.mission.segment_reference_bounds, worked out from the quintics) bound the reference the missions fly,
    sampled, from any start; and every segment stays inside the envelope the verdict's guard uses."""
    from neso.certificate import POLICY, ReferenceBounds

    from flight.mission import segment_reference_bounds

    bounds = segment_reference_bounds()
    envelope = ReferenceBounds.envelope(POLICY)
    for b in bounds.values():
        assert b.vel_mps <= envelope.vel_mps and b.acc_mps2 <= envelope.acc_mps2 and b.jerk_mps3 <= envelope.jerk_mps3
    dt = 1e-3
    seen: dict[str, list[np.ndarray]] = {}
    for command in COMMANDS:
        mission = Mission(MissionConfig())
        mission.start("hover", 0.0, np.array([0.0, 0.0, start_z]))
        mission.reference(0.0)
        mission.start(command, 0.0, np.array([0.0, 0.0, start_z]))
        for t in np.arange(0.0, 40.0, dt):
            ref = mission.reference(float(t))
            if ref is None:
                break
            seen.setdefault(mission.segment, []).append((ref.vel_enu_mps[2], ref.acc_enu_mps2[2]))
    assert {"landing_test", "lemniscate", "land", "hover"} <= set(seen) <= set(bounds)
    assert ("takeoff" in seen) == (abs(start_z - MissionConfig().takeoff_height_m) > MissionConfig().at_point_tol_m)
    for segment, rows in seen.items():
        v, a = np.array(rows).T
        jerk = np.abs(np.diff(a)) / dt
        b = bounds[segment]
        assert np.max(np.abs(v)) <= b.vel_mps * (1 + 1e-9) + 1e-12, segment
        assert np.max(np.abs(a)) <= b.acc_mps2 * (1 + 1e-9) + 1e-12, segment
        # a segment's first step may include the switch from the one before (a jump in z̈* the quintics avoid)
        assert np.max(jerk[1:], initial=0.0) <= b.jerk_mps3 * 1.001 + 1e-9, segment
