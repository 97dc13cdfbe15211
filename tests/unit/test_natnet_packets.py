"""NatNet packets (sim/natnet.py): built as OptiTrack's parsers read them (checked with the independent
`natnet` package's parser), pose conversion for both Motive up axes, malformed input refused; the world's
stream model (latency, lost windows, seeded jitter and dropouts); `neso up --mocap natnet`'s refusals and ports."""
from __future__ import annotations

import math

import numpy as np
import pytest
from natnet.data_descriptions import DataDescriptions
from natnet.data_frame import DataFrame
from natnet.packet_buffer import PacketBuffer
from natnet.server_info import ServerInfo as TheirServerInfo
from natnet.version import Version

from flight.source import FRAMES, MocapConfig, MocapSource, NatNetStreamConfig
from services.natnet_world import skip_ahead_s
from sim import natnet

V41 = Version(4, 1, 0, 0)


def their(packet: bytes):
    message_id, payload = natnet.split(packet)
    return message_id, PacketBuffer(payload)


def test_server_info_round_trips_and_the_independent_parser_agrees():
    data = natnet.server_info(data_port=1511, multicast=True, multicast_group="239.255.42.99", clock_hz=10_000_000)
    message_id, buf = their(data)
    assert message_id == natnet.NAT_SERVERINFO
    info = TheirServerInfo.read_from_buffer(buf, None)
    assert info.application_name == "Motive" and info.nat_net_protocol_version == V41
    mine = natnet.parse_server_info(natnet.split(data)[1])
    assert (mine.data_port, mine.multicast, mine.multicast_group, mine.clock_hz) == (1511, True, "239.255.42.99", 10**7)
    assert len(data) == 4 + 279  # libmotioncapture's sResponse, packed


@pytest.mark.parametrize("version", natnet.SUPPORTED)
def test_model_definitions_name_the_rigid_bodies_for_both_parsers(version):
    data = natnet.model_def({1: "uav1", 7: "cf 2"}, version)
    message_id, buf = their(data)
    assert message_id == natnet.NAT_MODELDEF
    theirs = DataDescriptions.read_from_buffer(buf, Version(*version))
    assert [(rb.id_num, rb.name) for rb in theirs.rigid_bodies] == [(1, "uav1"), (7, "cf 2")]
    assert natnet.parse_rigid_body_names(natnet.split(data)[1], version) == {1: "uav1", 7: "cf 2"}


@pytest.mark.parametrize("version", natnet.SUPPORTED)
def test_every_version_s_frame_reads_back_in_both_parsers_with_motive_s_times(version):
    bodies = [natnet.BodyPose(1, (0.5, 1.0, -2.0), (0.0, 0.7071068, 0.0, 0.7071068)),
              natnet.BodyPose(7, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), tracked=False)]
    data = natnet.frame_of_data(42, bodies, timestamp_s=1.25, mid_exposure_ticks=123_456_789, received_ticks=123_556_789,
                                transmit_ticks=123_600_000, clock_hz=10_000_000, version=version)
    message_id, buf = their(data)
    theirs = DataFrame.read_from_buffer(buf, Version(*version))
    mine = natnet.parse_frame(natnet.split(data)[1], version)
    assert mine.number == theirs.prefix.frame_number == 42
    assert [(b.id, b.tracked) for b in mine.bodies] == [(rb.id_num, rb.tracking_valid) for rb in theirs.rigid_bodies]
    assert mine.bodies[0].pos_m == pytest.approx(theirs.rigid_bodies[0].pos)
    assert (mine.mid_exposure_ticks, mine.received_ticks, mine.transmit_ticks) == (
        theirs.suffix.stamp_camera_mid_exposure, theirs.suffix.stamp_data_received, theirs.suffix.stamp_transmit)
    assert mine.timestamp_s == theirs.suffix.timestamp == 1.25


def test_a_3_x_model_walks_marker_sets_and_skeletons_and_stops_at_a_force_plate():
    """Before 4.1 nothing says how long a description is: marker sets and skeletons (whose bones are rigid bodies
    too) are read field by field; a kind not read (a force plate) ends the reading with the names found."""
    import struct
    marker_set = struct.pack("<i", 0) + b"set\0" + struct.pack("<i", 2) + b"m1\0m2\0"
    body = struct.pack("<i", 1) + b"uav1\0" + struct.pack("<ii3fi", 3, -1, 0.0, 0.0, 0.0, 1) + bytes(16)
    bone = b"bone\0" + struct.pack("<ii3fi", 9, -1, 0.0, 0.0, 0.0, 0)
    skeleton = struct.pack("<i", 2) + b"sk\0" + struct.pack("<ii", 5, 1) + bone
    plate = struct.pack("<i", 3) + b"\xff" * 40
    payload = struct.pack("<i", 4) + marker_set + body + skeleton + plate
    assert natnet.parse_rigid_body_names(payload, (3, 1)) == {3: "uav1"}


