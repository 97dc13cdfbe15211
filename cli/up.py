"""``neso up``: the whole system on this machine, every role its own process, from the declared graph."""
from __future__ import annotations

import argparse
import os

from runtime.bus import DEFAULT_HUB, SECURE_HUB
from runtime.graph import ROLES
from runtime.launcher import ProcessSpec, Supervisor, python_module_argv
from sim.px4_sitl import OFFBOARD_UDP_PORT, SIM_TCP_PORT

LOOP_ROLES = ("hub", "source", "estimator", "controller", "px4_gateway")  # what a late sample waits for
SHARED_ROLES = ("estimator", "controller", "recorder")  # --process-per-role: one process for every vehicle


# More vehicles' loops all on CPUs 1… do worse than sharing every CPU (python -m bench.hotpath, 2 CPUs, 30 s:
# 4 vehicles 1 miss isolated, 0 shared; 1 and 2 vehicles 0 either way, with shorter tails isolated).
ISOLATE_MAX_VEHICLES = 2
# From this many vehicles one estimator, controller and recorder process serves them all (2 CPUs, 50 Hz, 30 s,
# per vehicle / per role: 4 vehicles 12 / 0 misses, p99 10.9 / 3.8 ms; 8 vehicles 3336 / 25 misses of ~12,000).
PER_ROLE_FROM_VEHICLES = 3


