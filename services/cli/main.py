"""The `twin` command line.

Each command group lives in its own module under ``services/cli/`` and exposes
``register(subparsers)``; it adds its sub-command(s) and sets ``func`` on the parser
to a callable taking the parsed ``argparse.Namespace`` and returning an exit code.
Modules are imported lazily so that ``twin --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

#: command-group modules, in help order (``services.cli.<name>``)
COMMAND_MODULES: tuple[str, ...] = (
    "demo",  # twin demo
    "bus",  # twin record / replay / inspect / schemas
    "live",  # twin up / status / alerts
    "rtd",  # twin rtd analyze / funnel / lots / reproduce
    "dem",  # twin dem run
    "calibrate",  # twin calibrate design / fit / solve ; twin feeder simulate
    "mixing",  # twin mixing compute
    "compartment",  # twin compartment build / simulate
    "closeloop",  # twin close-loop
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twin", description="Digital twin of a continuous powder line."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"services.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"services.cli.{name}":
                raise
            continue
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
