"""``racecar-hw run`` (the daemon on real devices) and ``racecar-hw check-config``."""

from __future__ import annotations

import argparse
import asyncio
import sys

import yaml

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import unknown_key
from racecar_hw.config import check_config, describe_config, dump_config, load_config
from racecar_hw.daemon import Daemon
from racecar_hw.net.zenoh_logins import install_for
from racecar_hw.runtime.signals import StopSignals, add_restart_signing_handler, add_stop_handlers


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
                       description="Run the configured components on real devices until SIGINT, SIGTERM or "
                                   "SIGHUP; then brake, centre, flush the recorder and exit 0 "
                                   "(1 when a component failed or the recording did).")
    add_config_options(p)
    p.add_argument("--no-status", action="store_true", help="no live status panel")
    p.set_defaults(func=cmd_run)

    c = sub.add_parser("check-config", help="validate a config file and print the effective config",
                       description="Validate FILE (with any --set overrides) and print the effective "
                                   "configuration, every default filled in.")
    c.add_argument("file", nargs="?", help="config file (default: the shipped car config)")
    c.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter (repeatable)")
    c.add_argument("--describe", nargs="?", const="", default=None, metavar="SECTION",
                   help="list every parameter (of SECTION, e.g. vesc) with its default, as YAML")
    c.set_defaults(func=cmd_check_config)


def cmd_check_config(args: argparse.Namespace) -> int:
    """Print the effective config; or every error at once, each with the file and line (or the
    --set) its value came from, exit 1."""
    if args.describe is not None:
        return describe(args.describe)
    config, problems = check_config(args.file, args.overrides, build=Daemon)
    if problems:
        for problem in problems:
            print(f"racecar-hw check-config: {problem}", file=sys.stderr)
        return 1
    assert config is not None
    sys.stdout.write(dump_config(config))
    return 0


def describe(section: str) -> int:
    """Every parameter (of ``section``, when given) with its default as YAML and its documentation."""
    rows = describe_config()
    if section:
        sections = sorted({key.split(".", 1)[0] for key, _, _ in rows})
        name = section.rstrip(".")
        if name not in sections and name.rstrip("[]") + "[]" not in sections:
            raise ConfigError(name, unknown_key(name, sections, "section"))
        rows = [row for row in rows if row[0].split(".", 1)[0] in (name, name.rstrip("[]") + "[]")]
    for key, default, doc in rows:
        print(f"{key}: {yaml_value(default)}\n    {doc}")
    return 0


def yaml_value(value: object) -> str:
    """``value`` as one line of YAML (``null``, ``false``, ``[a, b]``), as a config file says it."""
    return yaml.safe_dump(value, default_flow_style=True, width=10_000).strip().removesuffix("...").strip()


def cmd_run(args: argparse.Namespace) -> int:
    config = load_config(args.config, args.overrides)
    install_for(config.zenoh)  # before the panel: it takes Python's standard output as it is then
    status = None
    if config.status.enabled and not args.no_status:
        from racecar_hw.runtime.panel import StatusPanel  # noqa: PLC0415 - rich, only for a panel

        status = StatusPanel(refresh_hz=config.status.refresh_hz)
    daemon = Daemon(config, status=status)
    if daemon.follower is not None:
        daemon.follower.load()  # a damaged bag is a one-line error before the car is touched
    with StopSignals(keep=True) as stops:  # noted until the loop handles them, and after it
        code = asyncio.run(run_daemon(daemon, noted=stops))
    code = exit_if_recording_failed("run", daemon) or code  # as sim: a recording asked for and lost
    if daemon.drives_itself():  # a bag or the figure-8 was to drive: say so when it never could
        code = code or exit_if_undriven("run", daemon)
    return code


def exit_if_undriven(command: str, daemon: Daemon) -> int:
    """1, after saying why on stderr, when no drive command reached a connected VESC; else 0.

    A command that drives (``follow``, ``run`` with a bag or the figure-8) must not report a
    success it did not have: a replay against a missing port drove nothing.
    """
    reason = daemon.undriven_reason()
    if reason is None:
        return 0
    print(f"racecar-hw {command}: {reason}", file=sys.stderr)
    return 1


def exit_if_recording_failed(command: str, daemon: Daemon) -> int:
    """1, after one line on stderr, when the bag recorder stopped early on a write error (a full or
    unwritable disk: the car drove on, the recording did not); else 0."""
    stats = daemon.recorder.stats if daemon.recorder is not None else None
    if stats is None or stats.error is None:
        return 0
    print(f"racecar-hw {command}: the recording failed: {stats.error} ({stats.flushed} messages "
          f"on disk, {stats.dropped} dropped; racecar-hw bag recover reads them)",
          file=sys.stderr)
    return 1


async def run_daemon(daemon: Daemon, stop: asyncio.Event | None = None, *,
                     noted: StopSignals | None = None) -> int:
    """Run ``daemon`` until SIGINT, SIGTERM (or one ``noted`` before the loop ran) or ``stop`` is set.
    SIGUSR1 (``systemctl reload``) restarts the MAVLink link's signing state. 1, after one line on
    stderr, when a component's failure ended the run (systemd then restarts the service)."""
    event = stop if stop is not None else asyncio.Event()
    loop = asyncio.get_running_loop()
    remove = add_stop_handlers(loop, lambda _sig: event.set(), noted=noted)
    remove_restart = add_restart_signing_handler(loop, daemon.restart_mavlink_signing)
    try:
        await daemon.run(event)
    finally:
        remove_restart()
        remove()
    if daemon.failure is not None:
        name, err = daemon.failure
        print(f"racecar-hw: stopped, braked: {name} failed: {err}", file=sys.stderr)
        return 1
    return 0
