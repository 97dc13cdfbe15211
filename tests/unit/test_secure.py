"""The secure bus's parts without a bus: the ACL made from the graph, the certificates
`neso secure init` writes, the one-line errors, and reading what the hub refused from Zenoh's log."""
from __future__ import annotations

import json
import os
import stat

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from cli.main import main
from runtime.acl import access_control, may
from runtime.bus import BusConfig
from runtime.graph import GRAPH, OUTSIDERS, ROLES, identities
from runtime.refusals import RefusalCounter
from runtime.schema import TOPICS, Keys
from runtime.secure import Credentials, SecureSetupError, router_config

ACL = access_control()
K = Keys("uav1")
SERVICES = [r for r in ROLES if r.bus_role != "router" and not r.identity]


def test_each_role_may_put_exactly_the_topics_the_graph_says_it_publishes():
    for role in SERVICES:
        for topic in TOPICS:
            assert may(ACL, role.name, "put", K.topic(topic)) == (topic in role.publishes), (role.name, topic)
        for kind in ("event", "health", "params"):
            assert may(ACL, role.name, "put", getattr(K, kind)(role.name))
            other = next(r.name for r in SERVICES if r.name != role.name)
            assert not may(ACL, role.name, "put", getattr(K, kind)(other)), (role.name, kind, other)
        assert may(ACL, role.name, "liveliness_token", K.alive(role.name))
        assert not may(ACL, "operator", "liveliness_token", K.alive(role.name))


def test_each_role_answers_only_its_own_queryables():
    for role in SERVICES:
        for other in SERVICES:
            for key in (K.param(other.name), K.cmd(other.name)):
                for message in ("declare_queryable", "reply"):
                    assert may(ACL, role.name, message, key) == (role is other), (role.name, message, key)


def test_only_the_operator_sends_commands_and_sets_parameters_and_only_the_trainer_offers():
    steering = {o.name for o in OUTSIDERS if o.steers}
    assert steering == {"operator"}
    forwarders = {r.cert_name for r in ROLES if r.bus_role == "router"}  # the hub forwards what it checked
    assert all(may(ACL, hub, "query", K.cmd("controller")) for hub in forwarders)
    for name in set(identities()) - forwarders:
        for service in GRAPH:
            assert may(ACL, name, "query", K.cmd(service)) == (name == "operator"), (name, service)
            assert may(ACL, name, "query", K.param(service)) == (name == "operator"), (name, service)
            assert may(ACL, name, "query", K.params(service)), "anyone may read parameters"
        assert may(ACL, name, "query", K.offer("estimator")) == (name == "trainer"), name
    assert may(ACL, "estimator", "declare_queryable", K.offer("estimator"))
    assert not may(ACL, "controller", "declare_queryable", K.offer("estimator"))


def test_the_dashboard_is_the_operator_and_replay_puts_only_recorded_streams():
    assert GRAPH["dashboard"].cert_name == "operator" and "dashboard" not in identities()
    for topic in TOPICS:
        assert may(ACL, "replay", "put", K.topic(topic)) == (topic in ("state", "truth", "estimate", "setpoint",
                                                                         "reference", "replay"))
    assert not may(ACL, "replay", "query", K.cmd("controller"))
    assert not may(ACL, "stranger", "declare_subscriber", "neso/uav1/state"), "an unknown name gets nothing"
    assert all(may(ACL, n, "declare_subscriber", "neso/uav1/state") for n in identities())


def test_the_acl_is_zenohs_shape_with_every_reference_resolved():
    rule_ids = [r["id"] for r in ACL["rules"]]
    subject_ids = [s["id"] for s in ACL["subjects"]]
    assert len(set(rule_ids)) == len(rule_ids) and len(set(subject_ids)) == len(subject_ids)
    assert set(subject_ids) == set(identities())
    for policy in ACL["policies"]:
        assert set(policy["rules"]) <= set(rule_ids) and set(policy["subjects"]) <= set(subject_ids)
    assert ACL["default_permission"] == "deny"
    assert {f for r in ACL["rules"] for f in r["flows"]} == {"ingress", "egress"}
    assert router_config(Credentials("/x", "hub"), ("tls/0.0.0.0:7447",))["access_control"] == ACL


def run_cli(*argv: str, capsys) -> tuple[int, str]:
    try:
        code = main(list(argv))
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 2
        print(exc.code)
    return code, capsys.readouterr().out


def test_secure_init_writes_v3_certificates_private_keys_0600_and_refuses_to_overwrite(tmp_path, capsys):
    d = str(tmp_path / "secure")
    code, out = run_cli("secure", "init", d, "--host", "ground.lab", "--host", "10.0.0.7", capsys=capsys)
    assert code == 0, out
    assert stat.S_IMODE(os.stat(d).st_mode) == 0o700
    for name in identities() + ["ca"]:
        key = os.path.join(d, f"{name}-key.pem")
        assert stat.S_IMODE(os.stat(key).st_mode) == 0o600, key
    ca = x509.load_pem_x509_certificate(open(os.path.join(d, "ca.pem"), "rb").read())
    for name in identities():
        cert = x509.load_pem_x509_certificate(open(os.path.join(d, f"{name}.pem"), "rb").read())
        assert cert.version == x509.Version.v3
        assert cert.subject.rfc4514_string() == f"CN={name}" and cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert "ground.lab" in san.get_values_for_type(x509.DNSName)
    with open(os.path.join(d, "router.json5")) as f:
        router = json.loads(f.read().split("\n", 1)[1])
    assert router["transport"]["link"]["tls"]["enable_mtls"] and router["access_control"] == ACL
    assert router["transport"]["link"]["tls"]["listen_certificate"] == os.path.join(os.path.abspath(d), "hub.pem")
    with open(os.path.join(d, "compose", "router.json5")) as f:
        assert '"/secure/hub-key.pem"' in f.read()
    before = open(os.path.join(d, "ca.pem"), "rb").read()
    code, out = run_cli("secure", "init", d, capsys=capsys)
    assert code == 1 and "already has a CA" in out and "--force" in out
    assert open(os.path.join(d, "ca.pem"), "rb").read() == before
    code, out = run_cli("secure", "init", d, "--force", capsys=capsys)
    assert code == 0 and open(os.path.join(d, "ca.pem"), "rb").read() != before


