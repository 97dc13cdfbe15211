"""``neso train``: train a network on recordings — through a vehicle's trainer, or here, offline.

    neso train [FILE.rrd|FILE.ulg|FILE.csv ...] [--base] [--label eso|tdr|applied] [--lipschitz L_N] [--epochs N]
               [--no-offer] [--force-offer] [--promote [--force]]
    neso train FILE.rrd|FILE.ulg --no-offer [--offline] [--network FILE] [--registry DIR]

A PX4 log (``.ulg``) or a NanoBench CSV is imported first (``neso recordings import``, into ``--import-dir``,
under ``--vehicle``) and the recording it becomes is trained on. With a trainer on the bus: sends
``train`` to ``neso/<v>/cmd/trainer`` and waits for that job's ``done``/``failed`` event; with
``--promote`` (after a passed offer and ``--shadow`` seconds in shadow) sends ``promote`` to the
estimator. With ``--offline``, or ``--no-offer`` and no trainer on the bus: the trainer's own job
(:func:`services.trainer.train_job`: dataset, training, certificate, registry) runs in this
process; a TDR warm-starts from ``--network``. Exit 0 when everything asked for happened, 1
otherwise (the reason is printed).
"""
from __future__ import annotations

import os
import re
import threading
import time
import uuid

from cli.busargs import add_bus_arguments, bus_from_args
from cli.recordings import IMPORT_DIR, add_import_arguments, import_files


def add_parser(subparsers) -> None:
    from recordings.layout import RECORDINGS_DIR
    from services.registry import DEFAULT_ROOT

    p = subparsers.add_parser("train", help="train a network on recordings (trainer service), offer it, promote it")
    p.add_argument("recordings", nargs="*", help=".rrd files, PX4 logs (.ulg) or NanoBench CSVs (imported first) "
                                                 "(default: the trainer's newest recording)")
    p.add_argument("--base", action="store_const", const="base", default="tdr", dest="train_mode",
                   help="train a base network from scratch on ESO-teacher flights (default recipe) instead of "
                        "retraining the active network (TDR, with its recipe)")
    p.add_argument("--label", default=None, choices=("eso", "tdr", "applied"),
                   help="override the recipe's label (eso: x̂_3 under eso; tdr: f_N + Δf̂; applied: lag-consistent)")
    p.add_argument("--lipschitz", type=float, default=None,
                   help="L_N in the recipe's units (default: the largest the certificate allows for the gains flown)")
    p.add_argument("--epochs", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-offer", action="store_false", dest="offer", help="store in the registry only")
    p.add_argument("--force-offer", action="store_true", help="offer even if predicted to fly worse or it learned nothing "
                   "(the estimator's certificate still gates it)")
    p.add_argument("--promote", action="store_true", help="promote the candidate once it has been in shadow")
    p.add_argument("--force", action="store_true", help="with --promote: even if uncertified or predicted worse")
    p.add_argument("--shadow", type=float, default=2.0, help="seconds in shadow before --promote (default 2)")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for the job")
    p.add_argument("--import-dir", default=IMPORT_DIR, help=f"where PX4 logs are imported to (default {IMPORT_DIR})")
    add_import_arguments(p)
    g = p.add_argument_group("offline (no bus)")
    g.add_argument("--offline", action="store_true",
                   help="train here without a bus (implied by --no-offer when no trainer is on the bus)")
    g.add_argument("--network", default=None,
                   help="offline tdr: the network to warm-start from (default the estimator's, "
                        "networks/base.safetensors, found from any folder)")
    g.add_argument("--registry", default=DEFAULT_ROOT, help="offline: where the network is stored")
    g.add_argument("--recordings-dir", default=RECORDINGS_DIR,
                   help="offline: where the newest recording is taken from when no FILE is given")
    add_bus_arguments(p)


def imported(paths: list[str], args) -> list[str]:
    """``paths`` with every PX4 log (``.ulg``) and NanoBench CSV replaced by the recording it was imported as
    (:class:`recordings.reader.RecordingError` naming the first one refused)."""
    from recordings.nanobench import is_nanobench_csv
    from recordings.reader import RecordingError

    logs = [p for p in paths if p.lower().endswith(".ulg") or is_nanobench_csv(p)]
    if not logs:
        return list(paths)
    written, refused = import_files(logs, args.import_dir, args, args.vehicle)
    if refused:
        raise RecordingError(refused[0])
    return [written.get(p, p) for p in paths]


def _train_args(args) -> dict:
    """The trainer's ``train`` args; PX4 logs among the recordings are imported here first."""
    out = {"mode": args.train_mode, "epochs": args.epochs, "offer": args.offer, "seed": args.seed,
           "force_offer": args.force_offer}
    if args.label is not None:
        out["label"] = args.label
    if args.recordings:
        out["recordings"] = [os.path.abspath(r) for r in imported(args.recordings, args)]
    if args.lipschitz is not None:
        out["lipschitz_bound"] = args.lipschitz
    return out


def offline(args) -> int:
    """The trainer's job in this process: no bus, no offer."""
    from neso.netfile import NetworkFileError, load_network
    from recordings.reader import RecordingError
    from flight.estimator import DEFAULT_NETWORK, shipped
    from services.trainer import TrainerConfig, parse_job, train_job

    if args.offer or args.promote:
        print("neso train: offline there is no estimator to offer to or promote in: add --no-offer "
              "(the network is stored in the registry; offer it later with `neso cmd estimator offer path=FILE`)")
        return 1
    config = TrainerConfig(registry=args.registry, recordings_dir=args.recordings_dir)
    try:
        job = parse_job(1, _train_args(args), config)
        active = None
        if job.mode == "tdr":
            path = shipped(args.network or DEFAULT_NETWORK)  # the project's own from any folder
            active = {"id": load_network(path).metadata.get("id", os.path.basename(path)), "path": path}
            print(f"neso train: offline, tdr warm-started from {path}", flush=True)
        result = train_job(job, config, args.vehicle, active)
    except (ValueError, RecordingError, NetworkFileError, OSError) as exc:
        print(f"neso train: {exc}")
        return 1
    print(f"trained offline: {result.summary()}")
    return 0


def _trainer_alive(session, keys, timeout_s: float = 2.0) -> bool:
    """Whether the vehicle's trainer holds its liveliness token. Asked again until ``timeout_s``: a
    session just opened may not have reached the hub yet, and an early answer is empty."""
    deadline = time.monotonic() + timeout_s
    while True:
        if list(session.liveliness().get(keys.alive("trainer"), timeout=0.25)):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)


