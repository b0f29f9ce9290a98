"""Every shipped scenario, with the obstacle memory on and off: how the car stopped.

The safety scenarios first; then those that only drive (figure8, teleop-override, vesc-replug), in
open floor where any stop for an obstacle would be a false one. Each scenario runs on the
fake-hardware loopback in real time (the real daemon, fake VESC and lidar, the world simulation),
once with the memory on (the default) and once with ``safety.memory.enabled: false``. From the
report: the speed driven, the interventions by reason, for the first report entry that brought the
car to a standstill the stopping distance (from the entry's start to standstill) and the distance
left to what it stopped for, the smallest clearance of the run, and whether the car touched
anything.

Nothing here is timed: the numbers are outcomes, for the table in docs/safety.md, measured rather
than asserted (the tests assert the outcomes that matter). ``--markdown`` prints that table.

Run ``python benchmarks/bench_safety_scenarios.py [--markdown] [NAME ...]``; ``run()`` returns
the rows for run_all.py.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import sys
from typing import Any

from table import print_rows

from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.scenario import load_scenario, scenario_names

#: The shipped scenarios that exercise the safety controller, then those that only drive.
_ORDER = ("wall", "obstacle", "corridor", "lidar-dropout", "reverse-wall", "crossing-person",
          "sliding-box", "figure8", "teleop-override", "vesc-replug")
#: Every shipped scenario in which someone drives, in that order (any newer one last); ``track``,
#: where nobody does (for the step API and code driving over Zenoh), is left out.
SCENARIOS = _ORDER + tuple(n for n in scenario_names() if n not in _ORDER and load_scenario(n).drivers)


def outcome(name: str, memory: bool) -> dict[str, Any]:
    """One run's numbers, from its report and trajectory."""
    scenario = load_scenario(name, [f"config.safety.memory.enabled={str(memory).lower()}"])
    loopback = Loopback(scenario)
    report = asyncio.run(loopback.run()).report
    assert loopback.world is not None
    samples = loopback.world.samples
    stops = [i for i in report["interventions"] if i["stopped_at_s"] is not None]
    first = stops[0] if stops else None
    # the speed that mattered: at the first intervention, else just before contact, else the top
    if report["interventions"]:
        speed = abs(report["interventions"][0]["speed_mps"] or 0.0)
    elif report["collisions"]:
        speed = abs(_speed_before(samples, report["collisions"][0][0]))
    else:
        speed = report["max_speed_mps"] or 0.0
    slowest = None
    if report["interventions"] and not stops:
        # the first intervention, with the entry that continues it when it became an obstacle stop
        first_run = report["interventions"][:1] + list(
            itertools.takewhile(lambda i: i["continues"], report["interventions"][1:]))
        start = first_run[0]["t_s"]
        end = first_run[-1]["ended_at_s"] or samples[-1].t
        slowest = min(abs(x.speed) for x in samples if start <= x.t <= end)
    return {
        "scenario": name, "memory": memory, "speed_mps": speed, "slowest_mps": slowest,
        "interventions": report["safety_interventions_by_reason"],
        "stopping_distance_m": first["stopping_distance_m"] if first else None,
        "distance_left_m": first["distance_left_m"] if first else None,
        "stopped_for": (f"{first['object'] or 'nothing'} ({first['source']})"
                        if first and first["source"] else (first["reason"] if first else None)),
        "min_clearance_m": report["min_clearance_m"],
        "collided": report["collided"],
    }


def result_text(o: dict[str, Any]) -> str:
    """What happened, in words."""
    if o["collided"]:
        return "**collision**"
    if o["stopping_distance_m"] is not None:
        return f"stopped for {o['stopped_for']}"
    if o["interventions"]:
        if o["slowest_mps"] >= o["speed_mps"] - 0.05:  # over before the car's speed changed
            return f"did not slow ({o['slowest_mps']:.1f} m/s), drove on"
        return f"slowed to {o['slowest_mps']:.1f} m/s, drove on"
    return "no intervention"


def run(names: tuple[str, ...] = SCENARIOS) -> list[dict]:
    """Rows per scenario and memory setting: clearance, stopping distance, interventions."""
    logging.getLogger().setLevel(logging.ERROR)
    rows = []
    for o in _outcomes(names):
        label = f"{o['scenario']}, memory {'on' if o['memory'] else 'off'}"
        rows.append({"name": f"{label}: smallest clearance", "value": o["min_clearance_m"], "unit": "m",
                     "target": None})
        rows.append({"name": f"{label}: stopping distance", "value": o["stopping_distance_m"]
                     if o["stopping_distance_m"] is not None else "-", "unit": "m", "target": None})
        rows.append({"name": f"{label}: interventions", "value": sum(o["interventions"].values()),
                     "unit": "", "target": None})
        rows.append({"name": f"{label}: result", "value": "collision" if o["collided"] else "no contact",
                     "unit": "", "target": None})
    return rows


def _speed_before(samples: list, t: float) -> float:
    """The car's speed (m/s) at the last sample before sim time ``t``."""
    before = [x.speed for x in samples if x.t < t]
    return before[-1] if before else 0.0


def _outcomes(names: tuple[str, ...]) -> list[dict[str, Any]]:
    return [outcome(name, memory) for name in names for memory in (True, False)]


def markdown(outcomes: list[dict[str, Any]]) -> str:
    """The docs/safety.md table."""
    lines = ["| scenario | speed (m/s) | memory | interventions | stopping distance (m) | "
             "distance left (m) | smallest clearance (m) | result |",
             "|---|---|---|---|---|---|---|---|"]
    for o in outcomes:
        by_reason = ", ".join(f"{n} {r}" for r, n in sorted(o["interventions"].items())) or "0"
        dist = "-" if o["stopping_distance_m"] is None else f"{o['stopping_distance_m']:.2f}"
        left = "-" if o["distance_left_m"] is None else f"{o['distance_left_m']:.2f}"
        lines.append(f"| {o['scenario']} | {o['speed_mps']:.1f} | {'on' if o['memory'] else 'off'} | "
                     f"{by_reason} | {dist} | {left} | {o['min_clearance_m']:.2f} | {result_text(o)} |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    names = tuple(a for a in argv if not a.startswith("-")) or SCENARIOS
    if "--markdown" in argv:
        logging.getLogger().setLevel(logging.ERROR)
        print(markdown(_outcomes(names)))
    else:
        print_rows(run(names))


if __name__ == "__main__":
    main(sys.argv[1:])
