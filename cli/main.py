"""The ``neso`` command. Each sub-command lives in its own module and is imported only when
run, so ``neso certify`` does not pay for torch or the simulator."""
from __future__ import annotations

import argparse
import importlib
import sys

# sub-command → module in this package with add_parser(subparsers) and run(args) -> int
SUBCOMMANDS = {
    "certify": "cli.certify",
    "experiment": "cli.experiment",
    "up": "cli.up",
    "run": "cli.run",
    "params": "cli.params",
    "cmd": "cli.cmd",
    "recordings": "cli.recordings",
    "replay": "cli.replay",
    "train": "cli.train",
    "networks": "cli.networks",
    "demo": "cli.demo",
    "secure": "cli.secure",
    "px4": "cli.px4",
    "preflight": "cli.preflight",
}


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of every sub-command, or, when ``argv`` names one, of that one only: some parsers import their
    defaults' modules (`neso up`'s every service config, `neso certify`'s the estimator), which every service process
    (``neso run``) paid for at its start, ~0.5 s of CPU each."""
    parser = argparse.ArgumentParser(prog="neso", description="Neural-ESO flight runtime")
    sub = parser.add_subparsers(dest="command", required=True)
    chosen = next((a for a in argv or () if not a.startswith("-")), None)
    for name, module in SUBCOMMANDS.items():
        if chosen not in SUBCOMMANDS or name == chosen:
            importlib.import_module(module).add_parser(sub)
        else:
            sub.add_parser(name)  # its name in the usage line, as without a choice
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    return importlib.import_module(SUBCOMMANDS[args.command]).run(args)


if __name__ == "__main__":
    sys.exit(main())
