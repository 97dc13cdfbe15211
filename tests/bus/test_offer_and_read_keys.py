"""The two keys a secure bus needs to tell requests apart, over real Zenoh sessions: an offer
travels on ``offer/<service>`` (never ``cmd``), and ``params/<service>`` answers reads only."""
from __future__ import annotations

import uuid

from runtime.client import _query, command, read_params
from runtime.node import Node
from runtime.params import Param, ParamSet
from runtime.schema import CommandReply, CommandRequest, Keys, ParamReply, ParamRequest
from tests.busutil import free_port, hub, peer, session

KEYS = Keys("uav1")


def test_offers_have_their_own_key_and_params_reads_cannot_set():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    done: list[tuple[str, dict]] = []
    with hub(endpoint):
        node = Node("estimator", vehicle="uav1", bus=peer(endpoint),
                    params=ParamSet((Param("pathway", "neural_eso", str, "pathway", choices=("neural_eso", "eso")),)))
        node.on_command(lambda name, args: (done.append((name, args)) or True, f"did {name}"))
        try:
            node.start()
            with session(peer(endpoint)) as s:
                reply = command(s, KEYS, "estimator", "offer", {"path": "x.safetensors"})  # the client picks the key
                assert reply.ok and done == [("offer", {"path": "x.safetensors"})]
                sneaked = _query(s, KEYS.cmd("estimator"), CommandRequest(
                    name="offer", args={"request": uuid.uuid4().hex, "path": "y"}).to_bytes(), CommandReply, 2.0)
                assert not sneaked.ok and "offer/estimator" in sneaked.message
                wrong = _query(s, KEYS.offer("estimator"), CommandRequest(
                    name="promote", args={"request": uuid.uuid4().hex}).to_bytes(), CommandReply, 2.0)
                assert not wrong.ok and "takes only offer" in wrong.message
                assert len(done) == 1
                assert read_params(s, KEYS, "estimator").values == {"pathway": "neural_eso"}
                refused = _query(s, KEYS.params("estimator"), ParamRequest(op="set", values={"pathway": "eso"}).to_bytes(),
                                 ParamReply, 2.0)
                assert not refused.ok and "read only" in refused.error
                assert node.params.values() == {"pathway": "neural_eso"}
        finally:
            node.close()
