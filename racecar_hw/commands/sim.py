"""``racecar-hw sim``: the daemon on the fake-hardware loopback, running a scenario."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from racecar_hw.base.errors import ConfigError
from racecar_hw.commands.daemon import add_config_options, exit_if_recording_failed
from racecar_hw.config import load_config
from racecar_hw.net.zenoh_logins import install_for
from racecar_hw.runtime.extras import require_extra
from racecar_hw.runtime.interrupts import INTERRUPTED
from racecar_hw.runtime.signals import StopSignals, add_restart_signing_handler, add_stop_handlers

if TYPE_CHECKING:  # the simulator is imported when the command runs: it needs the sim extra
    from racecar_hw.sim.fleet import Fleet
    from racecar_hw.sim.loopback import Loopback, SimResult
    from racecar_hw.sim.plot_worker import PlotWorker
    from racecar_hw.sim.scenario import Scenario

DEFAULT_SCENARIO = "figure8"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="run the daemon on fake hardware in a simulated world",
                       description="Run the real daemon against a fake VESC and a fake lidar moved by "
                                   "a 2D world simulation, following a scenario; write a JSON report, "
                                   "a trajectory CSV and a PNG plot.")
    p.add_argument("--scenario", "-s", default=DEFAULT_SCENARIO, metavar="NAME|FILE",
                   help=f"a shipped scenario or a scenario file (default {DEFAULT_SCENARIO})")
    p.add_argument("--list", action="store_true", help="list the shipped scenarios and exit")
    p.add_argument("--duration", type=_seconds, metavar="S",
                   help="seconds to run (default: the scenario's; with --follow, as long as the "
                        "replay, slowed down for the reverse cap if need be, and 1 s more)")
    p.add_argument("--report", metavar="FILE", help="write the JSON report here "
                                                    "(default: OUT/SCENARIO.json, as the plot and CSV)")
    p.add_argument("--out", metavar="DIR", help="directory for the trajectory CSV and plot "
                                                "(default: next to the report, else ./sim-out)")
    p.add_argument("--scenario-set", dest="scenario_overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="override a scenario key, e.g. drivers.0.speed_mps=3")
    p.add_argument("--record", metavar="DIR", help="record every topic to a bag in DIR (MCAP)")
    p.add_argument("--follow", metavar="BAG", help="drive by following this bag (into nav_0) instead "
                                                   "of the scenario's drivers")
    p.add_argument("--reverse", action="store_true", help="with --follow: backwards")
    p.add_argument("--follow-topic", default="",
                   help="with --follow: the topic in the bag (default: its only drive-command topic; "
                        "with several, its only mux input)")
    p.add_argument("--keyboard", action="store_true",
                   help="drive through the teleop input with the keyboard (arrows/WASD, space stops)")
    p.add_argument("--lockstep", action="store_true",
                   help="run the daemon and the fakes on the simulation's clock through in-memory "
                        "links: deterministic (see docs/sim.md); at real-time pace unless --speed")
    p.add_argument("--speed", type=_speed, metavar="N|max",
                   help="lockstep at N times real time, or max: as fast as the machine allows "
                        "(implies --lockstep; the default is real time over ptys and TCP)")
    p.add_argument("--no-status", action="store_true", help="no live status panel")
    p.add_argument("--no-plot", action="store_true",
                   help="draw no plot: the report and the trajectory CSV only (sweeps, batch runs; "
                        "the plot costs about a second of CPU)")
    add_config_options(p, default="the shipped sim config, config/sim.yaml")
    p.set_defaults(func=cmd_sim)


def _positive(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
    return value


def _seconds(text: str) -> float:
    return _positive(text, "a positive number of seconds")


def _speed(text: str) -> float:
    """``max`` (as fast as possible: math.inf) or a positive multiple of real time."""
    if text.strip().lower() == "max":
        return math.inf
    return _positive(text, "max or a positive number")


def offline_at_max_speed(speed: float | None, overrides: list[str], command: str) -> list[str]:
    """``--set``'s settings, after :data:`~racecar_hw.sim.loopback.OFFLINE_OVERRIDES` at ``--speed
    max`` (said on standard error): a run as fast as the machine allows is one nothing outside can
    keep pace with or take part in without changing it, so it serves no network, and it starts
    about a second sooner (docs/sim.md, "The network at --speed max"). ``--set`` turns an
    interface back on."""
    if speed is None or not math.isinf(speed):
        return overrides
    from racecar_hw.sim.loopback import OFFLINE_OVERRIDES  # noqa: PLC0415 - needs the sim extra

    print(f"{command}: --speed max runs off the network (no Zenoh, DDS, Foxglove, status page); "
          "--set zenoh.enabled=true (dds, foxglove, web) turns one on", file=sys.stderr, flush=True)
    return [*OFFLINE_OVERRIDES, *overrides]


def build_scenario(args: argparse.Namespace) -> Scenario:
    """The scenario to run: ``--scenario`` with ``--follow``'s driver, then ``--scenario-set``."""
    from racecar_hw.sim.scenario import load_scenario  # noqa: PLC0415 - with the command

    scenario_overrides: list[str] = []
    if args.follow and load_scenario(args.scenario, args.scenario_overrides).cars:
        raise ConfigError("--follow", f"scenario {args.scenario} has several cars; --follow drives one")
    if args.follow:
        # first, so that --scenario-set drivers.0.rate_hz=10 (or use_timestamps) applies to it
        bag = Path(args.follow).resolve()
        driver = {"type": "follow", "input": "nav_0", "bag": str(bag), "topic": args.follow_topic,
                  "reverse": args.reverse}
        scenario_overrides += ["drivers=" + json.dumps([driver]), "name=follow",
                               "description=" + json.dumps(
                                   f"Follow {bag.name}{' backwards' if args.reverse else ''} from the "
                                   f"{args.scenario} scenario's start")]
    scenario_overrides += args.scenario_overrides
    return load_scenario(args.scenario, scenario_overrides)


