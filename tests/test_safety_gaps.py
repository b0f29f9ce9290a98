"""A car drives through a gap it fits, with the obstacle memory on (the shipped config), in
lockstep: the memory once kept a remembered box corner (its cell's centre, 3.5 cm nearer than the
return) inside the swept corridor, and the car stopped in front of the gap for good, although the
lidar saw the way clear. (A noisy return remembered inside the corridor is the same mechanism:
tests/test_safety_memory.py shows it replaced by the next scan's returns; a whole run with range
noise passes or stops by the noise's draw beside the 5 cm margin, so it is no test.)"""

from __future__ import annotations

import pytest
from lockstep_sim import run_lockstep

pytestmark = pytest.mark.quiet  # lockstep, interfaces off

#: Boxes either side of the car's path, 0.6 m long; a 0.30 m wide car (0.40 m swept with its
#: 0.05 m margins) passes a gap of 0.44-0.46 m with 2-3 cm to spare beyond the margins.
GAP = """
map: room
start: {start}
duration_s: 8.0
world: {{noise_std_m: {noise}}}
drivers:
  - {{type: script, input: nav_0, steps: {steps}}}
obstacles:
  - {{name: left, shape: box, size_m: [0.6, 1.0], yaw_rad: {yaw}, at: {left}}}
  - {{name: right, shape: box, size_m: [0.6, 1.0], yaw_rad: {yaw}, at: {right}}}
"""


def test_the_car_drives_through_a_gap_it_fits(tmp_path):
    """Diagonal to the memory's grid after a gentle turn, no range noise: the rounding alone."""
    path = tmp_path / "gap.yaml"
    path.write_text(GAP.format(start="[-2.0, -2.0, 0.0]", steps="[[0.0, 1.5, 0.15], [1.0, 1.5, 0.0]]",
                               yaw=0.672686, left="[0.8034, 0.6922]", right="[1.7006, -0.4341]", noise=0.0))
    result, loopback = run_lockstep(str(path))
    report = result.report
    assert not report["collided"], report
    assert loopback.world is not None
    x, y = loopback.world.pose[0], loopback.world.pose[1]
    assert x > 1.6 and y > 0.5, (x, y, report["safety_interventions_by_reason"])  # past the gap
