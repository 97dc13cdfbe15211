"""Tiers by folder: every test gets the marker of the folder it lives in (``tests/<tier>/...``), so a
new test file needs nothing to be in its tier. ``slow`` is set by hand. At the end of a run, the
time each tier took: its tests' own time (setup + call + teardown, module fixtures included) and, since
workers run files side by side (``-n``, tests/README.md), the wall-clock span from its first test's start to its
last test's end; the run's whole span last."""
from __future__ import annotations

import functools
import json
import os
import re
import resource
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

TIERS = ("unit", "sim", "bus", "process", "browser", "px4")  # registered in pyproject.toml, with "slow"
TESTS = Path(__file__).resolve().parent

_seconds: dict[str, float] = defaultdict(float)
_counts: dict[str, int] = defaultdict(int)
_spans: dict[str, list[float]] = {}  # group → [first start, last stop] (epoch s)
_file_seconds: dict[str, float] = defaultdict(float)  # test file under tests/ → its tests' own time
_cpu_at_start: dict[str, float] = {}  # machine_cpu_s() at the session's start
_file_cpu_s: dict[str, float] = defaultdict(float)  # test file under tests/ → CPU its tests and their processes used


def tier_of(path: Path) -> str:
    """The tier of a test file: the first folder under tests/."""
    parts = Path(path).resolve().relative_to(TESTS).parts
    if len(parts) < 2 or parts[0] not in TIERS:
        raise pytest.UsageError(f"{path}: a test lives in one of tests/{{{','.join(TIERS)}}}/ (its tier)")
    return parts[0]


def pytest_configure(config):
    """With workers (``-n``), one math thread per process, workers and the processes their tests start alike: two
    workers on 2 cores whose BLAS and torch each spin up threads for every core took 10× longer on the same numpy."""
    if getattr(config.option, "numprocesses", None):
        for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(name, "1")
        if not os.environ.get("PYTEST_XDIST_WORKER"):  # the controller, which schedules
            _lanes.update(flight_lanes())


#: Two flying lanes only on a machine this idle when the run starts (``NESO_TEST_LANES`` unset): at most this many
#: cores busy with anything else, as make's ``--load-average`` starts no second job on a busy machine
QUIET_BUSY_CORES = 0.5


def flight_lanes(sample_s: float = 1.0) -> dict[str, object]:
    """How many flying lanes this run has, and why: ``NESO_TEST_LANES=1`` or ``2`` as asked; unset, two if the
    machine is quiet (at most :data:`QUIET_BUSY_CORES` busy over ``sample_s`` at the start, every process on it) and a
    worker can lower its nice again after computing (root's CAP_SYS_NICE), else one. Two real-time flights side by
    side on a machine whose other core is busy fail their wall-clock claims (tests/README.md, Workers)."""
    asked = os.environ.get("NESO_TEST_LANES", "")
    if asked not in ("", "1", "2"):
        raise pytest.UsageError(f"NESO_TEST_LANES={asked}: 1 or 2")
    if asked == "1":
        return {"lanes": 1, "why": "NESO_TEST_LANES=1"}
    renices = subprocess.run([sys.executable, "-c", "import os; os.nice(1); os.setpriority(os.PRIO_PROCESS, 0, 0)"],
                             capture_output=True).returncode == 0
    if asked == "2":
        if not renices:
            raise pytest.UsageError("NESO_TEST_LANES=2: a worker that computed must fly at nice 0 again, which needs "
                                    "root (CAP_SYS_NICE); run with one lane")
        return {"lanes": 2, "why": "NESO_TEST_LANES=2"}
    if not renices:
        return {"lanes": 1, "why": "a worker cannot lower its nice again (not root)"}
    before, started = machine_cpu_s(), time.monotonic()
    time.sleep(sample_s)
    after, elapsed_s = machine_cpu_s(), time.monotonic() - started
    busy_cores = sum(after[k] - before[k] for k in after if k != "idle") / elapsed_s
    quiet = busy_cores <= QUIET_BUSY_CORES
    return {"lanes": 2 if quiet else 1,
            "why": f"{busy_cores:.1f} cores busy at the start ({'at most' if quiet else 'more than'} "
                   f"{QUIET_BUSY_CORES:g})"}


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker
def pytest_collection_modifyitems(config, items):
    for item in items:
        item.add_marker(tier_of(item.path))
    # the long lanes first, so that workers start them at once (a file's tests stay together, in file order)
    items.sort(key=lambda item: ORDER.index(tier_of(item.path)))


