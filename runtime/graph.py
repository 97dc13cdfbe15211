"""The service graph, declared once: every role, what it publishes and subscribes, and how it runs.

The launcher starts these roles in this order, a node may only publish or subscribe what its
role declares here (:class:`runtime.node.Node` enforces it), and tests check that every
subscription has exactly one publisher of the same message type and that
``docker-compose.yml`` has one container per role.
"""
from __future__ import annotations

from dataclasses import dataclass

from runtime.schema import TOPICS, Message


@dataclass(frozen=True)
class Role:
    """One process. ``publishes``/``subscribes``: topic → message type (see ``runtime.schema``).
    ``module`` has ``add_arguments(parser)`` and ``run(args, bus) -> int``."""

    name: str
    module: str
    description: str
    publishes: dict[str, type[Message]]
    subscribes: dict[str, type[Message]]
    bus_role: str = "peer"  # "router" for the hub
    per_vehicle: bool = True  # False: one process for the whole bus (it watches every vehicle)
    enabled_by: str = ""  # `neso up` starts it only when this boolean option is set ("": always)
    watches: tuple[str, ...] = ()  # topics a watcher shows when someone publishes them (of every vehicle)
    identity: str = ""  # certificate common name on a secure bus ("": the role's name)
    offers_to: tuple[str, ...] = ()  # services it offers networks to (their ``offer`` key; runtime/acl.py)
    stop_grace_s: float | None = None  # SIGTERM → SIGKILL at a stop of `neso up` (None: the launcher's 2 s)

    @property
    def cert_name(self) -> str:
        return self.identity or self.name


@dataclass(frozen=True)
class Outsider:
    """An identity on a secure bus that is no service of the graph: a person's tools.
    ``publishes``: stream topics it may put for any vehicle; ``steers``: it may send commands
    and set parameters (query ``cmd/*`` and ``param/*``)."""

    name: str
    description: str
    publishes: tuple[str, ...] = ()
    steers: bool = False


def _topics(*names: str) -> dict[str, type[Message]]:
    return {name: TOPICS[name] for name in names}


ROLES: tuple[Role, ...] = (
    Role("hub", "services.hub", "Zenoh router every peer connects to (zenohd in containers)",
         publishes={}, subscribes={}, bus_role="router"),
    Role("source", "services.source", "state source: simulator (real time or lockstep) or motion capture",
         publishes=_topics("state", "truth"), subscribes=_topics("setpoint")),
    Role("estimator", "services.estimator", "Neural-ESO: state + last setpoint → f̂ = f_N + Δf̂",
         publishes=_topics("estimate", "network"), subscribes=_topics("state", "setpoint", "reference")),
    Role("controller", "services.controller", "mission + state + f̂ → attitude setpoint (local ESO if f̂ goes stale)",
         publishes=_topics("setpoint", "reference"), subscribes=_topics("state", "estimate", "network")),
    Role("recorder", "services.recorder", "every message of the vehicle into one Rerun .rrd per flight",
         publishes=_topics("recording"), subscribes=_topics("state", "truth", "estimate", "setpoint", "reference"),
         enabled_by="record", stop_grace_s=12.0),  # it finishes the flight's file first (services/recorder.py)
    Role("trainer", "services.trainer", "trains, certifies and stores networks from recordings; offers them to the estimator",
         publishes={}, subscribes=_topics("network"), enabled_by="trainer", offers_to=("estimator",)),
    Role("px4_gateway", "services.px4_gateway",
         "setpoints → PX4 offboard attitude through MAVSDK; vehicle telemetry back; mocap → external vision; the "
         "preflight verdict (no arming on a no-go)",
         publishes=_topics("telemetry", "preflight"), subscribes=_topics("setpoint", "state", "network"),
         enabled_by="mavlink_vehicle"),
    Role("dashboard", "dashboard.service", "operator's web dashboard (viser): watches every vehicle, steers by "
         "parameters and commands", publishes={}, subscribes={}, per_vehicle=False, enabled_by="dashboard",
         watches=("state", "truth", "estimate", "setpoint", "reference", "telemetry", "recording", "network",
                  "replay", "preflight"),
         identity="operator"),
)

# Who else may be on a secure bus (certificates from `neso secure init`, rights in runtime/acl.py).
OUTSIDERS: tuple[Outsider, ...] = (
    Outsider("operator", "the dashboard and the neso CLI (params, cmd, train): sets parameters, sends commands",
             steers=True),
    Outsider("replay", "neso replay --to-bus: a recorded flight published again",
             publishes=("state", "truth", "estimate", "setpoint", "reference", "replay")),
)

GRAPH: dict[str, Role] = {role.name: role for role in ROLES}


def role(name: str) -> Role:
    try:
        return GRAPH[name]
    except KeyError:
        raise KeyError(f"unknown service {name!r}; known: {list(GRAPH)}") from None


def identities(roles: tuple[Role, ...] = ROLES, outsiders: tuple[Outsider, ...] = OUTSIDERS) -> list[str]:
    """Every certificate common name a secure bus knows, each once, in declaration order."""
    return list(dict.fromkeys([r.cert_name for r in roles] + [o.name for o in outsiders]))


def check_graph(roles: tuple[Role, ...] = ROLES) -> list[str]:
    """Every defect of the declaration (empty if sound): a subscription without exactly one
    publisher, or a type that disagrees with the schema."""
    problems = []
    publishers: dict[str, list[str]] = {}
    for r in roles:
        for topic, cls in r.publishes.items():
            publishers.setdefault(topic, []).append(r.name)
            if TOPICS.get(topic) is not cls:
                problems.append(f"{r.name} publishes {topic} as {cls.__name__}, schema says {TOPICS.get(topic)}")
    for r in roles:
        for topic, cls in r.subscribes.items():
            pubs = publishers.get(topic, [])
            if len(pubs) != 1:
                problems.append(f"{r.name} subscribes {topic}, published by {pubs or 'nobody'} (need exactly one)")
            if TOPICS.get(topic) is not cls:
                problems.append(f"{r.name} subscribes {topic} as {cls.__name__}, schema says {TOPICS.get(topic)}")
    names = {r.name for r in roles}
    for r in roles:
        problems += [f"{r.name} offers networks to {t}, which is no role" for t in r.offers_to if t not in names]
    return problems