def _count_zenoh_logins(config_path: str | None, overrides: list[str]) -> None:
    """Count failed Zenoh logins when the config's Zenoh listener authenticates (before the panel
    takes Python's standard output); a config that does not load is the loopback's to report."""
    try:
        config = load_config(config_path, overrides)
    except ConfigError:
        return
    install_for(config.zenoh)


def cmd_sim(args: argparse.Namespace) -> int:
    from racecar_hw.sim.scenario import load_scenario, scenario_names  # noqa: PLC0415

    if args.list:
        for name in scenario_names():
            print(f"{name:18} {load_scenario(name).description}")
        return 0
    require_extra("sim", "the simulator (its maps and plot)")
    scenario = build_scenario(args)
    # a follow driver's bag, with the outputs: before anything starts (the plot's process, a daemon)
    if args.follow and not Path(args.follow).exists():
        raise ConfigError("--follow", f"bag not found: {args.follow}")
    scenario.check_bags()
    args.overrides = offline_at_max_speed(args.speed, args.overrides, "racecar-hw sim")
    out = Path(args.out) if args.out else (Path(args.report).parent if args.report else Path("sim-out"))
    check_outputs(args, out, Path(args.report or out / f"{scenario.name or 'sim'}.json"))
    if scenario.cars:
        return cmd_fleet(args, scenario, out)
    from racecar_hw.sim.plot_worker import PlotWorker  # noqa: PLC0415 - with the command

    if args.no_plot or not (args.lockstep or args.speed is not None):
        return _cmd_loopback(args, scenario, out, PlotWorker(None))
    # lockstep: the plot's process imports matplotlib on the other core while this one starts and
    # runs (in real time the plot is drawn here, as always: no second process competes with the
    # run for the host, whose timing is the run's)
    with PlotWorker.start() as plotter:
        return _cmd_loopback(args, scenario, out, plotter)


def check_outputs(args: argparse.Namespace, out: Path, report: Path) -> None:
    """Refuse, before anything runs, a report, output directory or bag directory that could not be
    written (a run that ends with nowhere to put its report loses it)."""
    from racecar_hw.sim.report import check_writable  # noqa: PLC0415 - needs the sim extra

    check_writable(out, "--out" if args.out or not args.report else "--report", directory=True)
    check_writable(report, "--report", directory=False)
    if args.record:
        check_writable(args.record, "--record", directory=True)