#: The flying lane's order: PX4's flights first (the longest), the browser's last, when the computing tiers are done:
#: Chromium runs at nice 19 (tests/browser/chromium.py), so beside the computing worker (nice 10) and a busy core it
#: got almost nothing and the dashboard's file took 251 s instead of 115 s (loaded run at 43a2213, browser after PX4)
ORDER = ("px4", "process", "browser", "sim", "bus", "unit")
#: The tiers that fly in real time. With workers their files run in one lane (or two: :func:`flight_lanes`), a lane's
#: files one after another on one worker; a worker that computes runs at nice :data:`COMPUTE_NICE`. What each
#: schedule measured (one lane green with a core busy; two lanes green on a quiet machine since PX4's and NatNet's
#: fly alone; every other two-lane schedule tried had failures) is in tests/README.md, Workers.
FLIGHT_TIERS = ("px4", "browser", "process")
COMPUTE_NICE = 10
#: Two lanes (a quiet machine, or ``NESO_TEST_LANES=2``: :func:`flight_lanes`): PX4's flights one after another on
#: one worker, with no other flight beside them (each two-lane run measured with another flight beside PX4 failed:
#: PX4's clock fell behind, tests/README.md) while the other worker computes; then NatNet's the same way; then the
#: other flights two at a time (each file whole on a worker), the computing tiers after them (:func:`next_unit`).
PX4_LANE = "px4 flights"
#: Two lanes: the flights that stream NatNet, one after another (Motive's data port is fixed, 1511 multicast on
#: loopback as a real Motive's: sim/natnet_server.py; two such flights at once would hear each other's frames), with
#: no other flight beside them either (beside one, at ddf8dcd: a lost body's second measured 1.08 s of the world, a
#: hover's states 0.3 s apart).
NATNET_LANE = "natnet flights"
#: The lanes that fly with nothing but computing beside them, in this order.
ALONE_LANES = (PX4_LANE, NATNET_LANE)
#: Two lanes: the flights that may fly beside NatNet's lane once the computing is done, instead of that worker
#: waiting idle (the computing, ~420 test-seconds, ends before PX4's and NatNet's lanes, ~560, do: quiet run at
#: 67e0a88). Each used under half a core in that run (out/test-files.json: CPU over seconds), and none claims a
#: wall-clock time tighter than seconds; not PX4's (its clock fell behind beside any flight).
BESIDE_NATNET = frozenset({  # not the replayed takeoff's 5 s window in the dashboard's plot (test_replay_dashboard,
    # failed beside a flight at c04d2f7), nor a recorder's crash losing at most 0.2 s (test_recorder)
    "process/test_canary.py",  # 28 s, 0.42 cores
    "browser/test_open_dashboard.py",  # 7 s, 0.21 cores
    "browser/test_viser_sender.py",  # 6 s, 0.02 cores
    "process/test_mocap_source.py",  # 3 s, 0.10 cores
    "process/test_gateway_words.py",  # 2 s, 0.20 cores
})
ONE_LANE = "flights"  # every flight in one lane (a busy machine, or NESO_TEST_LANES=1: flight_lanes)
_lanes: dict[str, object] = {}  # the controller's: flight_lanes() of this run


#: A file of a flying tier whose tests fly nothing in real time (real `neso` subprocesses that compute: offline
#: training, log import) says so with ``pytestmark = pytest.mark.offline``; it runs beside the flights, not among them.
OFFLINE_MARK = re.compile(r"^pytestmark = .*pytest\.mark\.offline\b", re.MULTILINE)


