"""``--priorities``: the loop's streams at Zenoh's real-time priority, the services' own reports low,
everything else at Zenoh's default; nothing changes without it, nor on the lowlatency transport (no QoS)."""
from __future__ import annotations

import zenoh

from runtime.bus import BusConfig, publisher_qos
from runtime.schema import LOOP_TOPICS, TOPICS
from tests.helpers import up_args


def test_without_priorities_every_stream_keeps_zenohs_default_priority():
    for stream in (*TOPICS, "service"):
        assert "priority" not in publisher_qos(BusConfig(), stream)
    assert publisher_qos(BusConfig(), "state") == {"express": True}
    assert publisher_qos(BusConfig(), "service") == {}


def test_with_priorities_the_loop_is_real_time_and_the_reports_low():
    bus = BusConfig(priorities=True)
    assert set(LOOP_TOPICS) == {"state", "estimate", "setpoint"}
    for topic in TOPICS:
        expected = zenoh.Priority.REAL_TIME if topic in LOOP_TOPICS else zenoh.Priority.DATA
        assert publisher_qos(bus, topic) == {"express": True, "priority": expected}, topic
    assert publisher_qos(bus, "service") == {"priority": zenoh.Priority.DATA_LOW}


def test_the_lowlatency_transport_has_no_priorities_to_set():
    assert "priority" not in publisher_qos(BusConfig(priorities=True, low_latency=True), "state")


def test_neso_up_hands_priorities_to_every_service():
    from cli.up import build_specs

    for spec in build_specs(up_args("--priorities")):
        if spec.name != "hub":  # a router forwards each message at the priority it was sent with
            assert "--priorities" in spec.argv, spec.name
    assert not any("--priorities" in s.argv for s in build_specs(up_args()))
