"""``racecar-hw sim``: the daemon on the fake-hardware loopback, running a scenario."""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
from pathlib import Path

from racecar_hw.commands.daemon import add_config_options
from racecar_hw.runtime.status import StatusPanel
from racecar_hw.sim.loopback import Loopback, write_report
from racecar_hw.sim.scenario import load_scenario, scenario_names

DEFAULT_SCENARIO = "figure8"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="run the daemon on fake hardware in a simulated world",
                       description="Run the real daemon against a fake VESC and a fake lidar moved by "
                                   "a 2D world simulation, following a scenario; write a JSON report, "
                                   "a trajectory CSV and a PNG plot.")
    p.add_argument("--scenario", "-s", default=DEFAULT_SCENARIO, metavar="NAME|FILE",
                   help=f"a shipped scenario or a scenario file (default {DEFAULT_SCENARIO})")
    p.add_argument("--list", action="store_true", help="list the shipped scenarios and exit")
    p.add_argument("--duration", type=float, metavar="S", help="override the scenario's duration")
    p.add_argument("--report", metavar="FILE", help="write the JSON report here "
                                                    "(default: OUT/report.json)")
    p.add_argument("--out", metavar="DIR", help="directory for the trajectory CSV and plot "
                                                "(default: next to the report, else ./sim-out)")
    p.add_argument("--scenario-set", dest="scenario_overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="override a scenario key, e.g. drivers.0.speed_mps=3")
    p.add_argument("--record", metavar="DIR", help="record every topic to a bag in DIR (MCAP)")
    p.add_argument("--follow", metavar="BAG", help="drive by following this bag (into nav_0) instead "
                                                   "of the scenario's drivers")
    p.add_argument("--reverse", action="store_true", help="with --follow: backwards")
    p.add_argument("--follow-topic", default="/vesc/low_level/ackermann_cmd_mux/input/teleop",
                   help="with --follow: the topic in the bag")
    p.add_argument("--keyboard", action="store_true",
                   help="drive through the teleop input with the keyboard (arrows/WASD, space stops)")
    p.add_argument("--no-status", action="store_true", help="no live status panel")
    add_config_options(p, default="the shipped sim config, config/sim.yaml")
    p.set_defaults(func=cmd_sim)


def cmd_sim(args: argparse.Namespace) -> int:
    if args.list:
        for name in scenario_names():
            print(f"{name:18} {load_scenario(name).description}")
        return 0
    scenario_overrides = list(args.scenario_overrides)
    if args.follow:
        driver = {"type": "follow", "input": "nav_0", "bag": str(Path(args.follow).resolve()),
                  "topic": args.follow_topic, "reverse": args.reverse}
        scenario_overrides.append("drivers=" + json.dumps([driver]))
    scenario = load_scenario(args.scenario, scenario_overrides)
    out = Path(args.out) if args.out else (Path(args.report).parent if args.report else Path("sim-out"))
    status = None if args.no_status else StatusPanel(title=f"racecar-hw sim: {scenario.name}")
    overrides = [*args.overrides, *(["keyboard.enabled=true"] if args.keyboard else [])]
    if args.record:
        overrides += ["recorder.enabled=true", f"recorder.path={args.record}"]
    loopback = Loopback(scenario, config_path=args.config, overrides=overrides, out_dir=out,
                        status=status, duration_s=args.duration)
    result = asyncio.run(_run(loopback))
    report = write_report(result, args.report or out / "report.json")
    print(json.dumps(result.report, indent=2))
    print(f"report: {report}\nplot: {result.plot_png}\ntrajectory: {result.trajectory_csv}")
    return 0


async def _run(loopback: Loopback):  # noqa: ANN202
    """Run the scenario; the first Ctrl-C (or SIGTERM) ends it early with its report, a second aborts."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(loopback.run())
    signals = [0]

    def on_signal() -> None:
        signals[0] += 1
        if signals[0] == 1:
            loopback.request_stop()
        else:
            task.cancel()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal)
    try:
        return await task
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
