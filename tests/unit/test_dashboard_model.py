"""The dashboard's model: messages in, figures out (no bus, no browser)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dashboard.model import (STATUS_SLOTS, CertificateShown, FleetModel, StatusItem, VehicleModel, certificate_shown,
                             status_line)
from dashboard.service import decode_into
from neso.types import OMEGA_O_RPS
from runtime.schema import (EstimateMsg, EventMsg, HealthMsg, Keys, NetworkMsg, RecordingMsg, ReferenceMsg,
                            SetpointMsg, StateMsg, TelemetryMsg)


def state(seq, z, stamp=100.0):
    return StateMsg(seq=seq, stamp_s=stamp, t_s=0.02 * seq, pos_enu_m=(0.0, 0.0, z), vel_enu_mps=(0.0, 0.0, 0.0),
                    roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, source="sim")


def reference(seq, z):
    return ReferenceMsg(seq=seq, stamp_s=100.0, t_s=0.02 * seq, pos_enu_m=(0.0, 0.0, z), vel_enu_mps=(0.0, 0.0, 0.0),
                        acc_enu_mps2=(0.0, 0.0, 0.0), yaw_rad=0.0, segment="hover")


def setpoint(seq, stamp, state_stamp, thrust=9.81):
    return SetpointMsg(seq=seq, stamp_s=stamp, state_stamp_s=state_stamp, t_s=0.02 * seq, roll_rad=0.0,
                       pitch_rad=0.0, yaw_rad=0.0, thrust_norm=0.5, thrust_n=thrust, acc_cmd_enu_mps2=(0.0, 0.0, 0.0),
                       estimate_source="estimator")


def estimate(seq, fn, dfh):
    return EstimateMsg(seq=seq, stamp_s=100.0, t_s=0.02 * seq, f_hat_mps2=(0.0, 0.0, fn + dfh), f_n_mps2=(0.0, 0.0, fn),
                       delta_f_hat_mps2=(0.0, 0.0, dfh), z=(0.0,) * 5, pathway="eso", network_id="n", warm_ticks=seq)


def test_messages_of_one_sample_share_a_row_whatever_their_order():
    v = VehicleModel("uav1")
    v.ingest("estimate", estimate(3, -0.5, 0.1), 0.0)
    v.ingest("reference", reference(3, 1.0), 0.0)
    v.ingest("state", state(3, 0.98), 0.0)
    v.ingest("setpoint", setpoint(3, 100.002, 100.0, thrust=10.5), 0.0)
    w = v.window()
    assert len(w["t"]) == 1
    assert (w["z"][0], w["ref_z"][0], w["f_n_z"][0], w["df_hat_z"][0], w["thrust_n"][0]) == pytest.approx(
        (0.98, 1.0, -0.5, 0.1, 10.5))
    assert w["f_hat_z"][0] == pytest.approx(-0.4)


def test_tracking_rms_is_over_the_window_of_source_time_only():
    v = VehicleModel("uav1", window_s=2.0)
    for k in range(500):  # 10 s at 50 Hz; the last 2.2 s have error ±0.01 m, before that 1 m
        err = 0.01 * (1 if k % 2 else -1) if k >= 390 else 1.0
        v.ingest("state", state(k, 1.0 + err), 0.0)
        v.ingest("reference", reference(k, 1.0), 0.0)
    rms_z, rms_3d = v.tracking_rms_m()
    assert rms_z == pytest.approx(0.01, rel=1e-6) and rms_3d == pytest.approx(0.01, rel=1e-6)
    assert len(v.window()["t"]) in (100, 101)  # t in [7.98, 9.98], give or take the float boundary


def test_loop_rate_and_latency_come_from_the_setpoint_stamps():
    v = VehicleModel("uav1")
    for k in range(200):
        stamp = 1000.0 + 0.02 * k
        v.ingest("state", state(k, 1.0, stamp=stamp), stamp + 0.0005)
        v.ingest("setpoint", setpoint(k, stamp + (0.002 if k % 10 else 0.010), stamp), 0.0)
    assert v.loop_rate_hz() == pytest.approx(50.0, rel=1e-6)
    p50, p99 = v.loop_latency_ms()
    assert p50 == pytest.approx(2.0) and p99 == pytest.approx(10.0)
    assert v.bus_latency_ms()[0] == pytest.approx(0.5)


def test_a_new_flight_clears_the_old_one():
    v = VehicleModel("uav1")
    for k in range(100):
        v.ingest("state", state(k, 1.0), 0.0)
    v.ingest("state", state(0, 0.3), 0.0)
    assert v.flights == 1 and len(v.window()["t"]) == 1 and len(v.trail) == 1


def test_late_messages_of_the_flight_before_a_restart_do_not_hide_the_new_one():
    """The world restarted at sample 3000 (t = 60 s); the old flight's last estimate and reference
    arrive after the new flight's first states. Kept, their rows' clock (60 s) would leave the new
    flight (t < 1 s) outside the 10 s window: plots blank, tracking RMS unknown, for 164 s."""
    v = VehicleModel("uav1")
    for k in range(2990, 3000):
        v.ingest("state", state(k, 1.0), 0.0)
    for k in range(40):
        v.ingest("state", state(k, 0.3), 0.0)
        v.ingest("reference", reference(k, 0.25), 0.0)
        if k == 2:
            v.ingest("estimate", estimate(3000, 0.1, 0.0), 0.0)
            v.ingest("reference", reference(3000, 1.0), 0.0)
    w = v.window()
    assert v.flights == 1 and len(w["t"]) == 40 and np.nanmax(w["t"]) == pytest.approx(0.78)
    assert v.tracking_rms_m()[0] == pytest.approx(0.05)
    v.ingest("estimate", estimate(41, 0.1, 0.0), 0.0)  # one sample ahead of its state: kept
    assert len(v.window()["t"]) == 41


def test_the_certificate_shown_is_the_estimators_verdict_not_the_pages():
    from neso.certificate import LoopPlant, NetworkSlopes, flight_certificate
    from neso.control import ControlConfig

    v = VehicleModel("uav1")
    assert v.certificate() is None and math.isnan(v.lipschitz()[0])  # nothing reported yet: nothing claimed
    verdict = flight_certificate(NetworkSlopes(9.2), kp=10.0, kd=6.0, omega_o=OMEGA_O_RPS,
                                 plant=LoopPlant.of(ControlConfig()))  # above the 6.94 the estimator allows
    v.ingest("network", NetworkMsg(stamp_s=1.0, seq=1, active={"id": "a", "lipschitz_norm": 0.5, "lipschitz_phys": 9.2},
                                   candidate={}, previous={}, shadow_error_rms_mps2=-1.0,
                                   certificate=verdict.to_dict()), 0.0)
    cert = v.certificate()
    assert not cert.holds and cert.margin == pytest.approx(verdict.margin) and "FAILS" in cert.text
    assert "cm" in cert.text  # the verdict states its |e_z| bound in centimetres (none here: it does not hold)
    assert cert.max_lipschitz_phys == pytest.approx(verdict.max_certified) and v.lipschitz() == (9.2, 0.5)


def test_bad_payloads_are_counted_never_fatal_and_routed_by_vehicle():
    m = FleetModel()
    decode_into(m, "state", "neso/uav1/state", b"\x00garbage", 0.0)
    decode_into(m, "state", "elsewhere/state", state(0, 1.0).to_bytes(), 0.0)
    assert m.rejected == 2 and "elsewhere/state" in m.last_rejection
    decode_into(m, "state", "neso/uav2/state", state(0, 1.0).to_bytes(), 0.0)
    health = HealthMsg(stamp_s=1.0, service="estimator", pid=1, uptime_s=1.0, ticks=1, rate_hz=50.0,
                       latency_p50_ms=0.1, latency_p99_ms=0.2, rejected={"state": 2.0}, staleness_s={"state": 0.01},
                       status="ok")
    decode_into(m, "health", Keys("uav2").health("estimator"), health.to_bytes(), 5.0)
    decode_into(m, "alive", Keys("uav2").alive("estimator"), b"1", 5.0)
    assert set(m.vehicles) == {"uav2"}  # a rejected payload makes no vehicle
    est = m.vehicles["uav2"].services["estimator"]
    assert est.alive and est.health.rate_hz == 50.0 and not est.stale(6.0) and est.stale(9.0)
    decode_into(m, "alive", Keys("uav2").alive("estimator"), b"", 6.0)
    assert not m.vehicles["uav2"].services["estimator"].alive
    assert math.isnan(m.vehicles["uav2"].tracking_rms_m()[0])  # no reference yet
    assert np.isfinite(m.vehicles["uav2"].window()["z"]).all()


def test_a_replayed_flight_is_labelled_not_live_with_its_origin():
    import dataclasses

    from dashboard.provenance import provenance_line
    from runtime.schema import ReplayMsg

    v = VehicleModel("uav1")
    assert provenance_line(v, 10.0) == "no samples"
    v.ingest("state", state(1, 1.0), 10.0)
    assert provenance_line(v, 10.5).startswith("● **LIVE** · state from sim")
    v.ingest("state", dataclasses.replace(state(2, 1.0), source="replay"), 11.0)
    assert "REPLAY (not live)" in provenance_line(v, 11.1) and "not announced" in provenance_line(v, 11.1)
    announced = ReplayMsg(stamp_s=11.0, file="/data/px4-sitl-takeoff-hover.rrd",
                          origin="PX4 log px4-sitl-takeoff-hover.ulg · PX4 v1.15.0 · PX4_SITL", t_s=3.0,
                          duration_s=30.7, speed=2.0, playing=True)
    v.ingest("replay", announced, 11.0)
    line = provenance_line(v, 11.2)
    assert "REPLAY (not live)" in line and "PX4 log px4-sitl-takeoff-hover.ulg" in line and "3.0 / 30.7 s at ×2" in line
    v.ingest("replay", dataclasses.replace(announced, playing=False), 12.0)
    assert provenance_line(v, 12.1).startswith("■ replay ended")
    assert provenance_line(v, 30.0).startswith("■ replay ended"), "the states stopped with it"


def health(service, t, **counters):
    return HealthMsg(stamp_s=t, service=service, pid=1, uptime_s=t, ticks=1, rate_hz=50.0, latency_p50_ms=0.1,
                     latency_p99_ms=0.2, rejected={}, staleness_s={}, status="ok", counters=counters)


def event(text, service="controller", level="warning"):
    return EventMsg(stamp_s=1.0, service=service, level=level, text=text)


def test_repeated_events_are_one_line_with_a_count_newest_first():
    v = VehicleModel("uav1")
    for k in range(12):
        v.ingest_event(event(f"no estimate for sample {100 + k} within 3 samples: flying on the local ESO"), 10.0 + k)
        if k == 5:
            v.ingest_event(event("world restarted with scenario ood_slope", "source", "info"), 15.5)
    first, second = v.recent_events(5)
    assert (first.count, first.text, first.first_s, first.last_s) == (
        12, "no estimate for sample 111 within 3 samples: flying on the local ESO", 10.0, 21.0)
    assert (second.service, second.count) == ("source", 1)
    for k in range(60):  # a bounded list: old distinct messages go
        v.ingest_event(event(f"distinct message {chr(65 + k % 26) * (1 + k // 26)}"), 30.0 + k)
    assert len(v.events) == 40


def test_misses_and_fall_backs_are_counted_over_the_last_minute_from_the_health_counters():
    v = VehicleModel("uav1")
    assert math.isnan(v.per_minute("source", "deadline_misses", 0.0)[0])
    for k in range(100):  # 100 s of 1 Hz reports; 2 misses a second for the first 50 s, then none
        v.ingest_health(health("source", float(k), deadline_misses=float(2 * min(k, 50))), float(k))
    assert v.per_minute("source", "deadline_misses", 99.0) == (22.0, 60.0)  # 39 → 99 s: 11 s of 2 misses
    v.ingest_health(health("source", 100.0, deadline_misses=3.0), 100.0)  # restarted: counts from 0
    assert v.per_minute("source", "deadline_misses", 100.0)[0] == 3.0


def test_certificate_shown_waits_for_the_estimator_then_shows_its_verdict():
    v = VehicleModel("uav1")
    v.ingest_params("controller", {"kp_xy": 6.0, "kd_xy": 4.5, "kp_z": 10.0, "kd_z": 6.0})
    assert certificate_shown(v).word == "waiting…", "the page computes no certificate of its own"
    verdict = {"holds": False, "margin": -30.9, "max_certified": 0.763, "lipschitz_phys": 31.6,
               "text": "FAILS: margin -30.9 (m/s²)/unit z"}
    v.ingest("network", NetworkMsg(stamp_s=1.0, seq=1, active={"id": "n"}, candidate={}, previous={},
                                   shadow_error_rms_mps2=-1.0, certificate=verdict), 1.0)
    shown = certificate_shown(v)
    assert (shown.word, shown.level, shown.text) == ("FAILS", "bad", verdict["text"])
    v.ingest("network", NetworkMsg(stamp_s=2.0, seq=2, active={"id": "n"}, candidate={}, previous={},
                                   shadow_error_rms_mps2=-1.0, certificate={**verdict, "holds": True, "margin": 0.2,
                                                                           "lipschitz_phys": 0.5,
                                                                           "text": "HOLDS: margin 0.2"}), 2.0)
    assert (certificate_shown(v).word, certificate_shown(v).level) == ("HOLDS", "ok")


def flying(v, t, *, thrust=9.8, source="sim", local=False):
    for k in range(int(t / 0.02)):
        s = 100.0 + 0.02 * k
        v.ingest("state", StateMsg(seq=k, stamp_s=s, t_s=0.02 * k, pos_enu_m=(0.0, 0.0, 1.0), vel_enu_mps=(0.0,) * 3,
                                   roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, source=source), s)
        v.ingest("estimate", estimate(k, 0.1, 0.0), s)
        v.ingest("reference", reference(k, 1.0), s)
        sp = setpoint(k, s + 0.001, s, thrust)
        v.ingest("setpoint", dataclasses.replace(sp, estimate_source="local_eso") if local else sp, s)


def test_the_status_line_colours_each_slot():
    v = VehicleModel("uav1")
    ok_cert = CertificateShown("HOLDS", "HOLDS: …", "ok")
    slots = lambda now, **kw: {i.slot: (i.text, i.level) for i in status_line(v, now, ok_cert, **kw)}  # noqa: E731
    st = slots(0.0)
    assert list(st) == list(STATUS_SLOTS) and st["source"] == ("NO DATA", "bad") and st["link"][1] == "off"
    flying(v, 2.0)
    for name in ("source", "estimator", "controller"):
        v.ingest_alive(name, True)
        v.ingest_health(health(name, 101.0, deadline_misses=0.0), 100.5)
        v.ingest_health(health(name, 102.0, deadline_misses=0.0), 101.9)
    st = slots(102.0)
    assert st["source"] == ("LIVE · sim", "ok") and st["armed"] == ("flying (sim)", "info")
    assert st["segment"] == ("hover", "info") and st["pathway"] == ("eso", "ok") and st["network"] == ("n", "ok")
    assert st["certificate"] == ("cert HOLDS", "ok") and st["recording"] == ("no recorder", "warn")
    assert st["link"] == ("50 Hz · 0 miss/min", "ok")
    v.ingest_health(health("source", 103.0, deadline_misses=4.0), 102.0)
    assert slots(102.0)["link"] == ("50 Hz · 4 miss/min", "warn")
    v.ingest("recording", RecordingMsg(stamp_s=1.0, recording=True, flight="f", segment=0, path="p.rrd",
                                       duration_s=12.4, size_bytes=1, dropped=0), 101.5)
    v.ingest("telemetry", TelemetryMsg(stamp_s=1.0, connected=True, armed=True, in_air=True, flight_mode="offboard",
                                       roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, pos_enu_m=(0.0,) * 3,
                                       vel_enu_mps=(0.0,) * 3, battery_v=15.0, battery_remaining=0.8,
                                       hover_thrust_norm=0.5, setpoint_age_s=0.02, failsafe=""), 101.5)
    st = slots(102.0)
    assert st["recording"] == ("● REC 12 s", "ok") and st["armed"] == ("ARMED · OFFBOARD · in air", "info")
    assert slots(104.0)["armed"] == ("idle (sim)", "off"), "telemetry once, no gateway: the controller's view"
    v.ingest_alive("px4_gateway", True)
    assert slots(104.0)["armed"] == ("PX4 SILENT", "bad") and slots(104.0)["source"][1] == "bad"
    v.ingest_alive("px4_gateway", False)
    v.ingest_alive("estimator", False)
    assert slots(102.0)["link"] == ("estimator, px4_gateway DOWN", "bad")
    w = VehicleModel("uav2")
    flying(w, 1.0, source="replay", local=True)
    st = {i.slot: (i.text, i.level) for i in status_line(w, 101.0, ok_cert)}
    assert st["source"] == ("REPLAY", "info") and st["pathway"] == ("LOCAL ESO", "bad")


def test_the_status_line_escapes_what_came_from_the_bus():
    from dashboard.text import status_html

    page = status_html("uav1", [StatusItem("network", "<img src=x onerror=alert(1)>", "ok", 'a "quote"')])
    assert "<img" not in page and "&lt;img" in page and "&quot;quote&quot;" in page
