"""``neso preflight``: is this vehicle ready to arm? The px4_gateway runs the checks (it holds the vehicle's MAVLink
link and refuses to arm on a no-go); this command asks it for a fresh verdict and prints it, one line per item
with its fix; exit 0 go, 1 no-go, 2 no gateway answered. ``neso preflight table [--write]``: the PX4 parameter
table (flight/px4_params.py) as the lab table; ``--write`` regenerates the files made from it."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
README = REPO / "services" / "README.md"
TABLE_BEGIN = "<!-- lab table: generated from flight/px4_params.py by `neso preflight table --write` -->"
TABLE_END = "<!-- end of the generated lab table -->"


def add_parser(subparsers) -> None:
    from cli.busargs import add_bus_arguments

    p = subparsers.add_parser("preflight", help="check the vehicle before arming (PX4 parameters, EKF2, motion "
                                                "capture, services, certificate, battery); exit 0 go, 1 no-go")
    p.add_argument("action", nargs="?", default="check", choices=("check", "table"),
                   help="check (default): ask the px4_gateway for its verdict; table: the PX4 parameter table")
    p.add_argument("--write", action="store_true",
                   help="table: write sim/px4/neso_quad.params and services/README.md's lab table from it")
    p.add_argument("--timeout", type=float, default=20.0, help="check: seconds to wait for the verdict")
    add_bus_arguments(p)


def readme_with_table(text: str, table: str) -> str:
    """``text`` (services/README.md) with the lab table between its markers replaced by ``table``; ValueError
    when the markers are missing."""
    start, end = text.find(TABLE_BEGIN), text.find(TABLE_END)
    if start < 0 or end < start:
        raise ValueError(f"{README}: the markers of the generated lab table are missing")
    return text[:start + len(TABLE_BEGIN)] + "\n" + table + text[end:]


def write_generated() -> list[str]:
    """Rewrite the airframe file and the README's lab table from flight/px4_params.py; the files changed."""
    from flight.px4_params import airframe_text, lab_table
    from sim.px4_sitl import PARAMS_FILE

    changed = []
    for path, text in ((PARAMS_FILE, airframe_text()), (README, readme_with_table(README.read_text(), lab_table()))):
        if path.read_text() != text:
            path.write_text(text)
            changed.append(str(path.relative_to(REPO)))
    return changed


def run(args) -> int:
    if args.action == "table":
        from flight.px4_params import lab_table

        if not args.write:
            print(lab_table(), end="")
            return 0
        changed = write_generated()
        print(f"written: {', '.join(changed)}" if changed else "up to date: sim/px4/neso_quad.params, "
                                                             "services/README.md's lab table")
        return 0
    return check(args)


def check(args) -> int:
    """Ask the vehicle's px4_gateway for a fresh verdict and print it; 0 go, 1 no-go, 2 nobody answered."""
    from cli.busargs import bus_from_args, refusal_hint
    from runtime.bus import open_session
    from runtime.client import ServiceUnavailable, command
    from runtime.schema import Keys

    with open_session(bus_from_args(args)) as session:
        try:
            reply = command(session, Keys(args.vehicle), "px4_gateway", "preflight", timeout_s=args.timeout)
        except ServiceUnavailable:
            print(f"neso preflight: no px4_gateway of vehicle {args.vehicle!r} answered within {args.timeout:g} s"
                  f"{refusal_hint(args)}: start it (`neso up --vehicle px4|mavlink`, or `neso run px4_gateway "
                  "--mavlink …` against a vehicle)", flush=True)
            return 2
    print(f"preflight of vehicle {args.vehicle} (the px4_gateway's checks; it refuses to arm on a NO-GO):")
    print(reply.message, flush=True)
    return 0 if reply.ok else 1
