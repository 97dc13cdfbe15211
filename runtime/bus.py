"""Zenoh session configuration: one machine by default, several by override.

The embedded default: a hub (a session in ``router`` mode listening on
``tcp/127.0.0.1:7447``) and every service a ``peer`` that connects to it and listens on
``tcp/127.0.0.1:0`` so other peers can link to it directly (they do, and keep talking if
the hub goes). Multicast scouting is off: the default would find strangers on the LAN and
containers have none. Connect retries start at 100 ms and cap at 500 ms, so a service
started before the hub links up within half a second of it.

For several machines: give ``connect`` (the hub's or a ``zenohd`` router's endpoint) and
``listen`` (an address the other machines can reach), or a whole Zenoh config file
(``config_file``), whose settings the explicit ones then override.

Secure (``credentials``, :mod:`runtime.secure`): ``tls/`` endpoints only, mutual TLS as the
credentials' identity, and the graph's access-control list (:mod:`runtime.acl`) on this
session's ingress, in every session alike (peers link directly, past the hub).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

DEFAULT_HUB = "tcp/127.0.0.1:7447"
SECURE_HUB = "tls/127.0.0.1:7447"
MODES = ("peer", "client", "router")
#: Zenoh's priorities, as its config names each one's transmit queue (``transport/link/tx/queue/size``).
ZENOH_PRIORITIES = ("control", "real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low",
                    "background")


@dataclass(frozen=True)
class BusConfig:
    """Where and how a process joins the bus.

    ``connect``/``listen``: Zenoh endpoints (``tcp/host:port``). ``mode``: ``peer`` (services),
    ``router`` (the hub), ``client`` (a tool that only talks through a router).
    ``config_file``: a Zenoh JSON5 config loaded first. ``low_latency``: Zenoh's
    ``transport/unicast/lowlatency`` (every session on the bus must agree; QoS off).
    ``priorities``: the loop's streams published at Zenoh's real-time priority and health, events
    and parameter broadcasts at low priority (:func:`publisher_qos`); off: all at Zenoh's default.
    ``tx_queue_batches``: how many batches each priority's transmit queue holds per link (Zenoh's
    default is 2). Our puts are express (one message, one batch) and congestion-controlled by
    dropping after 1 ms: with 2, a sample's puts back to back were dropped whenever the process's
    transmit thread was not scheduled within that millisecond — on a loaded machine 0.8–7 % of the
    samples of a 50 Hz loop lost their later topics, a third to a half with two more cores busy
    (tests/process/test_bus_under_load.py); with 16, none in 7 of 8 runs, 2 samples once against
    23 beside it. 16 is the most Zenoh documents; a frozen subscriber still costs its publisher
    nothing but drops.
    """

    connect: tuple[str, ...] = (DEFAULT_HUB,)
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    mode: str = "peer"
    config_file: str | None = None
    low_latency: bool = False
    priorities: bool = False
    retry_period_init_ms: int = 100
    retry_period_max_ms: int = 500
    tx_queue_batches: int = 16
    credentials: object = None  # runtime.secure.Credentials: TLS, mTLS and the ACL
    extra: dict = field(default_factory=dict)  # raw "path": json-value settings, applied last

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if not 1 <= self.tx_queue_batches <= 16:
            raise ValueError(f"tx_queue_batches must be 1 to 16 (Zenoh's range), got {self.tx_queue_batches}")
        for endpoint in (*self.connect, *self.listen):
            if "/" not in endpoint:
                raise ValueError(f"endpoint {endpoint!r} must look like tcp/127.0.0.1:7447")
            if self.credentials is not None and not endpoint.startswith("tls/"):
                raise ValueError(f"endpoint {endpoint!r}: a secure bus speaks tls/ only (e.g. {SECURE_HUB})")

    def settings(self) -> dict[str, object]:
        """The config path → value pairs this applies on top of Zenoh's defaults (or the file)."""
        out: dict[str, object] = {
            "mode": self.mode,
            "scouting/multicast/enabled": False,
            # Both sides of a peer pair dial each other (default: only the greater id dials). A peer
            # restarted while others run was measured missing a direct link otherwise, and then lost
            # its traffic when the hub died.
            "scouting/gossip/autoconnect_strategy": {"peer": {"to_router": "always", "to_peer": "always"}},
            "scouting/gossip/target": {"router": ["router", "peer"], "peer": ["router", "peer"]},
            "connect/endpoints": list(self.connect),
            "listen/endpoints": list(self.listen),
            "connect/retry": {
                "period_init_ms": self.retry_period_init_ms,
                "period_max_ms": self.retry_period_max_ms,
                "period_increase_factor": 2,
            },
            "transport/link/tx/queue/size": {priority: self.tx_queue_batches for priority in ZENOH_PRIORITIES},
        }
        if self.low_latency:
            out["transport/unicast/lowlatency"] = True
            out["transport/unicast/qos/enabled"] = False
        if self.credentials is not None:
            from runtime.acl import access_control

            out["transport/link/tls"] = self.credentials.tls()
            out["access_control"] = access_control()
        out.update(self.extra)
        return out

    def zenoh_config(self):
        import zenoh

        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        for path, value in self.settings().items():
            conf.insert_json5(path, json.dumps(value))
        return conf


def hub_config(endpoint: str = DEFAULT_HUB, **overrides) -> BusConfig:
    """The hub: a router listening on ``endpoint`` and connecting to nothing."""
    return BusConfig(connect=(), listen=(endpoint,), mode="router", **overrides)


def publisher_qos(config: BusConfig, stream: str) -> dict:
    """``declare_publisher`` keyword arguments for ``stream``: a topic of ``runtime.schema.TOPICS``
    or ``"service"`` (a service's health, events and parameter broadcasts)."""
    import zenoh

    from runtime.schema import LOOP_TOPICS

    qos: dict = {} if stream == "service" else {"express": True}
    if config.priorities and not config.low_latency:  # the lowlatency transport has no QoS
        qos["priority"] = (zenoh.Priority.REAL_TIME if stream in LOOP_TOPICS else
                           zenoh.Priority.DATA_LOW if stream == "service" else zenoh.Priority.DATA)
    return qos


def open_session(config: BusConfig):
    """A Zenoh session for ``config``. Close it (``with`` or ``.close()``): a process whose
    session is never closed can hang at interpreter exit."""
    import zenoh

    return zenoh.open(config.zenoh_config())


def close_session(session, declared: list) -> None:
    """Undeclare ``declared`` (subscribers, queryables, tokens; newest first, each best effort:
    one may already be gone with its session) and close ``session``."""
    for entity in reversed(declared):
        try:
            entity.undeclare()
        except Exception:
            pass
    declared.clear()
    session.close()
