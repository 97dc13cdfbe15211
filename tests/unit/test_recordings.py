"""Recordings on synthetic messages: layout, writer → reader round trip, a file cut short,
training-set extraction rules, flight boundaries."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from neso.features import DEFAULT_FEATURE_SET, ThrustLag, feature_set
from neso.netfile import load_network
from recordings.dataset import load_training_set, select
from recordings.layout import channel_entity, channel_of, entity, fields_of, message_type, parse_channel_entity
from recordings.reader import RecordingError, read_recording
from recordings.writer import FlightWriter, segment_path
from runtime.schema import TOPICS, EventMsg, ParamStateMsg, SetpointMsg, StateMsg, TelemetryMsg
from services.recorder import FlightTracker, RecorderConfig
from tests.helpers import EXAMPLE, EXAMPLES, PERIOD_S, flight_messages, write_recording

def test_entity_paths_mirror_the_key_expressions_and_every_field_has_a_kind():
    assert channel_of("neso/uav1/state") == ("uav1", "state")
    assert channel_of("neso/uav1/health/estimator") == ("uav1", "health/estimator")
    assert channel_of("neso/uav1/param/estimator") is None and channel_of("other/uav1/state") is None
    assert entity("uav1", "state", "pos_enu_m") == "neso/uav1/state/pos_enu_m"
    assert channel_entity("uav1", "health/estimator") == "neso/uav1/health/estimator"
    assert parse_channel_entity("/neso/uav1/health/estimator") == ("uav1", "health/estimator")
    assert parse_channel_entity("/neso/uav1/state/pos_enu_m") is None, "a plotted field, not a channel"
    for cls in TOPICS.values():
        assert [f.name for f in fields_of(cls)] == [f.name for f in dataclasses.fields(cls)]
    assert message_type("params/estimator") is ParamStateMsg


def test_every_message_type_reads_back_exactly(tmp_path):
    path = tmp_path / "all.rrd"
    channels = {"param_state": "params/estimator", "event": "event/estimator", "health": "health/estimator"}
    written = [(channels.get(m.TYPE, m.TYPE), m) for m in EXAMPLES if channels.get(m.TYPE, m.TYPE) in TOPICS
               or m.TYPE in channels]
    write_recording(path, written * 3)
    rec = read_recording(path)
    assert rec.vehicle == "uav1" and rec.properties["flight"]["flight"] == "uav1-test"
    assert rec.properties["params"]["estimator"] == {"pathway": "eso"}
    for channel, msg in written:
        assert rec.channel(channel).messages() == [msg] * 3, channel


def test_a_flight_reads_back_bit_exact_in_publication_order(tmp_path):
    msgs = flight_messages(300)
    write_recording(tmp_path / "f.rrd", msgs, flush_every=37)
    rec = read_recording(tmp_path / "f.rrd")
    for channel in ("state", "truth", "estimate", "setpoint", "reference", "health/estimator", "params/estimator"):
        assert rec.channel(channel).messages() == [m for c, m in msgs if c == channel], channel
    est = rec.channel("estimate")
    assert est.columns["z"].shape == (300, 5) and est.columns["z"].dtype == np.float64


def test_an_estimate_whose_z_changes_length_mid_flight_reads_back_exactly(tmp_path):
    """A network with other inputs promoted mid-flight changes the length of z; the recorder once failed
    on it ("inhomogeneous shape") and stopped recording."""
    msgs = flight_messages(120)
    for i, (channel, msg) in enumerate(msgs):
        if channel == "estimate" and msg.seq % 3 == 1:
            msgs[i] = (channel, dataclasses.replace(msg, z=msg.z[:3]))
    write_recording(tmp_path / "f.rrd", msgs, flush_every=41)
    est = read_recording(tmp_path / "f.rrd").channel("estimate")
    assert est.messages() == [m for c, m in msgs if c == "estimate"]
    assert est.columns["z"].shape == (120, 5) and np.isnan(est.columns["z"][1, 3:]).all()


def test_a_file_cut_short_is_read_up_to_its_last_flush(tmp_path):
    msgs = flight_messages(200)
    path = tmp_path / "cut.rrd"
    write_recording(path, msgs, flush_every=100, close=False)  # no footer, as after kill -9
    full = path.read_bytes()
    path.write_bytes(full[: int(len(full) * 0.6)])  # and the tail of the last write torn off
    rec = read_recording(path)
    read = total = 0
    for channel in ("state", "truth", "estimate", "setpoint", "reference"):
        got = rec.channel(channel).messages()
        sent = [m for c, m in msgs if c == channel]
        assert got == sent[: len(got)], f"{channel}: a prefix, exactly"
        read, total = read + len(got), total + len(sent)
    assert 0 < read < total


def test_not_a_recording_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not an rrd at all" * 10)
    with pytest.raises(RecordingError, match="bad.rrd"):
        read_recording(bad)
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "missing.rrd")
    (tmp_path / "empty.rrd").write_bytes(b"")
    with pytest.raises(RecordingError, match="empty"):
        read_recording(tmp_path / "empty.rrd")


def test_eso_training_set_has_the_network_input_and_x3_label_and_skips_cold_ground_and_other_pathways(tmp_path):
    msgs = flight_messages(200, on_ground_until=40, thrust_zero_from=180)
    write_recording(tmp_path / "eso.rrd", msgs)
    ts = load_training_set(tmp_path / "eso.rrd", "eso", skip_s=0.5)
    est = [m for c, m in msgs if c == "estimate"]
    states = [m for c, m in msgs if c == "state"]
    # warm after 25 samples (0.5 s at 50 Hz), airborne from 40, thrust until 179
    keep = [k for k, m in enumerate(est) if m.warm_ticks >= 25 and 40 <= k < 180]
    assert len(ts) == len(keep) == 140
    # inputs rebuilt from the recorded states whatever network flew: [p_z, v_z, roll, pitch, v_xy]
    speed = load_training_set(tmp_path / "eso.rrd", "eso", skip_s=0.5, feature_set_key="state_speed@1")
    assert speed.feature_set == "state_speed@1"
    expected_z = [(states[k].pos_enu_m[2], states[k].vel_enu_mps[2], states[k].roll_rad, states[k].pitch_rad,
                   np.hypot(*states[k].vel_enu_mps[:2])) for k in keep]
    np.testing.assert_array_equal(speed.z, np.array(expected_z))
    assert ts.feature_set == DEFAULT_FEATURE_SET and ts.z.shape == (140, feature_set(DEFAULT_FEATURE_SET).size)
    np.testing.assert_array_equal(ts.y_mps2, np.array([est[k].f_hat_mps2[2] for k in keep]))
    assert ts.label == "eso" and ts.vehicle == "uav1" and ts.recordings == (str(tmp_path / "eso.rrd"),)
    paper = load_training_set(tmp_path / "eso.rrd", "eso", feature_set_key="paper@1")
    setpoints = [m for c, m in msgs if c == "setpoint"]  # the paper's T_{k-1}: the thrust of the setpoint before
    np.testing.assert_array_equal(paper.z[:, 2], [setpoints[k - 1].thrust_n for k in keep])
    with pytest.raises(RecordingError, match="no usable 'tdr' samples.*pathway not neural_eso"):
        load_training_set(tmp_path / "eso.rrd", "tdr")


def test_tdr_training_set_is_f_n_plus_delta_f_hat_over_several_recordings(tmp_path):
    a, b = flight_messages(100, pathway="neural_eso"), flight_messages(80, pathway="neural_eso", seq0=500, warm0=30)
    write_recording(tmp_path / "a.rrd", a)
    write_recording(tmp_path / "b.rrd", b)
    ts = load_training_set([tmp_path / "a.rrd", tmp_path / "b.rrd"], "tdr")
    est = [m for c, m in a if c == "estimate" and m.warm_ticks >= 25] + [m for c, m in b if c == "estimate"]
    assert len(ts) == len(est) == 76 + 80
    np.testing.assert_allclose(ts.y_mps2, [m.f_n_mps2[2] + m.delta_f_hat_mps2[2] for m in est], rtol=0, atol=0)
    with pytest.raises(RecordingError, match="no usable 'eso'"):
        load_training_set(tmp_path / "a.rrd", "eso")


def test_a_resent_sample_counts_once(tmp_path):
    msgs = flight_messages(60)
    at = [i for i, (c, _) in enumerate(msgs) if c == "estimate"][40]
    write_recording(tmp_path / "r.rrd", msgs[: at + 1] + [msgs[at]] + msgs[at + 1:])  # answered again (a lockstep re-send)
    sel = select(read_recording(tmp_path / "r.rrd"), "eso", feature_set(DEFAULT_FEATURE_SET), ThrustLag())
    assert len(sel.y_mps2) == 60 - 24


def test_recordings_of_two_vehicles_are_refused_together(tmp_path):
    write_recording(tmp_path / "a.rrd", flight_messages(60))
    w = FlightWriter(tmp_path / "b.rrd", vehicle="uav2", flight="uav2-test")
    for c, m in flight_messages(60):
        w.add(c, m)
    w.close()
    with pytest.raises(RecordingError, match="different vehicles"):
        load_training_set([tmp_path / "a.rrd", tmp_path / "b.rrd"], "eso")


def test_segment_paths():
    assert str(segment_path("d", "uav1-x", 2)) == "d/uav1-x.seg2.rrd"


def _sp(seq, thrust):
    return SetpointMsg(seq=seq, stamp_s=1.0, state_stamp_s=1.0, t_s=0.0, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0,
                       thrust_norm=thrust / 20, thrust_n=thrust, acc_cmd_enu_mps2=(0.0, 0.0, 0.0),
                       estimate_source="estimator")


def _st(seq):
    return StateMsg(seq=seq, stamp_s=1.0, t_s=seq * PERIOD_S, pos_enu_m=(0, 0, 1), vel_enu_mps=(0, 0, 0), roll_rad=0.0,
                    pitch_rad=0.0, yaw_rad=0.0, source="sim")


def _tel(armed, in_air):
    return TelemetryMsg(stamp_s=1.0, connected=True, armed=armed, in_air=in_air, flight_mode="offboard", roll_rad=0.0,
                        pitch_rad=0.0, yaw_rad=0.0, pos_enu_m=(0.0, 0.0, 1.0), vel_enu_mps=(0.0, 0.0, 0.0),
                        battery_v=15.0, battery_remaining=0.8, hover_thrust_norm=0.5, setpoint_age_s=0.02, failsafe="")


def test_flight_starts_after_half_a_second_of_thrust_ends_after_two_without_and_at_a_source_restart():
    tr = FlightTracker(RecorderConfig())
    assert not tr.on_message("setpoint", _sp(0, 5.0), 0.0).start, "no state seen yet"
    tr.on_message("state", _st(0), 0.0)
    assert tr.on_message("setpoint", _sp(1, 5.0), 0.3).start == "", "not yet flying for 0.5 s"
    assert tr.on_message("setpoint", _sp(2, 5.0), 0.51).start.startswith("flying for 0.5 s: thrust commanded")
    assert tr.on_message("setpoint", _sp(3, 0.0), 0.6).stop == ""
    assert tr.on_message("setpoint", _sp(4, 5.0), 1.0).stop == "", "a short break is no landing"
    tr.on_message("setpoint", _sp(5, 0.0), 1.1)
    tr.on_message("state", _st(50), 2.9)
    assert tr.tick(3.0).stop == "" and tr.tick(3.1).stop.startswith("landed: not flying for 2 s")
    assert tr.on_message("setpoint", _sp(61, 5.0), 3.2).start == ""
    assert tr.on_message("setpoint", _sp(62, 5.0), 3.7).start
    tr.on_message("state", _st(70), 3.8)
    assert "restarted" in tr.on_message("state", _st(0), 3.9).stop
    tr.on_message("setpoint", _sp(1, 5.0), 3.92)
    assert tr.tick(4.0).stop == "" and "no state samples" in tr.tick(6.0).stop


def test_a_lockstep_flight_faster_than_the_wall_starts_and_ends_in_its_own_time():
    """A lockstep world 20× faster than the wall: half a second of the flight's own time (its states' ``t_s``) starts
    it, two seconds of it without thrust end it, though only 25 and 100 ms of the wall went by (a 3 s lockstep flight
    was once over before 0.5 s of the wall, and went unrecorded)."""
    tr = FlightTracker(RecorderConfig())

    def sample(k: int, thrust: float) -> list:  # the world's 20 ms, arrived 1 ms of the wall after the last one
        return [tr.on_message("state", _st(k), k * 0.001), tr.on_message("setpoint", _sp(k, thrust), k * 0.001)]

    started = [(k, d.start) for k in range(26) for d in sample(k, 5.0) if d.start]
    assert len(started) == 1 and started[0][0] == 25 and started[0][1].startswith("flying for 0.5 s"), started
    landed = [(k, d.stop) for k in range(26, 200) for d in sample(k, 0.0) if d.stop]
    assert len(landed) == 1 and landed[0][1].startswith("landed: not flying for 2 s"), landed
    assert landed[0][0] * PERIOD_S - 26 * PERIOD_S == pytest.approx(2.0, abs=PERIOD_S), landed  # 2 s of its time


def test_telemetry_decides_when_present_and_a_flapping_signal_never_makes_flights():
    """The issue's PX4 case: the controller commands thrust, the vehicle says disarmed (10 Hz):
    no flight at all, however long; then a real one, armed and in the air, is one flight."""
    tr = FlightTracker(RecorderConfig())
    tr.on_message("state", _st(0), 0.0)
    decisions = []
    for k in range(1500):  # 30 s at 50 Hz
        now = k * 0.02
        decisions.append(tr.on_message("setpoint", _sp(k, 6.0), now))
        if k % 5 == 0:
            decisions.append(tr.on_message("telemetry", _tel(armed=False, in_air=False), now))
        decisions.append(tr.tick(now))
    assert not any(d.start or d.stop for d in decisions)
    # a vehicle whose in-air flag flickers on the ground (armed, 0.2 s in the air, 0.2 s not): still nothing
    for k in range(200):
        decisions.append(tr.on_message("telemetry", _tel(armed=True, in_air=(k // 2) % 2 == 0), 30.0 + 0.1 * k))
    assert not any(d.start for d in decisions)
    starts, stops = [], []
    for k in range(300):  # 30 s: 10 s flying, 20 s landed and disarmed
        flying = k < 100
        d = tr.on_message("telemetry", _tel(armed=flying, in_air=flying), 60.0 + 0.1 * k)
        starts += [d.start] if d.start else []
        stops += [d.stop] if d.stop else []
    assert starts == ["flying for 0.5 s: armed and in the air (telemetry)"]
    assert stops == ["landed: not flying for 2 s (disarmed, on the ground (telemetry))"]
    # telemetry gone for longer than its timeout: the controller's setpoints decide again
    assert tr.on_message("setpoint", _sp(2000, 6.0), 100.0).start == ""
    assert tr.on_message("setpoint", _sp(2001, 6.0), 100.6).start.endswith("thrust commanded (controller)")


def test_operator_stop_in_the_air_waits_for_a_landing_and_start_is_manual():
    tr = FlightTracker(RecorderConfig())
    tr.on_message("state", _st(0), 0.0)
    tr.on_message("setpoint", _sp(0, 5.0), 0.0)
    assert tr.on_message("setpoint", _sp(1, 5.0), 0.6).start
    assert tr.command("stop")[0].stop == "operator stop"
    assert not tr.on_message("setpoint", _sp(2, 5.0), 2.0).start, "still in the air: no automatic restart"
    tr.on_message("setpoint", _sp(3, 0.0), 2.1)
    tr.on_message("state", _st(50), 4.0)
    assert not tr.tick(4.2).start
    tr.on_message("setpoint", _sp(4, 5.0), 4.3)
    assert tr.on_message("setpoint", _sp(5, 5.0), 4.9).start
    tr2 = FlightTracker(RecorderConfig(auto=False))
    tr2.on_message("state", _st(0), 0.0)
    assert not tr2.on_message("setpoint", _sp(0, 5.0), 0.0).start
    assert not tr2.on_message("setpoint", _sp(1, 5.0), 1.0).start
    assert tr2.command("start")[0].start == "operator start"
    assert tr2.on_message("setpoint", _sp(70, 0.0), 5.0).stop == "", "a manual recording ends by command only"
    assert tr2.tick(9.0).stop == ""
    with pytest.raises(ValueError):
        tr2.command("pause")


# -- the example recording shipped with the project ---------------------------------------------


def test_the_example_recording_is_small_and_gives_a_first_training_set():
    assert EXAMPLE.stat().st_size < 2_000_000
    ts = load_training_set(EXAMPLE, "eso")
    rec = read_recording(EXAMPLE)
    est = rec.channel("estimate")
    assert len(est) == 600 and set(est.columns["pathway"]) == {"eso"}
    # every warm sample (0.5 s = 25 periods) of the 12 s landing test, none on the ground
    assert len(ts) == int(np.sum(est.columns["warm_ticks"] >= 25)) == 576
    assert ts.z.shape == (576, feature_set(DEFAULT_FEATURE_SET).size) and ts.vehicle == "uav1"
    z_height = ts.z[:, 0]
    assert 0.05 < z_height.min() < 0.15 and 0.95 < z_height.max() < 1.05, "from 1 m down to 0.1 m"
    assert rec.properties["params"]["estimator"]["pathway"] == "eso"


def test_catalog_lists_the_example_and_flags_an_unreadable_file(tmp_path):
    from recordings.catalog import catalog, format_table

    (tmp_path / "good.rrd").write_bytes(EXAMPLE.read_bytes())
    (tmp_path / "bad.rrd").write_bytes(b"garbage" * 100)
    (tmp_path / ".x.compacting.rrd").write_bytes(b"scratch")
    entries = {Path(e.path).name: e for e in catalog(tmp_path)}
    assert set(entries) == {"good.rrd", "bad.rrd"}
    good = entries["good.rrd"]
    assert (good.vehicle, good.scenario, good.pathways, good.networks, good.lipschitz_bounds) == (
        "uav1", "nominal_landing", ("eso",), ("base-L1.0",), (1.0,))
    assert abs(good.duration_s - 11.98) < 1e-6 and good.samples == 600
    assert entries["bad.rrd"].error
    table = format_table(list(entries.values()))
    assert "UNREADABLE" in table and "nominal_landing" in table


def test_what_if_reproduces_the_flown_estimate_and_tells_another_one_apart():
    from recordings.replay import WhatIf, what_if

    rec = read_recording(EXAMPLE)
    same = what_if(rec, WhatIf())
    assert same.config["pathway"] == "eso" and same.samples > 500
    # the same estimator on the same inputs: the lockstep flight is reproduced exactly
    assert max(same.diff_max_mps2) < 1e-9
    other = what_if(rec, WhatIf.parse("pathway=neural_eso,omega_o=25"))
    assert other.diff_rms_mps2[2] > 0.01
    assert other.flown_err_rms_mps2 == same.flown_err_rms_mps2 and other.whatif_err_rms_mps2 != same.whatif_err_rms_mps2
    with pytest.raises(ValueError, match="unknown what-if setting"):
        WhatIf.parse("gain=3")
    # the network named is the one that ran: the one trained for an L_N (base-x0.5's, typed with 4 s.f.),
    # or the default network scaled to one no file was trained for
    half = load_network("networks/base-x0.5.safetensors").lipschitz_bound_physical()
    trained = what_if(rec, WhatIf.parse(f"pathway=neural_eso,L_N={half:.4g}"))
    assert trained.config["network"] == f"base-x0.5@L{half:.4g} (file networks/base-x0.5.safetensors)"
    scaled = what_if(rec, WhatIf.parse("pathway=neural_eso,L_N=0.3"))
    assert scaled.config["network"] == "base@L0.3 (scaled networks/base.safetensors)"
    assert "unused" in what_if(rec, WhatIf.parse("L_N=0.5")).config["network"], "flown under eso"
    for bad, why in (("L_N=-1", "positive"), ("L_N=nan", "positive"), ("omega_o=x", "not a number"),
                     ("pathway=fast", "not one of"), ("network=no/such.safetensors", "no such file")):
        with pytest.raises(ValueError, match=why):
            WhatIf.parse(bad)


def test_bus_schedule_is_in_flight_order_and_paced_by_sample_time():
    from recordings.replay import bus_schedule, restamped

    sched = bus_schedule(read_recording(EXAMPLE))
    offsets = [o for o, _, _ in sched]
    assert offsets == sorted(offsets) and abs(offsets[-1] - 11.98) < 1e-9
    assert [t for _, t, _ in sched[:2]] == ["state", "truth"]
    state = restamped(sched[0][2], 5.0)
    assert state.source == "replay" and state.stamp_s == 5.0 and state.pos_enu_m == sched[0][2].pos_enu_m


def test_a_recorder_restarted_mid_flight_repairs_the_cut_file_and_writes_the_next_segment(tmp_path, monkeypatch):
    from services.recorder import Recorder

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))  # the rerun CLI's analytics settings
    statuses = []
    config = RecorderConfig(directory=str(tmp_path), compact=True)
    msgs = flight_messages(120)
    first = Recorder(config, "uav1", publish_status=statuses.append, log=lambda *_: None)
    for channel, msg in msgs[:300]:
        first._handle(("msg", channel, msg.to_bytes(), 10.0 + msg.stamp_s))
    first.writer.flush()  # flushed as the writer thread would, then "killed": never closed
    flight = first.flight
    assert statuses[-1].recording and statuses[-1].flight == flight and statuses[-1].segment == 0
    logs = []
    second = Recorder(config, "uav1", publish_status=statuses.append, log=logs.append)
    second.prepare()  # repairs the cut file; it is then on the pending list too, and compacted once only
    for channel, msg in msgs[300:]:
        second._handle(("msg", channel, msg.to_bytes(), 10.0 + msg.stamp_s))
    assert (second.flight, second.segment) == (flight, 1)
    second._handle(("msg", "state", b"\x93garbage", 20.0))
    second.stop()
    second._end("test over", keep_active=False)
    second.join_compactions()
    seg0, seg1 = read_recording(tmp_path / f"{flight}.seg0.rrd"), read_recording(tmp_path / f"{flight}.seg1.rrd")
    assert seg1.properties["start"]["resumed"] is True and seg1.properties["summary"]["rejected"] == 1
    states = seg0.channel("state").messages() + seg1.channel("state").messages()
    assert states == [m for c, m in msgs if c == "state"], "the two segments hold the whole flight, once"
    from recordings.reader import verify

    assert verify(tmp_path / f"{flight}.seg0.rrd")[0], "the cut segment was repaired"
    rewrites = [line for line in logs if line.startswith(f"{tmp_path / flight}.seg0.rrd: ")]
    assert rewrites == [f"{tmp_path / flight}.seg0.rrd: compacted (repaired after a crash), "
                        f"{(tmp_path / f'{flight}.seg0.rrd').stat().st_size / 1e3:.0f} kB"], rewrites
    assert not (tmp_path / ".uav1.active.json").exists()


def test_a_recorder_that_cannot_write_reports_it_and_keeps_running(tmp_path):
    import threading

    from services.recorder import Recorder

    blocked = tmp_path / "not-a-folder"
    blocked.write_text("a file where the recordings folder should be")
    reports, statuses = [], []
    rec = Recorder(RecorderConfig(directory=str(blocked / "flights")), "uav1", publish_status=statuses.append,
                   log=lambda *_: None, report=lambda level, text: reports.append((level, text)))
    thread = threading.Thread(target=rec.run)
    thread.start()
    for channel, msg in flight_messages(30):
        rec.offer(channel, msg.to_bytes(), 1.0 + msg.stamp_s)
    time.sleep(0.5)
    rec.stop()
    thread.join(10)
    assert not thread.is_alive() and rec.errors >= 2 and reports and reports[0][0] == "error"
    assert "not-a-folder" in rec.last_error and rec.writer is None
    assert statuses and not statuses[-1].recording


def test_a_compacted_file_that_split_a_channel_by_component_reads_back_whole(tmp_path, monkeypatch):
    """`rerun rrd optimize` may store a channel's long texts in a chunk of their own (seen with the canary's
    events); the reader gathers every field by row id."""
    from recordings.reader import repair

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))  # the rerun CLI writes its analytics config there
    w = FlightWriter(tmp_path / "events.rrd", vehicle="uav1", flight="uav1-test")
    texts = [f"canary {k}: " + "→ z RMS 0.75 cm before, 2.27 cm after; " * 8 for k in range(4)]
    for k, text in enumerate(texts):
        w.add("event/estimator", EventMsg(stamp_s=100.0 + k, service="estimator", level="warning", text=text))
        w.flush()
    w.close()
    repair(tmp_path / "events.rrd")
    events = read_recording(tmp_path / "events.rrd").channel("event/estimator")
    assert events.columns["text"] == texts and list(events.columns["level"]) == ["warning"] * 4
    assert list(events.columns["stamp_s"]) == [100.0, 101.0, 102.0, 103.0]


def test_what_the_viewer_plots_z_alone_named_the_loop_latency_and_the_trail(tmp_path):
    """The viewer's legends list no hidden x/y series, the latency plot has a value per sample, the
    3D view has the positions its trail is drawn from."""
    from rerun.chunk import RrdReader

    msgs = flight_messages(60)
    write_recording(tmp_path / "f.rrd", msgs)
    columns: dict[str, list] = {}
    for chunk in RrdReader(str(tmp_path / "f.rrd")).stream():
        batch = chunk.to_record_batch()
        for name in ("Scalars:scalars", "SeriesLines:names", "Points3D:positions"):
            if name in batch.schema.names:
                columns.setdefault(f"{chunk.entity_path}|{name}", []).extend(batch.column(name).to_pylist())
    assert columns["/neso/uav1/estimate/f_hat_mps2|SeriesLines:names"] == [["f̂ z"]]
    f_hat = columns["/neso/uav1/estimate/f_hat_mps2|Scalars:scalars"]
    assert f_hat == [[m.f_hat_mps2[2]] for c, m in msgs if c == "estimate"], "one series: z"
    assert columns["/neso/uav1/state/pos_enu_m|SeriesLines:names"] == [["state z"]]
    latency = [v for (v,) in columns["/neso/uav1/setpoint/loop_latency_ms|Scalars:scalars"]]
    assert latency == pytest.approx([(m.stamp_s - m.state_stamp_s) * 1e3 for c, m in msgs if c == "setpoint"])
    trail = columns["/neso/uav1/state/point|Points3D:positions"]
    states = [m for c, m in msgs if c == "state"]
    assert len(trail) == 60 and trail[5][0] == pytest.approx(states[5].pos_enu_m), "a position per sample"


def test_the_catalog_says_where_the_states_came_from_natnet_version_server_body_and_px4(tmp_path):
    """Before: a NatNet flight was listed as "mocap" (its source's parameters were recorded empty) and a PX4 SITL
    flight as "sim"."""
    from recordings.catalog import catalog, format_table
    from recordings.writer import FlightWriter
    from tests.helpers import EXAMPLES

    state = next(m for m in EXAMPLES if isinstance(m, StateMsg))
    telemetry = next(m for m in EXAMPLES if type(m).__name__ == "TelemetryMsg")
    flights = {
        "natnet": ({"kind": "natnet", "natnet_version": "4.1.0.0", "server": "192.168.1.5:1510",
                    "server_app": "Motive 3.1.0.0", "rigid_body": "uav1"}, "mocap", ""),
        "px4": ({"kind": "sim", "scenario": "nominal_landing", "link": "px4"}, "sim", "PX4 v1.16.0 6ea3539"),
    }
    for name, (description, source, autopilot) in flights.items():
        w = FlightWriter(tmp_path / f"{name}.rrd", vehicle="uav1", flight=name,
                         properties={"params": {"source": description}})
        w.add("state", dataclasses.replace(state, source=source))
        if autopilot:
            w.add("telemetry", dataclasses.replace(telemetry, autopilot=autopilot))
        w.close()
    got = {e.flight: e.source for e in catalog(tmp_path)}
    assert got == {"natnet": "NatNet 4.1 uav1@192.168.1.5:1510",
                   "px4": "sim nominal_landing in PX4 SITL · PX4 v1.16.0 6ea3539"}
    assert "NatNet 4.1 uav1@192.168.1.5:1510" in format_table(catalog(tmp_path))
