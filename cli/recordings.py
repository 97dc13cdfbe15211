"""``neso recordings``: the flight catalog, repairing a file cut short, what a file gives as training
data, importing a PX4 log or NanoBench CSVs, and exporting a recording as MCAP."""
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
    im = sub.add_parser("import", help="PX4 flight logs (.ulg) or NanoBench Crazyflie flights (.csv, .csv.gz, .csv.xz) "
                                       "as recordings (state, thrust, status)")
    add_import_arguments(im)
    im.add_argument("files", nargs="+", metavar="FILE", help="PX4 ULog files or NanoBench CSVs (by their suffix)")
    im.add_argument("--vehicle", default="uav1", help="vehicle name the flight is recorded under (default uav1)")
    im.add_argument("--out", default=IMPORT_DIR, help=f"folder, or a .rrd path for one file (default {IMPORT_DIR}/<name>.rrd)")
    ex = sub.add_parser("export", help="a recording as MCAP (JSON messages, JSON Schemas) for Foxglove and PlotJuggler")
    ex.add_argument("file", help="an .rrd recording")
    ex.add_argument("--mcap", required=True, metavar="OUT.mcap", help="the MCAP file to write")


def add_import_arguments(parser) -> None:
    """The options of a PX4 log or NanoBench import (shared with ``neso train FILE.ulg|FILE.csv``)."""
    parser.add_argument("--mass-kg", type=float, default=None,
                        help="vehicle mass for thrust in N (default: PX4 the nominal model's 1 kg, flagged as assumed; "
                             "NanoBench the Crazyflie 2.1's 0.029 kg, the firmware's CF_MASS)")
    parser.add_argument("--thrust-scale", type=float, default=None,
                        help="NanoBench: the thrust as this multiple of the firmware's curve (default: the median of "
                             "the imported flights' own fits)")
    parser.add_argument("--hover-thrust", type=float, default=None,
                        help="normalised hover thrust (default: hover_thrust_estimate, else MPC_THR_HOVER, else steady hover)")
    parser.add_argument("--thrust-source", default=None,
                        help="topic.field of the thrust (default: the first the log has of vehicle_thrust_setpoint.xyz[2], "
                             "actuator_controls_0.control[3], vehicle_attitude_setpoint.thrust_body[2], .thrust)")


def import_config(args, vehicle: str):
    from recordings.px4 import ImportConfig

    return ImportConfig(vehicle=vehicle, mass_kg=args.mass_kg, hover_thrust_norm=args.hover_thrust,
                        thrust_source=args.thrust_source)


def nanobench_config(args, vehicle: str):
    from recordings.nanobench import NanoBenchConfig

    given = {"mass_kg": args.mass_kg, "thrust_scale": args.thrust_scale}
    return NanoBenchConfig(vehicle=vehicle, **{k: v for k, v in given.items() if v is not None})


def import_files(paths: list[str], out: str, args, vehicle: str) -> tuple[dict[str, str], list[str]]:
    """({file: recording written}, one-line refusals) for the PX4 logs (.ulg) and NanoBench CSVs (one import: one
    thrust scale) among ``paths``, dispatched by suffix; each import's report is printed as it goes, the refusals
    are the caller's to print."""
    from pathlib import Path

    from recordings.nanobench import import_nanobench, is_nanobench_csv
    from recordings.px4 import ImportRefused
    from recordings.px4_import import import_px4_log

    unknown = [p for p in paths if not (p.lower().endswith(".ulg") or is_nanobench_csv(p))]
    if unknown:
        raise ValueError(f"{unknown[0]}: neither a PX4 log (.ulg) nor a NanoBench CSV (.csv, .csv.gz, .csv.xz)")
    csvs = [p for p in paths if is_nanobench_csv(p)]
    if csvs and (args.hover_thrust is not None or args.thrust_source is not None):
        raise ValueError("--hover-thrust and --thrust-source are for PX4 logs; a NanoBench thrust takes --thrust-scale")
    if len(paths) > 1 and out.endswith(".rrd"):
        raise ValueError(f"--out {out}: one .rrd path for {len(paths)} files; give a folder")
    written: dict[str, str] = {}
    refused: list[str] = []
    for path in (p for p in paths if p.lower().endswith(".ulg")):
        try:
            result = import_px4_log(path, out, import_config(args, vehicle))
        except ImportRefused as exc:
            refused.append(str(exc))
            continue
        print(result.report(), flush=True)
        written[path] = str(result.path)
    if csvs:
        run = import_nanobench(csvs, out, nanobench_config(args, vehicle))
        by_file = {r.flight.info["file"]: r for r in run.imported}
        for path in csvs:
            if str(Path(path).resolve()) in by_file:
                result = by_file[str(Path(path).resolve())]
                print(result.report(), flush=True)
                written[path] = str(result.path)
        refused += [why for _, why in run.refused]
    return written, refused


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
            refused = import_files(args.files, args.out, args, args.vehicle)[1]
            for why in refused:
                print(f"error: {why}")
            return 1 if refused else 0
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
