"""``neso recordings``: the flight catalog, repairing a file cut short, what a file gives as training
data, importing a PX4 log, and exporting a recording as MCAP."""
from __future__ import annotations

IMPORT_DIR = "out/imports"


def add_parser(subparsers) -> None:
    from recordings.layout import RECORDINGS_DIR

    p = subparsers.add_parser("recordings", help="list recorded flights, repair one, count its training pairs, "
                                                 "import a PX4 log, export as MCAP")
    sub = p.add_subparsers(dest="action", required=True)
    ls = sub.add_parser("list", help="flight, vehicle, source, duration, pathway, network, size of every .rrd")
    ls.add_argument("directory", nargs="?", default=RECORDINGS_DIR, help=f"folder (or one file) (default {RECORDINGS_DIR})")
    rp = sub.add_parser("repair", help="rewrite files with `rerun rrd optimize` (a crash-cut file gets its footer)")
    rp.add_argument("files", nargs="+")
    ds = sub.add_parser("dataset", help="the training pairs one or more recordings give (no training)")
    ds.add_argument("files", nargs="+")
    ds.add_argument("--label", default="eso", choices=("eso", "tdr", "applied"),
                    help="eso: x̂_3 under eso; tdr: f_N + Δf̂ under neural_eso; applied: lag-consistent (any pathway)")
    ds.add_argument("--features", default=None, help="feature set of the inputs (default: the default network's, "
                                                     "applied@1; paper@1 for the paper's)")
    ds.add_argument("--skip", type=float, default=0.5, help="seconds of estimator warm-up skipped")
    im = sub.add_parser("import", help="a PX4 flight log (.ulg) as a recording (state, thrust, status, PX4's messages)")
    add_import_arguments(im)
    im.add_argument("file", help="a PX4 ULog file")
    im.add_argument("--vehicle", default="uav1", help="vehicle name the flight is recorded under (default uav1)")
    im.add_argument("--out", default=IMPORT_DIR, help=f"folder, or a .rrd path (default {IMPORT_DIR}/<log name>.rrd)")
    ex = sub.add_parser("export", help="a recording as MCAP (JSON messages, JSON Schemas) for Foxglove and PlotJuggler")
    ex.add_argument("file", help="an .rrd recording")
    ex.add_argument("--mcap", required=True, metavar="OUT.mcap", help="the MCAP file to write")


def add_import_arguments(parser) -> None:
    """The options of a PX4 log import (shared with ``neso train FILE.ulg``)."""
    parser.add_argument("--mass-kg", type=float, default=None,
                        help="vehicle mass for thrust in N (default: the nominal model's 1 kg, flagged as assumed)")
    parser.add_argument("--hover-thrust", type=float, default=None,
                        help="normalised hover thrust (default: hover_thrust_estimate, else MPC_THR_HOVER, else steady hover)")
    parser.add_argument("--thrust-source", default=None,
                        help="topic.field of the thrust (default: the first the log has of vehicle_thrust_setpoint.xyz[2], "
                             "actuator_controls_0.control[3], vehicle_attitude_setpoint.thrust_body[2], .thrust)")


def import_config(args, vehicle: str):
    from recordings.px4 import ImportConfig

    return ImportConfig(vehicle=vehicle, mass_kg=args.mass_kg, hover_thrust_norm=args.hover_thrust,
                        thrust_source=args.thrust_source)


def run(args) -> int:
    from recordings.reader import RecordingError

    try:
        if args.action == "list":
            from recordings.catalog import catalog, format_table

            entries = catalog(args.directory)
            if not entries:
                print(f"no recordings in {args.directory}")
                return 0
            print(format_table(entries))
            return 1 if any(e.error for e in entries) else 0
        if args.action == "repair":
            from recordings.reader import repair, verify

            for f in args.files:
                repair(f)
                ok, out = verify(f)
                print(f"{f}: {'verified' if ok else 'STILL FAILS verify: ' + out}")
            return 0
        if args.action == "import":
            from recordings.px4_import import import_px4_log

            print(import_px4_log(args.file, args.out, import_config(args, args.vehicle)).report())
            return 0
        if args.action == "export":
            from recordings.mcap_export import export_mcap

            print(export_mcap(args.file, args.mcap).report())
            return 0
        from neso.features import DEFAULT_FEATURE_SET
        from recordings.dataset import load_training_set

        ts = load_training_set(args.files, args.label, feature_set_key=args.features or DEFAULT_FEATURE_SET,
                               skip_s=args.skip)
        print(f"{len(ts)} training pairs ({ts.label} labels) of vehicle {ts.vehicle} from {len(ts.recordings)} "
              f"recording(s); label mean {ts.y_mps2.mean():.3f} m/s², std {ts.y_mps2.std():.3f} m/s²; inputs "
              f"{ts.feature_set}, thrust lag {ts.thrust_lag.time_constant_s * 1e3:.1f} ms + delay "
              f"{ts.thrust_lag.delay_s * 1e3:.1f} ms ({ts.lag_source})")
        return 0
    except (RecordingError, ValueError, OSError) as exc:
        print(f"error: {exc}")
        return 1
