"""The router config `neso secure init` writes for a `zenohd` hub (docker-compose.yml), loaded by
Zenoh itself and run as the hub of real TLS sessions in this process: the operator is answered,
the recorder is not, and nothing without this CA's certificate links."""
from __future__ import annotations

import json
import time

import pytest
import zenoh

from runtime.bus import BusConfig
from runtime.client import ServiceUnavailable, get_params, set_params
from runtime.node import Node
from runtime.params import Param, ParamSet
from runtime.schema import Keys
from tests.busutil import free_port, secure_init, secure_peer, session

KEYS = Keys("uav1")


@pytest.fixture(scope="module")
def bus(tmp_path_factory):
    directory = secure_init(str(tmp_path_factory.mktemp("secure") / "creds"))
    endpoint = f"tls/127.0.0.1:{free_port()}"
    conf = zenoh.Config.from_file(f"{directory}/router.json5")  # what zenohd -c reads
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    with zenoh.open(conf) as router:
        node = Node("estimator", vehicle="uav1", bus=secure_peer(endpoint, directory, "estimator"),
                    params=ParamSet((Param("pathway", "neural_eso", str, "estimator pathway", choices=("neural_eso", "eso")),)))
        try:
            node.start()
            yield directory, endpoint, router
        finally:
            node.close()


def test_the_router_config_is_zenohs_and_lets_the_operator_steer(bus):
    directory, endpoint, _ = bus
    with session(secure_peer(endpoint, directory, "operator", mode="client")) as s:
        assert set_params(s, KEYS, "estimator", {"pathway": "eso"}, timeout_s=3.0).ok
        assert get_params(s, KEYS, "estimator").values["pathway"] == "eso"


def test_the_router_refuses_the_recorder_and_strangers(bus):
    directory, endpoint, _ = bus
    with session(secure_peer(endpoint, directory, "recorder", mode="client")) as s:
        with pytest.raises(ServiceUnavailable):
            set_params(s, KEYS, "estimator", {"pathway": "neural_eso"}, timeout_s=1.0)
    with session(BusConfig(connect=(f"tcp/{endpoint[4:]}",))) as s:
        time.sleep(0.5)
        assert list(s.info.routers_zid()) == [] and list(s.info.peers_zid()) == []
