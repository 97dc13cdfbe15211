"""Every message round-trips bit-exactly; malformed, unknown-version and out-of-range payloads are refused."""
from __future__ import annotations

import dataclasses
import math
import random

import msgpack
import pytest

from neso.estimator import PATHWAYS as METHOD_PATHWAYS
from runtime import schema
from runtime.schema import (PATHWAYS, SCHEMA_VERSION, CommandReply, CommandRequest, EstimateMsg, EventMsg, HealthMsg,
                            Keys, Message, ParamReply, ParamRequest, ParamStateMsg, ReferenceMsg, SchemaError,
                            SetpointMsg, StateMsg, TruthMsg, TelemetryMsg, RecordingMsg, NetworkMsg,
                            any_vehicle, vehicle_of)

V3 = (0.1, -2.5, 1e-300)
EXAMPLES: list[Message] = [
    StateMsg(seq=3, stamp_s=12.5, t_s=0.06, pos_enu_m=V3, vel_enu_mps=V3, roll_rad=0.1, pitch_rad=-0.2,
             yaw_rad=3.0, source="sim"),
    TruthMsg(seq=3, stamp_s=1.0, t_s=0.06, pos_enu_m=V3, vel_enu_mps=V3, disturbance_acc_enu_mps2=V3,
             on_ground=False, crashed=False, scenario="nominal_landing"),
    EstimateMsg(seq=3, stamp_s=1.0, t_s=0.06, f_hat_mps2=V3, f_n_mps2=V3, delta_f_hat_mps2=V3,
                z=(1.0, 0.0, 9.81, 0.01, -0.02), pathway="neural_eso", network_id="base-L1", warm_ticks=4),
    SetpointMsg(seq=3, stamp_s=1.0, state_stamp_s=0.9, t_s=0.06, roll_rad=0.0, pitch_rad=0.1, yaw_rad=0.0,
                thrust_norm=0.5, thrust_n=9.81, acc_cmd_enu_mps2=V3, estimate_source="estimator", estimate_stamp_s=0.95),
    ReferenceMsg(seq=3, stamp_s=1.0, t_s=0.06, pos_enu_m=V3, vel_enu_mps=V3, acc_enu_mps2=V3, yaw_rad=0.0,
                 segment="landing_test"),
    EventMsg(stamp_s=1.0, service="controller", level="warning", text="flying on the local ESO"),
    HealthMsg(stamp_s=1.0, service="estimator", pid=42, uptime_s=3.0, ticks=150, rate_hz=50.0, latency_p50_ms=0.1,
              latency_p99_ms=0.3, rejected={"state": 2.0}, staleness_s={"state": 0.01}, status="ok",
              counters={"deadline_misses": 3.0}),
    ParamRequest(op="set", values={"pathway": "eso", "lipschitz_bound": 0.5}),
    ParamReply(ok=False, service="estimator", values={"pathway": "eso"}, error="why"),
    ParamStateMsg(stamp_s=1.0, service="estimator", seq=10, values={"pathway": "eso"}, note="pathway eso"),
    CommandRequest(name="takeoff", args={"height_m": 1.0}),
    CommandReply(ok=True, service="controller", message="takeoff starts at the next sample"),
    TelemetryMsg(stamp_s=1.0, connected=True, armed=True, in_air=True, flight_mode="OFFBOARD", roll_rad=0.01,
                 pitch_rad=-0.02, yaw_rad=1.5, pos_enu_m=V3, vel_enu_mps=V3, battery_v=15.8, battery_remaining=0.8,
                 hover_thrust_norm=0.42, setpoint_age_s=0.02, failsafe=""),
    RecordingMsg(stamp_s=1.0, recording=True, flight="uav1-20261121-050000", segment=0,
                 path="recordings/uav1-20261121-050000.rrd", duration_s=12.5, size_bytes=123456, dropped=0),
    NetworkMsg(stamp_s=1.0, seq=100, active={"id": "base-L1", "source": "file", "lipschitz_norm": 1.0,
                                             "lipschitz_phys": 31.6},
               candidate={}, previous={}, shadow_error_rms_mps2=-1.0),
]


