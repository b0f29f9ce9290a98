"""Lockstep speed: how much faster than real time each shipped scenario runs on virtual time.

Per scenario, one lockstep run as fast as the machine allows (in this process, network interfaces
off, no plot): the real seconds the run took (the report's ``clock.real_time_s``), and the
speed-up, sim seconds per real second. Then the issue's command as a user types it,
``racecar-hw sim --scenario figure8 --speed max --duration 60`` (off the network, as ``--speed
max`` runs; with ``--network``, every interface turned back on with ``--set``; the plot written,
interpreter start-up included), timed from outside: its target is a tenth of the 60 s simulated,
and its start-up alone (the same with ``--duration 1``) is shown beside it.
With ``--real``, each scenario is also run in real time and the two runs' path lengths compared
(the outcome must not change: within 1 %).

The real seconds are wall time: a busy machine inflates them; the run's own CPU seconds are shown
beside them.

Run: ``python benchmarks/bench_lockstep.py [--real] [--rounds=N] [--cli-only] [--network] [SCENARIO ...]``
(``--cli-only``: figure8 alone, then the command N times); ``run()`` returns the rows for
benchmarks/run_all.py.
"""

from __future__ import annotations

import asyncio
import os
import resource
import subprocess
import sys
import tempfile
import time

from table import print_rows

from racecar_hw.runtime import lockstep
from racecar_hw.sim.fleet import Fleet
from racecar_hw.sim.loopback import OFFLINE_OVERRIDES, Loopback
from racecar_hw.sim.scenario import load_scenario, scenario_names

QUIET = OFFLINE_OVERRIDES
#: ``--network``: the command with every interface turned back on, as it ran before it went offline
NETWORK = tuple(key.replace("=false", "=true") for key in OFFLINE_OVERRIDES)
#: The issue's bar: a lockstep run at max speed takes at most a tenth of its simulated time.
TARGET_SPEEDUP = 10.0


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def scenario_rows(name: str, real: bool) -> list[dict]:
    cpu = _cpu_s()
    scenario = load_scenario(name)
    runner = (Fleet(scenario, overrides=QUIET) if scenario.cars
              else Loopback(scenario, overrides=QUIET, lockstep=True))
    report = lockstep.run(runner.run()).report
    cpu = _cpu_s() - cpu
    wall = report["clock"]["real_time_s"]
    rows = [{"name": f"{name}: lockstep run", "value": wall, "unit": "s", "target": None},
            {"name": f"{name}: lockstep CPU", "value": round(cpu, 2), "unit": "s", "target": None},
            {"name": f"{name}: speed-up", "value": round(report["sim_time_s"] / wall, 1),
             "unit": "x", "target": TARGET_SPEEDUP, "higher_is_better": True}]
    if real and not scenario.cars:  # (several cars run in lockstep only)
        timed = Loopback(load_scenario(name), overrides=QUIET)
        slow = asyncio.run(timed.run()).report
        differ = abs(report["distance_m"] - slow["distance_m"]) / max(slow["distance_m"], 1e-9)
        rows.append({"name": f"{name}: path length vs real time", "value": round(100 * differ, 2),
                     "unit": "%", "target": 1.0})
        rows.append({"name": f"{name}: collided (lockstep / real time)",
                     "value": f"{report['collided']}/{slow['collided']}", "unit": "", "target": None})
    return rows


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def cli_seconds(duration_s: float, network: bool = False) -> tuple[float, float]:
    """Wall seconds of ``racecar-hw sim --scenario figure8 --speed max --duration D``, and the CPU
    seconds of it and its plot worker.

    As a user's Python runs it: with the byte-code cache (``__pycache__``) written, so
    ``PYTHONDONTWRITEBYTECODE`` (set in some development shells) is dropped for it; without the
    cache every run compiles the project's modules again (about 0.3 s here).
    """
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with tempfile.TemporaryDirectory() as out:
        cpu = _children_cpu_s()
        started = time.perf_counter()
        subprocess.run([sys.executable, "-m", "racecar_hw.cli", "sim", "--scenario", "figure8",
                        "--speed", "max", "--duration", str(duration_s), "--no-status", "--out", out,
                        *(arg for key in (NETWORK if network else ()) for arg in ("--set", key))],
                       check=True, capture_output=True, env=env)
        return time.perf_counter() - started, _children_cpu_s() - cpu


def run(names: list[str] | None = None, real: bool = False, rounds: int = 1,
        network: bool = False) -> list[dict]:
    rows: list[dict] = []
    for name in names or scenario_names():
        rows += scenario_rows(name, real)
    cli_seconds(1.0, network)  # writes the byte-code cache, as a user's first run does
    for k in range(rounds):
        load = os.getloadavg()[0]
        (full, full_cpu), (startup, startup_cpu) = cli_seconds(60.0, network), cli_seconds(1.0, network)
        tag = f" (round {k + 1}, load {load:.1f})" if rounds > 1 else f" (load {load:.1f})"
        tag += ", every interface on" if network else ""
        rows.append({"name": "CLI figure8 --speed max --duration 60" + tag, "value": round(full, 2),
                     "unit": "s", "target": 6.0})
        rows.append({"name": "... its CPU (sim and plot worker)", "value": round(full_cpu, 2),
                     "unit": "s", "target": None})
        rows.append({"name": "CLI start-up and report (--duration 1)", "value": round(startup, 2),
                     "unit": "s", "target": None})
        rows.append({"name": "... its CPU", "value": round(startup_cpu, 2), "unit": "s", "target": None})
    return rows


def main(argv: list[str]) -> int:
    real = "--real" in argv
    cli_only = "--cli-only" in argv
    network = "--network" in argv
    rounds = next((int(a.split("=", 1)[1]) for a in argv if a.startswith("--rounds=")), 1)
    names = [a for a in argv if not a.startswith("--")]
    print_rows(run(names or None, real, rounds, network) if not cli_only
               else run(["figure8"], False, rounds, network))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
