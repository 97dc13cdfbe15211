"""``neso up --isolate``: the loop's processes on CPUs 1…, everything else on CPU 0, from their first instruction."""
from __future__ import annotations

import os
import sys

from cli.up import LOOP_ROLES, build_specs, cpu_sets, isolating
from runtime.launcher import ProcessSpec, Supervisor
from tests.helpers import up_args


def test_cpu_sets_split_the_allowed_cpus_and_do_nothing_on_one_cpu():
    assert cpu_sets(True, (0, 1)) == ((1,), (0,))
    assert cpu_sets(True, tuple(range(8))) == (tuple(range(1, 8)), (0,))
    assert cpu_sets(True, (0,)) == ((), ())
    assert cpu_sets(False, tuple(range(8))) == ((), ())
    # a container (or taskset) allowing CPUs 4 and 6 of a bigger machine: never a CPU it may not use
    assert cpu_sets(True, (6, 4)) == ((6,), (4,))
    assert set(sum(cpu_sets(True), ())) <= os.sched_getaffinity(0)


def test_isolation_is_on_by_default_with_two_cpus_and_up_to_two_vehicles_and_pins_every_role():
    assert isolating(up_args("--name", "a", "--name", "b"), cpus=(0, 1))
    assert not isolating(up_args("--name", "a", "--name", "b", "--name", "c"), cpus=(0, 1))  # bench: 3+ share better
    assert not isolating(up_args(), cpus=(3,))
    assert isolating(up_args("--isolate", "--name", "a", "--name", "b", "--name", "c"), cpus=(0, 1))
    assert not isolating(up_args("--no-isolate"), cpus=tuple(range(8)))
    loop, other = cpu_sets(True)
    specs = {s.name: s for s in build_specs(up_args("--isolate", "--name", "a", "--name", "b"))}
    for name, spec in specs.items():
        role = name.split("/")[-1]
        assert spec.cpus == (loop if role in LOOP_ROLES else other), name
    assert {"a/recorder", "b/trainer", "dashboard"} <= set(specs)
    assert all(s.cpus == () for s in build_specs(up_args("--no-isolate")))


def test_a_process_starts_with_its_affinity():
    cpu = max(os.sched_getaffinity(0))
    sup = Supervisor([ProcessSpec("pinned", (sys.executable, "-c", "import time; time.sleep(30)"), cpus=(cpu,))],
                     echo=lambda line: None)
    sup.start()
    try:
        assert os.sched_getaffinity(sup.procs["pinned"].pid) == {cpu}
    finally:
        sup.stop()


def test_from_three_vehicles_one_process_per_role_serves_them_all_sources_stay_per_vehicle():
    from cli.up import PER_ROLE_FROM_VEHICLES, SHARED_ROLES, sharing_processes

    names = [a for i in range(PER_ROLE_FROM_VEHICLES) for a in ("--name", f"v{i}")]
    assert sharing_processes(up_args(*names))
    assert not sharing_processes(up_args(*names[:-2]))  # one vehicle fewer: a process per vehicle and role
    assert sharing_processes(up_args("--process-per-role", "--name", "a", "--name", "b"))
    assert not sharing_processes(up_args("--process-per-role"))  # one vehicle: nothing to share
    assert not sharing_processes(up_args("--no-process-per-role", *names))
    specs = {s.name: s for s in build_specs(up_args(*names, "--no-dashboard"))}
    vehicles = ",".join(f"v{i}" for i in range(PER_ROLE_FROM_VEHICLES))
    for role in SHARED_ROLES:
        argv = specs[role].argv
        assert argv[argv.index("--vehicles") + 1] == vehicles, role
    assert {f"v{i}/source" for i in range(PER_ROLE_FROM_VEHICLES)} <= set(specs)
    assert not any(name.endswith(("/estimator", "/controller", "/recorder")) for name in specs)