def _cmd_loopback(args: argparse.Namespace, scenario: Scenario, out: Path, plotter: PlotWorker) -> int:
    """One car: the daemon on the loopback, in real time or lockstep; the plot drawn by ``plotter``
    (``PlotWorker(None)``: in this process)."""
    from racecar_hw.runtime.panel import StatusPanel  # noqa: PLC0415 - rich, with the command
    from racecar_hw.sim.loopback import Loopback, write_report  # noqa: PLC0415 - needs the extra

    overrides = [*args.overrides, *(["keyboard.enabled=true"] if args.keyboard else [])]
    if args.record:
        overrides += ["recorder.enabled=true", f"recorder.path={args.record}"]
    _count_zenoh_logins(args.config, overrides)
    status = None if args.no_status else StatusPanel(title=f"racecar-hw sim: {scenario.name}")
    # --follow: the run lasts as long as the replay, unless a duration is given
    given = args.duration is not None or any(o.partition("=")[0].strip() == "duration_s"
                                             for o in args.scenario_overrides)
    lockstep = args.lockstep or args.speed is not None
    loopback = Loopback(scenario, config_path=args.config, overrides=overrides, out_dir=out,
                        status=status, duration_s=args.duration,
                        until_replay_ends=bool(args.follow) and not given, lockstep=lockstep,
                        plotter=plotter, plot=not args.no_plot)
    with StopSignals(keep=True) as stops:  # noted until the loop handles them, and after it
        if lockstep:
            from racecar_hw.runtime import lockstep as virtual  # noqa: PLC0415 - with the option

            speed = args.speed if args.speed is not None else 1.0
            result = virtual.run(_run(loopback, stops), None if math.isinf(speed) else speed)
        else:
            result = asyncio.run(_run(loopback, stops))
    if result is None:  # a third signal: stopped at once, nothing written
        return INTERRUPTED
    report = write_report(result, args.report or out / f"{scenario.name or 'sim'}.json")
    # after the daemon has closed the status panel: a few lines, the whole report is in the file
    print(summary(result.report))
    print(outputs(result.report, report, "--no-plot" if args.no_plot else "Ctrl-C skipped it"))
    code = 0
    failure = loopback.daemon.failure if loopback.daemon is not None else None
    if failure is not None:  # the report says so too (stop_reason)
        print(f"racecar-hw sim: stopped early: {failure[0]} failed: {failure[1]}", file=sys.stderr)
        code = 1
    if loopback.daemon is not None:  # the report says so too (recording_error)
        code = exit_if_recording_failed("sim", loopback.daemon) or code
    return code


def cmd_fleet(args: argparse.Namespace, scenario: Scenario, out: Path) -> int:
    """A scenario with several cars: one daemon per car, all in one lockstep loop (paced at real
    time unless ``--speed``), no status panel; the report has a section per car."""
    from racecar_hw.runtime import lockstep as virtual  # noqa: PLC0415 - with the command
    from racecar_hw.sim.fleet import Fleet  # noqa: PLC0415 - needs the sim extra
    from racecar_hw.sim.report import write_report  # noqa: PLC0415

    if args.keyboard:
        raise ConfigError("--keyboard", f"scenario {scenario.name} has several cars; --keyboard drives "
                                        "one (give each car its drivers in the scenario, or drive them "
                                        "over Zenoh: docs/sim.md, \"Several cars\")")
    _count_zenoh_logins(args.config, args.overrides)
    fleet = Fleet(scenario, config_path=args.config, overrides=args.overrides, out_dir=out,
                  duration_s=args.duration, record_dir=args.record, plot=not args.no_plot)
    speed = args.speed if args.speed is not None else 1.0
    with StopSignals(keep=True) as stops:  # noted until the loop handles them, and after it
        result = virtual.run(_run(fleet, stops), None if math.isinf(speed) else speed)
    if result is None:
        return INTERRUPTED
    path = write_report(result, args.report or out / f"{scenario.name or 'sim'}.json")
    print(fleet_summary(result.report))
    print(f"report:     {path}")
    print(f"plot:       {result.report['plot_png'] or 'none (--no-plot)'}")
    for name, car in result.report["cars"].items():
        print(f"{name + ':':11} plot {car['plot_png'] or 'none'}, trajectory {car['trajectory_csv']}")
        for bag in car.get("bags") or []:
            print(f"{'':11} bag {bag}")
    failed = [exit_if_recording_failed(f"sim: car {name}", car.daemon)
              for name, car in fleet.cars.items() if car.daemon is not None]
    return 1 if any(failed) else 0


def fleet_summary(report: dict[str, Any]) -> str:
    """Each car's headline numbers, then the contacts between cars."""
    lines = []
    for name, car in report["cars"].items():
        lines.append(f"car {name} (namespace {car['namespace']}):")
        lines += ["  " + line for line in summary(car).splitlines()]
    contacts = report["car_collisions"]
    lines.append("cars collided: " + "; ".join(f"{c['car']} hit {c['other']} at {c['t_s']:.2f} s"
                                               for c in contacts) if contacts else "no car hit another")
    return "\n".join(lines)


