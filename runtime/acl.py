"""The bus's access-control list, generated from the service graph (``runtime/graph.py``).

Zenoh's ``access_control`` with ``default_permission: deny``: a message passes a session only
if a rule allows it for the certificate common name (CN) of the link it came in on. Every
session of a secure bus, the hub and each peer, runs this same list on what it **receives**
(ingress), because peers link to each other directly and the hub never sees that traffic
(measured: a put from a ``recorder`` certificate reached a peer without an ACL through the
direct link while the hub's ACL refused it). What a session sends (egress) to a known identity
is allowed; to an unknown common name nothing goes.

Who may do what (any vehicle ``*``):

- every identity: subscribe to ``neso/**``, watch and query liveliness, read parameters
  (query ``params/<service>``);
- each role of the graph: put its declared topics and its own ``event``/``health``/``params``,
  hold its own ``alive`` token, declare and answer its own ``param``/``cmd`` queryables (and
  ``offer`` if a role offers to it);
- ``operator``: query ``cmd/*`` and ``param/*`` (commands and parameter sets);
- a role with ``offers_to`` (the trainer): query ``offer/<target>``;
- ``replay``: put the recorded stream topics;
- ``hub``: anything (it forwards what it has already checked on its own ingress).
"""
from __future__ import annotations

from runtime.graph import OUTSIDERS, ROLES, Outsider, Role
from runtime.schema import ROOT

READ = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
EVERY_MESSAGE = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                 "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
PER_SERVICE_PUT = ("event", "health", "params")  # what every service publishes under its own name
ANSWERED = ("param", "cmd", "params")  # the queryables every service declares and answers


def _key(kind: str, service: str = "") -> str:
    return f"{ROOT}/*/{kind}" + (f"/{service}" if service else "")


def _rule(rule_id: str, messages: list[str], keys: list[str], flow: str = "ingress") -> dict:
    return {"id": rule_id, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": keys}


def access_control(roles: tuple[Role, ...] = ROLES, outsiders: tuple[Outsider, ...] = OUTSIDERS) -> dict:
    """The ``access_control`` section of a Zenoh config for every session of a secure bus."""
    rules: list[dict] = []
    grants: dict[str, list[str]] = {}  # common name → rule ids

    def grant(name: str, rule: dict) -> None:
        rules.append(rule)
        grants.setdefault(name, []).append(rule["id"])

    names = [r.cert_name for r in roles] + [o.name for o in outsiders]
    everyone = list(dict.fromkeys(names))
    # with default deny Zenoh filters egress too: send anything to any known identity
    rules.append(_rule("send", EVERY_MESSAGE, ["**"], flow="egress"))
    rules.append(_rule("read", READ, [f"{ROOT}/**"]))
    rules.append(_rule("read-params", ["query"], [_key("params", "*")]))
    offered = {t for r in roles for t in r.offers_to}
    for role in roles:
        if role.bus_role == "router":
            grant(role.cert_name, {**_rule(f"{role.name}-forward", EVERY_MESSAGE, ["**"])})
            continue
        if role.identity:  # runs as another identity (the dashboard as the operator): no rights of its own
            continue
        puts = [_key(topic) for topic in role.publishes] + [_key(kind, role.name) for kind in PER_SERVICE_PUT]
        grant(role.name, _rule(f"{role.name}-publish", ["put"], puts))
        grant(role.name, _rule(f"{role.name}-alive", ["liveliness_token"], [_key("alive", role.name)]))
        answered = [_key(kind, role.name) for kind in ANSWERED + (("offer",) if role.name in offered else ())]
        grant(role.name, _rule(f"{role.name}-answer", ["declare_queryable", "reply"], answered))
        if role.offers_to:
            grant(role.name, _rule(f"{role.name}-offer", ["query"], [_key("offer", t) for t in role.offers_to]))
    for outsider in outsiders:
        if outsider.publishes:
            grant(outsider.name, _rule(f"{outsider.name}-publish", ["put"], [_key(t) for t in outsider.publishes]))
        if outsider.steers:
            grant(outsider.name, _rule(f"{outsider.name}-steer", ["query"], [_key("cmd", "*"), _key("param", "*")]))
    subjects = [{"id": name, "cert_common_names": [name]} for name in everyone]
    policies = [{"id": "everyone-reads", "rules": ["send", "read", "read-params"], "subjects": everyone}]
    policies += [{"id": f"{name}-rights", "rules": ids, "subjects": [name]} for name, ids in grants.items()]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def may(acl: dict, name: str, message: str, key: str) -> bool:
    """Whether ``acl`` lets identity ``name`` send ``message`` on the concrete ``key`` (for tests
    and ``neso secure show``; Zenoh itself is the enforcer). Chunk wildcards ``*`` and a trailing
    ``**`` only, which is all :func:`access_control` writes."""
    rules = {r["id"]: r for r in acl["rules"] if "ingress" in r["flows"]}
    for policy in acl["policies"]:
        if name not in policy["subjects"]:
            continue
        for rule in (rules[i] for i in policy["rules"] if i in rules):
            if message in rule["messages"] and any(_matches(k, key) for k in rule["key_exprs"]):
                return rule["permission"] == "allow"
    return acl["default_permission"] == "allow"


def _matches(pattern: str, key: str) -> bool:
    p, k = pattern.split("/"), key.split("/")
    if p and p[-1] == "**":
        return len(k) >= len(p) - 1 and all(a in ("*", b) for a, b in zip(p[:-1], k))
    return len(p) == len(k) and all(a in ("*", b) for a, b in zip(p, k))
