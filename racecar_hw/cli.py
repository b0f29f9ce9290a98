"""The ``racecar-hw`` command line.

``main()`` only parses arguments. Each command lives in its own module under
:mod:`racecar_hw.commands`, which provides ``register(subparsers)``; the registered handler is a
typed function that takes the parsed arguments and returns an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
from collections.abc import Sequence

from racecar_hw import __version__
from racecar_hw.base.errors import RacecarError
from racecar_hw.runtime.console import setup_logging
from racecar_hw.runtime.own_packages import find_foreign_packages

#: Command modules under racecar_hw.commands, in the order ``--help`` lists them.
COMMANDS: tuple[str, ...] = (
    "daemon",
    "sim",
    "follow",
    "bag",
    "vesc",
    "lidar",
    "topic",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every command registered."""
    parser = argparse.ArgumentParser(
        prog="racecar-hw",
        description="Hardware bridge daemon for 1/10-scale autonomous race cars.")
    parser.add_argument("--version", action="version", version=f"racecar-hw {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"racecar_hw.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``racecar-hw`` console script."""
    # Before any command module imports vesc, lidar_drivers, mux or safety.
    foreign = find_foreign_packages()
    if foreign:
        for package in foreign:
            print(f"racecar-hw: {package.message()}", file=sys.stderr)
        return 2
    parser = build_parser()
    args = parser.parse_args(argv)
    level = {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    setup_logging(level)  # a blocked stderr never stops the control loop
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        code = int(args.func(args))
        sys.stdout.flush()  # here, where a closed pipe can be told apart from a failure
        return code
    except KeyboardInterrupt:
        return 130
    except RacecarError as err:
        print(f"racecar-hw {args.command}: {err}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # the reader went away (racecar-hw vesc-info | head): stop quietly, as a Unix tool does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE


if __name__ == "__main__":
    sys.exit(main())
