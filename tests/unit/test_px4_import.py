"""PX4 logs (the shared real ones, and real ULog bytes made from them) → recordings: frames, thrust,
time base, refusals, partial logs; the offline ESO teacher; MCAP export round trip."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from neso.features import DEFAULT_FEATURE_SET, ThrustLag, feature_set
from neso.frames import quat_ned_from_enu_euler
from recordings.dataset import load_training_set, select
from recordings.mcap_export import export_mcap, json_schema
from recordings.px4 import (ImportConfig, ImportRefused, euler_enu_flu_from_euler_ned_frd,
                            euler_enu_flu_from_quat_ned_frd, held, period_average, px4_flight, read_ulog)
from recordings.px4_import import import_px4_log
from recordings.reader import read_recording
from recordings.replay import WhatIf, what_if
from recordings.teacher import eso_teacher
from tests.helpers import EXAMPLE
from tests.ulogfiles import (CUBE_LOG, SITL_LOG, data_messages, messages, resubscribed, topic_ids, with_appended,
                             without_topics)



@pytest.fixture(scope="module")
def sitl(tmp_path_factory):
    """The SITL takeoff-and-hover log imported once: (result, recording read back)."""
    out = tmp_path_factory.mktemp("imports")
    result = import_px4_log(SITL_LOG, out)
    return result, read_recording(result.path)


def test_both_shared_logs_import_with_what_was_imported_from_where(tmp_path):
    for log, hardware, thrust, hover in ((SITL_LOG, "PX4_SITL", "vehicle_thrust_setpoint.xyz[2]", "hover_thrust_estimate"),
                                        (CUBE_LOG, "CUBEPILOT_CUBEORANGE", "actuator_controls_0.control[3]",
                                         "MPC_THR_HOVER")):
        result = import_px4_log(log, tmp_path)
        rec = read_recording(result.path)
        info = rec.properties["import"]
        assert info["file_name"] == log.name and info["hardware"] == hardware
        assert info["topics"]["thrust"] == thrust and info["topics"]["hover_thrust"] == hover
        assert info["topics"]["state"].startswith("vehicle_local_position")
        assert info["mass_assumed"] is True and info["mass_kg"] == 1.0
        assert info["px4_version"].startswith("v1.15.0" if log == SITL_LOG else "v1.11.2")
        assert rec.properties["summary"]["end_reason"] == "imported"
        n = info["samples"]
        assert len(rec.channel("state")) == n == len(rec.channel("setpoint")) and n > 300
        assert {m.source for m in rec.channel("state").messages()} == {"px4"}
        assert len(rec.channel("event/px4")) > 0 and len(rec.channel("telemetry")) > 0
    cube = read_recording(tmp_path / "cubeorange-flight.rrd").properties["import"]
    assert cube["state_rate_hz"] > 90 and "dropouts" in " ".join(cube["notes"])
    assert cube["hover_thrust_source"].startswith("parameter MPC_THR_HOVER = 0.45")


def test_enu_altitude_rises_during_the_sitl_takeoff(sitl):
    result, rec = sitl
    state = rec.channel("state")
    t, z = np.asarray(state.columns["t_s"]), np.asarray(state.columns["pos_enu_m"])[:, 2]
    tel = rec.channel("telemetry")
    modes = tel.columns["flight_mode"]
    takeoff_t = np.asarray(tel.columns["stamp_s"])[modes.index("AUTO_TAKEOFF")]
    before = z[t < takeoff_t]
    assert abs(before.mean()) < 0.1, "on the ground before the takeoff"
    top = int(np.argmax(z))
    assert z[top] > 2.0 and t[top] > takeoff_t, "PX4's NED z went negative: up in ENU"
    lift = np.flatnonzero((t < t[top]) & (z < 0.1))[-1]  # the last sample on the ground before the top
    assert t[lift] >= takeoff_t - 0.2 and t[top] - t[lift] < 10.0
    climb = slice(lift, top + 1)
    assert np.all(np.diff(z[climb]) > -0.02), "it climbs without sinking back"
    rising = (z > 0.3) & (z < 2.0) & (t < t[top])
    vz = np.asarray(state.columns["vel_enu_mps"])[rising, 2]
    assert rising.sum() > 5 and np.all(vz > 0.05), "ENU velocity up while climbing"


def test_attitude_maps_back_to_px4s_quaternion(sitl):
    """Every imported attitude (ENU/FLU, ZYX) converted back to NED/FRD is the logged quaternion."""
    log, _ = read_ulog(SITL_LOG)
    att = log.get_dataset("vehicle_attitude")
    q = np.stack([att.data[f"q[{i}]"].astype(float) for i in range(4)], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rpy = euler_enu_flu_from_quat_ned_frd(q)
    assert np.ptp(rpy[:, 2]) > 0.01 or np.ptp(rpy[:, 0]) > 0.001, "the attitude moved"
    worst = 0.0
    for qi, (r, p, y) in zip(q, rpy):
        back = np.array(quat_ned_from_enu_euler(r, p, y))
        worst = max(worst, min(np.max(np.abs(back - qi)), np.max(np.abs(back + qi))))
    assert worst < 1e-6, worst
    # and the recorded state holds exactly those attitudes (the newest at or before each state)
    result, rec = sitl
    state = rec.channel("state")
    t_att = (att.data["timestamp"].astype(np.int64) - result.flight.info["log_start_us"]) / 1e6
    expected = held(t_att, rpy, np.asarray(state.columns["t_s"]))
    got = np.stack([state.columns[k] for k in ("roll_rad", "pitch_rad", "yaw_rad")], axis=1)
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_level_attitudes_map_as_the_frames_module_says():
    """Level, heading north in NED (identity) is yaw π/2 in ENU; roll stays, pitch flips (small angles)."""
    np.testing.assert_allclose(euler_enu_flu_from_quat_ned_frd(np.array([[1.0, 0, 0, 0]]))[0], [0, 0, math.pi / 2],
                               atol=1e-12)
    rpy = euler_enu_flu_from_euler_ned_frd(np.array([[0.1, 0.2, 0.3]]))[0]
    np.testing.assert_allclose(rpy, [0.1, -0.2, math.pi / 2 - 0.3], atol=1e-12)


def test_thrust_in_newtons_is_normalised_thrust_times_mg_over_hover_thrust(tmp_path):
    result = import_px4_log(SITL_LOG, tmp_path, ImportConfig(mass_kg=1.6))
    f = result.flight
    np.testing.assert_allclose(f.thrust_n, f.thrust_norm * 1.6 * 9.81 / f.hover_thrust_norm, rtol=1e-12)
    steady = steady_flight(f.vel_enu_mps[:, 2], f.pos_enu_m[:, 2]) & f.in_air
    assert steady.sum() > 15 and abs(np.median(f.thrust_n[steady]) / (1.6 * 9.81) - 1.0) < 0.05, \
        "m·g when the vertical velocity is steady (the RTL descent)"
    assert f.info["mass_assumed"] is False and f.info["mass_kg"] == 1.6
    rec = read_recording(result.path)
    sp = rec.channel("setpoint")
    np.testing.assert_allclose(sp.columns["thrust_n"], np.asarray(sp.columns["thrust_norm"]) * 1.6 * 9.81
                               / f.hover_thrust_norm, rtol=1e-12)
    given = import_px4_log(SITL_LOG, tmp_path / "given", ImportConfig(hover_thrust_norm=0.4)).flight
    np.testing.assert_allclose(given.thrust_n, given.thrust_norm * 9.81 / 0.4, rtol=1e-12)
    assert given.info["hover_thrust_source"] == "given: 0.4"


@pytest.mark.parametrize("log", [CUBE_LOG, SITL_LOG], ids=["cubeorange", "sitl"])
def test_labels_in_m_per_s2_do_not_depend_on_the_mass_given_at_import(tmp_path, log):
    """The newtons scale with --mass-kg, so the labels (and the thrust response found) must not: the
    dataset takes the recording's own mass. Once 1 kg was used whatever the import said (2.65 kg: the
    applied labels' mean came out −16.9 m/s² instead of −0.27 on real flights)."""
    nominal = import_px4_log(log, tmp_path / "1kg").path
    heavy = import_px4_log(log, tmp_path / "heavy", ImportConfig(mass_kg=2.65)).path
    for label in ("applied", "eso"):
        a = load_training_set(nominal, label)
        b = load_training_set(heavy, label)
        assert (a.mass_kg, b.mass_kg) == (1.0, 2.65)
        assert a.thrust_lag == b.thrust_lag and a.lag_source == b.lag_source  # identified, or the fit's edge said
        np.testing.assert_allclose(b.y_mps2, a.y_mps2, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.z, a.z, rtol=0, atol=1e-9)