@functools.cache
def flies(relative: str) -> bool:
    """Whether the test file ``relative`` (under tests/) flies in real time: its tier is a flying one and it is not
    marked ``offline``."""
    return relative.split("/")[0] in FLIGHT_TIERS and not OFFLINE_MARK.search((TESTS / relative).read_text())


def worker_group(nodeid: str, lanes: int | None = None) -> str:
    """The unit of work a test is in (``lanes``: 1 or 2; None: this run's, one outside the controller): with one lane
    every file that :func:`flies` is in :data:`ONE_LANE`, its files one after another; with two, PX4's files are in
    :data:`PX4_LANE`; any other file is its own unit (a module's tests share its fixtures, so they never split over
    workers)."""
    relative = nodeid.split("::")[0].removeprefix("tests/")
    if not flies(relative):
        return relative
    if (lanes or _lanes.get("lanes", 1)) == 1:
        return ONE_LANE
    if relative.split("/")[0] == "px4":
        return PX4_LANE
    return NATNET_LANE if streams_natnet(relative) else relative


#: What a test file that streams NatNet says: it starts the simulated Motive (``--mocap natnet``, ``--natnet-...``
#: flags, or ``sim.natnet_server`` itself)
NATNET_STREAM = re.compile(r"""natnet_server|["']natnet["']|--natnet""")


@functools.cache
def streams_natnet(relative: str) -> bool:
    """Whether the test file ``relative`` (under tests/) may stream NatNet (:data:`NATNET_STREAM`; a file that only
    names NatNet in prose, as ``test_world_waits.py`` does, flies among the others)."""
    return bool(NATNET_STREAM.search((TESTS / relative).read_text()))


def unit_flies(unit: str) -> bool:
    """Whether a unit of :func:`worker_group` flies in real time."""
    return unit in (ONE_LANE, PX4_LANE, NATNET_LANE) or flies(unit)


def next_unit(waiting: list[str], alone_elsewhere: str | None) -> str | None:
    """Two lanes: the unit a worker with room takes next out of ``waiting`` (in collection order), or None to wait:
    the :data:`ALONE_LANES` first, in order; while one of them flies on the other worker (``alone_elsewhere``: its
    name) only computing units, and once they are done, beside NatNet's lane, the flights of :data:`BESIDE_NATNET`,
    so that no other flight runs beside PX4's and only light ones beside NatNet's (the worker flying it takes the next unit itself: xdist runs a worker's
    last test only once it has the one after); then flights before computing (the computing tiers, niced, run beside
    flights; a flight left for last would run alone), the browser's first."""
    computing = [u for u in waiting if not unit_flies(u)]
    if alone_elsewhere:
        light = [u for u in waiting if u in BESIDE_NATNET] if alone_elsewhere == NATNET_LANE else []
        return (computing or light or [None])[0]
    alone = [lane for lane in ALONE_LANES if lane in waiting]
    # the longest first, so that none is left to fly alone at the end: the browser's files (the dashboard's 70 s)
    flights = sorted((u for u in waiting if unit_flies(u)), key=lambda u: not u.startswith("browser/"))
    return (alone or flights or computing or [None])[0]


def pytest_runtest_setup(item):
    """A worker that computes (unit, sim, bus, offline files) yields the CPU to the one that flies: nice 10 for its
    computing tests, nice 0 again for a flight (two lanes: a worker flies after computing; lowering its nice again
    needs root's CAP_SYS_NICE, which :func:`flight_lanes` checks before it chooses two)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        nice = 0 if flies(str(Path(item.path).resolve().relative_to(TESTS))) else COMPUTE_NICE
        if os.getpriority(os.PRIO_PROCESS, 0) != nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)


def own_cpu_s() -> float:
    """CPU time, in core-seconds, this process and every process it started and reaped (with their own reaped ones:
    services, PX4, Chromium) have used so far."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    """Each phase's report carries the CPU used since the previous phase ended (``cpu_s`` in its user properties):
    a module's processes reaped at its last teardown count for that file."""
    report = yield
    now = own_cpu_s()
    report.user_properties.append(("cpu_s", now - _cpu_mark.get("at", now)))
    _cpu_mark["at"] = now
    return report


