"""``racecar-hw follow``: replay a bag's drive commands into a mux input of the running car."""

from __future__ import annotations

import argparse
import asyncio
import os

from racecar_hw.bags.follow import BagFollower
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build
from racecar_hw.commands.daemon import (
    add_config_options,
    exit_if_recording_failed,
    exit_if_undriven,
    run_daemon,
)
from racecar_hw.config import FollowerSection, load_config
from racecar_hw.daemon import Daemon
from racecar_hw.net.zenoh_logins import install_for
from racecar_hw.runtime.signals import StopSignals
from racecar_hw.teleop.arming import ArmingChange


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("follow", help="drive the car by replaying a bag's drive commands",
                       description="Run the daemon with a bag follower: the bag's AckermannDriveStamped "
                                   "or AckermannDrive commands (or Twist / TwistStamped, converted "
                                   "with the wheelbase) enter a mux input, so the deadman, "
                                   "priorities and the safety controller still apply. Exits when the "
                                   "bag ends (brake and centre). The car config starts disarmed: "
                                   "give --arm to follow armed.")
    p.add_argument("bag", help="ROS 1 .bag file or ROS 2 bag directory (sqlite3 or MCAP)")
    p.add_argument("--topic", default=None,
                   help="topic in the bag (default: its only drive-command topic; with several, "
                        "its only mux input)")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument("--rate", type=float, default=20.0, metavar="HZ", help="fixed rate (default 20)")
    timing.add_argument("--timestamps", action="store_true", help="replay at the bag's own timing")
    p.add_argument("--time-scale", type=float, default=1.0, metavar="X", help="speed up the timing")
    p.add_argument("--reverse", action="store_true",
                   help="backwards: reversed order, negated speed, same steering")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--input", default="nav_0", help="mux input name to drive (default nav_0)")
    p.add_argument("--arm", action="store_true",
                   help="start armed when the config starts disarmed (the car config does); the "
                        "gamepad's BACK or a ground station still disarms it, which ends the replay")
    add_config_options(p)
    p.set_defaults(func=cmd_follow)


def cmd_follow(args: argparse.Namespace) -> int:
    overrides = [*args.overrides, *(["arming.start_armed=true"] if args.arm else [])]
    config = load_config(args.config, overrides)
    install_for(config.zenoh)  # before the progress bar takes Python's standard output
    topics = {inp.name: inp.topic for inp in config.mux.inputs}
    if args.input not in topics:
        raise ConfigError("--input", f"no mux input {args.input!r}; inputs: " + ", ".join(topics))
    config.follower = build(FollowerSection, {
        "enabled": True, "bag": args.bag, "topic": args.topic or "", "input_topic": topics[args.input],
        "rate_hz": args.rate, "use_timestamps": args.timestamps, "time_scale": args.time_scale,
        "reverse": args.reverse, "loop": args.loop}, "follower")
    daemon = Daemon(config)
    follower = daemon.follower
    assert follower is not None
    follower.load()  # a missing, damaged or out-of-limits bag is a one-line error before the car is touched
    follower.hopeless = lambda: missing_vesc_port(daemon)
    if not config.arming.start_armed:
        raise ConfigError("arming.start_armed", "the car starts disarmed, so it would stand still "
                          "while the bag plays; give --arm to follow armed (the gamepad's BACK "
                          "still disarms it)")
    # here, not at the top: every command's module is imported to build the parser, the daemon's too
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415

    with Progress(TextColumn("following"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeRemainingColumn()) as bar:
        task = bar.add_task("bag", total=1.0)
        follower.progress = lambda fraction, eta: bar.update(task, completed=fraction)
        with StopSignals(keep=True) as stops:  # noted until the loop handles them, and after it
            code = asyncio.run(_follow(daemon, follower, stops))
    if daemon.arming.changes and not daemon.arming.armed:
        print(f"racecar-hw follow: stopped at {follower.published} commands: {daemon.arming.reason}")
    code = exit_if_recording_failed("follow", daemon) or code
    return code or exit_if_undriven("follow", daemon)


def missing_vesc_port(daemon: Daemon) -> str | None:
    """Why a replay cannot reach the VESC: its configured port is a device path that does not
    exist (once the driver failed to open it). None while it may yet connect: a port that exists,
    a URL, ``auto``, or a VESC that connected before. A replay then ends at once (exit 1, saying
    why) rather than waiting for a car that cannot get ready and playing the bag into nothing."""
    vesc, port = daemon.vesc, daemon.config.vesc.port
    if vesc is None or vesc.ever_connected or vesc.last_error is None:
        return None
    if port == "auto" or "://" in port or os.path.exists(port):
        return None
    return f"the VESC's port {port} does not exist"


async def _follow(daemon: Daemon, follower: BagFollower, stops: StopSignals) -> int:
    stop = asyncio.Event()

    def on_arming(change: ArmingChange) -> None:
        if not change.armed:  # the operator took the car away: the replay must not resume later
            follower.stop()

    daemon.arming.on_change(on_arming)

    async def stop_when_done() -> None:
        while not follower.done:
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)  # let the final stop command reach the VESC
        stop.set()

    daemon.add_task(stop_when_done())
    return await run_daemon(daemon, stop, noted=stops)
