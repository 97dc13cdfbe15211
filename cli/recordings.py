"""``neso recordings``: the flight catalog, repairing a file cut short, and what a file gives as training data."""
from __future__ import annotations

DEFAULT_DIR = "out/recordings"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("recordings", help="list recorded flights, repair one, count its training pairs")
    sub = p.add_subparsers(dest="action", required=True)
    ls = sub.add_parser("list", help="flight, vehicle, scenario, duration, pathway, network, size of every .rrd")
    ls.add_argument("directory", nargs="?", default=DEFAULT_DIR, help=f"folder (or one file) (default {DEFAULT_DIR})")
    rp = sub.add_parser("repair", help="rewrite files with `rerun rrd optimize` (a crash-cut file gets its footer)")
    rp.add_argument("files", nargs="+")
    ds = sub.add_parser("dataset", help="the training pairs one or more recordings give (no training)")
    ds.add_argument("files", nargs="+")
    ds.add_argument("--label", default="eso", choices=("eso", "tdr", "applied"),
                    help="eso: x̂_3 under eso; tdr: f_N + Δf̂ under neural_eso; applied: lag-consistent (any pathway)")
    ds.add_argument("--features", default=None, help="feature set of the inputs (default: the default network's, "
                                                     "e.g. state_speed@1; paper@1 for the paper's)")
    ds.add_argument("--skip", type=float, default=0.5, help="seconds of estimator warm-up skipped")


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
        from neso.features import DEFAULT_FEATURE_SET
        from recordings.dataset import load_training_set

        ts = load_training_set(args.files, args.label, feature_set_key=args.features or DEFAULT_FEATURE_SET,
                               skip_s=args.skip)
        print(f"{len(ts)} training pairs ({ts.label} labels) of vehicle {ts.vehicle} from {len(ts.recordings)} "
              f"recording(s); label mean {ts.y_mps2.mean():.3f} m/s², std {ts.y_mps2.std():.3f} m/s²; inputs "
              f"{ts.feature_set}, thrust lag {ts.thrust_lag.time_constant_s * 1e3:.1f} ms + delay "
              f"{ts.thrust_lag.delay_s * 1e3:.1f} ms")
        return 0
    except (RecordingError, ValueError) as exc:
        print(f"error: {exc}")
        return 1