def add_parser(subparsers) -> None:
    from dashboard.service import DashboardConfig
    from flight.controller import ControllerConfig
    from flight.estimator import EstimatorConfig
    from flight.mission import COMMANDS
    from flight.source import SourceConfig
    from neso.control import GAIN_SETS
    from neso.types import PATHWAYS
    from services.recorder import RecorderConfig
    from services.trainer import TrainerConfig
    from sim.scenarios import SCENARIOS

    src, est, ctl, dash = SourceConfig(), EstimatorConfig(), ControllerConfig(), DashboardConfig()

    p = subparsers.add_parser("up", help="start the hub and every service (simulator source) and supervise them")
    p.add_argument("--scenario", default=src.scenario, choices=sorted(SCENARIOS))
    p.add_argument("--mission", default=ctl.mission, choices=("idle",) + COMMANDS, help="mission flown from the start")
    p.add_argument("--start", default=src.start, choices=("scenario", "ground"), help="start pose of the vehicle")
    p.add_argument("--lockstep", action="store_true", help="deterministic: the sim waits for each setpoint")
    p.add_argument("--lockstep-pace", type=float, default=src.lockstep_pace,
                   help="with --lockstep: at most this multiple of real time (0: as fast as the services answer)")
    p.add_argument("--duration", type=float, default=src.duration_s, help="seconds of flight, then stop (0: until Ctrl-C)")
    p.add_argument("--rate", type=float, default=src.rate_hz, help="control rate Hz (every service of the loop)")
    p.add_argument("--seed", type=int, default=src.seed, help="world seed of the first vehicle (the next: +1, …)")
    p.add_argument("--network", default=None, help=f"network file (default: {est.network}, certified)")
    p.add_argument("--allow-uncertified", action="store_true",
                   help="fly a --network whose stability certificate fails (recorded as an event)")
    p.add_argument("--pathway", default=est.pathway, choices=PATHWAYS)
    p.add_argument("--name", action="append", default=None, dest="names",
                   help="vehicle name, repeatable: each gets its own services under neso/<name>/ (default uav1)")
    p.add_argument("--vehicle", default="direct", choices=("direct", "mavlink", "px4"),
                   help="how setpoints reach the vehicle: direct (the sim source applies them), mavlink (the sim "
                        "is a PX4 on a MAVLink UDP port, flown by the px4_gateway through MAVSDK) or px4 (real PX4 "
                        "SITL, built by `make px4`, flies the sim as its simulator; the px4_gateway flies PX4)")
    p.add_argument("--px4-instance", type=int, default=0, choices=range(10), metavar="0-9",
                   help="--vehicle px4: PX4 SITL instance of the first vehicle (the next: +1, …); its ports are 4560, 14540, "
                        "14580, 18570 + instance")
    p.add_argument("--mass-kg", type=float, default=ctl.mass_kg,
                   help="the vehicle's mass as the controller flies it (its thrust in newtons is for it); the estimator "
                        "certifies what flies for it, and refuses a network with a thrust input made for another mass")
    p.add_argument("--time-sync", action="store_true",
                   help="the px4_gateway answers PX4's TIMESYNC and dates ODOMETRY by the capture (see neso run "
                        "px4_gateway -h; off by default)")
    p.add_argument("--px4-params", default="",
                   help="--vehicle px4: PX4 SITL's airframe file (default: the world's, sim/px4/neso_quad.params; "
                        "another one rehearses a vehicle set up otherwise: `neso preflight` names what is wrong)")
    p.add_argument("--gains", default=None, choices=tuple(GAIN_SETS),
                   help="the controller's start-up gains (live parameters after): paper, or px4 (xy softer for PX4's "
                        "slower attitude loop; the default with --vehicle px4, paper otherwise)")
    p.add_argument("--mocap", default="direct", choices=("direct", "natnet"),
                   help="how the simulated world's motion capture reaches the source: direct, or natnet (a simulated "
                        "Motive streams NatNet on loopback, read by the motioncapture optitrack client as in a lab)")
    p.add_argument("--natnet-port", type=int, default=src.natnet.port,
                   help="--mocap natnet: the simulated Motive's command port (data: +1; with several vehicles one Motive "
                        "streams them all, fed by their worlds on +2)")
    p.add_argument("--natnet-up-axis", default=src.natnet.up_axis, choices=("y", "z"), help="--mocap natnet: Motive's up axis")
    p.add_argument("--natnet-rate", type=float, default=src.natnet.rate_hz,
                   help="--mocap natnet: frame rate in Hz, 100-360 (0: the world's mocap model's, 100 Hz)")
    p.add_argument("--natnet-lost", default=src.natnet.lost,
                   help="--mocap natnet: world-time windows with the rigid body untracked, 'start:duration,...' in s")
    p.add_argument("--natnet-jitter", type=float, default=src.natnet.jitter_ms,
                   help="--mocap natnet: std of each frame's send time in ms (half-normal: frames only ever late)")
    p.add_argument("--natnet-version", default=src.natnet.version, choices=("3.0", "3.1", "4.0", "4.1"),
                   help="--mocap natnet: the NatNet version the simulated Motive speaks")
    p.add_argument("--mavlink-port", type=int, default=14540, help="UDP port of the gateway's MAVLink link (--vehicle mavlink)")
    p.add_argument("--mavlink-log", default="", help="--vehicle mavlink: the simulated PX4 logs what it received here")
    p.add_argument("--hub", default=None, help=f"hub endpoint (default {DEFAULT_HUB}; --secure: {SECURE_HUB})")
    p.add_argument("--wait-for", default="", help="services the world waits for besides its loop and the recorder "
                                                  "(comma-separated)")
    p.add_argument("--low-latency", action="store_true", help="Zenoh lowlatency transport on every process")
    p.add_argument("--process-per-role", action=argparse.BooleanOptionalAction, default=None,
                   help="one estimator, one controller and one recorder process serve every vehicle (a thread per "
                        "vehicle) instead of one process per vehicle and role; sources stay per vehicle (default: "
                        f"on from {PER_ROLE_FROM_VEHICLES} vehicles)")
    p.add_argument("--priorities", action="store_true",
                   help="every process publishes the loop's streams at Zenoh's real-time priority, the rest lower")
    p.add_argument("--isolate", action=argparse.BooleanOptionalAction, default=None,
                   help="pin the loop (hub, source, estimator, controller, px4_gateway) to all but the first CPU "
                        "this may use (CPUs 1… on a whole machine) and everything else (recorder, trainer, "
                        "dashboard) to that first one, so they never take the loop's CPU "
                        f"(default: on with 2 or more CPUs and at most {ISOLATE_MAX_VEHICLES} vehicles)")
    p.add_argument("--no-record", dest="record", action="store_false", help="no recorder (default: record every flight)")
    p.add_argument("--recordings-dir", default=RecorderConfig().directory, help="where the recorder writes flights")
    p.add_argument("--no-trainer", action="store_false", dest="trainer", help="do not start the trainer service")
    p.add_argument("--registry", default=TrainerConfig().registry, help="where the trainer stores networks")
    p.add_argument("--no-dashboard", action="store_false", dest="dashboard", help="do not start the web dashboard")
    p.add_argument("--dashboard-host", default=dash.host, help="dashboard address (default loopback only)")
    p.add_argument("--dashboard-port", type=int, default=dash.port, help="dashboard port (default %(default)s)")
    from cli.busargs import add_secure_arguments

    add_secure_arguments(p.add_argument_group("security"))