def outputs(report: dict[str, Any], report_path: Path, no_plot: str) -> str:
    """Where each output of the run went: the report, the plot (``no_plot``: why there is none, if
    there is none), the trajectory, any bag."""
    plot = report["plot_png"] or f"none ({no_plot})"
    lines = [f"report:     {report_path}", f"plot:       {plot}",
             f"trajectory: {report['trajectory_csv']}"]
    lines += [f"bag:        {bag}" for bag in report.get("bags") or []]
    return "\n".join(lines)


def summary(report: dict[str, Any]) -> str:
    """The report's headline numbers in three lines, and a warning for a replay cut short."""
    pose = report["final_pose"]

    def num(value: float | None, fmt: str, unit: str) -> str:
        return "-" if value is None else f"{value:{fmt}} {unit}"

    stopped = (f"interrupted by {report['stop_reason']} after" if report.get("interrupted")
               else "ran")
    reasons = report.get("safety_interventions_by_reason") or {}
    by = f" ({', '.join(f'{k} {v}' for k, v in reasons.items())})" if reasons else ""
    yaw = None if pose["yaw"] is None else math.degrees(pose["yaw"])
    return "\n".join([
        f"{report['scenario']}: {stopped} {report['sim_time_s']:.1f} s of sim time, drove "
        f"{num(report['distance_m'], '.2f', 'm')}, "
        + ("COLLIDED" if report["collided"] else "no collision"),
        f"min clearance {_clearance(report)}, safety interventions {report['safety_interventions']}{by}",
        f"final pose x {num(pose['x'], '.2f', 'm')}  y {num(pose['y'], '.2f', 'm')}  "
        f"yaw {num(yaw, '.0f', 'deg')}",
        *_live(report),
        *_cut_short(report),
    ])


def _live(report: dict[str, Any]) -> list[str]:
    """Where the live view and the status page were during the run, when they were on."""
    live = report.get("live") or {}
    names = {"foxglove": "live view (Foxglove)", "web": "status page"}
    parts = [f"{names[k]} {url}" for k, url in live.items() if k in names]
    return [f"{' and '.join(parts)} (while it ran)"] if parts else []


def _cut_short(report: dict[str, Any]) -> list[str]:
    """A warning for each replay the run's duration ended before its last command."""
    if report.get("interrupted"):
        return []  # stopped by the user: the summary says so already
    return [f"WARNING: the replay of {Path(f['bag']).name} was cut short: {f['followed']:.0%} of it "
            f"followed when the run's duration ({report['duration_s']:g} s) ended; the replay takes "
            f"{f['replay_s']:.1f} s (give a longer --duration, or, with --follow, none)"
            for f in report.get("follow") or [] if not f["complete"]]


def _clearance(report: dict[str, Any]) -> str:
    value, cap = report["min_clearance_m"], report["clearance_cap_m"]
    if value is None:
        return "-"
    return f"{cap:g} m or more (measured up to {cap:g} m)" if value >= cap else f"{value:.2f} m"


async def _run(loopback: Loopback | Fleet, stops: StopSignals) -> SimResult | None:
    """Run the scenario (one car's loopback, or a fleet of them); the first SIGINT/SIGTERM (or one
    ``stops`` noted before the loop ran) ends it as its duration would (brake, write the report for
    the time driven), a second one hurries that (the report at once: no roll to rest, no plot), a
    third stops at once (None: nothing written)."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(loopback.run())
    signals = 0

    def on_signal(sig: int) -> None:
        nonlocal signals
        signals += 1
        if signals == 1 and loopback.stop_reason == "duration":
            loopback.request_stop(signal.Signals(sig).name)
        elif signals <= 2:
            print("racecar-hw sim: stopping: the report without waiting for the car to stop or "
                  "drawing the plot; once more to abort with nothing written", file=sys.stderr, flush=True)
            loopback.hurry()
        else:
            task.cancel()

    def restart_signing() -> str:
        cars = getattr(loopback, "cars", None)  # a fleet's
        daemons = [car.daemon for car in cars.values()] if cars is not None else [loopback.daemon]
        if any(d is None for d in daemons):
            return "the daemon is not running yet"
        return "; ".join(d.restart_mavlink_signing() for d in daemons if d is not None)

    remove = add_stop_handlers(loop, on_signal, noted=stops)
    remove_restart = add_restart_signing_handler(loop, restart_signing)
    try:
        return await task
    except asyncio.CancelledError:
        if task.cancelled():
            return None
        raise
    finally:
        remove_restart()
        remove()