def run(args) -> int:
    if args.offline:
        return offline(args)
    from runtime.bus import open_session
    from runtime.schema import Keys

    keys = Keys(args.vehicle)
    with open_session(bus_from_args(args)) as session:
        if _trainer_alive(session, keys):
            return _through_the_trainer(args, session, keys)
    if not args.offer and not args.promote:
        print(f"neso train: no trainer of {args.vehicle} on the bus: training here, offline", flush=True)
        return offline(args)
    print(f"neso train: no trainer of {args.vehicle} on the bus (is `neso up` running?); --no-offer trains offline")
    return 1


def _through_the_trainer(args, session, keys) -> int:
    from recordings.reader import RecordingError
    from runtime.client import ServiceUnavailable, command
    from runtime.schema import EventMsg, SchemaError

    try:
        train_args = dict(_train_args(args), request=uuid.uuid4().hex)
    except (RecordingError, ValueError, OSError) as exc:
        print(f"neso train: {exc}")
        return 1
    events: list[str] = []
    arrived = threading.Condition()

    def on_event(sample) -> None:
        try:
            msg = EventMsg.from_bytes(sample.payload.to_bytes())
        except SchemaError:
            return
        with arrived:
            events.append(msg.text)
            arrived.notify_all()

    sub = session.declare_subscriber(keys.event("trainer"), on_event)
    try:
        reply = command(session, keys, "trainer", "train", train_args, timeout_s=5.0)
    except ServiceUnavailable as exc:
        print(f"neso train: {exc}")
        return 1
    print(f"trainer: {reply.message}")
    if not reply.ok:
        return 1
    job = re.match(r"job (\d+) queued", reply.message).group(1)
    done = re.compile(rf"^job {job} (done|failed): ")
    deadline = time.monotonic() + args.timeout
    result = None
    with arrived:
        while result is None and time.monotonic() < deadline:
            result = next((e for e in events if done.match(e)), None)
            if result is None:
                arrived.wait(0.2)
    sub.undeclare()
    if result is None:
        print(f"neso train: job {job} did not finish within {args.timeout:g} s")
        return 1
    print(f"trainer: {result}")
    if re.match(rf"^job {job} failed: ", result):
        return 1
    if args.offer and "; offer accepted:" not in result:
        return 1
    if args.promote:
        time.sleep(args.shadow)
        reply = command(session, keys, "estimator", "promote", {"request": uuid.uuid4().hex, "force": args.force}, timeout_s=5.0)
        print(f"estimator: {reply.message}")
        return 0 if reply.ok else 1
    return 0