def test_missing_credentials_and_plain_endpoints_are_one_line_errors(tmp_path, capsys):
    with pytest.raises(SecureSetupError, match="neso secure init"):
        Credentials(str(tmp_path), "estimator").check()
    with pytest.raises(ValueError, match="tls/ only"):
        BusConfig(connect=("tcp/127.0.0.1:7447",), listen=(), credentials=Credentials("/x", "operator"))
    code, out = run_cli("params", "get", "estimator", "--secure", "--secure-dir", str(tmp_path), capsys=capsys)
    assert code != 0 and "no credentials for 'operator'" in out and "Traceback" not in out
    code, out = run_cli("up", "--secure", "--secure-dir", str(tmp_path), capsys=capsys)
    assert code == 2 and "no credentials for 'hub'" in out
    code, out = run_cli("secure", "init", str(tmp_path / "x"), "--days", "0", capsys=capsys)
    assert code == 2 and "--days" in out


def test_neso_up_secure_gives_every_child_its_certificate_and_tls_endpoints():
    from cli.main import build_parser
    from cli.up import build_specs

    specs = build_specs(build_parser().parse_args(["up", "--secure", "--secure-dir", "/s"]))
    for spec in specs:
        argv = list(spec.argv)
        assert argv[argv.index("--secure-dir") + 1] == "/s" and "--secure" in argv, spec.name
        endpoint = argv[argv.index("--connect" if "--connect" in argv else "--listen") + 1]
        assert endpoint == "tls/127.0.0.1:7447", spec.name


# Lines as this Zenoh (1.10.2) writes them, colours and all (captured from a secure hub).
LOG = [
    "\x1b[2m2026-11-23T19:57:18.401158Z\x1b[0m \x1b[35mTRACE\x1b[0m rx-1 ThreadId(10) \x1b[2mzenoh::net::routing::"
    "interceptor::access_control\x1b[0m\x1b[2m:\x1b[0m cb37 on Interface(lo)+CertCommonName(estimator)+Transport(Tls)+"
    "cb37 is unauthorized to Query (ingress) on neso",  # a cache being filled: nothing was dropped
    "2026-11-23T19:57:19.807277Z TRACE rx-1 ThreadId(10) zenoh::net::routing::interceptor::access_control: 27c7 on "
    "Interface(lo)+CertCommonName(recorder)+Transport(Tls)+27c7 is unauthorized to Query (ingress) on "
    "neso/uav1/param/estimator",
    "2026-11-23T19:57:19.807314Z TRACE rx-1 ThreadId(10) zenoh::net::routing::interceptor: Msg intercepted!",
    "2026-11-23T19:57:20.1Z TRACE rx-0 ThreadId(9) zenoh::net::routing::interceptor::access_control: Using cached "
    "result: 27c7 is unauthorized to Query (ingress) on neso/uav1/param/estimator",
    "2026-11-23T19:57:20.1Z TRACE rx-0 ThreadId(9) zenoh::net::routing::interceptor: Msg intercepted!",
    "2026-11-23T19:57:20.2Z TRACE rx-0 ThreadId(9) zenoh::net::routing::interceptor::access_control: Using cached "
    "result: 5f0e is authorized to Put (ingress) on neso/uav1/state",
    "2026-11-23T19:58:09.285983Z  WARN acc-0 ThreadId(06) zenoh_link_tls::unicast: invalid peer certificate: "
    "UnknownIssuer. Hint: increase the system open file limit.",
    "2026-11-23T19:58:10.588267Z  WARN acc-0 ThreadId(06) zenoh_link_tls::unicast: invalid peer certificate: "
    "certificate expired: verification time 1795463890 (UNIX), but certificate is not valid after 1795291086 "
    "(172804 seconds ago). Hint: increase the system open file limit.",
]


def test_the_hub_counts_each_refused_message_by_identity_and_each_refused_link():
    counter = RefusalCounter()
    said = [s for s in map(counter.feed, LOG) if s]
    assert said == ["access control refused Query (ingress) on neso/uav1/param/estimator from recorder (1 so far)",
                    "refused a TLS link: UnknownIssuer (1 so far)",
                    "refused a TLS link: certificate expired (1 so far)"]
    assert counter.messages == {("recorder", "Query (ingress)", "neso/uav1/param/estimator"): 2}
    for _ in range(8):
        for line in LOG[3:5]:
            said = counter.feed(line)
    assert said == "access control refused Query (ingress) on neso/uav1/param/estimator from recorder (10 so far)"
