"""The preflight verdict (flight/preflight.py): a ready vehicle is a go with one line per item; each check that
fails is a no-go naming the item and its fix; jitter and latency are reported and only warn."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest

from flight.preflight import GO, NO_GO, WARNING, PreflightInputs, ServiceSeen, ev_delay_to_set_ms, preflight, \
    table_from_items
from flight.px4_params import checked
from sim.px4_sitl import load_params

WORLD = {p.name: float(load_params()[p.name]) for p in checked()}
HEALTHY = {n: ServiceSeen(True, 0.4, "ok") for n in ("source", "estimator", "controller", "recorder", "px4_gateway")}
MOCAP = {"mocap_rate_hz": 100.0, "mocap_latency_p50_ms": 12.0, "mocap_latency_p99_ms": 14.0, "mocap_jitter_ms": 2.0,
         "motive_latency_ms": 10.0, "mocap_gap_max_ms": 10.0, "mocap_frames_out_of_order": 0.0, "rigid_body_tracked": 1.0}
READY = PreflightInputs(
    connected=True, autopilot="PX4 v1.16.0 6ea3539", armable=True, params=WORLD, local_position_ok=True,
    ev_offset_m=0.002, ev_height_offset_m=-0.004, origin_alt_m=0.0, mocap=MOCAP, state_age_s=0.01, services=HEALTHY, delay_ms=(12.5, 15.0),
    px4_uses_capture_time=False, certificate={"holds": True, "text": "certificate holds: L_N 3.8 vs 7.4"},
    battery_remaining=0.9, battery_v=16.2)


def verdicts(inputs: PreflightInputs) -> dict[str, tuple[str, str, str]]:
    return {i.name: (i.verdict, i.found, i.fix) for i in preflight(inputs).items}


def test_a_ready_vehicle_is_a_go_with_one_line_per_item():
    v = preflight(READY)
    assert v.go, v.table()
    names = [i.name for i in v.items]
    assert names[:2] == ["autopilot", "PX4 pre-arm checks"]
    for p in checked():
        assert p.name in names
    for name in ("EKF2 fuses the motion capture", "global origin", "rigid body seen", "motion capture rate", "motion capture latency",
                 "motion capture jitter", "service source", "service estimator", "service controller", "certificate",
                 "battery"):
        assert name in names
    table = v.table()
    assert len(table.splitlines()) == len(v.items) + 1 and table.splitlines()[-1].startswith("GO:")
    assert table_from_items(v.as_items()) == table  # what the bus carries prints the same


@pytest.mark.parametrize("p", [p for p in checked() if not p.required.measured], ids=lambda p: p.name)
def test_each_required_parameter_wrong_in_turn_is_named_with_its_fix(p):
    wrong = {**WORLD, p.name: -7.0}
    verdict, found, fix = verdicts(replace(READY, params=wrong))[p.name]
    assert verdict == p.required.severity and found == "-7" and fix.startswith(f"param set {p.name} ")
    assert preflight(replace(READY, params=wrong)).go == (p.required.severity != NO_GO)


def test_ekf2_ev_qmin_at_px4s_default_is_a_no_go():
    v = preflight(replace(READY, params={**WORLD, "EKF2_EV_QMIN": 0.0}))
    assert not v.go and [i.name for i in v.no_go()] == ["EKF2_EV_QMIN"]
    assert v.table().splitlines()[-1] == "NO-GO: EKF2_EV_QMIN"
    assert "param set EKF2_EV_QMIN 1" in v.table()


def test_a_parameter_the_vehicle_lacks_and_unread_parameters_are_no_go():
    assert verdicts(replace(READY, params={**WORLD, "EKF2_EV_QMIN": None}))["EKF2_EV_QMIN"][:2] == (NO_GO, "missing")
    v = preflight(replace(READY, params={}, params_error="COM_OF_LOSS_T: TIMEOUT"))
    assert [i.name for i in v.no_go()] == ["PX4 parameters"]


def test_jitter_latency_and_gaps_are_reported_and_only_warn():
    shaky = {**MOCAP, "mocap_latency_p50_ms": 150.0, "mocap_latency_p99_ms": 420.0, "mocap_jitter_ms": 270.0,
             "mocap_gap_max_ms": 410.0}
    got = verdicts(replace(READY, mocap=shaky))
    assert got["motion capture jitter"][:2] == (WARNING, "270.0 ms (p99 − p50)")
    assert got["motion capture latency"][0] == WARNING and "p99 420.0 ms" in got["motion capture latency"][1]
    assert got["motion capture gaps"][0] == WARNING
    assert preflight(replace(READY, mocap=shaky)).go


@pytest.mark.parametrize("change,item", [
    (dict(connected=False), "autopilot"),
    (dict(armable=False, armable_why="CRITICAL: Preflight Fail: heading estimate not stable"), "PX4 pre-arm checks"),
    (dict(local_position_ok=False), "EKF2 fuses the motion capture"),
    (dict(ev_offset_m=0.4), "EKF2 fuses the motion capture"),
    (dict(ev_height_offset_m=487.8), "EKF2 fuses the motion capture"),
    (dict(origin_alt_m=488.0), "global origin"),
    (dict(mocap={**MOCAP, "rigid_body_tracked": 0.0}), "rigid body seen"),
    (dict(state_age_s=math.inf), "rigid body seen"),
    (dict(mocap={**MOCAP, "mocap_rate_hz": 30.0}), "motion capture rate"),
    (dict(services={k: v for k, v in HEALTHY.items() if k != "estimator"}), "service estimator"),
    (dict(services={**HEALTHY, "controller": ServiceSeen(True, 9.0)}), "service controller"),
    (dict(certificate={"holds": False, "text": "certificate FAILS"}), "certificate"),
    (dict(certificate=None), "certificate"),
    (dict(battery_remaining=0.2), "battery"),
])
def test_what_no_parameter_shows_is_checked_too(change, item):
    v = preflight(replace(READY, **change))
    assert not v.go and item in [i.name for i in v.no_go()], v.table()
    assert all(i.fix for i in v.no_go())


def test_an_origin_above_0_m_is_a_no_go_only_with_vision_height_and_none_yet_only_warns():
    """PX4 v1.16 restarts vision height without the origin's altitude (flight.preflight._origin): with
    EKF2_HGT_REF 3 an origin at 488 m (PX4 SITL's home) is a no-go naming the fix; with the barometer's height it is
    not this check's business; none reported yet is a warning (the gateway is about to send one)."""
    got = verdicts(replace(READY, origin_alt_m=488.0))["global origin"]
    assert got[0] == NO_GO and "488 m off" in got[1] and "--global-origin lat,lon,0" in got[2]
    assert verdicts(replace(READY, origin_alt_m=488.0, params={**WORLD, "EKF2_HGT_REF": 0.0}))["global origin"][0] == GO
    assert verdicts(replace(READY, origin_alt_m=None))["global origin"][0] == WARNING
    height = verdicts(replace(READY, ev_height_offset_m=487.8))["EKF2 fuses the motion capture"]
    assert height[0] == NO_GO and "+487.80 m" in height[1]


def test_the_ev_delay_to_set_is_the_measured_delay_or_zero_once_px4_takes_the_capture_time():
    assert ev_delay_to_set_ms(READY) == 12.5
    assert ev_delay_to_set_ms(replace(READY, px4_uses_capture_time=True)) == 0.0
    got = verdicts(replace(READY, params={**WORLD, "EKF2_EV_DELAY": 40.0}))["EKF2_EV_DELAY"]
    assert got[0] == WARNING and got[2].startswith("param set EKF2_EV_DELAY 12") and "12.5 ms" in got[1]
    assert verdicts(replace(READY, params={**WORLD, "EKF2_EV_DELAY": 10.0}))["EKF2_EV_DELAY"][0] == GO
    synced = verdicts(replace(READY, px4_uses_capture_time=True, params={**WORLD, "EKF2_EV_DELAY": 10.0}))
    assert synced["EKF2_EV_DELAY"][0] == WARNING and synced["EKF2_EV_DELAY"][2].startswith("param set EKF2_EV_DELAY 0")


def test_the_gateway_recomputes_the_estimators_certificate_through_its_public_api():
    """The network report's certificate (what flight.estimator computes) judged again with
    neso.certificate.flight_certificate: the same verdict; a report of another form falls back to the estimator's
    own verdict and says so."""
    from types import SimpleNamespace

    from flight.estimator import network_certificate
    from neso.certificate import LoopPlant
    from neso.control import ControlConfig
    from neso.netfile import load_network
    from services.px4_preflight import CertificateCheck
    from tests.helpers import BASE

    report = network_certificate(load_network(BASE), 10.0, 6.0, 15.0, LoopPlant.of(ControlConfig())).to_dict()
    again = CertificateCheck().verdict(SimpleNamespace(certificate=report))
    assert (again["holds"], again["text"]) == (report["holds"], report["text"])
    odd = CertificateCheck().verdict(SimpleNamespace(certificate={"holds": True, "text": "certificate holds"}))
    assert odd["holds"] and "the estimator's verdict: its report could not be recomputed here" in odd["text"]
    assert CertificateCheck().verdict(None) is None
