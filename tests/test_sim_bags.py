"""Record a figure-8 in the loopback simulation, then follow the bag forwards and backwards.

Everything real: the daemon records through its recorder while the figure-8 drives the teleop
input; the follower reads the bag back and drives nav_0 through the mux and safety controller.
"""

from __future__ import annotations

import asyncio
import json
import math

from conftest import NO_ZENOH

from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.scenario import load_scenario

TELEOP = "/vesc/low_level/ackermann_cmd_mux/input/teleop"


#: On a loaded machine the whole process, fake lidar included, can be held up for tens of
#: milliseconds; a scan then ages past the default 0.1 s timeout and the safety controller rightly
#: stops the car, at different moments in each run. Retracing is what this file tests (staleness is
#: tested in test_safety_*), so its runs allow scans to be half a second old.
TOLERATE_STALLS = "safety.scan_timeout_s=0.5"


def _run(scenario_overrides: list[str], overrides: list[str] = ()) -> dict:
    scenario = load_scenario("figure8", scenario_overrides)
    loopback = Loopback(scenario, overrides=[TOLERATE_STALLS, NO_ZENOH, *overrides])
    report = asyncio.run(loopback.run()).report
    print(json.dumps({k: report.get(k) for k in ("final_pose", "distance_m", "collided", "max_speed_mps",
                                                  "safety_interventions_by_reason", "control")}))
    return report


def _pose(report: dict) -> tuple[float, float, float]:
    p = report["final_pose"]
    return p["x"], p["y"], p["yaw"]


def test_recorded_figure8_is_retraced_forwards_and_backwards(tmp_path):
    bags = tmp_path / "bags"
    recorded = _run(["drivers.0.input=teleop"],
                    ["recorder.enabled=true", f"recorder.path={bags}", "recorder.name=fig8",
                     f"recorder.topics=[{TELEOP}, /odom, /tf_static]"])
    bag = bags / "fig8"  # one rosbag2 bag (a split recording would add files to it)
    assert (bag / "metadata.yaml").exists(), list(bags.rglob("*"))
    end = _pose(recorded)
    assert not recorded["collided"]

    # The bag's own timing: a tick the figure-8 driver skipped while the machine was held up
    # leaves a gap in the bag, which a fixed-rate replay would close up (and so cut the path short).
    follow = {"type": "follow", "input": "nav_0", "bag": str(bag), "topic": TELEOP,
              "use_timestamps": True}
    forward = _run([f"drivers={json.dumps([follow])}"])
    fx, fy, fyaw = _pose(forward)
    assert math.hypot(fx - end[0], fy - end[1]) < 0.3, (end, _pose(forward))
    assert not forward["collided"]

    # Backwards from where the forward run ended, with the car's default reverse cap (0.5 m/s, for
    # a lidar that cannot see behind): the recorded 1 m/s is too fast in reverse, so the follower
    # halves every speed and doubles the timing, and the path is still retraced (it takes twice as
    # long: the run is given the time).
    back = dict(follow, reverse=True)
    backward = _run([f"drivers={json.dumps([back])}", f"start=[{fx}, {fy}, {fyaw}]", "duration_s=28"])
    bx, by, _ = _pose(backward)
    assert backward["max_speed_mps"] <= 0.55  # within the reverse cap all the way
    assert math.hypot(bx, by) < 0.5, _pose(backward)
    assert not backward["collided"]
