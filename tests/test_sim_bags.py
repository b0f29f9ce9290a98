"""Record a figure-8 in the loopback simulation, then follow the bag forwards and backwards.

Everything real: the daemon records through its recorder while the figure-8 drives the teleop
input; the follower reads the bag back and drives nav_0 through the mux and safety controller.
The recording is made in real time (over a pty and TCP, on a machine that holds the process up
now and then: the gaps a loaded machine leaves in a bag); the replays run in lockstep
(tests/lockstep_sim.py), as fast as the machine allows and never held up.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator

import pytest
from conftest import QUIET_NET, ahead_here, ahead_of_ordinary_load
from lockstep_sim import run_lockstep

from racecar_hw.bags.follow import holes, load_commands
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.scenario import load_scenario

TELEOP = "/vesc/low_level/ackermann_cmd_mux/input/teleop"


#: On a loaded machine the whole process, fake lidar included, can be held up for tens of
#: milliseconds; a scan then ages past the default 0.1 s timeout and the safety controller rightly
#: stops the car, at different moments in each run. Retracing is what this file tests (staleness is
#: tested in test_safety_*), so its real-time recording allows scans to be half a second old (the
#: replays, in lockstep, keep the default timeout: no scan is ever late there).
TOLERATE_STALLS = "safety.scan_timeout_s=0.5"


#: Freezes this process (SIGSTOP) for ``argv[2]`` s every ``argv[3]`` s until its stdin closes, and
#: always lets it go on (SIGCONT) before it looks again.
FREEZER = """
import os, select, signal, sys, time
pid, hold, every = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
while not select.select([sys.stdin], [], [], every)[0]:
    os.kill(pid, signal.SIGSTOP)
    time.sleep(hold)
    os.kill(pid, signal.SIGCONT)
"""


@contextlib.contextmanager
def held_up(hold_s: float = 0.13, every_s: float = 0.7) -> Iterator[None]:
    """The whole process, fake devices and world included, held up now and then, as a loaded
    machine holds it up (the world keeps real time). The figure-8 driver then skips ticks, and
    its recording has gaps of 0.13 s and more: what made a backwards replay fall short."""
    # ahead of the other workers' load, so that each hold lasts ``hold_s``, not as long as a
    # loaded machine makes the freezer wait to end it
    freezer = subprocess.Popen([sys.executable, "-c", FREEZER, str(os.getpid()), str(hold_s), str(every_s)],
                               stdin=subprocess.PIPE, preexec_fn=ahead_of_ordinary_load)
    try:
        yield
    finally:
        assert freezer.stdin is not None
        freezer.stdin.close()  # it ends at its next look, after any freeze it began
        freezer.wait(timeout=30)


def _run(scenario_overrides: list[str], overrides: list[str] = (), *,
         until_replay_ends: bool = False) -> dict:
    """The figure-8 scenario with ``scenario_overrides``, in real time."""
    scenario = load_scenario("figure8", scenario_overrides)
    loopback = Loopback(scenario, overrides=[TOLERATE_STALLS, *QUIET_NET, *overrides],
                        until_replay_ends=until_replay_ends)
    report = asyncio.run(loopback.run()).report
    return _shown(report)


def _replay(scenario_overrides: list[str]) -> dict:
    """The figure-8 scenario with ``scenario_overrides`` in lockstep, for as long as its replay."""
    report = run_lockstep("figure8", *scenario_overrides, until_replay_ends=True)[0].report
    assert report["control"]["missed_ticks"] == 0 and report["safety_interventions"] == 0, report
    return _shown(report)


def _shown(report: dict) -> dict:
    print(json.dumps({k: report.get(k) for k in ("final_pose", "distance_m", "collided", "max_speed_mps",
                                                  "safety_interventions_by_reason", "control",
                                                  "duration_s", "sim_time_s", "follow")}))
    return report


def _pose(report: dict) -> tuple[float, float, float]:
    p = report["final_pose"]
    return p["x"], p["y"], p["yaw"]


@pytest.mark.slow
def test_recorded_figure8_is_retraced_forwards_and_backwards(tmp_path):
    bags = tmp_path / "bags"
    # a recording with gaps, as a loaded machine makes them (the replays are not held up); ahead of
    # the other workers, so that the holds are its only gaps (a hole the mux's timeout could not
    # bridge stops the replayed car where the frozen recording's car drove on)
    with ahead_here(), held_up():
        recorded = _run(["drivers.0.input=teleop"],
                        ["recorder.enabled=true", f"recorder.path={bags}", "recorder.name=fig8",
                         f"recorder.topics=[{TELEOP}, /odom, /tf_static]"])
    bag = bags / "fig8"  # one rosbag2 bag (a split recording would add files to it)
    assert (bag / "metadata.yaml").exists(), list(bags.rglob("*"))
    gaps = holes(load_commands(bag, TELEOP), factor=2.0)  # over 0.1 s, twice the 20 Hz spacing
    assert len(gaps) >= 10 and max(h.gap_s for h in gaps) >= 0.13, gaps  # the recording has its gaps
    end = _pose(recorded)
    assert not recorded["collided"]

    # The bag's own timing: a tick the figure-8 driver skipped while the machine was held up
    # leaves a gap in the bag, which a fixed-rate replay would close up (and so cut the path short).
    # Each run lasts as long as its replay (and a settle time), also when a loaded machine makes
    # the replay end late: a fixed duration could end it before the last command.
    follow = {"type": "follow", "input": "nav_0", "bag": str(bag), "topic": TELEOP,
              "use_timestamps": True}
    forward = _replay([f"drivers={json.dumps([follow])}"])
    fx, fy, fyaw = _pose(forward)
    assert forward["follow"][0]["complete"]
    assert math.hypot(fx - end[0], fy - end[1]) < 0.3, (end, _pose(forward))
    assert not forward["collided"]

    # Backwards from where the forward run ended, with the car's default reverse cap (0.5 m/s, for
    # a lidar that cannot see behind): the recorded 1 m/s is too fast in reverse, so the follower
    # halves every speed and doubles the timing, and the path is still retraced (it takes twice as
    # long). The follower repeats each command halfway to the next, so a gap in the recording that
    # the mux's 0.2 s timeout bridged (0.15 s) is bridged in the replay too instead of stopping the
    # car (0.3 s): without the repeats this run ended 1.1 to 1.5 m from the start.
    back = dict(follow, reverse=True)
    backward = _replay([f"drivers={json.dumps([back])}", f"start=[{fx}, {fy}, {fyaw}]"])
    bx, by, _ = _pose(backward)
    (replay,) = backward["follow"]
    assert replay["complete"] and replay["speed_scale"] == 0.5
    assert backward["max_speed_mps"] <= 0.55  # within the reverse cap all the way
    assert math.hypot(bx, by) < 0.5, _pose(backward)
    assert not backward["collided"]
