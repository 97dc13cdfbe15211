"""PX4 SITL as a set-up step (sim/px4/build.sh), its airframe file and command line (sim.px4_sitl), and how
`neso up --vehicle px4` wires PX4, the world and the gateway together. The build itself and the flight are
in tests/px4/."""
from __future__ import annotations

import hashlib
import os
import shutil
import stat
import subprocess
import sys
import time
from dataclasses import replace

import pytest

from cli.main import build_parser
from cli.up import build_specs
from sim.px4_sitl import SIM_MODEL, load_params, sitl_command
from tests.helpers import REPO

BUILD = REPO / "sim" / "px4" / "build.sh"
REQUIREMENTS = REPO / "sim" / "px4" / "build-requirements.txt"
SUBMODULES = ("src/modules/mavlink/mavlink", "src/drivers/gps/devices", "src/lib/events/libevents",
              "src/modules/uxrce_dds_client/Micro-XRCE-DDS-Client", "src/lib/heatshrink/heatshrink")
# a stand-in for PX4's build: what `make px4_sitl_nofft` leaves (a binary, etc/), and which python it ran with
FAKE_MAKEFILE = """px4_sitl_nofft px4_sitl_default:
\tmkdir -p build/$@/bin build/$@/etc
\tcp /bin/true build/$@/bin/px4
\tcommand -v python > build/$@/etc/python
"""
GIT = ("git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "init.defaultBranch=main", "-c", "protocol.file.allow=always")


def git(cwd, *args: str) -> None:
    subprocess.run([*GIT, *args], cwd=cwd, check=True, capture_output=True)


def fake_px4_tree(path, tag: str = "v1.16.0", submodules: bool = False):
    """A PX4-Autopilot-shaped git tree at ``tag`` whose make targets stand in for the SITL build (``submodules``: the
    five SITL needs as real git submodules, each a repository of its own beside it)."""
    (path / "src" / "modules").mkdir(parents=True)
    (path / "boards" / "px4" / "sitl").mkdir(parents=True)
    (path / "Makefile").write_text(FAKE_MAKEFILE)
    (path / "src" / "modules" / "README").write_text("modules")
    (path / "boards" / "px4" / "sitl" / "default.px4board").write_text("CONFIG_PLATFORM_POSIX=y\n")
    git(path, "init", "-q")
    if submodules:
        for i, sub in enumerate(SUBMODULES):
            origin = path.parent / f"sub{i}"
            origin.mkdir()
            (origin / "README").write_text(sub)
            git(origin, "init", "-q")
            git(origin, "add", "-A")
            git(origin, "commit", "-q", "-m", sub)
            git(path, "submodule", "add", "-q", f"file://{origin}", sub)
    else:
        for sub in SUBMODULES:
            (path / sub).mkdir(parents=True)
            (path / sub / "README").write_text(sub)
    git(path, "add", "-A")
    git(path, "commit", "-q", "-m", "PX4")
    git(path, "tag", tag)
    return path


def build_python(tmp_path):
    """PX4's build requirements as `build.sh requirements` leaves them (a venv whose stamp names the file)."""
    pyenv = tmp_path / "pyenv"
    (pyenv / "bin").mkdir(parents=True)
    (pyenv / "bin" / "python").symlink_to(sys.executable)
    (pyenv / ".installed").write_text(f"sha256 {hashlib.sha256(REQUIREMENTS.read_bytes()).hexdigest()}\n")
    return pyenv


def run_build(tmp_path, *args: str, **env) -> subprocess.CompletedProcess:
    """build.sh with every place it looks in ``tmp_path`` (no shared folder, cache, venv or clone of this machine's)
    and PX4's repository at a file URL that does not exist (no network) unless ``env`` says otherwise."""
    full = {k: v for k, v in os.environ.items() if k not in ("PX4_SRC", "NESO_PX4_HOME")}
    full.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), NESO_SHARED=str(tmp_path / "shared"),
                NESO_PX4_PYTHON=str(tmp_path / "pyenv"), NESO_PX4_REPO=f"file://{tmp_path}/no-such-repository",
                GIT_CONFIG_COUNT="1", GIT_CONFIG_KEY_0="protocol.file.allow", GIT_CONFIG_VALUE_0="always")
    full.update(env)
    return subprocess.run(["bash", str(BUILD), *args], env=full, capture_output=True, text=True, timeout=120)


