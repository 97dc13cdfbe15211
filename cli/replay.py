"""``neso replay FILE``: a recorded flight in the Rerun viewer, back on the bus, or flown by another estimator."""
from __future__ import annotations

import os
import signal
import subprocess

from runtime.signals import Signalled


def add_parser(subparsers) -> None:
    from cli.busargs import add_bus_arguments

    p = subparsers.add_parser("replay", help="open a recording in the Rerun viewer, publish it on the bus (--to-bus) "
                                             "or run another estimator configuration on it (--what-if)")
    p.add_argument("file", help="an .rrd written by the recorder")
    p.add_argument("--web", action="store_true", help="web viewer on 127.0.0.1 instead of the native one")
    p.add_argument("--web-port", type=int, default=9090, help="web viewer HTTP port (default 9090)")
    p.add_argument("--grpc-port", type=int, default=9876, help="viewer gRPC port (default 9876)")
    p.add_argument("--to-bus", action="store_true", help="publish the recorded flight at its recorded pace")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed factor for --to-bus (default 1)")
    p.add_argument("--as", dest="as_vehicle", default=None,
                   help="vehicle name to publish under (default: the recorded one; pick another beside a live one)")
    p.add_argument("--what-if", default=None, metavar="CONFIG",
                   help="estimator config to run offline, e.g. pathway=neural_eso,L_N=0.5,omega_o=20,network=FILE")
    add_bus_arguments(p)


def run(args) -> int:
    from recordings.reader import RecordingError, read_recording

    try:
        if args.what_if is not None:
            from recordings.replay import WhatIf, what_if

            print(what_if(read_recording(args.file), WhatIf.parse(args.what_if)).report())
            return 0
        if args.to_bus:
            return _to_bus(args, read_recording(args.file))
        from recordings.replay import viewer_argv

        argv = viewer_argv(args.file, web=args.web, web_port=args.web_port, grpc_port=args.grpc_port)
        if args.web:
            print(f"web viewer: http://127.0.0.1:{args.web_port} (Ctrl-C to stop)", flush=True)
        proc = subprocess.Popen(argv, start_new_session=True)  # its own group: the wrapper and the native viewer
        stop = Signalled().install()  # a flag, never an event set in the handler (runtime/signals.py)
        stop.wait(also=lambda: proc.poll() is not None)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        return 0 if stop.is_set() else proc.returncode
    except (RecordingError, ValueError) as exc:
        print(f"error: {exc}")
        return 1


def _to_bus(args, rec) -> int:
    from cli.busargs import bus_from_args
    from recordings.replay import bus_schedule, origin_of, publish_schedule
    from runtime.bus import open_session

    vehicle = args.as_vehicle or rec.vehicle
    schedule = bus_schedule(rec)
    stop = Signalled().install()
    origin = origin_of(rec)
    print(f"replaying {args.file} ({schedule[-1][0]:.1f} s, {len(schedule)} messages; {origin}) as neso/{vehicle}/ "
          f"at ×{args.speed:g}", flush=True)
    with open_session(bus_from_args(args, identity="replay")) as session:
        n = publish_schedule(session, vehicle, schedule, speed=args.speed, stop=stop,
                             provenance=(os.path.abspath(args.file), origin),
                             on_progress=lambda t, m: print(f"  t = {t:.1f} s (sample {m.seq})", flush=True))
    print(f"published {n} of {len(schedule)} messages", flush=True)
    return 0
