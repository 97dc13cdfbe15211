"""PX4 SITL as a set-up step (sim/px4/build.sh), its airframe file and command line (sim.px4_sitl), and how
`neso up --vehicle px4` wires PX4, the world and the gateway together. The build itself and the flight are
in tests/px4/."""
from __future__ import annotations

import hashlib
import os
from dataclasses import replace
import stat
import subprocess

import pytest

from cli.main import build_parser
from cli.up import build_specs
from sim.px4_sitl import SIM_MODEL, load_params, sitl_command
from tests.helpers import REPO

BUILD = REPO / "sim" / "px4" / "build.sh"


def run_build(tmp_path, **env) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if k != "PX4_SRC"}
    full.update(NESO_PX4_HOME=str(tmp_path / "cache"), NESO_SHARED=str(tmp_path / "shared"), **env)
    return subprocess.run(["bash", str(BUILD)], env=full, capture_output=True, text=True, timeout=60)


def test_without_a_source_the_setup_says_so_in_one_line_and_goes_on(tmp_path):
    done = run_build(tmp_path)
    assert done.returncode == 0
    assert done.stdout.count("\n") == 1 and "no PX4 source" in done.stdout and "PX4_SRC" in done.stdout
    assert not (tmp_path / "cache").exists()


def test_a_build_stamped_for_the_same_tarball_is_not_built_again(tmp_path):
    shared = tmp_path / "shared" / "px4"
    shared.mkdir(parents=True)
    tarball = shared / "px4-v1.16.0-sitl-src.tar.xz"
    tarball.write_bytes(b"not really a tarball")
    cache = tmp_path / "cache"
    (cache / "bin").mkdir(parents=True)
    (cache / "bin" / "px4").write_text("#!/bin/sh\n")
    (cache / "bin" / "px4").chmod(stat.S_IRWXU)
    digest = hashlib.sha256(tarball.read_bytes()).hexdigest()
    (cache / ".built").write_text(f"tarball sha256 {digest}\nv1.16.0, test\n")
    done = run_build(tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == f"px4: up to date in {cache} (v1.16.0, test)"
    os.utime(tarball, (0, 0))  # the same content copied elsewhere, another time: the same source
    done = run_build(tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == f"px4: up to date in {cache} (v1.16.0, test)"
    tarball.unlink()  # the source gone: the build is kept and said so
    done = run_build(tmp_path)
    assert done.returncode == 0 and "kept the build" in done.stdout


def test_a_px4_src_that_is_no_px4_tree_is_refused(tmp_path):
    done = run_build(tmp_path, PX4_SRC=str(tmp_path))
    assert done.returncode == 2 and "no PX4-Autopilot tree" in done.stderr


def test_the_airframe_file_parses_and_a_bad_line_is_named(tmp_path):
    params = load_params()
    assert params["EKF2_EV_CTRL"] == "15" and params["EKF2_GPS_CTRL"] == "0" and params["CA_ROTOR_COUNT"] == "4"
    bad = tmp_path / "bad.params"
    bad.write_text("# fine\nEKF2_EV_CTRL 15\nMC_ROLL_P fast\n")
    with pytest.raises(ValueError, match="bad.params:3: MC_ROLL_P's value 'fast'"):
        load_params(bad)
    bad.write_text("EKF2_EV_CTRL = 15\n")
    with pytest.raises(ValueError, match=":1: expected 'NAME VALUE'"):
        load_params(bad)


def test_px4_starts_as_instance_n_with_the_airframe_in_its_environment():
    argv, env = sitl_command(2, {"EKF2_EV_CTRL": "15"}, base_env={"PATH": "/bin"})
    assert argv[0].endswith("/bin/px4") and argv[1:4] == ["-d", "-i", "2"] and argv[4].endswith("/etc")
    assert env == {"PATH": "/bin", "PX4_SIM_MODEL": SIM_MODEL, "PX4_PARAM_EKF2_EV_CTRL": "15"}


def test_neso_px4_without_a_build_is_one_clear_line_and_exit_2(tmp_path):
    done = subprocess.run([str(REPO / ".venv" / "bin" / "neso"), "px4"], capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, NESO_PX4_HOME=str(tmp_path / "none")))
    assert done.returncode == 2 and done.stdout.count("\n") == 1 and "make px4" in done.stdout


def last_value(argv, flag: str) -> str:
    """What argparse takes for ``flag``: the value after its last occurrence."""
    return argv[len(argv) - 1 - argv[::-1].index(flag) + 1]


def test_up_with_px4_runs_px4_the_world_as_its_simulator_and_the_gateway_per_vehicle():
    specs = {s.name: s.argv for s in build_specs(build_parser().parse_args(
        ["up", "--vehicle", "px4", "--name", "a", "--name", "b"]))}
    for i, v in enumerate(("a", "b")):
        px4, source, gateway = specs[f"{v}/px4"], specs[f"{v}/source"], specs[f"{v}/px4_gateway"]
        assert px4[px4.index("px4") + 1:px4.index("--instance") + 2] == ("--instance", str(i))
        assert source[source.index("--link") + 1] == "px4" and source[source.index("--px4-port") + 1] == str(4560 + i)
        assert last_value(source, "--start") == "ground"  # PX4 boots and arms on the ground
        assert gateway[gateway.index("--mavlink") + 1] == f"udpin://127.0.0.1:{14540 + i}"
        assert "sim" in gateway[gateway.index("--forward-sources") + 1].split(",")
    assert "px4" not in [s.name for s in build_specs(build_parser().parse_args(["up", "--vehicle", "mavlink"]))]
    shifted = {s.name: s.argv for s in build_specs(build_parser().parse_args(["up", "--vehicle", "px4", "--px4-instance", "3"]))}
    assert last_value(shifted["px4"], "--instance") == "3" and last_value(shifted["source"], "--px4-port") == "4563"
    assert last_value(shifted["px4_gateway"], "--mavlink") == "udpin://127.0.0.1:14543"


def test_the_controller_starts_on_the_px4_gains_with_px4_and_the_papers_otherwise():
    from neso.control import GAIN_SETS

    def gains(*flags):
        specs = {s.name: s.argv for s in build_specs(build_parser().parse_args(["up", *flags]))}
        return last_value(specs["controller"], "--gains")

    assert gains("--vehicle", "px4") == "px4" and gains("--vehicle", "mavlink") == "paper" and gains() == "paper"
    assert gains("--vehicle", "px4", "--gains", "paper") == "paper"  # the faithful variant, chosen
    assert GAIN_SETS["px4"][0][:2] == (2.0, 2.0) and GAIN_SETS["px4"][0][2] == GAIN_SETS["paper"][0][2]  # z: the paper's


def test_up_with_px4_refuses_lockstep_in_one_line(capsys):
    from cli.up import run

    assert run(build_parser().parse_args(["up", "--vehicle", "px4", "--lockstep"])) == 2
    assert "real time only" in capsys.readouterr().out


def test_the_dashboard_shows_px4s_version_and_its_own_words():
    from dashboard.model import VehicleModel
    from dashboard.text import vehicle_markdown
    from tests.helpers import EXAMPLES

    tel = next(m for m in EXAMPLES if type(m).__name__ == "TelemetryMsg")
    v = VehicleModel("uav1")
    v.ingest("telemetry", replace(tel, autopilot="PX4 v1.16.0 6ea3539",
                                  status_text="CRITICAL: Arming denied: Resolve system health failures first"), 1.0)
    text = vehicle_markdown(v)
    assert "PX4 v1.16.0 6ea3539" in text and "**PX4 says**: CRITICAL: Arming denied" in text


def test_neso_up_hands_px4_another_airframe_and_refuses_a_bad_one_in_one_line(tmp_path, capsys):
    from cli.up import run

    other = tmp_path / "defaults.params"
    other.write_text("EKF2_EV_CTRL 0\n")
    args = build_parser().parse_args(["up", "--vehicle", "px4", "--px4-params", str(other)])
    px4 = next(s for s in build_specs(args) if s.name == "px4")
    assert list(px4.argv[-2:]) == ["--params", str(other)]
    other.write_text("EKF2_EV_CTRL fifteen\n")
    assert run(args) == 2 and "neso up: --px4-params: " in capsys.readouterr().out