_cpu_mark: dict[str, float] = {}


def machine_cpu_s() -> dict[str, float]:
    """The machine's CPU time since boot, every process on it (``/proc/stat``'s cpu line), in core-seconds:
    ``user`` (nice 0), ``niced``, ``kernel`` (system, interrupts), ``idle`` (with I/O wait), ``stolen``."""
    ticks = [int(v) / os.sysconf("SC_CLK_TCK") for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:9]]
    user, niced, system, idle, iowait, irq, softirq, steal = ticks
    return {"user": user, "niced": niced, "kernel": system + irq + softirq, "idle": idle + iowait, "stolen": steal}


def pytest_sessionstart(session):
    """The machine's CPU time at the start (read again at the end, :func:`pytest_terminal_summary`); the flight
    budgets found before on this machine known to this process, as the trainer and `neso experiment paper` know them
    (services/certificate_cache.py): each verified before use, one that fails is bisected again."""
    from services.certificate_cache import adopt_budgets

    _cpu_at_start.update(machine_cpu_s())
    adopt_budgets()


def pytest_sessionfinish(session):
    """The budgets this process found, kept for the next run (and for the services its tests start later)."""
    from services.certificate_cache import keep_budgets

    keep_budgets()


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """With workers (``-n``): every :func:`worker_group` whole on one worker, in collection order (xdist's own
    ``loadgroup`` marks no longer reach the node ids under pytest 9)."""
    from xdist.scheduler import LoadScopeScheduling

    class Groups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return worker_group(nodeid)

    class TwoLanes(Groups):
        """:func:`next_unit` decides what a worker takes; a worker with nothing it may take waits, and every worker is
        offered work again whenever a test ends anywhere (a lane flown alone done frees the other)."""

        def _alone_elsewhere(self, node) -> str | None:
            """The :data:`ALONE_LANES` lane flying on another worker than ``node``, not done; None if none is."""
            return next((lane for other, work in self.assigned_work.items() if other is not node
                         for lane in ALONE_LANES if lane in work and not all(work[lane].values())), None)

        def _assign_work_unit(self, node) -> None:
            unit = next_unit(list(self.workqueue), self._alone_elsewhere(node))
            if unit is None:
                return
            self.assigned_work.setdefault(node, {})[unit] = work = self.workqueue.pop(unit)
            collection = self.registered_collections[node]
            node.send_runtest_some([collection.index(nodeid) for nodeid, done in work.items() if not done])

        def mark_test_complete(self, node, item_index: int, duration: float = 0) -> None:
            nodeid = self.registered_collections[node][item_index]
            self.assigned_work[node][self._split_scope(nodeid)][nodeid] = True
            for each in self.nodes:
                self._reschedule(each)

    config.option.loadscopereorder = False
    return (TwoLanes if _lanes.get("lanes", 1) == 2 else Groups)(config, log)



def pytest_collection_finish(session):
    """A px4 tier without PX4 built is one error before any test runs (never a failure per test): ``make setup``
    builds it or fails saying how to get it."""
    if any(item.get_closest_marker("px4") for item in session.items):
        _refuse_without_px4()


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids):
    """The same with workers (``-n``): the controller sees what they collected, before any test runs."""
    if any(nodeid.startswith("tests/px4/") for nodeid in ids):
        _refuse_without_px4()


def _refuse_without_px4() -> None:
    from sim.px4_sitl import missing_px4

    if missing_px4():
        raise pytest.UsageError(f"the px4 tier cannot run: {missing_px4()}")


def pytest_runtest_logreport(report):
    """Counted where the reports arrive: in the only process, or in the controller of the workers."""
    tier = report.nodeid.split("/")[1] if report.nodeid.startswith("tests/") else ""
    if tier not in TIERS:
        return
    _file_seconds[report.nodeid.split("::")[0].removeprefix("tests/")] += report.duration
    _file_cpu_s[report.nodeid.split("::")[0].removeprefix("tests/")] += dict(report.user_properties).get("cpu_s", 0.0)
    for group in (tier, "slow") if "slow" in report.keywords else (tier,):
        _seconds[group] += report.duration
        _counts[group] += report.when == "setup"
        span = _spans.setdefault(group, [report.start, report.stop])
        span[0], span[1] = min(span[0], report.start), max(span[1], report.stop)