def service_argv(role: str, vehicle: str, args, index: int) -> tuple[str, ...]:
    """The ``neso run`` command line of one role for one vehicle."""
    common = ["--vehicle", vehicle, "--connect", hub_endpoint(args)] + secure_argv(args)
    if args.low_latency:
        common.append("--low-latency")
    if args.priorities:
        common.append("--priorities")
    if args.lockstep:
        common.append("--lockstep")
    specific: list[str] = []
    if role == "source":
        from flight.source import SourceConfig

        # the recorder too: a flight it joined late would be recorded without its start
        recorder = ("recorder",) if args.record else ()
        wait_for = ",".join(SourceConfig().wait_for + recorder + tuple(s for s in args.wait_for.split(",") if s))
        specific = ["--scenario", args.scenario, "--seed", str(args.seed + index), "--rate", str(args.rate),
                    "--start", args.start, "--duration", str(args.duration), "--wait-for", wait_for]
        if args.lockstep:
            specific += ["--lockstep-pace", str(args.lockstep_pace)]
    elif role == "estimator":
        specific = ["--pathway", args.pathway, "--rate", str(args.rate), "--mass-kg", str(args.mass_kg)]
        if args.network is not None:
            specific += ["--network", args.network]
        if args.allow_uncertified:
            specific += ["--allow-uncertified"]
    elif role == "controller":
        specific = ["--mission", args.mission, "--rate", str(args.rate), "--gains", controller_gains(args),
                    "--mass-kg", str(args.mass_kg)]
    elif role == "recorder":
        specific = ["--recordings-dir", args.recordings_dir]
    elif role == "trainer":
        specific = ["--registry", args.registry, "--recordings-dir", args.recordings_dir]
    elif role == "px4_gateway":
        port = OFFBOARD_UDP_PORT + args.px4_instance + index if args.vehicle == "px4" else args.mavlink_port + index
        specific = ["--mavlink", f"udpin://127.0.0.1:{port}", "--forward-sources", "sim,mocap"]
        specific += ["--time-sync"] if args.time_sync else []
    if role == "source" and args.mocap == "natnet":
        specific += ["--mocap-stream", "natnet", "--natnet-up-axis", args.natnet_up_axis, "--natnet-lost",
                     args.natnet_lost, "--natnet-jitter", str(args.natnet_jitter), "--natnet-version",
                     args.natnet_version]
        if shared_motive(args):  # one Motive streams every vehicle's rigid body, named after the vehicle
            specific += ["--natnet-port", str(args.natnet_port), "--natnet-feed", str(motive_feed_port(args)),
                         "--natnet-body-id", str(index + 1), "--rigid-body", vehicle,
                         "--natnet-rate", str(motive_rate_hz(args))]
        else:
            specific += ["--natnet-port", str(args.natnet_port), "--natnet-rate", str(args.natnet_rate)]
    if role == "source" and args.vehicle == "px4":  # PX4 SITL instance `index` connects to 4560 + index
        specific += ["--link", "px4", "--px4-port", str(SIM_TCP_PORT + args.px4_instance + index), "--start", "ground"]
    elif role == "source" and args.vehicle == "mavlink":
        specific += ["--link", "mavlink", "--mavlink-out", f"udpout:127.0.0.1:{args.mavlink_port + index}"]
        if args.mavlink_log:
            specific += ["--mavlink-log", args.mavlink_log if index == 0 else f"{args.mavlink_log}.{vehicle}"]
    elif role == "dashboard":
        specific = ["--host", args.dashboard_host, "--port", str(args.dashboard_port), "--nice", "0"]  # launcher nices it
    return python_module_argv("cli.main", "run", role, *common, *specific)


