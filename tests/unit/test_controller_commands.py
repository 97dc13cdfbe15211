"""The controller's operator commands beyond the missions: arm, disarm, hold, abort; a lemniscate's cycles."""
from __future__ import annotations

import subprocess
import sys

import numpy as np

from runtime.schema import StateMsg
from flight.controller import ControllerConfig, ControllerCore
from tests.busutil import REPO
from tests.helpers import estimate, fixed_clock


def moving_state(seq, z, vz=0.0):
    return StateMsg(seq=seq, stamp_s=1.0, t_s=0.02 * (seq + 1), pos_enu_m=(0.3, -0.2, z), vel_enu_mps=(0.0, 0.0, vz),
                    roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, source="sim")


def step(core, seq, z, vz=0.0):
    core.on_state(moving_state(seq, z, vz), 0.02 * seq)
    out = core.on_estimate(estimate(seq), 0.02 * seq + 0.001)
    return out[0] if out else (None, None)


def test_a_controller_started_idle_is_disarmed_and_refuses_take_off_until_armed():
    core = ControllerCore(ControllerConfig(mission="idle"), clock=fixed_clock)
    step(core, 0, 0.0)
    ok, why = core.command("takeoff", {})
    assert not ok and "arm" in why
    assert core.command("arm", {}) == (True, "armed: take-off allowed")
    assert core.command("takeoff", {})[0]
    _, ref = step(core, 1, 0.0)
    assert ref.segment == "takeoff"
    ok, why = core.command("disarm", {})
    assert not ok and "ground" in why  # not while flying


def test_a_controller_started_flying_is_armed():
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    assert core.armed and core.command("landing_test", {})[0]


def test_hold_freezes_the_reference_where_the_vehicle_is():
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    step(core, 0, 1.0)
    core.command("landing_test", {})
    for k in range(1, 100):
        _, ref = step(core, k, 1.0 - 0.004 * k, vz=-0.2)
    z_now = 1.0 - 0.004 * 99
    assert core.command("hold", {})[0]
    _, ref = step(core, 100, z_now, vz=-0.2)
    assert ref.segment == "hold"
    np.testing.assert_allclose(ref.pos_enu_m, (0.3, -0.2, z_now))
    assert ref.vel_enu_mps == (0.0, 0.0, 0.0)
    _, ref2 = step(core, 101, z_now - 0.003)
    assert ref2.pos_enu_m == ref.pos_enu_m  # frozen


def test_abort_lands_from_where_the_vehicle_is():
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    step(core, 0, 1.0)
    core.command("lemniscate", {})
    step(core, 1, 0.8)
    assert core.command("abort", {})[0]
    _, ref = step(core, 2, 0.8)
    assert ref.segment == "land"
    np.testing.assert_allclose(ref.pos_enu_m, (0.3, -0.2, 0.8), atol=1e-9)
    assert any(level == "warning" and "abort" in text for level, text in core.events)


def test_hold_and_abort_on_the_ground_are_refused_with_the_reason():
    core = ControllerCore(ControllerConfig(mission="idle"), clock=fixed_clock)
    step(core, 0, 0.0)
    for name in ("hold", "abort"):
        ok, why = core.command(name, {})
        assert not ok and "on the ground" in why


def test_a_land_ends_with_motors_idle_when_the_vehicle_rests_on_its_feet_above_the_landed_height():
    """The simulated vehicle's body origin rests 0.05 m above the floor, above ``landed_height_m``:
    the land still ends (reference on the floor for 1 s, vehicle low), where it used to push on
    the floor with minimum thrust for ever, and a recorder never saw the flight end."""
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    step(core, 0, 0.3)
    assert core.command("land", {})[0]
    thrusts = []
    for k in range(1, 150):  # 3 s: the 0.35 m transit takes ~1.2 s, then 1 s on the floor
        setpoint, ref = step(core, k, max(0.05, 0.3 - 0.3 * 0.02 * k))
        thrusts.append(setpoint.thrust_n)
    assert thrusts[-1] == 0.0 and thrusts[10] > 0.0
    assert any("landed" in text for _, text in core.events)
    assert core.mission.segment == "idle"


def test_a_command_given_a_world_time_starts_at_that_sample_whatever_its_latency():
    """``at_t_s``: the mission starts at the first sample at or after that world time (paired runs of `neso demo
    tdr` start each lemniscate at the same world time, however late the command came); a wrong value is refused."""
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    step(core, 0, 1.0)
    ok, why = core.command("landing_test", {"at_t_s": 0.1})  # sample 4's world time (t = 0.02 (seq + 1))
    assert ok and "world t = 0.10 s" in why
    segments = [step(core, k, 1.0)[1].segment for k in range(1, 7)]
    assert segments == ["hover", "hover", "hover", "transit", "transit", "transit"], segments  # its transit first
    ok, why = core.command("landing_test", {"at_t_s": "soon"})
    assert not ok and "at_t_s" in why


def test_a_lemniscate_flies_the_cycles_asked_and_a_wrong_count_is_refused():
    """``cycles``: the lemniscate flies that many 6 s cycles (the mission's 5 without it); a count that is not a whole
    number in 1-20, or given to another command, is refused with the reason and nothing starts."""
    durations = {}
    for cycles in (None, 3):
        core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
        step(core, 0, 0.25)
        ok, why = core.command("lemniscate", {} if cycles is None else {"cycles": cycles})
        assert ok, why
        segments = [step(core, k, 0.25)[1].segment for k in range(1, 2500)]
        assert segments[-1] == "hover"
        durations[cycles] = 0.02 * segments.count("lemniscate")  # world s of the lemniscate, its ramp included
    assert abs(durations[3] - (durations[None] - 2 * 6.0)) < 0.03, durations
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    step(core, 0, 1.0)
    for name, args in (("lemniscate", {"cycles": 0}), ("lemniscate", {"cycles": 21}), ("lemniscate", {"cycles": 2.5}),
                       ("lemniscate", {"cycles": True}), ("landing_test", {"cycles": 3})):
        ok, why = core.command(name, args)
        assert not ok and "cycles" in why and "1-20" in why, (name, args, why)
    assert core._pending_command is None


def test_neso_demo_tdr_refuses_a_wrong_cycle_count_in_one_line_before_anything_starts(tmp_path):
    done = subprocess.run([sys.executable, "-m", "cli.main", "demo", "tdr", "--lemniscate-cycles", "0", "--workdir",
                           str(tmp_path / "work")], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == "neso demo tdr: --lemniscate-cycles 0: 1-20\n", done
    assert not (tmp_path / "work").exists(), "nothing started"
