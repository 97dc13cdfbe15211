"""The services' step objects, driven directly (no bus)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.params import Param, ParamSet
from runtime.schema import StateMsg
from flight.controller import ControllerConfig, ControllerCore
from flight.estimator import EstimatorConfig, EstimatorCore, NetworkChoice, estimator_params, load_flown_network
from flight.source import MocapConfig, MocapSource, frame_matrix
from tests.helpers import BASE, REPO, estimate, fixed_clock


def state(seq, z=1.0, t=None):
    return StateMsg(seq=seq, stamp_s=1.0, t_s=0.02 * (seq + 1) if t is None else t, pos_enu_m=(0.0, 0.0, z),
                    vel_enu_mps=(0.0, 0.0, 0.0), roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, source="sim")


# -- parameters -------------------------------------------------------------------------------
def test_param_set_refuses_invalid_values_with_the_reason_and_changes_nothing():
    ps = ParamSet((Param("gain", 1.0, float, "g", lo=0, hi=10), Param("mode", "a", str, "m", choices=("a", "b"))),
                  check=lambda v: "gain 7 is unlucky" if v["gain"] == 7 else None)
    for bad, reason in (({"gain": 11}, "outside"), ({"gain": "x"}, "number"), ({"mode": "c"}, "one of"),
                        ({"nope": 1}, "unknown"), ({"gain": math.nan}, "outside"), ({"gain": 7}, "unlucky"),
                        ({"gain": 2, "mode": "c"}, "one of")):
        ok, why, values = ps.request(bad)
        assert not ok and reason in why
        assert values == {"gain": 1.0, "mode": "a"}
        assert ps.take_pending() == {}
    ok, _, values = ps.request({"gain": 2})
    assert ok and values["gain"] == 2.0 and ps.effective()["gain"] == 1.0  # not until the tick boundary
    assert ps.take_pending() == {"gain": 2.0} and ps.effective()["gain"] == 2.0


# -- estimator ---------------------------------------------------------------------------------
def _bound(stem: str) -> float:
    """The physical L_N a shipped network states."""
    return load_flown_network(str(REPO / "networks" / f"{stem}.safetensors"))[0].lipschitz_bound_physical()


@pytest.fixture(scope="module")
def choice():
    net, source = load_flown_network(BASE)
    return NetworkChoice(net, source, str(REPO / "networks"))


def test_a_bound_with_a_trained_network_on_disk_loads_it(choice):
    half = _bound("base-x0.5")
    assert choice.refusal(half) is None
    net, note = choice.network_for(half)
    assert net.lipschitz_bound_physical() == half and "base-x0.5" in note and "trained for" in note


def test_a_bound_without_one_scales_the_loaded_network_to_meet_its_certificate(choice):
    """L_N is the physical bound on the state inputs (the certificate's loop gain): the scaled network meets it."""
    bound = 0.9 * _bound("base")
    net, note = choice.network_for(bound)
    assert net.certified_lipschitz_state() <= bound * (1 + 1e-9) and "scaled" in note


def test_a_bound_above_the_training_bound_without_a_network_is_refused(choice):
    assert "above" in choice.refusal(1.5 * _bound("base"))
    assert choice.refusal(_bound("base-x2")) is None  # base-x2 is on disk
    assert choice.refusal(0.5 * _bound("base")) is None  # scaling down is always possible


def test_estimator_core_applies_pathway_and_bound_at_the_next_sample(choice):
    core = EstimatorCore(EstimatorConfig(network=BASE), choice.loaded, choice, clock=fixed_clock)
    ps = ParamSet(estimator_params(core.config, _bound("base")), check=core.check)
    assert not ps.request({"lipschitz_bound": 1.5 * _bound("base")})[0]  # above its training bound, none on disk
    out = core.on_state(state(0), 0.0)
    assert out[0].pathway == "neural_eso" and out[0].warm_ticks == 1
    half = _bound("base-x0.5")
    assert ps.request({"pathway": "eso", "lipschitz_bound": half})[0]
    note = core.apply(ps.take_pending())
    assert "pathway eso" in note and "base-x0.5" in note
    out = core.on_state(state(1), 0.0)
    assert out[0].pathway == "eso" and out[0].network_id == f"base-x0.5@L{half:.4g}"
    assert core.on_state(state(1), 0.0) == out, "a re-sent sample gets the same answer"


def test_a_new_bound_is_certified_before_the_lock_so_the_check_under_it_solves_nothing(choice):
    """The node runs ``prepare`` outside its lock and ``check`` under it (runtime.node): the check of a new L_N must
    find its certificate warm. Before, ``prepare`` warmed only the flying network's, and the check solved the new
    one's SDPs under the lock (0.35 s idle; a CI run's reply missed its 2 s while the loop waited)."""
    from neso.certificate import flight_certificate

    core = EstimatorCore(EstimatorConfig(network=BASE), choice.loaded, choice, clock=fixed_clock)
    ps = ParamSet(estimator_params(core.config, _bound("base")), check=core.check, prepare=core.prepare)
    change = {"lipschitz_bound": 0.77 * _bound("base")}  # asked by no other test: not in the cache yet
    before = flight_certificate.cache_info().misses
    ps.prepare(change)
    warmed = flight_certificate.cache_info().misses
    assert warmed > before, "prepare solved the new bound's certificate"
    assert ps.request(change)[0]
    assert flight_certificate.cache_info().misses == warmed, "the check under the lock found it warm"


def test_lockstep_estimator_waits_for_the_previous_setpoint(choice):
    from runtime.schema import SetpointMsg

    core = EstimatorCore(EstimatorConfig(network=BASE, lockstep=True), choice.loaded, choice, clock=fixed_clock)
    assert len(core.on_state(state(0), 0.0)) == 1
    assert core.on_state(state(1), 0.0) == []
    sp = SetpointMsg(seq=0, stamp_s=1.0, state_stamp_s=1.0, t_s=0.02, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0,
                     thrust_norm=0.5, thrust_n=9.81, acc_cmd_enu_mps2=(0.0, 0.0, 0.0), estimate_source="estimator")
    assert [e.seq for e in core.on_setpoint(sp, 0.0)] == [1]


def _setpoint(seq: int):
    from runtime.schema import SetpointMsg

    return SetpointMsg(seq=seq, stamp_s=1.0, state_stamp_s=1.0, t_s=0.02 * (seq + 1), roll_rad=0.0, pitch_rad=0.0,
                       yaw_rad=0.0, thrust_norm=0.5, thrust_n=9.81, acc_cmd_enu_mps2=(0.0, 0.0, 0.0),
                       estimate_source="estimator")


def test_a_lockstep_state_whose_setpoint_never_came_does_not_hold_up_the_states_after_it(choice):
    """Setpoint 1 lost: state 2 waits for it; the controller flies 2 on its own (after ``lockstep_stale_s``) and
    the loop moves on. State 2 is then stale: it must not stay at the head of the queue, where every later state
    that arrives before its own previous setpoint would wait behind it for good (before: sample 4 never answered,
    so the controller flew it on its local ESO too; found reading the code for test_tdr_loop's silent samples)."""
    core = EstimatorCore(EstimatorConfig(network=BASE, lockstep=True), choice.loaded, choice, clock=fixed_clock)
    assert [e.seq for e in core.on_state(state(0), 0.0)] == [0]
    core.on_setpoint(_setpoint(0), 0.0)
    assert [e.seq for e in core.on_state(state(1), 0.0)] == [1]
    assert core.on_state(state(2), 0.0) == []  # setpoint 1 lost on the way
    assert core.on_setpoint(_setpoint(2), 0.0) == []  # flown on the controller's local ESO: nothing to answer
    assert [e.seq for e in core.on_state(state(3), 0.0)] == [3]
    assert core.on_state(state(4), 0.0) == []  # before its setpoint 3: waits
    assert [e.seq for e in core.on_setpoint(_setpoint(3), 0.0)] == [4]
    assert core.events == [("warning", "lockstep: no setpoint 1 came for state 2; the loop moved on without it "
                                       "(at state 3)")]


# -- controller -------------------------------------------------------------------------------
def test_a_lost_setpoint_in_lockstep_is_sent_again_with_the_sources_resend_and_the_loop_goes_on(choice):
    """Lockstep's triangle heals a lost message with the source's re-send of the state it has no setpoint for. A
    setpoint lost on its way to the estimator only (the source got it and sent the next state) left the estimator
    waiting for it and the controller waiting for the estimate until the local ESO flew (a loaded run's
    test_tdr_loop: "no setpoint 5248 came for state 5249"); the controller now sends it again on that re-send."""
    ctrl = ControllerCore(ControllerConfig(), clock=fixed_clock)
    est = EstimatorCore(EstimatorConfig(network=BASE, lockstep=True), choice.loaded, choice, clock=fixed_clock)
    for k in range(3):
        answers = est.on_state(state(k), 0.0)
        assert ctrl.on_state(state(k), 0.0) == [] and [e.seq for e in answers] == [k]
        (sp, _), = ctrl.on_estimate(answers[0], 0.0)
        if k < 2:  # setpoint 2 lost on the way to the estimator
            est.on_setpoint(sp, 0.0)
    assert est.on_state(state(3), 0.0) == [] and ctrl.on_state(state(3), 0.0) == []
    resent, = ctrl.on_state(state(3), 1.0)  # the source's re-send of state 3, 1 s later
    assert resent[0].seq == 2
    answers = est.on_setpoint(resent[0], 1.0)
    assert [e.seq for e in answers] == [3] and est.events == []
    (sp, _), = ctrl.on_estimate(answers[0], 1.0)
    assert sp.seq == 3 and sp.estimate_source == "estimator"
    assert ctrl.on_state(state(0), 2.0) == [] and ctrl.on_state(state(0), 2.1) == [], \
        "a new flight's sample 0, sent again before its estimate came: nothing of the last flight's answers it"


def test_controller_pairs_state_and_estimate_in_either_order():
    core = ControllerCore(ControllerConfig(), clock=fixed_clock)
    assert core.on_state(state(0), 0.0) == []
    (sp, ref), = core.on_estimate(estimate(0), 0.001)
    assert sp.seq == 0 and sp.estimate_source == "estimator" and ref.segment == "hover"
    assert sp.estimate_stamp_s == 1.0, "the estimate's stamp rides along: a late setpoint tells who was late"
    assert core.on_estimate(estimate(1), 0.02) == []
    (sp, _), = core.on_state(state(1), 0.021)
    assert sp.seq == 1


def test_controller_falls_back_to_its_local_eso_when_the_estimate_is_stale_and_returns_when_warm():
    cfg = ControllerConfig(stale_timeout_s=0.06, warmup_ticks=25)
    core = ControllerCore(cfg, clock=fixed_clock)
    t = 0.0
    for k in range(10):
        core.on_state(state(k), t)
        core.on_estimate(estimate(k), t + 0.001)
        t += 0.02
    # estimator dies: states keep coming, nothing answers them until the watchdog fires
    fallback_at = None
    for k in range(10, 20):
        out = core.on_state(state(k), t)
        for step in (0.005 * i for i in range(1, 4)):
            out += core.check_stale(t + step)
        if out and fallback_at is None:
            fallback_at = k
            assert out[0][0].estimate_source == "local_eso" and out[0][0].estimate_stamp_s == 0.0
        t += 0.02
    assert fallback_at is not None and fallback_at <= 13, "within 3 periods of the first missing estimate"
    assert any(level == "warning" and "local ESO" in text and "the estimator's newest answer was for sample 9" in text
               for level, text in core.events)
    assert core.fallbacks == 1
    # a restarted estimator that is not warm yet is not used
    out = core.on_state(state(20), t)
    assert out[0][0].estimate_source == "local_eso"
    assert core.on_estimate(estimate(20, warm=3), t) == [] and core.using_local
    core.on_estimate(estimate(20, warm=30), t)
    assert not core.using_local
    (sp, _), = core.on_state(state(21), t + 0.02) or core.on_estimate(estimate(21), t + 0.021)
    assert sp.estimate_source == "estimator"


def test_controller_falls_back_at_the_sample_after_three_unanswered_ones_without_its_watchdog():
    """A late watchdog thread (a loaded machine) must not delay the fallback: the fourth sample
    in a row without an estimate is flown on the local ESO when it arrives."""
    core = ControllerCore(ControllerConfig(stale_timeout_s=0.06, stale_samples=3), clock=fixed_clock)
    t = 0.0
    for k in range(10):
        core.on_state(state(k), t)
        core.on_estimate(estimate(k), t + 0.001)
        t += 0.02
    assert [core.on_state(state(k), t + 0.02 * (k - 10)) for k in (10, 11, 12)] == [[], [], []]
    (sp, _), = core.on_state(state(13), t + 0.06)
    assert sp.seq == 13 and sp.estimate_source == "local_eso"


def test_controller_gain_change_keeps_the_force_continuous():
    core = ControllerCore(ControllerConfig(), clock=fixed_clock)
    core.on_state(state(0, z=0.9), 0.0)
    (sp0, _), = core.on_estimate(estimate(0, fz=0.0), 0.0)
    core.apply_gains({"kp_xy": 6.0, "kd_xy": 4.5, "kp_z": 40.0, "kd_z": 6.0})
    core.on_state(state(1, z=0.9), 0.02)
    (sp1, _), = core.on_estimate(estimate(1, fz=0.0), 0.02)
    assert abs(sp1.thrust_n - sp0.thrust_n) <= core.config.control.force_step_limit_n + 1e-9


def test_the_controller_flies_the_vehicles_mass_and_reports_it_as_a_parameter():
    from dataclasses import replace

    from flight.controller import CONTROLLER_PARAMS, gain_values, resolved

    heavy = ControllerConfig(mass_kg=2.65)
    assert resolved(heavy).control.vehicle.mass_kg == 2.65 and gain_values(resolved(heavy).control)["mass_kg"] == 2.65
    assert "mass_kg" in {p.name for p in CONTROLLER_PARAMS}
    thrust = {}
    for mass in (1.0, 2.65):
        core = ControllerCore(replace(ControllerConfig(), mass_kg=mass), clock=fixed_clock)
        core.on_state(state(0, z=1.0), 0.0)
        (sp, _), = core.on_estimate(estimate(0, fz=0.0), 0.0)
        thrust[mass] = sp.thrust_n
    assert thrust[2.65] == pytest.approx(2.65 * thrust[1.0], rel=1e-9)  # newtons for the vehicle flown
    soft = ControllerCore(ControllerConfig(gains="px4", mass_kg=2.65), clock=fixed_clock)  # the set named, mass kept
    assert gain_values(soft.config.control) == {"kp_xy": 2.0, "kd_xy": 2.0, "kp_z": 10.0, "kd_z": 6.0, "mass_kg": 2.65}
    core = ControllerCore(ControllerConfig(), clock=fixed_clock)
    core.apply_gains({**gain_values(core.config.control), "mass_kg": 1.4})
    assert core.config.mass_kg == 1.4 and core.config.control.vehicle.mass_kg == 1.4


def test_mission_commands_take_effect_at_the_next_sample():
    core = ControllerCore(ControllerConfig(mission="hover"), clock=fixed_clock)
    core.on_state(state(0), 0.0)
    core.on_estimate(estimate(0), 0.0)
    assert core.command("fly_to_mars", {})[0] is False
    assert core.command("land", {})[0]
    core.on_state(state(1), 0.02)
    (_, ref), = core.on_estimate(estimate(1), 0.02)
    assert ref.segment == "land"


# -- motion capture mapping -------------------------------------------------------------------
def test_mocap_y_up_frame_maps_to_enu_and_velocity_follows():
    src = MocapSource(MocapConfig(frame="y_up", vel_cutoff_hz=1e6), rate_hz=50.0, clock=fixed_clock)
    # y-up frame: 1 m above the floor is y = 1; "towards the operator" z = -2 is 2 m north (ENU y)
    msg = src.frame(0.0, np.array([0.5, 1.0, -2.0]), (1.0, 0.0, 0.0, 0.0))
    assert msg.pos_enu_m == pytest.approx((0.5, 2.0, 1.0))
    assert (msg.roll_rad, msg.pitch_rad, msg.yaw_rad) == pytest.approx((0, 0, 0))
    assert src.frame(0.01, np.array([0.5, 1.01, -2.0]), (1.0, 0.0, 0.0, 0.0)) is None  # between control ticks
    msg = src.frame(0.02, np.array([0.5, 1.02, -2.0]), (1.0, 0.0, 0.0, 0.0))
    assert msg.vel_enu_mps == pytest.approx((0.0, 0.0, 1.0)) and msg.t_s == pytest.approx(0.02)
    # a yaw of 90° about the mocap's up axis (y) is a yaw of 90° in ENU
    c = math.cos(math.pi / 4)
    msg = src.frame(0.04, np.array([0.5, 1.02, -2.0]), (c, 0.0, c, 0.0))
    assert msg.yaw_rad == pytest.approx(math.pi / 2)


def test_mocap_frame_must_be_a_rotation():
    assert frame_matrix("1 0 0 0 1 0 0 0 1").tolist() == np.eye(3).tolist()
    for bad in ("2 0 0 0 1 0 0 0 1", "1 0 0 0 1 0 0 0 -1", "zup", "1 2 3"):
        with pytest.raises(ValueError):
            frame_matrix(bad)