def hub_endpoint(args) -> str:
    return args.hub or (SECURE_HUB if args.secure else DEFAULT_HUB)


def secure_argv(args) -> list[str]:
    """The options that put a child on the secure bus (each presents its role's certificate)."""
    if not args.secure:
        return []
    return ["--secure"] + (["--secure-dir", args.secure_dir] if args.secure_dir else [])


def check_credentials(args, roles) -> str:
    """Why ``neso up --secure`` cannot start (one line), or "" when every certificate is there."""
    if not args.secure:
        return ""
    from runtime.secure import Credentials, SecureSetupError, default_dir

    if not hub_endpoint(args).startswith("tls/"):
        return f"--hub {args.hub}: a secure bus speaks tls/ only (e.g. {SECURE_HUB})"
    for role in roles:
        try:
            Credentials(args.secure_dir or default_dir(), role.cert_name).check()
        except SecureSetupError as exc:
            return str(exc)
    return ""


def role_enabled(args, role) -> bool:
    """Whether ``neso up`` starts ``role``: always, or when its ``enabled_by`` option is set
    (``mavlink_vehicle`` is derived from ``--vehicle mavlink`` or ``px4``)."""
    if not role.enabled_by:
        return True
    if role.enabled_by == "mavlink_vehicle":
        return args.vehicle in ("mavlink", "px4")
    return bool(getattr(args, role.enabled_by))


def allowed_cpus() -> tuple[int, ...]:
    """The CPUs this process may run on (a container or ``taskset`` may allow fewer than the machine has)."""
    return tuple(sorted(os.sched_getaffinity(0)))


def isolating(args, cpus: tuple[int, ...] | None = None) -> bool:
    """``--isolate`` as given, else on with 2 or more CPUs (of ``cpus``, default :func:`allowed_cpus`) and at
    most :data:`ISOLATE_MAX_VEHICLES` vehicles."""
    if args.isolate is not None:
        return args.isolate
    return len(cpus or allowed_cpus()) >= 2 and len(args.names or ["uav1"]) <= ISOLATE_MAX_VEHICLES