def test_a_frame_reads_back_field_by_field_in_the_independent_parser():
    bodies = [natnet.BodyPose(1, (0.5, 1.0, -2.0), (0.0, 0.7071068, 0.0, 0.7071068)),
              natnet.BodyPose(7, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), tracked=False, mean_error_m=0.0004)]
    data = natnet.frame_of_data(42, bodies, timestamp_s=1.25, mid_exposure_ticks=123_456_789, received_ticks=123_556_789,
                                transmit_ticks=123_600_000, clock_hz=10_000_000)
    message_id, buf = their(data)
    assert message_id == natnet.NAT_FRAMEOFDATA
    frame = DataFrame.read_from_buffer(buf, V41)
    assert frame.prefix.frame_number == 42
    assert [(rb.id_num, rb.tracking_valid) for rb in frame.rigid_bodies] == [(1, True), (7, False)]
    assert frame.rigid_bodies[0].pos == pytest.approx((0.5, 1.0, -2.0)) and frame.rigid_bodies[0].rot == pytest.approx(
        (0.0, 0.7071068, 0.0, 0.7071068))
    assert frame.suffix.timestamp == 1.25
    assert (frame.suffix.stamp_camera_mid_exposure, frame.suffix.stamp_data_received, frame.suffix.stamp_transmit) == (
        123_456_789, 123_556_789, 123_600_000)
    # it reads the 2-byte frame params where 4.1 puts the precision timestamp (4 + 4 bytes; OptiTrack's own
    # natnetsdk reads those for 4.x), then stops: 8 + 2 (params) + 4 (end tag) - 2 bytes unread
    assert buf.pointer == len(natnet.split(data)[1]) - 12


@pytest.mark.parametrize("bad", [b"", b"\x07", b"\x07\x00\x10\x00abc"])
def test_a_short_or_lying_datagram_is_refused(bad):
    with pytest.raises(natnet.NatNetError):
        natnet.split(bad)


@pytest.mark.parametrize("up_axis,frame", [("y", "y_up"), ("z", "enu")])
@pytest.mark.parametrize("rpy_deg", [(0, 0, 90), (10, 0, 0), (10, -5, 90), (0, 0, -170)])
def test_motive_poses_come_back_to_enu_through_the_sources_frame(up_axis, frame, rpy_deg):
    rpy = tuple(math.radians(a) for a in rpy_deg)
    pos, (qx, qy, qz, qw) = natnet.motive_pose((1.0, 2.0, 0.5), rpy, up_axis)
    assert np.allclose(np.array(FRAMES[frame]) @ pos, (1.0, 2.0, 0.5))
    state = MocapSource(MocapConfig(frame=frame), 50.0, clock=lambda: 0.0).frame(0.0, np.array(pos), (qw, qx, qy, qz))
    assert np.allclose((state.roll_rad, state.pitch_rad, state.yaw_rad), rpy, atol=1e-9)


def test_y_up_puts_the_height_on_motive_y_and_north_on_minus_z():
    pos, quat = natnet.motive_pose((1.0, 2.0, 0.5), (0.0, 0.0, math.radians(90)), "y")
    assert pos == (1.0, 0.5, -2.0)
    # yaw 90 deg about ENU up is a rotation about Motive's +y: q = (0, sin 45, 0, cos 45)
    assert quat == pytest.approx((0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5)))


def test_lost_windows_parse_or_refuse():
    assert NatNetStreamConfig(lost="5:1, 8.5:0.25").lost_windows() == ((5.0, 1.0), (8.5, 0.25))
    with pytest.raises(ValueError, match="start:duration"):
        NatNetStreamConfig(lost="5-1").lost_windows()


