"""``racecar-hw run`` (the daemon on real devices) and ``racecar-hw check-config``."""

from __future__ import annotations

import argparse
import asyncio
import sys

from racecar_hw.config import describe_config, dump_config, load_config
from racecar_hw.daemon import Daemon
from racecar_hw.net.zenoh_logins import install_for
from racecar_hw.runtime.signals import StopSignals, add_restart_signing_handler, add_stop_handlers
from racecar_hw.runtime.status import StatusPanel


def add_config_options(parser: argparse.ArgumentParser, default: str = "the shipped car config") -> None:
    """``--config`` and ``--set``, shared by every command that builds the daemon.

    ``default`` names the configuration the command uses when ``--config`` is not given.
    """
    parser.add_argument("--config", "-c", metavar="FILE",
                        help=f"daemon configuration (default: {default})")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one parameter, e.g. --set vesc.port=/dev/ttyACM0 (repeatable)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the daemon on the car's real devices",
                       description="Run the configured components on real devices until SIGINT or "
                                   "SIGTERM; then brake, centre, flush the recorder and exit 0.")
    add_config_options(p)
    p.add_argument("--no-status", action="store_true", help="no live status panel")
    p.set_defaults(func=cmd_run)

    c = sub.add_parser("check-config", help="validate a config file and print the effective config",
                       description="Validate FILE (with any --set overrides) and print the effective "
                                   "configuration, every default filled in.")
    c.add_argument("file", nargs="?", help="config file (default: the shipped car config)")
    c.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter (repeatable)")
    c.add_argument("--describe", action="store_true", help="list every parameter with its default")
    c.set_defaults(func=cmd_check_config)


def cmd_check_config(args: argparse.Namespace) -> int:
    if args.describe:
        for key, default, doc in describe_config():
            print(f"{key} = {default!r}\n    {doc}")
        return 0
    config = load_config(args.file, args.overrides)
    sys.stdout.write(dump_config(config))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    config = load_config(args.config, args.overrides)
    install_for(config.zenoh)  # before the panel: it takes Python's standard output as it is then
    status = (StatusPanel(refresh_hz=config.status.refresh_hz)
              if config.status.enabled and not args.no_status else None)
    daemon = Daemon(config, status=status)
    if daemon.follower is not None:
        daemon.follower.load()  # a damaged bag is a one-line error before the car is touched
    with StopSignals() as stops:  # until the loop's handlers are in place: noted, handed to them
        return asyncio.run(run_daemon(daemon, noted=stops))


async def run_daemon(daemon: Daemon, stop: asyncio.Event | None = None, *,
                     noted: StopSignals | None = None) -> int:
    """Run ``daemon`` until SIGINT, SIGTERM (or one ``noted`` before the loop ran) or ``stop`` is set.
    SIGUSR1 (``systemctl reload``) restarts the MAVLink link's signing state."""
    event = stop if stop is not None else asyncio.Event()
    loop = asyncio.get_running_loop()
    remove = add_stop_handlers(loop, lambda _sig: event.set(), noted=noted)
    remove_restart = add_restart_signing_handler(loop, daemon.restart_mavlink_signing)
    try:
        await daemon.run(event)
    finally:
        remove_restart()
        remove()
    return 0