def test_only_samples_in_the_air_are_labelled(tmp_path):
    """PX4's land detector (the imported telemetry's in_air) keeps the ground out of the labels: on the
    ground the floor, not the thrust, holds the vehicle, and a label there is −(T/m − g) ≈ g."""
    rec = read_recording(import_px4_log(CUBE_LOG, tmp_path).path)
    ts = load_training_set(rec.path, "applied")
    in_air = np.asarray(rec.channel("telemetry").columns["in_air"]).astype(bool)
    assert 0 < len(ts) < 0.5 * len(rec.channel("state")) and in_air.mean() < 0.5


def steady_flight(vz: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Samples clear of the ground whose vertical velocity hardly changes (no vertical acceleration)."""
    dv = np.abs(np.gradient(vz))
    return (dv < 0.02) & (z > 0.3) & (np.abs(vz) > 0.2)


def test_the_thrust_of_a_period_is_the_mean_of_the_held_thrust_over_it():
    t_src = np.array([0.0, 0.05, 0.1, 0.15, 0.2])
    u = np.array([0.2, 0.4, 0.6, 0.8, 1.0])
    t = np.array([0.0, 0.1, 0.2])
    last = np.array([False, False, True])
    np.testing.assert_allclose(period_average(t_src, u, t, last), [0.3, 0.7, 1.0])
    np.testing.assert_allclose(held(t_src, u, np.array([-1.0, 0.07, 0.2, 5.0])), [0.2, 0.4, 1.0, 1.0])


def test_an_older_px4s_scalar_thrust_is_read():
    """PX4 ≤ v1.9 logs vehicle_attitude_setpoint.thrust (0–1); no thrust_body, no thrust setpoint topic."""
    from recordings.px4 import _thrust_source

    class Topic:
        def __init__(self, name, data):
            self.name, self.multi_id, self.data = name, 0, data

    class Log:
        data_list = [Topic("vehicle_attitude_setpoint", {"timestamp": np.array([1, 2], dtype=np.uint64),
                                                         "thrust": np.array([0.4, 0.5], dtype=np.float32)})]

    topic, fld, sign, ds = _thrust_source(Log(), None)
    assert (topic, fld, sign) == ("vehicle_attitude_setpoint", "thrust", 1.0)
    assert _thrust_source(Log(), "vehicle_thrust_setpoint.xyz[2]") is None


def refused(tmp_path, data: bytes | None, name: str, *needles: str):
    src = tmp_path / name
    if data is not None:
        src.write_bytes(data)
    out = tmp_path / f"out-{name}"
    with pytest.raises(ImportRefused) as err:
        import_px4_log(src, out)
    text = str(err.value)
    assert "\n" not in text and all(n in text for n in needles), text
    assert not out.exists(), "nothing written"
    return text


def test_bad_logs_are_refused_in_one_line_and_nothing_is_written(tmp_path):
    sitl = SITL_LOG.read_bytes()
    refused(tmp_path, sitl[:3000], "truncated.ulg", "truncated")
    refused(tmp_path, sitl[:10], "header-only.ulg", "not a PX4 ULog")
    refused(tmp_path, np.random.default_rng(1).bytes(200_000), "random.ulg", "not a PX4 ULog")
    refused(tmp_path, b"ULog\x01\x12\x35\x01" + np.random.default_rng(2).bytes(200_000), "random-after-magic.ulg",
            "truncated or corrupt")
    refused(tmp_path, without_topics(sitl, "vehicle_local_position"), "no-position.ulg",
            "topic vehicle_local_position (x, y, z, vx, vy, vz)")
    refused(tmp_path, without_topics(sitl, "vehicle_thrust_setpoint", "vehicle_attitude_setpoint"), "no-thrust.ulg",
            "thrust (one of vehicle_thrust_setpoint.xyz[2]", "vehicle_attitude_setpoint.thrust)")
    refused(tmp_path, None, "does-not-exist.ulg", "no such file")
    both = refused(tmp_path, without_topics(sitl, "vehicle_local_position", "vehicle_attitude"), "no-state.ulg")
    assert "vehicle_local_position" in both and "vehicle_attitude" in both, "every missing topic named"


def test_the_topic_removed_is_really_gone_from_the_bytes():
    sitl = SITL_LOG.read_bytes()
    stripped = without_topics(sitl, "vehicle_local_position")
    assert topic_ids(sitl, "vehicle_local_position") and not topic_ids(stripped, "vehicle_local_position")
    log, torn = read_ulog(SITL_LOG)
    assert torn is None and log.get_dataset("vehicle_attitude") is not None
    assert sum(1 for _ in messages(stripped)) < sum(1 for _ in messages(sitl))


def test_appended_data_and_a_torn_last_message_import_what_is_valid_and_say_what_was_skipped(tmp_path):
    sitl = SITL_LOG.read_bytes()
    later = data_messages(sitl, "vehicle_local_position")[-10:]
    extra = resubscribed(sitl, "vehicle_local_position", later, msg_id=250, dt_us=40_000_000)
    torn = extra[-30:-7]  # a message cut by the end of the file
    path = tmp_path / "appended.ulg"
    path.write_bytes(with_appended(sitl, extra + torn))
    whole = px4_flight(SITL_LOG)
    got = import_px4_log(path, tmp_path).flight
    assert len(got) == len(whole) + 10, "the appended samples are read"
    np.testing.assert_allclose(got.t_s[-10:] - whole.t_s[-10:], 40.0)
    np.testing.assert_array_equal(got.pos_enu_m[:len(whole)], whole.pos_enu_m)
    text = " ".join(got.info["skipped"] + got.info["notes"])
    assert "ends inside a message" in text and "appended data" in text
    assert got.info["gaps"]["count"] == 1 and got.info["gaps"]["longest_s"] > 35


def test_a_dropout_in_the_state_is_kept_as_a_gap_and_the_teacher_restarts_after_it(tmp_path):
    """Ten seconds of vehicle_local_position removed mid-hover: nothing is invented across the gap, the
    ESO restarts after it (warm-up skipped again) instead of integrating over time it never saw."""
    import struct

    sitl = SITL_LOG.read_bytes()
    start_us = struct.unpack_from("<Q", sitl, 8)[0]
    ids = topic_ids(sitl, "vehicle_local_position")
    out = bytearray(sitl[:16])
    for off, kind, payload in messages(sitl):
        if kind == "D" and struct.unpack_from("<H", payload)[0] in ids:
            ts = struct.unpack_from("<Q", payload, 2)[0]
            if 20e6 < ts - start_us < 24e6:
                continue
        out += sitl[off:off + 3 + len(payload)]
    path = tmp_path / "dropout.ulg"
    path.write_bytes(bytes(out))
    result = import_px4_log(path, tmp_path)
    gaps = result.flight.info["gaps"]
    assert gaps["count"] == 1 and 3.5 < gaps["longest_s"] < 4.5
    run = eso_teacher(read_recording(result.path))
    after = np.flatnonzero(run.t_s > 24.0)[:3]
    assert not run.warm[after].any(), "the observer restarted after the gap"
    assert run.warm[np.flatnonzero(run.t_s > 25.0)[0]]


def test_the_offline_teacher_reproduces_the_flown_eso_of_the_example_exactly():
    rec = read_recording(EXAMPLE)
    run = eso_teacher(rec)
    flown = np.asarray(rec.channel("estimate").columns["f_hat_mps2"])
    assert len(run) == len(flown) == 600 and run.warm.sum() == 576
    np.testing.assert_allclose(run.f_hat_mps2[run.warm], flown[run.warm], atol=1e-9)


def test_eso_pairs_from_an_imported_flight_come_from_the_offline_teacher(sitl):
    result, rec = sitl
    sel = select(rec, "eso", feature_set(DEFAULT_FEATURE_SET), ThrustLag())
    run = eso_teacher(rec)
    keep = run.warm & run.airborne
    assert len(sel.y_mps2) == keep.sum() > 100
    np.testing.assert_array_equal(sel.y_mps2, run.f_hat_mps2[keep, 2])
    assert sel.dropped["on the ground"] > 100, "the minutes on the ground before the takeoff are left out"
    steady = keep & steady_flight(run.vel_enu_mps[:, 2], run.pos_enu_m[:, 2])
    assert steady.sum() > 15 and abs(np.median(run.f_hat_mps2[steady, 2])) < 0.3, \
        "at a steady vertical speed the hover-thrust estimate explains gravity: the ESO's residual is small"
    ts = load_training_set(result.path, "eso")
    assert len(ts) == len(sel.y_mps2) and ts.vehicle == "uav1"
    with pytest.raises(Exception, match="no usable 'tdr' samples"):
        load_training_set(result.path, "tdr")


def test_what_if_on_an_imported_flight_is_measured_against_the_offline_eso(sitl):
    _, rec = sitl
    same = what_if(rec, WhatIf(pathway="eso"))
    assert same.against == "ESO offline" and max(same.diff_max_mps2) == 0.0
    other = what_if(rec, WhatIf(omega_o_rps=25.0))
    assert other.diff_rms_mps2[2] > 0.01 and "ESO offline" in other.report()


def test_mcap_export_round_trips_every_message_of_the_example_recording(tmp_path):
    from mcap.reader import make_reader

    rec = read_recording(EXAMPLE)
    summary = export_mcap(rec, tmp_path / "example.mcap")
    source = {f"neso/{v}/{name}": ch.messages() for v, chans in rec.vehicles.items() for name, ch in chans.items()}
    got: dict[str, list] = {}
    schemas = {}
    with open(tmp_path / "example.mcap", "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            got.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
            schemas[channel.topic] = (schema.name, schema.encoding, channel.message_encoding, json.loads(schema.data))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert set(got) == set(source) and summary.channels == {k: len(v) for k, v in source.items()}
    assert sum(summary.channels.values()) > 3000
    for topic, msgs in source.items():
        assert len(got[topic]) == len(msgs), topic
        order = sorted(range(len(msgs)), key=lambda i: (round(msgs[i].stamp_s * 1e9), i))
        for (log_time, values), i in zip(got[topic], order):
            m = msgs[i]
            assert log_time == round(m.stamp_s * 1e9)
            assert type(m).validate(**values) == m, topic  # every field, bit-exact
        name, encoding, message_encoding, schema = schemas[topic]
        assert (encoding, message_encoding) == ("jsonschema", "json") and schema == json_schema(type(msgs[0]))
    assert "neso.flight" in metadata and json.loads(metadata["neso.flight"]["vehicle"]) == "uav1"
