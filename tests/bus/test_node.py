"""`runtime.node.Node` and the `runtime.client` functions over real Zenoh sessions, in one process.

A hub (router) and peers on loopback endpoints, multicast scouting off (runtime/bus.py): the
estimator role's node with the estimator's real parameters, and an operator's client session.
No subprocesses, no real time: what the adapter does with what arrives.
"""
from __future__ import annotations

import dataclasses
import os
import random
import time

import msgpack
import pytest
import zenoh

from neso.types import OMEGA_O_RPS
from runtime.client import command, get_params, set_params
from runtime.node import Node
from runtime.params import ParamSet
from runtime.schema import CommandReply, HealthMsg, Keys, ParamReply, StateMsg
from flight.estimator import EstimatorConfig, NetworkChoice, estimator_params, load_flown_network
from tests.busutil import free_port, hub, peer, session
from tests.helpers import BASE, EXAMPLES, REPO

KEYS = Keys("uav1")
VALID_STATE = next(m for m in EXAMPLES if isinstance(m, StateMsg))


@pytest.fixture(scope="module")
def endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint):
        yield endpoint


@pytest.fixture(scope="module")
def choice():
    net, source = load_flown_network(BASE)
    return NetworkChoice(net, source, str(REPO / "networks"))


class Estimator:
    """The estimator role's node with its real parameter set; records what its handlers got."""

    def __init__(self, endpoint: str, choice: NetworkChoice, command_s: float = 0.0, check_s: float = 0.0) -> None:
        """``command_s``, ``check_s``: how long each command, each parameter check takes."""
        self.params = ParamSet(estimator_params(EstimatorConfig(network=BASE), 1.0),
                               check=lambda p: (time.sleep(check_s), choice.refusal(p["lipschitz_bound"]))[1])
        self.node = Node("estimator", vehicle="uav1", bus=peer(endpoint), params=self.params)
        self.states: list[StateMsg] = []
        self.commands: list[tuple[str, dict]] = []
        self.command_s = command_s
        self.node.subscribe("state", lambda msg, _received: self.states.append(msg))
        self.node.on_command(self._on_command)

    def _on_command(self, name: str, args: dict) -> tuple[bool, str]:
        self.commands.append((name, args))
        time.sleep(self.command_s)
        if name == "explode":
            raise RuntimeError("a bug in a handler")
        return name == "promote", f"{name} number {len(self.commands)}"


@pytest.fixture
def estimator(endpoint, choice):
    e = Estimator(endpoint, choice)
    e.node.start()
    try:
        yield e
    finally:
        e.node.close()


@pytest.fixture
def client(endpoint):
    with session(peer(endpoint)) as s:
        yield s


def wait_until(condition, timeout_s: float = 5.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{what} not met within {timeout_s} s"
        time.sleep(0.01)


def test_parameters_are_set_or_refused_with_the_reason_and_a_refusal_changes_nothing(estimator, client):
    assert get_params(client, KEYS, "estimator").values == {"pathway": "neural_eso", "lipschitz_bound": 1.0,
                                                            "omega_o_rps": OMEGA_O_RPS}
    reply = set_params(client, KEYS, "estimator", {"pathway": "eso", "lipschitz_bound": 0.5})
    assert reply.ok and reply.values["pathway"] == "eso" and reply.values["lipschitz_bound"] == 0.5
    for values, reason in (({"lipschitz_bound": 50.0}, "above"), ({"pathway": "magic"}, "pathway must be one of"),
                           ({"omega_o_rps": 20.0}, "outside"), ({"gain": 1.0}, "unknown parameter"),
                           ({"pathway": "nn", "lipschitz_bound": -1.0}, "outside")):
        reply = set_params(client, KEYS, "estimator", values)
        assert not reply.ok and reason in reply.error, (values, reply.error)
    assert get_params(client, KEYS, "estimator").values["pathway"] == "eso", "all or nothing"
    assert estimator.params.take_pending() == {"pathway": "eso", "lipschitz_bound": 0.5}


def _malformed(rng: random.Random) -> bytes:
    body = msgpack.unpackb(VALID_STATE.to_bytes())
    kind = rng.randrange(4)
    if kind == 0:
        return bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 100)))
    if kind == 1:
        return VALID_STATE.to_bytes()[: rng.randrange(0, len(VALID_STATE.to_bytes()))]
    if kind == 2:
        return msgpack.packb({**body, "v": 99})
    return msgpack.packb({**body, "pos_enu_m": [0.0, float("nan"), 1.0]})


