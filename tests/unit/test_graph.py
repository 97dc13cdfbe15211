"""The service graph is declared once; the launcher and docker-compose.yml agree with it."""
from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from cli.main import build_parser
from cli.up import build_specs, role_enabled
from runtime.graph import GRAPH, ROLES, Role, check_graph
from runtime.schema import EstimateMsg, StateMsg

REPO = Path(__file__).resolve().parents[2]


def test_every_subscription_has_exactly_one_publisher_of_the_same_type():
    assert check_graph() == []


def test_the_check_catches_a_missing_publisher_a_second_publisher_and_a_wrong_type():
    orphan = Role("x", "m", "", publishes={}, subscribes={"estimate": EstimateMsg})
    twice = Role("y", "m", "", publishes={"state": StateMsg}, subscribes={})
    wrong = Role("z", "m", "", publishes={}, subscribes={"state": EstimateMsg})
    no_estimator = tuple(r for r in ROLES if r.name != "estimator")
    assert any("estimate" in p and "nobody" in p for p in check_graph(no_estimator + (orphan,)))
    assert any("state" in p and "exactly one" in p for p in check_graph(ROLES + (twice,)))
    assert any("EstimateMsg" in p for p in check_graph(ROLES + (wrong,)))


def test_launcher_starts_exactly_the_declared_roles():
    args = build_parser().parse_args(["up"])
    specs = build_specs(args)
    assert [s.name for s in specs] == [r.name for r in ROLES if role_enabled(args, r)]
    for spec in specs:
        i = spec.argv.index("run")
        assert spec.argv[i + 1] == spec.name


def test_launcher_runs_one_set_of_services_per_vehicle_with_one_hub():
    args = build_parser().parse_args(["up", "--name", "a", "--name", "b"])
    names = [s.name for s in build_specs(args)]
    assert names.count("hub") == 1
    assert {"a/estimator", "b/estimator", "a/controller", "b/source"} <= set(names)


def test_docker_compose_has_one_container_per_role_with_explicit_endpoints():
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    services = compose["services"]
    assert set(services) == set(GRAPH)
    hub = services["hub"]
    assert hub["image"].startswith("eclipse/zenoh:")
    assert hub["command"] == ["-c", "/secure/compose/router.json5"]  # `neso secure init` writes it: TLS, ACL
    assert any(v.endswith(":/secure:ro") for v in hub["volumes"])
    for name, svc in services.items():
        if GRAPH[name].bus_role == "router":
            continue
        cmd = svc["command"]
        assert cmd[:2] == ["run", name], name
        assert cmd[cmd.index("--connect") + 1] == "tls/hub:7447", name
        assert cmd[cmd.index("--listen") + 1].startswith("tls/"), name
        assert "--secure" in cmd and cmd[cmd.index("--secure-dir") + 1] == "/secure", name
        assert any(v.endswith(":/secure:ro") for v in svc["volumes"])
        assert "hub" in svc["depends_on"], name
        assert any(v.endswith(":/data/networks") for v in svc["volumes"])
        assert any(v.endswith(":/data/recordings") for v in svc["volumes"])
        # every option in the command is one the service's real CLI accepts
        build_parser().parse_args(cmd)
        # docker's SIGTERM → SIGKILL grace (10 s unless set) is at least the role's (the recorder's file)
        grace = float(svc.get("stop_grace_period", "10s").rstrip("s"))
        assert GRAPH[name].stop_grace_s is None or grace >= GRAPH[name].stop_grace_s, name


def test_every_role_module_has_the_service_entry_points():
    import importlib

    for r in ROLES:
        module = importlib.import_module(r.module)
        assert callable(module.add_arguments) and callable(module.run)
        module.add_arguments(argparse.ArgumentParser())


def test_the_px4_gateway_runs_only_with_the_mavlink_vehicle_and_both_share_one_port():
    direct = [s.name for s in build_specs(build_parser().parse_args(["up"]))]
    assert "px4_gateway" not in direct
    specs = {s.name: s.argv for s in build_specs(build_parser().parse_args(["up", "--vehicle", "mavlink",
                                                                             "--mavlink-port", "15000"]))}
    assert "px4_gateway" in specs
    gateway, source = specs["px4_gateway"], specs["source"]
    assert gateway[gateway.index("--mavlink") + 1] == "udpin://127.0.0.1:15000"
    assert source[source.index("--link") + 1] == "mavlink"
    assert source[source.index("--mavlink-out") + 1] == "udpout:127.0.0.1:15000"

def test_the_world_waits_for_its_loop_the_recorder_when_it_records_and_any_service_asked():
    def waits(*flags: str) -> list[str]:
        source = {s.name: s.argv for s in build_specs(build_parser().parse_args(["up", *flags]))}["source"]
        return source[source.index("--wait-for") + 1].split(",")

    assert waits() == ["estimator", "controller", "recorder"]  # every flight recorded from its sample 0
    assert waits("--no-record") == ["estimator", "controller"]
    assert waits("--no-record", "--wait-for", "probe") == ["estimator", "controller", "probe"]


def test_a_per_bus_role_runs_once_for_all_vehicles_and_can_be_turned_off():
    args = build_parser().parse_args(["up", "--name", "a", "--name", "b", "--dashboard-port", "8181"])
    specs = {s.name: s for s in build_specs(args)}
    assert [n for n in specs if n.endswith("dashboard")] == ["dashboard"]
    argv = specs["dashboard"].argv
    assert argv[argv.index("--port") + 1] == "8181" and argv[argv.index("--host") + 1] == "127.0.0.1"
    assert not specs["dashboard"].essential and specs["a/controller"].essential  # a page never stops a flight
    assert specs["dashboard"].nice == 10 and specs["a/controller"].nice == 0
    off = build_parser().parse_args(["up", "--no-dashboard"])
    assert "dashboard" not in [s.name for s in build_specs(off)]


def test_a_service_process_parses_its_own_role_only_and_every_role_still_parses():
    """`neso run hub` loads neither another role's module nor another command's defaults (every service process paid
    ~0.7 s of CPU for them at its start); each role's own arguments are there once chosen."""
    import subprocess
    import sys

    probe = ("import sys; from cli.main import build_parser; "
             "a = build_parser(sys.argv[1:]).parse_args(sys.argv[1:]); "
             "print(a.service, sorted(m for m in ('scipy', 'torch', 'flight.estimator', 'services.recorder') "
             "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe, "run", "hub", "--listen", "tcp/127.0.0.1:7447"], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == ["hub", "[]"], out
    for role in GRAPH.values():
        assert build_parser(["run", role.name]).parse_args(["run", role.name]).service == role.name
    args = build_parser(["run", "recorder"]).parse_args(["run", "recorder", "--flush-period", "0.2"])
    assert args.cfg__flush_period_s == 0.2