def pytest_terminal_summary(terminalreporter):
    if not _counts:
        return
    terminalreporter.section("time per tier")
    terminalreporter.write_line(f"{'':<8} {'tests s':>8} {'wall s':>7}  (wall: first start to last end; workers run "
                                "tiers side by side)")
    for tier in (*TIERS, "slow"):
        if _counts.get(tier):
            note = " (marked slow; also counted in their tier)" if tier == "slow" else ""
            span = _spans[tier][1] - _spans[tier][0]
            terminalreporter.write_line(f"{tier:<8} {_seconds[tier]:8.1f} {span:7.1f}  {_counts[tier]:4d} tests{note}")
    total = sum(_seconds[t] for t in TIERS)
    spans = [_spans[t] for t in TIERS if t in _spans]
    wall = max(s[1] for s in spans) - min(s[0] for s in spans)
    terminalreporter.write_line(f"{'all':<8} {total:8.1f} {wall:7.1f}  {sum(_counts[t] for t in TIERS):4d} tests")
    lanes: dict[str, float] = {}
    for relative, seconds in sorted(_file_seconds.items(), key=lambda kv: not flies(kv[0])):
        lane = worker_group(f"tests/{relative}") if flies(relative) else "computing"
        lane = lane if lane in (ONE_LANE, PX4_LANE, NATNET_LANE, "computing") else "other flights"
        lanes[lane] = lanes.get(lane, 0.0) + seconds
    chosen = (f"{_lanes['lanes']} flying lane(s), {_lanes['why']}: " + ("a lane's files one after another on one worker"
              if _lanes["lanes"] == 1 else "PX4's, then NatNet's, alone beside the computing tiers (NatNet's "
              "also beside the light flights once the computing is done), then the others two at a time")
              if _lanes else "one worker")
    terminalreporter.write_line(f"lanes ({chosen}), test-seconds: " +
                                ", ".join(f"{lane} {s:.1f} s" for lane, s in lanes.items()))
    slowest = sorted(((s, f) for f, s in _file_seconds.items() if flies(f)), reverse=True)[:12]
    if slowest:
        terminalreporter.write_line("the flying lane's slowest files: " +
                                    ", ".join(f"{f} {s:.0f} s" for s, f in slowest))
    heaviest = sorted(((s, f) for f, s in _file_cpu_s.items()), reverse=True)[:15]
    terminalreporter.write_line(f"CPU the tests and their processes used: {sum(_file_cpu_s.values()):.0f} "
                                "core-seconds; the heaviest files: " + ", ".join(f"{f} {s:.0f}" for s, f in heaviest))
    files = {f: {"seconds": round(_file_seconds[f], 1), "cpu_s": round(_file_cpu_s.get(f, 0.0), 1), "flies": flies(f)}
             for f in sorted(_file_seconds, key=_file_seconds.get, reverse=True)}
    (TESTS.parent / "out").mkdir(exist_ok=True)
    (TESTS.parent / "out" / "test-files.json").write_text(json.dumps(files, indent=1) + "\n")
    terminalreporter.write_line("every file's seconds and CPU: out/test-files.json")
    used = {k: v - _cpu_at_start[k] for k, v in machine_cpu_s().items()}
    busy, cores = used["user"] + used["niced"] + used["kernel"] + used["stolen"], os.cpu_count()
    terminalreporter.write_line(
        f"the machine's CPU over the run (every process on it, the tests' and any other): {busy:.0f} of "
        f"{busy + used['idle']:.0f} core-seconds busy (nice 0 {used['user']:.0f}, niced {used['niced']:.0f}, kernel "
        f"{used['kernel']:.0f}, stolen {used['stolen']:.0f}), {used['idle']:.0f} idle: that work spread evenly over "
        f"{cores} cores would take {busy / cores:.0f} s")