def test_malformed_payloads_are_dropped_and_counted_and_valid_ones_delivered(estimator, client):
    health: list[HealthMsg] = []
    sub = client.declare_subscriber(KEYS.health("estimator"),
                                    lambda s: health.append(HealthMsg.from_bytes(s.payload.to_bytes())))
    pub = client.declare_publisher(KEYS.topic("state"), congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        rng = random.Random(3)
        wait_until(lambda: health, what="a health report")  # the subscriber is linked (reports come at 1 Hz)
        for i in range(500):
            pub.put(_malformed(rng))
            if i % 50 == 0:
                pub.put(dataclasses.replace(VALID_STATE, seq=i).to_bytes())
        wait_until(lambda: len(estimator.states) == 10 and estimator.node.stats.rejected["state"] == 500,
                   what="10 states delivered and 500 payloads rejected")
        assert [m.seq for m in estimator.states] == list(range(0, 500, 50))
        n = len(health)
        wait_until(lambda: len(health) > n and health[-1].rejected["state"] == 500, 3.0, "the count on the bus")
        bad_query = client.get(KEYS.param("estimator"), payload=b"\xc1 not msgpack", timeout=2.0)
        (reply,) = list(bad_query)
        assert reply.err is not None and not ParamReply.from_bytes(reply.err.payload.to_bytes()).ok
        (reply,) = list(client.get(KEYS.cmd("estimator"), payload=msgpack.packb({"v": 1}), timeout=2.0))
        assert reply.err is not None and not CommandReply.from_bytes(reply.err.payload.to_bytes()).ok
        assert estimator.node.stats.rejected["param"] == 1 and estimator.node.stats.rejected["cmd"] == 1
        assert estimator.commands == [], "nothing ran"
    finally:
        pub.undeclare()
        sub.undeclare()


def test_a_command_is_done_once_per_request_id(estimator, client):
    first = command(client, KEYS, "estimator", "promote", {"request": "r1"})
    again = command(client, KEYS, "estimator", "promote", {"request": "r1"})
    other = command(client, KEYS, "estimator", "promote")  # a fresh id
    assert first.ok and first.message == again.message == "promote number 1"
    assert other.message == "promote number 2" and len(estimator.commands) == 2
    refused = command(client, KEYS, "estimator", "rollback")
    assert not refused.ok and refused.message == "rollback number 3"
    failed = command(client, KEYS, "estimator", "explode")
    assert (failed.ok, failed.message) == (False, "command failed (see events)")


def test_a_slow_command_the_client_repeats_runs_once(endpoint, choice, client):
    slow = Estimator(endpoint, choice, command_s=1.0)  # the client re-asks every 0.25 s meanwhile
    slow.node.start()
    try:
        reply = command(client, KEYS, "estimator", "promote", timeout_s=5.0)
    finally:
        slow.node.close()
    assert reply.ok and reply.message == "promote number 1"
    assert len(slow.commands) == 1


def test_liveliness_while_started_and_a_health_report_every_second(endpoint, choice, client):
    tokens: list[str] = []
    sub = client.liveliness().declare_subscriber(KEYS.alive("estimator"), lambda s: tokens.append(str(s.kind)))
    health: list[tuple[float, HealthMsg]] = []
    hsub = client.declare_subscriber(KEYS.health("estimator"), lambda s: health.append(
        (time.monotonic(), HealthMsg.from_bytes(s.payload.to_bytes()))))
    e = Estimator(endpoint, choice)
    try:
        time.sleep(0.3)
        assert not list(client.liveliness().get(KEYS.alive("estimator"), timeout=0.5)), "not alive before start"
        e.node.start()
        wait_until(lambda: tokens == ["SampleKind.PUT"], what="the liveliness token")
        wait_until(lambda: len(health) >= 3, 5.0, "three health reports")
        gaps = [b[0] - a[0] for a, b in zip(health, health[1:])]
        assert all(0.5 < g < 2.0 for g in gaps), gaps
        assert {h.service for _, h in health} == {"estimator"} and health[-1][1].pid == os.getpid()
    finally:
        e.node.close()
    try:
        wait_until(lambda: tokens[-1] == "SampleKind.DELETE", 3.0, "the token withdrawn at close")
    finally:
        sub.undeclare()
        hsub.undeclare()


def test_a_change_the_service_takes_seconds_to_check_reaches_the_page_as_its_answer(endpoint, choice, client):
    """The dashboard's requests wait :attr:`DashboardConfig.request_timeout_s` for the service's answer: an L_N the
    estimator took over 2 s to certify on a busy machine was shown as "refused · ServiceUnavailable" (the page's old
    2 s) while the estimator applied it."""
    import threading

    from dashboard.service import BusFacade, DashboardConfig

    slow = Estimator(endpoint, choice, check_s=3.0)
    slow.node.start()
    facade = BusFacade(client, timeout_s=DashboardConfig().request_timeout_s)
    answered, replies = threading.Event(), []
    try:
        bound = get_params(client, KEYS, "estimator").values["lipschitz_bound"]
        facade.set_params("uav1", "estimator", {"lipschitz_bound": bound}, lambda ok, text: (replies.append((ok, text)),
                                                                                             answered.set()))
        assert answered.wait(15.0)
    finally:
        facade.close()
        slow.node.close()
    assert replies == [(True, f"estimator will apply {{'lipschitz_bound': {bound!r}}}")], replies
