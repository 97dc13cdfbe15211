"""Tiers by folder: every test gets the marker of the folder it lives in (``tests/<tier>/...``), so a
new test file needs nothing to be in its tier. ``slow`` is set by hand. At the end of a run, the
time each tier took (setup + call + teardown of its tests, module fixtures included)."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import pytest

TIERS = ("unit", "sim", "bus", "process", "browser", "px4")  # registered in pyproject.toml, with "slow"
TESTS = Path(__file__).resolve().parent

_groups: dict[str, tuple[str, ...]] = {}  # node id → its tier, and "slow" if it is marked so
_seconds: dict[str, float] = defaultdict(float)
_counts: dict[str, int] = defaultdict(int)


def tier_of(path: Path) -> str:
    """The tier of a test file: the first folder under tests/."""
    parts = Path(path).resolve().relative_to(TESTS).parts
    if len(parts) < 2 or parts[0] not in TIERS:
        raise pytest.UsageError(f"{path}: a test lives in one of tests/{{{','.join(TIERS)}}}/ (its tier)")
    return parts[0]


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker
def pytest_collection_modifyitems(config, items):
    for item in items:
        tier = tier_of(item.path)
        item.add_marker(tier)
        _groups[item.nodeid] = (tier, "slow") if item.get_closest_marker("slow") else (tier,)


def pytest_collection_finish(session):
    """A px4 tier without PX4 built is one error before any test runs (never a failure per test): ``make setup``
    builds it or fails saying how to get it."""
    if any(item.get_closest_marker("px4") for item in session.items):
        from sim.px4_sitl import missing_px4

        if missing_px4():
            raise pytest.UsageError(f"the px4 tier cannot run: {missing_px4()}")


def pytest_runtest_logreport(report):
    for group in _groups.get(report.nodeid, ()):
        _seconds[group] += report.duration
        _counts[group] += report.when == "setup"


def pytest_terminal_summary(terminalreporter):
    if not _counts:
        return
    terminalreporter.section("time per tier")
    for tier in (*TIERS, "slow"):
        if _counts.get(tier):
            note = " (marked slow; also counted in their tier)" if tier == "slow" else ""
            terminalreporter.write_line(f"{tier:<8} {_seconds[tier]:7.1f} s  {_counts[tier]:4d} tests{note}")
    total = sum(_seconds[t] for t in TIERS)
    terminalreporter.write_line(f"{'all':<8} {total:7.1f} s  {sum(_counts[t] for t in TIERS):4d} tests")