def cpu_sets(isolate: bool, cpus: tuple[int, ...] | None = None) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(the loop's CPUs, everything else's CPUs) for ``--isolate``, out of ``cpus`` (default
    :func:`allowed_cpus`): the first for everything else, the rest for the loop; both empty (any CPU)
    when off or on one CPU."""
    cpus = tuple(sorted(cpus)) if cpus else allowed_cpus()
    if not isolate or len(cpus) < 2:
        return (), ()
    return cpus[1:], cpus[:1]


def sharing_processes(args) -> bool:
    """``--process-per-role`` as given, else on from :data:`PER_ROLE_FROM_VEHICLES` vehicles (never for one)."""
    n = len(args.names or ["uav1"])
    return n > 1 and (args.process_per_role if args.process_per_role is not None else n >= PER_ROLE_FROM_VEHICLES)


def build_specs(args) -> list[ProcessSpec]:
    vehicles = args.names or ["uav1"]
    loop_cpus, other_cpus = cpu_sets(isolating(args))

    def cpus(role_name: str) -> tuple[int, ...]:
        return loop_cpus if role_name in LOOP_ROLES else other_cpus
    specs = []
    for role in ROLES:
        if not role_enabled(args, role):
            continue
        if role.bus_role == "router":
            argv = python_module_argv("cli.main", "run", role.name, "--listen", hub_endpoint(args), *secure_argv(args))
            if args.low_latency:
                argv += ("--low-latency",)
            specs.append(ProcessSpec(role.name, argv, cpus=cpus(role.name), stop_timeout_s=role.stop_grace_s))
            continue
        if not role.per_vehicle:  # optional roles (enabled_by) are never the reason a flight stops
            specs.append(ProcessSpec(role.name, service_argv(role.name, vehicles[0], args, 0),
                                     essential=not role.enabled_by, nice=10 if role.enabled_by else 0,
                                     cpus=cpus(role.name), stop_timeout_s=role.stop_grace_s))
            continue
        if sharing_processes(args) and role.name in SHARED_ROLES:
            specs.append(ProcessSpec(role.name, (*service_argv(role.name, vehicles[0], args, 0), "--vehicles",
                                                 ",".join(vehicles)),
                                     cpus=cpus(role.name), stop_timeout_s=role.stop_grace_s))
            continue
        if role.name == "source" and shared_motive(args):  # the mocap system, before the sources that read it
            specs.append(ProcessSpec("motive", motive_argv(args), cpus=loop_cpus))
        for i, vehicle in enumerate(vehicles):
            name = role.name if len(vehicles) == 1 else f"{vehicle}/{role.name}"
            finishes = role.name == "source" and args.duration > 0
            specs.append(ProcessSpec(name, service_argv(role.name, vehicle, args, i), finishes=finishes,
                                     cpus=cpus(role.name), stop_timeout_s=role.stop_grace_s))
            if role.name == "source" and args.vehicle == "px4":  # the autopilot: no bus role, a process of the loop
                specs.append(ProcessSpec("px4" if len(vehicles) == 1 else f"{vehicle}/px4",
                                         px4_argv(args.px4_instance + i, vehicle, args.px4_params),
                                         cpus=loop_cpus))
    return specs


def controller_gains(args) -> str:
    """The controller's start-up gain set: ``--gains``, else px4 on real PX4 (its attitude loop answers in 160–200 ms;
    the paper's xy gains limit-cycle there) and the paper's on the world's own inner loop."""
    return args.gains or ("px4" if args.vehicle == "px4" else "paper")


def shared_motive(args) -> bool:
    """``--mocap natnet`` with several vehicles: one simulated Motive (``sim/natnet_motive.py``) streams them all,
    as a lab's one Motive PC does; with one vehicle its world runs its own."""
    return args.mocap == "natnet" and len(args.names or ["uav1"]) > 1


def motive_feed_port(args) -> int:
    """The shared Motive's loopback UDP port for the worlds' samples: after its command and data ports."""
    return args.natnet_port + 2


def motive_rate_hz(args) -> float:
    """The shared Motive's frame rate: ``--natnet-rate``, else the scenario's motion capture's (every world
    samples at it)."""
    from sim.scenarios import make_scenario

    return float(args.natnet_rate or make_scenario(args.scenario).mocap.rate_hz)


def motive_argv(args) -> tuple[str, ...]:
    """The shared simulated Motive of :func:`shared_motive`: every vehicle's rigid body, IDs 1, 2, … in order."""
    return python_module_argv("sim.natnet_motive", "--port", str(args.natnet_port), "--feed-port",
                              str(motive_feed_port(args)), "--bodies", ",".join(args.names),
                              "--rate", str(motive_rate_hz(args)), "--up-axis", args.natnet_up_axis,
                              "--seed", str(args.seed), "--jitter-ms", str(args.natnet_jitter),
                              "--natnet-version", args.natnet_version)


def px4_workdir(instance: int, vehicle: str) -> str:
    """PX4 SITL ``instance``'s working folder for ``vehicle`` under ``neso up``: emptied at each (re)start so PX4
    boots fresh; its ULogs (``log/<date>/*.ulg``, one per arming) stay there until the next."""
    import tempfile

    return os.path.join(tempfile.gettempdir(), f"neso-px4-{os.getuid()}-{instance}-{vehicle}")


def px4_argv(instance: int, vehicle: str, params: str = "") -> tuple[str, ...]:
    """``neso px4`` as PX4 SITL ``instance`` for ``vehicle``, in :func:`px4_workdir`; ``params``: another airframe
    file."""
    return python_module_argv("cli.main", "px4", "--instance", str(instance), "--workdir",
                              px4_workdir(instance, vehicle), *(("--params", params) if params else ()))


