"""Scenarios in lockstep: the real daemon and the fakes on virtual time, through in-memory links.

Two runs of a scenario with the same seed must agree exactly (apart from the report's
run-specific keys: paths, ports, real seconds), on an idle machine or beside a process that burns
a core; and a lockstep run must drive as a real-time one does.

The first of the two runs is the shipped scenario's shared run (tests/lockstep_sim.py,
:func:`~lockstep_sim.shipped_run`: the one the hazard and scenario tests check), the second
one this test's own, beside the burner.
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest
from conftest import ahead_of_other_load, reaped
from lockstep_sim import OFFLINE, shares_run, shipped_run
from zenoh_util import free_port

from racecar_hw.runtime import lockstep
from racecar_hw.sim.fleet import Fleet
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.report import RUN_SPECIFIC, comparable
from racecar_hw.sim.scenario import load_scenario, scenario_names

#: The burner spins at the lowest priority (SCHED_IDLE, and niceness 19 where that policy is not
#: to be had): it takes every cycle the machine has spare and is preempted by any other runnable
#: thread, the lockstep run's included, but does not take a core from the other pytest-xdist
#: workers, nor from an alone test's niceness-19 flooder beside it (docs/tests.md, "The CPU burner").
BURNER_NICE = 19
#: It spins until its parent (the test's process) is gone: a worker killed mid-test leaves none behind.
BURNER = (f"import os; os.nice({BURNER_NICE})\n"
          "try:\n    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\n"
          "except (OSError, AttributeError):\n    pass\n"
          "parent = os.getppid()\nwhile os.getppid() == parent: pass")


@contextmanager
def cpu_burners(n: int = 1) -> Iterator[list[subprocess.Popen]]:
    """``n`` processes that spin a core each, at the lowest priority (:data:`BURNER`)."""
    procs = [subprocess.Popen([sys.executable, "-c", BURNER]) for _ in range(n)]
    try:
        yield procs
    finally:
        for proc in procs:
            with reaped(proc):
                proc.kill()


def run(name: str, overrides: tuple[str, ...] = (), **kw) -> tuple[dict, list]:
    """One lockstep run of the shipped scenario ``name``: its report and its trajectory (with
    several cars, racecar_hw.sim.fleet: every car's, one after the other)."""
    scenario = load_scenario(name)
    if scenario.cars:
        fleet = Fleet(scenario, overrides=[*OFFLINE, *overrides], **kw)
        report = lockstep.run(fleet.run()).report
        return report, [s for car in fleet.cars.values() if car.world for s in car.world.samples]
    loopback = Loopback(scenario, overrides=[*OFFLINE, *overrides], lockstep=True, **kw)
    result = lockstep.run(loopback.run())
    assert loopback.world is not None
    return result.report, list(loopback.world.samples)


#: The scenarios whose two runs take over 10 s on a 2-core machine (long simulated times, two
#: daemons): ``slow``, so that they start first (tests/conftest.py), and with a longer time limit
#: than pytest-timeout's 300 s: on a machine shared with other test runs the miscalibrated car's
#: two runs (120 s of standing then, 20 s now) took 310 s, and pytest-timeout cannot end a lockstep
#: run (docs/tests.md): its exception ends one of the run's tasks, and the run goes on with a lidar
#: that stopped scanning.
LONG = {"miscalibrated-figure8", "two-cars"}
LONG_TIMEOUT_S = 1200


@pytest.mark.parametrize("name", [
    pytest.param(name, marks=[shares_run(name), *([pytest.mark.slow, pytest.mark.timeout(LONG_TIMEOUT_S)]
                                                  if name in LONG else [])])
    for name in scenario_names()])
def test_two_lockstep_runs_agree_exactly_even_beside_cpu_burners(name):
    first, first_path = shipped_run(name)  # the shared run: lockstep_sim.run_lockstep's, as run() does
    with cpu_burners() as burners:
        second, second_path = run(name)
        assert all(proc.poll() is None for proc in burners)  # it burned all along
    assert first["clock"]["mode"] == "lockstep" and first["clock"]["speed"] == "max"
    assert comparable(first) == comparable(second)
    assert first_path == second_path
    assert len(first_path) > 100  # the world stepped all along


def test_the_run_specific_keys_are_all_that_is_left_out():
    report = {"scenario": "x", "trajectory_csv": "a", "plot_png": "b", "bags": [], "live": {},
              "clock": {"mode": "lockstep", "speed": "max", "real_time_s": 1.5}}
    assert comparable(report) == {"scenario": "x", "clock": {"mode": "lockstep", "speed": "max"}}
    assert len(RUN_SPECIFIC) == 5


def test_recorded_bags_of_two_lockstep_runs_hold_the_same_messages(tmp_path):
    from rosbags.highlevel import AnyReader  # noqa: PLC0415 - the test extra

    def messages(folder: Path) -> list[tuple[str, int, bytes]]:
        bags = sorted(p for p in folder.iterdir() if p.is_dir())
        assert len(bags) == 1
        with AnyReader([bags[0]]) as reader:
            return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]

    got = []
    for k in range(2):
        out = tmp_path / f"bags{k}"
        report, _ = run("obstacle", ("recorder.enabled=true", f"recorder.path={out}"))
        assert report["bags"]
        got.append(messages(out))
    assert len(got[0]) > 1000
    assert {topic for topic, _, _ in got[0]} >= {"/scan", "/odom", "/tf"}
    assert got[0] == got[1]  # topics, receive times (sim time) and serialized bytes


@pytest.mark.alone  # its real-time run is on the machine's pace (docs/tests.md, "Alone")
def test_the_cli_at_max_speed_drives_as_real_time_does(tmp_path):
    """``racecar-hw sim --scenario figure8 --speed max`` as typed (off the network, as that speed
    runs) against the same scenario in real time over ptys and TCP with every interface on as
    shipped: the same path length within 1 %, no collision."""
    # The two runs are independent (their own outputs; only the real-time one listens), so they run at once:
    # the lockstep one takes the CPU the real-time one, ahead of it, leaves over while it waits on
    # the wall clock (the real-time run lasts the scenario's duration, whatever runs beside it).
    domain = random.randrange(100, 230)
    # the real-time run on free ports and a DDS domain of its own: never a user's sim or another test's
    own = ["--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]', "--set", "foxglove.port=0",
           "--set", "web.port=0", "--set", f"dds.domain_id={domain}"]
    reports, errors = {}, {}
    with ExitStack() as running:
        procs = {}
        for mode, args in (("real", own), ("max", ["--speed", "max"])):
            cmd = [sys.executable, "-m", "racecar_hw.cli", "sim", "--scenario", "figure8", "--no-status",
                   "--out", str(tmp_path / mode), *args]
            procs[mode] = running.enter_context(reaped(subprocess.Popen(
                cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                preexec_fn=ahead_of_other_load if mode == "real" else None)))
        for mode, proc in procs.items():
            _, errors[mode] = proc.communicate(timeout=300)
            assert proc.returncode == 0, errors[mode]
            reports[mode] = json.loads((tmp_path / mode / "figure8.json").read_text())
    real, fast = reports["real"], reports["max"]
    assert fast["clock"]["mode"] == "lockstep" and real["clock"]["mode"] == "real time"
    assert not real["collided"] and not fast["collided"]
    assert fast["distance_m"] == pytest.approx(real["distance_m"], rel=0.01)
    assert fast["safety_interventions"] == 0
    assert set(real["live"]) == {"foxglove", "web"}  # the live interfaces were on in real time
    assert fast["live"] == {}  # and off at --speed max, which says so
    assert "--speed max runs off the network" in errors["max"]
