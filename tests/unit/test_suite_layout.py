"""The test suite's own rules (tests/README.md): every test file in a tier folder, and no test module
importing another (shared builders live in tests/helpers.py, tests/busutil.py, tests/browser/chromium.py), and
the files of the flying tiers on one worker unless marked ``offline``; how many flying lanes a run has."""
from __future__ import annotations

import ast
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import (BESIDE_NATNET, FLIGHT_TIERS, OFFLINE_MARK, NATNET_LANE, ONE_LANE, PX4_LANE, TIERS, flies,
                            flight_lanes, next_unit, unit_flies, worker_group)

TESTS = Path(__file__).resolve().parents[1]


def test_every_test_file_is_in_a_tier_folder():
    misplaced = [str(p.relative_to(TESTS)) for p in TESTS.rglob("test_*.py")
                 if p.relative_to(TESTS).parts[0] not in TIERS or len(p.relative_to(TESTS).parts) != 2]
    assert misplaced == [], f"put these under tests/<tier>/ with a tier in {TIERS}"


def test_no_module_imports_a_test_module():
    offenders = []
    for path in TESTS.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            offenders += [f"{path.relative_to(TESTS)}: {n}" for n in names
                          if n.startswith("tests.") and n.rsplit(".", 1)[-1].startswith("test_")]
    assert offenders == [], "move what they share to tests/helpers.py"


def test_the_flying_tiers_files_fly_in_their_lane_unless_marked_offline():
    files = sorted(p.relative_to(TESTS).as_posix() for p in TESTS.rglob("test_*.py"))
    marked = {f for f in files if OFFLINE_MARK.search((TESTS / f).read_text())}
    assert marked and all(f.split("/")[0] in FLIGHT_TIERS for f in marked), "offline means: of a flying tier"
    for f in files:
        group = worker_group(f"tests/{f}::test_x", lanes=2)
        flying = f.split("/")[0] in FLIGHT_TIERS and f not in marked
        natnet = flying and "natnet" in (TESTS / f).read_text().lower() and not f.startswith("px4/") and \
            f != "process/test_world_waits.py"  # it names NatNet in prose only
        assert group == (PX4_LANE if f.startswith("px4/") else NATNET_LANE if natnet else f), (f, group)
        assert unit_flies(group) == flying, f
        assert worker_group(f"tests/{f}::test_x", lanes=1) == (ONE_LANE if flying else f), f


def test_two_lanes_fly_px4_then_natnet_alone_then_the_other_flights_before_computing():
    """What a worker takes next with two lanes (conftest.next_unit): PX4's lane first, then NatNet's; while one of
    them flies on the other worker, computing first, then beside NatNet's (never PX4's) the light flights, or
    nothing (wait); after them the flights, the browser's first, then computing."""
    flight, browser, computing = "process/test_live_flight.py", "browser/test_dashboard.py", "unit/test_mission.py"
    light = "process/test_canary.py"
    assert flight not in BESIDE_NATNET and browser not in BESIDE_NATNET and light in BESIDE_NATNET
    assert next_unit([flight, NATNET_LANE, PX4_LANE, computing], alone_elsewhere=None) == PX4_LANE
    assert next_unit([flight, NATNET_LANE, browser, light, computing], alone_elsewhere=PX4_LANE) == computing
    assert next_unit([flight, NATNET_LANE, browser, light], alone_elsewhere=PX4_LANE) is None
    assert next_unit([flight, browser, light, computing], alone_elsewhere=NATNET_LANE) == computing
    assert next_unit([flight, browser, light], alone_elsewhere=NATNET_LANE) == light
    assert next_unit([flight, browser], alone_elsewhere=NATNET_LANE) is None
    assert next_unit([flight, browser, NATNET_LANE, computing], alone_elsewhere=None) == NATNET_LANE
    assert next_unit([flight, browser, computing], alone_elsewhere=None) == browser
    assert next_unit([computing, flight], alone_elsewhere=None) == flight
    assert next_unit([computing], alone_elsewhere=None) == computing
    assert next_unit([], alone_elsewhere=None) is None


def test_the_flights_beside_natnets_lane_are_files_that_fly_and_neither_px4s_nor_natnets():
    for f in BESIDE_NATNET:
        assert (TESTS / f).is_file() and flies(f), f
        assert worker_group(f"tests/{f}::test_x", lanes=2) == f, f


def test_a_machine_with_a_core_busy_flies_one_lane_and_the_lanes_asked_are_flown(monkeypatch):
    """conftest.flight_lanes: unset, two flying lanes only on a quiet machine; a core kept busy by another process
    (as in issue 31's loaded runs) makes it one. ``NESO_TEST_LANES`` decides when set, and only 1 or 2."""
    monkeypatch.delenv("NESO_TEST_LANES", raising=False)
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)  # its interpreter started and spinning
        chosen = flight_lanes(sample_s=1.0)
    finally:
        busy.kill()
        busy.wait()
    assert chosen["lanes"] == 1, chosen
    monkeypatch.setenv("NESO_TEST_LANES", "1")
    assert flight_lanes()["lanes"] == 1
    monkeypatch.setenv("NESO_TEST_LANES", "3")
    with pytest.raises(pytest.UsageError, match="NESO_TEST_LANES=3: 1 or 2"):
        flight_lanes()
