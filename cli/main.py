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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="neso", description="Neural-ESO flight runtime")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in SUBCOMMANDS.values():
        importlib.import_module(module).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return importlib.import_module(SUBCOMMANDS[args.command]).run(args)


if __name__ == "__main__":
    sys.exit(main())