class _Collect:
    """Stands in for the server's queue: what WorldStream submits."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, float, list]] = []

    def submit(self, send_at_s, mid_exposure_s, bodies) -> None:
        self.frames.append((send_at_s, mid_exposure_s, bodies))


def test_the_world_stream_sends_each_sample_after_its_latency_and_flags_the_lost_window():
    from sim.natnet_server import StreamModel, WorldStream

    out = _Collect()
    stream = WorldStream(out, StreamModel(latency_s=0.010, lost=((0.5, 0.25),)), body_id=3, anchor_s=100.0, seed=1)
    for k in range(100):
        stream.sample(k * 0.01, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    assert len(out.frames) == 100
    assert all(send == pytest.approx(mid + 0.010) for send, mid, _ in out.frames)
    untracked = [round(mid - 100.0, 2) for _, mid, bodies in out.frames if not bodies[0].tracked]
    assert untracked == [round(0.5 + 0.01 * i, 2) for i in range(25)]
    assert {bodies[0].id for _, _, bodies in out.frames} == {3}


def test_jitter_and_dropouts_are_seeded_and_never_send_before_the_exposure():
    from sim.natnet_server import StreamModel, WorldStream

    runs = []
    for _ in range(2):
        out = _Collect()
        stream = WorldStream(out, StreamModel(latency_s=0.0, jitter_std_s=0.001, dropout=0.2), body_id=1, anchor_s=0.0,
                             seed=7)
        for k in range(2000):
            stream.sample(k * 0.01, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
        runs.append([(send, mid) for send, mid, _ in out.frames])
        assert 0.17 < stream.dropped / 2000 < 0.23
    assert runs[0] == runs[1]
    late = np.array([send - mid for send, mid in runs[0]])
    assert late.min() >= 0.0 and 0.0005 < np.mean(late) < 0.0011  # |N(0, 1 ms)|: mean 0.8 ms


def test_neso_up_refuses_natnet_with_lockstep_or_px4_sitl(capsys):
    from cli.main import build_parser
    from cli.up import run

    for extra in (["--lockstep"], ["--vehicle", "px4"]):
        assert run(build_parser().parse_args(["up", "--mocap", "natnet", *extra])) == 2
        assert "--mocap natnet runs in real time with --vehicle direct or mavlink only" in capsys.readouterr().out


def test_neso_up_streams_several_vehicles_from_one_simulated_motive_and_one_from_its_own():
    from cli.main import build_parser
    from cli.up import build_specs

    def specs(*names: str) -> dict:
        args = ["up", "--mocap", "natnet", "--natnet-port", "3000"] + [a for n in names for a in ("--name", n)]
        return {s.name: list(s.argv) for s in build_specs(build_parser().parse_args(args))}

    def opt(argv: list, flag: str) -> str:
        return argv[argv.index(flag) + 1]

    two = specs("a", "b")
    motive = two["motive"]
    assert list(two).index("motive") < list(two).index("a/source"), "the mocap system starts before its readers"
    assert (opt(motive, "--port"), opt(motive, "--feed-port"), opt(motive, "--bodies")) == ("3000", "3002", "a,b")
    for i, v in enumerate(("a", "b")):
        argv = two[f"{v}/source"]
        assert opt(argv, "--mocap-stream") == "natnet" and opt(argv, "--natnet-port") == "3000"
        assert (opt(argv, "--natnet-feed"), opt(argv, "--natnet-body-id"), opt(argv, "--rigid-body")) == \
            ("3002", str(i + 1), v)
        assert float(opt(argv, "--natnet-rate")) == float(opt(motive, "--rate")) == 100.0  # the scenario's mocap rate
    one = specs()
    assert "motive" not in one and "--natnet-feed" not in one["source"] and opt(one["source"], "--natnet-port") == "3000"


def test_the_source_refuses_a_natnet_stream_it_cannot_run_in_one_line():
    from dataclasses import replace

    from flight.source import SourceConfig
    from services.source import natnet_refusal

    ok = SourceConfig(mocap_stream="natnet")
    assert natnet_refusal(ok) == "" and natnet_refusal(replace(ok, natnet=NatNetStreamConfig(rate_hz=360.0))) == ""
    assert natnet_refusal(replace(ok, link="mavlink")) == ""  # a simulated PX4 in a room with OptiTrack
    assert "real time with --link direct or mavlink only" in natnet_refusal(replace(ok, lockstep=True))
    assert "real time with --link direct or mavlink only" in natnet_refusal(replace(ok, link="px4"))
    assert "start:duration" in natnet_refusal(replace(ok, natnet=NatNetStreamConfig(lost="1-2")))
    for rate in (50.0, 400.0, 120.5):
        assert "100-360" in natnet_refusal(replace(ok, natnet=NatNetStreamConfig(rate_hz=rate)))


@pytest.mark.parametrize("rate_hz", [100.0, 360.0])
def test_a_late_simulated_world_moves_motives_exposures_on_by_whole_frames(rate_hz):
    frame_s = 1.0 / rate_hz
    for late_s in (0.0207, 0.02, 0.0451, 0.31, 1.0):
        skip = skip_ahead_s(late_s, frame_s)
        frames = skip / frame_s
        assert abs(frames - round(frames)) < 1e-9 and late_s - 1e-12 <= skip < late_s + frame_s, (late_s, skip)
