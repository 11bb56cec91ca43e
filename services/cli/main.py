"""The `twin` command line.

Each command group lives in its own module under ``services/cli/`` and exposes
``register(subparsers)``; it adds its sub-command(s) and sets ``func`` on the parser
to a callable taking the parsed ``argparse.Namespace`` and returning an exit code.
Modules are imported lazily so that ``twin --help`` stays fast.

One error style for every command: a bad argument, a missing or unreadable file, an invalid
configuration, a bus that cannot be reached or a twin that refuses is one line
``error: <what>, <field/value>`` on stderr and exit status 2, without a traceback unless
``--debug`` (:func:`error_text`).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import NoReturn

#: command-group modules, in help order (``services.cli.<name>``)
COMMAND_MODULES: tuple[str, ...] = (
    "demo",  # twin demo
    "bus",  # twin record / replay / inspect / recover / schemas / router
    "live",  # twin up / status / alerts / plant simulate
    "dashboard",  # twin dashboard
    "rtd",  # twin rtd analyze / funnel / lots / reproduce
    "dem",  # twin dem run
    "calibrate",  # twin calibrate design / fit / solve ; twin feeder simulate
    "mixing",  # twin mixing compute
    "compartment",  # twin compartment build / simulate
    "closeloop",  # twin close-loop
    "opcua",  # twin bridge opcua / plant-opcua / import
    "trace",  # twin trace ; twin batch report
    "audit",  # twin audit verify / export
)

#: exit status of every command-line error
USAGE_ERROR = 2


class Parser(argparse.ArgumentParser):
    """argparse with the CLI's error style: ``error: <message>`` on one line, exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_ERROR, f"error: {message} (see {self.prog} --help)\n")


def error_text(exc: BaseException) -> str:
    """The one-line text of an error: what went wrong and the field or value concerned."""
    from pydantic import ValidationError

    from schemas.base import validation_summary

    if isinstance(exc, ValidationError):
        return f"invalid {exc.title}, {validation_summary(exc)}"
    if isinstance(exc, FileNotFoundError):
        return f"file not found, {exc.filename or exc}"
    if isinstance(exc, OSError) and exc.filename:
        return f"{(exc.strerror or type(exc).__name__).lower()}, {exc.filename}"
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if type(exc).__module__.startswith("zenoh") or type(exc).__name__ == "ZError":
        return f"the bus refused or cannot be reached, {text.split(' at /')[0]}"
    if isinstance(exc, (ValueError, RuntimeError, OSError)):
        return text
    return f"{type(exc).__name__}: {text} (an internal error; --debug shows where)"


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="twin", description="Digital twin of a continuous powder line.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument(
        "--debug", action="store_true", help="show the traceback of an error (and debug logging)"
    )
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
        level=logging.DEBUG if args.verbose or args.debug else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return USAGE_ERROR
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except SystemExit as exc:  # a command stopping with a message: the same one-line error
        if isinstance(exc.code, str):
            print(f"error: {exc.code}", file=sys.stderr, flush=True)
            return USAGE_ERROR
        raise
    except Exception as exc:  # noqa: BLE001 - every error is one line unless --debug
        if args.debug:
            raise
        print(f"error: {error_text(exc)}", file=sys.stderr, flush=True)
        return USAGE_ERROR


if __name__ == "__main__":
    sys.exit(main())
