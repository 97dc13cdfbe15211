"""``neso px4``: real PX4 SITL with the world's airframe, in the foreground (``neso up --vehicle px4``
supervises it). The process becomes PX4 itself (exec), in a fresh working folder of its own, so a restart is
a fresh boot; PX4 then connects to the world (``neso run source --link px4``) on TCP 4560 + instance and
offers its offboard MAVLink link to UDP 14540 + instance (``neso run px4_gateway``)."""
from __future__ import annotations

import os
import shutil
import tempfile


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("px4", help="run PX4 SITL (built by `make px4`) as the world's autopilot")
    p.add_argument("--instance", type=int, default=0,
                   help="PX4 instance: simulator TCP port 4560 + instance, offboard UDP 14540 + instance")
    p.add_argument("--params", default="", help="airframe parameter file (default: sim/px4/neso_quad.params)")
    p.add_argument("--workdir", default="", help="PX4's working folder, emptied first: parameters, logs (.ulg) "
                                                 "(default: a new temporary folder)")


def run(args) -> int:
    from sim.px4_sitl import PARAMS_FILE, load_params, missing_px4, sitl_command

    problem = missing_px4()
    if problem:
        print(f"neso px4: {problem}", flush=True)
        return 2
    try:
        params = load_params(args.params or PARAMS_FILE)
    except (OSError, ValueError) as exc:
        print(f"neso px4: {exc}", flush=True)
        return 2
    if args.instance < 0:
        print("neso px4: --instance must be 0 or more", flush=True)
        return 2
    workdir = args.workdir or tempfile.mkdtemp(prefix=f"neso-px4-{args.instance}-")
    if args.workdir:
        shutil.rmtree(workdir, ignore_errors=True)
        os.makedirs(workdir)
    argv, env = sitl_command(args.instance, params)
    print(f"neso px4: PX4 SITL instance {args.instance} in {workdir} ({len(params)} airframe parameters)", flush=True)
    os.chdir(workdir)
    os.execve(argv[0], argv, env)
    return 1  # not reached