def run(args) -> int:
    vehicles = args.names or ["uav1"]
    if args.lockstep_pace < 0 or (args.lockstep_pace and not args.lockstep):
        print(f"neso up: --lockstep-pace {args.lockstep_pace:g}: a multiple of real time ≥ 0, with --lockstep", flush=True)
        return 2
    if args.lockstep and args.vehicle in ("mavlink", "px4"):
        print(f"neso up: --vehicle {args.vehicle} runs in real time only (MAVSDK and the MAVLink link keep their own "
              "clock)", flush=True)
        return 2
    if args.mocap == "natnet" and (args.lockstep or args.vehicle == "px4"):
        print("neso up: --mocap natnet runs in real time with --vehicle direct or mavlink only (the stream keeps its "
              "own clock; PX4 SITL steps the world itself)", flush=True)
        return 2
    if args.vehicle == "px4":
        from sim.px4_sitl import load_params, missing_px4

        if args.px4_params:
            try:
                load_params(args.px4_params)
            except (OSError, ValueError) as exc:
                print(f"neso up: --px4-params: {exc}", flush=True)
                return 2
        if missing_px4():
            print(f"neso up: {missing_px4()}", flush=True)
            return 2
    problem = check_credentials(args, [r for r in ROLES if role_enabled(args, r)])
    if problem:
        print(f"neso up: {problem}", flush=True)
        return 2
    supervisor = Supervisor(build_specs(args), echo=lambda line: print(line, flush=True))
    security = " (secure: mutual TLS, access control)" if args.secure else ""
    print(f"neso up: hub {hub_endpoint(args)}{security}; vehicles {vehicles} (keys neso/<vehicle>/...); scenario {args.scenario}, "
          f"mission {args.mission}, {'lockstep' if args.lockstep else 'real time'} at {args.rate:g} Hz", flush=True)
    if args.mocap == "natnet":
        bodies = f"one Motive streaming rigid bodies {vehicles}" if shared_motive(args) else "a simulated Motive"
        print(f"  motion capture:   NatNet from {bodies} on 127.0.0.1:{args.natnet_port}, "
              f"{args.natnet_up_axis}-up, NatNet {args.natnet_version}, read by the source's NatNet client", flush=True)
    loop_cpus, other_cpus = cpu_sets(isolating(args))
    if loop_cpus:
        print(f"  CPUs:             loop (hub, source, estimator, controller, px4_gateway) on {list(loop_cpus)}, "
              f"the rest on {list(other_cpus)} (--no-isolate: any)", flush=True)
        cpu_list = ",".join(map(str, other_cpus))
        print(f"  a browser here:   taskset -c {cpu_list} chromium ...  keeps it off the loop's CPUs "
              "(docs/benchmarks.md 'The hot path': what pages on the loop's CPU cost it)", flush=True)
    if sharing_processes(args):
        print(f"  processes:        one {', one '.join(SHARED_ROLES)} for all {len(vehicles)} vehicles, a source each "
              "(--no-process-per-role: one per vehicle)", flush=True)
    flag = " --secure" if args.secure else ""
    if controller_gains(args) != "paper":
        from neso.control import GAIN_SETS

        print(f"  controller gains: {controller_gains(args)} (kp, kd {GAIN_SETS[controller_gains(args)]}; --gains paper: "
              "the paper's)", flush=True)
    if args.vehicle in ("mavlink", "px4"):
        print(f"  preflight:        neso preflight{flag}  (the px4_gateway checks the vehicle every second and refuses "
              "`arm` on a NO-GO)", flush=True)
    print(f"  live parameters:  neso params get estimator{flag} | neso params set estimator pathway=eso{flag}", flush=True)
    print(f"  missions:         neso cmd controller landing_test{flag}  (takeoff | hover | lemniscate | land | arm | hold | "
          "abort)", flush=True)
    if args.dashboard:
        print(f"  dashboard:        http://{args.dashboard_host}:{args.dashboard_port}", flush=True)
    print("  stop:             Ctrl-C", flush=True)
    supervisor.start()
    return supervisor.run()