def all_message_classes():
    return {cls for cls in vars(schema).values()
            if isinstance(cls, type) and issubclass(cls, Message) and cls is not Message}


def test_fields_added_later_have_defaults_so_older_payloads_still_decode():
    """estimate_stamp_s and counters came after the first recordings and peers: a payload without them decodes."""
    import msgpack

    for msg, name, default in ((EXAMPLES[3], "estimate_stamp_s", 0.0), (EXAMPLES[6], "counters", {})):
        body = msgpack.unpackb(msg.to_bytes())
        del body[name]
        assert getattr(type(msg).from_bytes(msgpack.packb(body)), name) == default


def test_every_message_class_has_an_example():
    assert {type(m) for m in EXAMPLES} == all_message_classes()


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip_is_exact(msg):
    back = type(msg).from_bytes(msg.to_bytes())
    assert back == msg
    assert type(msg).from_bytes(back.to_bytes()) == back


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_malformed_variants_are_refused(msg):
    body = msgpack.unpackb(msg.to_bytes())
    bad = [b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb([1, 2]), msg.to_bytes()[:-1],
           msgpack.packb({**body, "v": SCHEMA_VERSION + 1}), msgpack.packb({**body, "type": "other"}),
           msgpack.packb({**body, "surprise": 1})]
    for fld in dataclasses.fields(msg):
        required = fld.default is dataclasses.MISSING and fld.default_factory is dataclasses.MISSING
        if required:
            bad.append(msgpack.packb({k: v for k, v in body.items() if k != fld.name}))
        bad.append(msgpack.packb({**body, fld.name: [None, {"x": b"\x00"}]}))
    for data in bad:
        with pytest.raises(SchemaError):
            type(msg).from_bytes(data)


@pytest.mark.parametrize("field,value", [
    ("pos_enu_m", [0.0, 0.0]), ("pos_enu_m", [0.0, math.nan, 0.0]), ("pos_enu_m", [0.0, 0.0, math.inf]),
    ("pos_enu_m", [0.0, 0.0, 1e9]), ("roll_rad", 7.0), ("seq", -1), ("seq", 1.5), ("seq", True),
    ("source", "camera"), ("t_s", "now"),
])
def test_out_of_range_state_fields_are_refused(field, value):
    body = msgpack.unpackb(EXAMPLES[0].to_bytes())
    with pytest.raises(SchemaError, match=field):
        StateMsg.from_bytes(msgpack.packb({**body, field: value}))


def test_setpoint_thrust_outside_0_1_is_refused():
    body = msgpack.unpackb(EXAMPLES[3].to_bytes())
    for value in (-0.01, 1.01, math.nan):
        with pytest.raises(SchemaError, match="thrust_norm"):
            SetpointMsg.from_bytes(msgpack.packb({**body, "thrust_norm": value}))


def test_random_bytes_never_raise_anything_but_schema_error():
    rng = random.Random(0)
    for _ in range(3000):
        data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 200)))
        for cls in (StateMsg, SetpointMsg, EstimateMsg, ParamRequest):
            try:
                cls.from_bytes(data)
            except SchemaError:
                pass


def test_schema_pathways_mirror_the_method():
    assert PATHWAYS == METHOD_PATHWAYS


def test_keys_are_built_in_one_place_and_names_are_checked():
    k = Keys("uav1")
    assert k.topic("state") == "neso/uav1/state"
    assert k.param("estimator") == "neso/uav1/param/estimator"
    assert k.alive("controller") == "neso/uav1/alive/controller"
    for bad in ("", "a/b", "*", "uav 1", "-x"):
        with pytest.raises(ValueError):
            Keys(bad)
    with pytest.raises(KeyError):
        k.topic("nonsense")


def test_any_vehicle_keys_and_the_vehicle_a_key_belongs_to():
    assert any_vehicle("state") == "neso/*/state"
    assert vehicle_of(Keys("uav2").topic("state")) == "uav2"
    assert vehicle_of(Keys("uav2").health("estimator")) == "uav2"
    with pytest.raises(ValueError):
        vehicle_of("other/uav1/state")
