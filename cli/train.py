"""``neso train``: ask a vehicle's trainer to train on recordings, wait for the result, optionally promote.

    neso train [FILE.rrd|FILE.ulg ...] [--base] [--label eso|tdr|applied] [--lipschitz L_N] [--epochs N]
               [--no-offer] [--force-offer] [--promote [--force]]

A PX4 log (``.ulg``) is imported first (``neso recordings import``, into ``--import-dir``, under
``--vehicle``) and the recording it becomes is trained on. Sends ``train`` to ``neso/<v>/cmd/trainer`` and waits for that job's ``done``/``failed`` event;
with ``--promote`` (after a passed offer and ``--shadow`` seconds in shadow) sends ``promote`` to
the estimator. Exit 0 when everything asked for happened, 1 otherwise (the reason is printed).
"""
from __future__ import annotations

import re
import threading
import time
import uuid

from cli.busargs import add_bus_arguments, bus_from_args
from cli.recordings import IMPORT_DIR, add_import_arguments, import_config


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("train", help="train a network on recordings (trainer service), offer it, promote it")
    p.add_argument("recordings", nargs="*", help=".rrd files or PX4 logs (.ulg, imported first) "
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
    p.add_argument("--force-offer", action="store_true", help="offer even if predicted to fly worse")
    p.add_argument("--promote", action="store_true", help="promote the candidate once it has been in shadow")
    p.add_argument("--force", action="store_true", help="with --promote: even if uncertified or predicted worse")
    p.add_argument("--shadow", type=float, default=2.0, help="seconds in shadow before --promote (default 2)")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for the job")
    p.add_argument("--import-dir", default=IMPORT_DIR, help=f"where PX4 logs are imported to (default {IMPORT_DIR})")
    add_import_arguments(p)
    add_bus_arguments(p)


def imported(paths: list[str], args) -> list[str]:
    """``paths`` with every PX4 log (``.ulg``) replaced by the recording it was imported as."""
    from recordings.px4_import import import_px4_log

    out = []
    for path in paths:
        if path.lower().endswith(".ulg"):
            result = import_px4_log(path, args.import_dir, import_config(args, args.vehicle))
            print(result.report(), flush=True)
            path = str(result.path)
        out.append(path)
    return out


def run(args) -> int:
    import os

    from runtime.bus import open_session
    from runtime.client import ServiceUnavailable, command
    from runtime.schema import EventMsg, Keys, SchemaError

    keys = Keys(args.vehicle)
    train_args = {"mode": args.train_mode, "epochs": args.epochs, "offer": args.offer, "seed": args.seed,
                  "force_offer": args.force_offer, "request": uuid.uuid4().hex}
    if args.label is not None:
        train_args["label"] = args.label
    if args.recordings:
        from recordings.reader import RecordingError

        try:
            train_args["recordings"] = [os.path.abspath(r) for r in imported(args.recordings, args)]
        except (RecordingError, ValueError, OSError) as exc:
            print(f"neso train: {exc}")
            return 1
    if args.lipschitz is not None:
        train_args["lipschitz_bound"] = args.lipschitz
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

    with open_session(bus_from_args(args)) as session:
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
            reply = command(session, keys, "estimator", "promote", {"request": uuid.uuid4().hex, "force": args.force},
                            timeout_s=5.0)
            print(f"estimator: {reply.message}")
            return 0 if reply.ok else 1
    return 0
