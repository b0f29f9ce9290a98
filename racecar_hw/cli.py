"""The ``racecar-hw`` command line.

``main()`` only parses arguments. Each command lives in its own module under
:mod:`racecar_hw.commands`, which provides ``register(subparsers)``; the registered handler is a
typed function that takes the parsed arguments and returns an exit code.
"""

from __future__ import annotations

import argparse
import atexit
import gc
import importlib
import logging
import os
import signal
import sys
from collections.abc import Sequence

from racecar_hw import __version__
from racecar_hw.base.errors import RacecarError
from racecar_hw.runtime.interrupts import INTERRUPTED, STOP_SIGNALS, StopSignals, ignore_restart_signing

#: Command modules under racecar_hw.commands, in the order ``--help`` lists them.
COMMANDS: tuple[str, ...] = (
    "daemon",
    "sim",
    "follow",
    "calibrate",
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
    """Entry point of the ``racecar-hw`` console script.

    First of all SIGINT, SIGTERM and SIGHUP are handled: start-up takes about a second, and a stop signal
    in it ends the command quietly with status 130 once the imports are done
    (:mod:`racecar_hw.runtime.interrupts`), instead of a traceback, or of being lost by a
    background job that inherited SIGINT ignored. The slower imports come after that.
    """
    _skip_the_last_collection()
    ignore_restart_signing()  # its default kills: the daemon takes it once it runs
    try:
        with StopSignals() as stops:
            return _main(argv, stops)
    except KeyboardInterrupt:  # a stop signal before the command took over its handling
        return INTERRUPTED


def _skip_the_last_collection() -> None:
    """At exit, freeze the heap (``gc.freeze``) before the interpreter's final full collection.

    That collection walks every object still alive (a sim's type stores, map, trajectory and
    daemon: about 0.2 s of the command's end) only to find the few cycles a process about to end
    leaves. Everything is closed and flushed by then (the commands close what they opened);
    frozen objects are still freed by reference counting as the modules are torn down. Registered
    once per process; a process that imports this module without calling ``main`` is unaffected.
    """
    global _freeze_at_exit  # noqa: PLW0603 - one registration per process
    if not _freeze_at_exit:
        _freeze_at_exit = True
        atexit.register(gc.freeze)


_freeze_at_exit = False


def _main(argv: Sequence[str] | None, stops: StopSignals) -> int:
    # imported once the stop signals are handled (see main): these two take tens of milliseconds
    from racecar_hw.runtime.console import setup_logging  # noqa: PLC0415
    from racecar_hw.runtime.own_packages import find_foreign_packages  # noqa: PLC0415

    # Before any command module imports vesc, lidar_drivers, mux or safety.
    foreign = find_foreign_packages()
    if foreign:
        for package in foreign:
            print(f"racecar-hw: {package.message()}", file=sys.stderr)
        return 2
    parser = build_parser()
    stops.interrupt()  # the imports are done: a stop signal noted in them, or any later, interrupts
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
    except RacecarError as err:
        print(f"racecar-hw {args.command}: {err}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # the reader went away (racecar-hw vesc-info | head): stop quietly, as a Unix tool does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE


def console() -> None:
    """The ``racecar-hw`` console script (and ``python -m racecar_hw.cli``): :func:`main`, then the
    exit with its status, a stop signal ignored from then on. The command has finished (its bag
    closed, its report written); a second Ctrl-C during the interpreter's exit would otherwise meet
    Python's own handler again and end the process as killed by SIGINT (status -2), not with the
    command's status."""
    code = main()
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    console()