def test_without_any_way_to_px4_the_setup_fails_in_one_line_naming_the_three_ways(tmp_path):
    done = run_build(tmp_path)
    assert done.returncode == 1 and done.stdout == ""
    (line,) = done.stderr.splitlines()
    assert "PX4 v1.16.0 not found" in line and "PX4_SRC" in line and f"{tmp_path}/shared/px4" in line
    assert "no-such-repository (tag v1.16.0)" in line  # PX4's official repository, here a file URL that is not there
    assert not (tmp_path / "xdg").exists()


def test_the_tarball_builds_offline_with_the_cached_build_requirements_and_is_named_v1_16_0(tmp_path):
    tree = fake_px4_tree(tmp_path / "PX4-Autopilot")
    shutil.rmtree(tree / ".git")  # the tarball is a tree without git (build.sh makes one and tags it)
    (tmp_path / "shared" / "px4").mkdir(parents=True)
    subprocess.run(["tar", "-cJf", str(tmp_path / "shared" / "px4" / "px4-v1.16.0-sitl-src.tar.xz"), "-C",
                    str(tmp_path), "PX4-Autopilot"], check=True)
    done = run_build(tmp_path)
    assert done.returncode == 1 and "build requirements are not in" in done.stderr and "make setup" in done.stderr
    pyenv = build_python(tmp_path)
    done = run_build(tmp_path)
    assert done.returncode == 0, done.stderr
    home = tmp_path / "xdg" / "neso" / "px4-v1.16.0"
    assert (home / "version").read_text() == "v1.16.0\n" and os.access(home / "bin" / "px4", os.X_OK)
    assert (home / "etc" / "python").read_text().strip() == str(pyenv / "bin" / "python")  # PX4's generators: the venv's
    assert f"built PX4 v1.16.0 (px4_sitl_nofft)" in done.stdout
    done = run_build(tmp_path)
    assert done.returncode == 0 and done.stdout.startswith(f"px4: up to date in {home}")


def test_a_px4_src_is_named_by_its_own_tag_and_only_v1_16_0_completes_the_setup(tmp_path):
    build_python(tmp_path)
    old = fake_px4_tree(tmp_path / "old", tag="v1.15.4")
    done = run_build(tmp_path, PX4_SRC=str(old))
    home = tmp_path / "xdg" / "neso" / "px4-v1.15.4"
    assert (home / "version").read_text() == "v1.15.4\n" and not (tmp_path / "xdg" / "neso" / "px4-v1.16.0").exists()
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert f"NESO_PX4_HOME={home}" in done.stderr and "need v1.16.0" in done.stderr
    assert (old / "build" / "px4_sitl_default").is_dir(), "a lab's own tree keeps its build folder"
    done = run_build(tmp_path, PX4_SRC=str(fake_px4_tree(tmp_path / "new")))
    assert done.returncode == 0 and (tmp_path / "xdg" / "neso" / "px4-v1.16.0" / "version").read_text() == "v1.16.0\n"


def test_px4s_repository_is_cloned_at_the_tag_with_the_sitl_submodules_and_rebuilds_without_it(tmp_path):
    build_python(tmp_path)
    upstream = fake_px4_tree(tmp_path / "upstream" / "PX4-Autopilot", submodules=True)
    cdr = tmp_path / "upstream" / "Micro-CDR"
    cdr.mkdir()
    git(cdr, "init", "-q")
    git(cdr, "commit", "-q", "--allow-empty", "-m", "cdr")
    env = dict(NESO_PX4_REPO=f"file://{upstream}", NESO_MICRO_CDR_REPO=f"file://{cdr}")
    done = run_build(tmp_path, **env)
    assert done.returncode == 0, done.stdout + done.stderr
    clone = tmp_path / "xdg" / "neso" / "px4-src-v1.16.0"
    assert all((clone / sub / "README").read_text() == sub for sub in SUBMODULES)
    assert (clone / "boards" / "px4" / "sitl" / "nofft.px4board").read_text() == "CONFIG_MODULES_GYRO_FFT=n\n"
    assert (tmp_path / "xdg" / "neso" / "px4-src-v1.16.0.micro-cdr.git").is_dir()  # for the DDS client's CMake
    home = tmp_path / "xdg" / "neso" / "px4-v1.16.0"
    assert (home / "version").read_text() == "v1.16.0\n" and not (clone / "build" / "px4_sitl_nofft").exists()
    shutil.rmtree(home)
    shutil.rmtree(tmp_path / "upstream")  # offline now: the kept clone builds again
    done = run_build(tmp_path, **env)
    assert done.returncode == 0 and (home / "bin" / "px4").exists(), done.stderr


