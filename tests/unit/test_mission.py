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
