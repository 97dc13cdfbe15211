"""The dashboard's model: messages in, figures out (no bus, no browser)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dashboard.model import FleetModel, VehicleModel
from dashboard.service import decode_into
from runtime.schema import (EstimateMsg, HealthMsg, Keys, NetworkMsg, ReferenceMsg, SetpointMsg, StateMsg)


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


def test_the_certificate_shown_is_the_estimators_verdict_not_the_pages():
    from neso.certificate import flight_certificate

    v = VehicleModel("uav1")
    assert v.certificate() is None and math.isnan(v.lipschitz()[0])  # nothing reported yet: nothing claimed
    verdict = flight_certificate(3.2, kp=10.0, kd=6.0, omega_o=15.0)
    v.ingest("network", NetworkMsg(stamp_s=1.0, seq=1, active={"id": "a", "lipschitz_norm": 0.5, "lipschitz_phys": 3.2},
                                   candidate={}, previous={}, shadow_error_rms_mps2=-1.0,
                                   certificate=verdict.to_dict()), 0.0)
    cert = v.certificate()
    assert not cert.holds and cert.margin == pytest.approx(verdict.margin) and "FAILS" in cert.text
    assert cert.max_lipschitz_phys == pytest.approx(verdict.max_certified) and v.lipschitz() == (3.2, 0.5)


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