def test_build_requirements_are_pinned_and_installed_once(tmp_path):
    pins = [line.split("#")[0].strip() for line in REQUIREMENTS.read_text().splitlines() if line.split("#")[0].strip()]
    assert {p.split("==")[0] for p in pins} == {"empy", "jinja2", "kconfiglib", "pyyaml", "jsonschema", "packaging",
                                                "future", "pyros-genmsg", "lxml"} and all("==" in p for p in pins)
    assert "empy==3." in REQUIREMENTS.read_text()  # PX4 v1.16 uses empy's 3.x API
    build_python(tmp_path)
    done = run_build(tmp_path, "requirements")  # stamped for this file: nothing to install, no package index asked
    assert done.returncode == 0 and done.stdout == "" and done.stderr == ""


def test_a_build_stamped_for_the_same_tarball_is_not_built_again(tmp_path):
    shared = tmp_path / "shared" / "px4"
    shared.mkdir(parents=True)
    tarball = shared / "px4-v1.16.0-sitl-src.tar.xz"
    tarball.write_bytes(b"not really a tarball")
    cache = tmp_path / "xdg" / "neso" / "px4-v1.16.0"
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


@pytest.mark.parametrize("command", [("px4",), ("up", "--vehicle", "px4"), ("experiment", "paper", "--world", "px4"),
                                     ("demo", "tdr", "--world", "px4")], ids=" ".join)
def test_every_command_that_needs_px4_says_so_in_one_line_at_once_without_a_build(tmp_path, command):
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "cli.main", *command], cwd=REPO, capture_output=True, text=True,
                          timeout=60, env=dict(os.environ, NESO_PX4_HOME=str(tmp_path / "none")))
    assert done.returncode == 2 and done.stderr == "" and done.stdout.count("\n") == 1, done.stdout + done.stderr
    assert "PX4 SITL is not built" in done.stdout and "make setup" in done.stdout
    assert time.monotonic() - started < 30, "at once: nothing waited for"  # demo tdr waited 60 s for a PX4 that never came


def test_the_benchmarks_px4_row_says_so_in_one_line_without_a_build(tmp_path, monkeypatch):
    from bench.px4 import COLUMNS, px4_rows

    monkeypatch.setenv("NESO_PX4_HOME", str(tmp_path / "none"))
    (row,) = px4_rows(quick=True)
    assert len(row) == len(COLUMNS) and row[0] == "not measured" and "PX4 SITL is not built" in row[-1]


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


def test_the_px4_tier_without_px4_is_one_error_before_any_test_runs(tmp_path):
    done = subprocess.run([sys.executable, "-m", "pytest", "tests/px4", "-p", "no:cacheprovider", "-p", "no:xdist"],
                          cwd=REPO, capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, NESO_PX4_HOME=str(tmp_path / "none")))
    errors = [line for line in (done.stdout + done.stderr).splitlines() if "ERROR" in line or "FAILED" in line]
    assert done.returncode == pytest.ExitCode.USAGE_ERROR and "no tests ran" in done.stdout, done.stdout + done.stderr
    assert errors == [f"ERROR: the px4 tier cannot run: PX4 SITL is not built ({tmp_path}/none/bin/px4 missing): run "
                      "`make setup` (it builds PX4 v1.16.0 from $PX4_SRC, ../shared/px4/ or PX4's repository: "
                      "sim/px4/build.sh)"], errors


def test_a_px4_instance_chosen_here_is_not_chosen_by_another_process():
    """Parallel flights on one machine (test workers, a benchmark) each get their own PX4 instance: the choice is
    held (a lock file per instance, until released or the process ends), not only probed, so two choosers never
    race to the same ports."""
    from cli.paper_px4 import free_px4_instance, release_px4_instance

    other = [sys.executable, "-c", "from cli.paper_px4 import free_px4_instance; print(free_px4_instance())"]
    mine = free_px4_instance()
    try:
        theirs = int(subprocess.run(other, cwd=REPO, capture_output=True, text=True, timeout=60, check=True).stdout)
        assert theirs != mine
    finally:
        release_px4_instance(mine)


def test_neso_up_hands_px4_another_airframe_and_refuses_a_bad_one_in_one_line(tmp_path, capsys):
    from cli.up import run

    other = tmp_path / "defaults.params"
    other.write_text("EKF2_EV_CTRL 0\n")
    args = build_parser().parse_args(["up", "--vehicle", "px4", "--px4-params", str(other)])
    px4 = next(s for s in build_specs(args) if s.name == "px4")
    assert list(px4.argv[-2:]) == ["--params", str(other)]
    other.write_text("EKF2_EV_CTRL fifteen\n")
    assert run(args) == 2 and "neso up: --px4-params: " in capsys.readouterr().out
