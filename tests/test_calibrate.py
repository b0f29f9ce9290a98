"""``racecar-hw calibrate --sim`` as a user runs it: a real process, the real daemon on the fake
hardware, a simulated car whose true gains differ from the config (scenario ``miscalibrated``).
It must find them, write them, and then a figure-8 must end where odometry says; and it must stop
the car and say why when the operator lets go, the safety controller steps in or the wall is not
where it should be."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import pytest
from conftest import QUIET_NET, ahead_of_other_load, set_args
from zenoh_util import ROOT

VALUE = re.compile(r"^(\w+): (\S+) \(true: (\S+)\)", re.MULTILINE)


def _calibrate(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "racecar_hw.cli", "calibrate", "--sim", *args,
                           *set_args(*QUIET_NET)], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT, preexec_fn=ahead_of_other_load)


def _figure8(tmp_path, config) -> dict:
    out = tmp_path / f"fig8-{config.stem}"
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "sim",
                           "--scenario", "miscalibrated-figure8",
                           "--config", str(config), "--no-status", "--out", str(out),
                           "--report", str(out / "report.json"), *set_args(*QUIET_NET)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT,
                          preexec_fn=ahead_of_other_load)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((out / "report.json").read_text())


def test_calibrate_finds_the_miscalibrated_cars_gains_and_odometry_closes_after(tmp_path):
    config = tmp_path / "car.yaml"
    shutil.copy(ROOT / "config" / "sim.yaml", config)
    shipped = config.read_text()
    proc = _calibrate("--config", str(config), "--write", str(config))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    found = {name: (float(a), float(b)) for name, a, b in VALUE.findall(proc.stdout)}
    gain, offset, steer = (found[k] for k in ("speed_to_erpm_gain", "steering_angle_to_servo_offset",
                                              "steering_angle_to_servo_gain"))
    assert gain[0] == pytest.approx(gain[1], rel=0.02)
    assert offset[0] == pytest.approx(offset[1], abs=0.005)
    assert steer[0] == pytest.approx(steer[1], rel=0.03)
    # written into the file, its comments kept, and the diff shown
    written = config.read_text()
    assert "speed_to_erpm_gain" in written and written.startswith(shipped.splitlines()[0])
    assert f"+++ {config}" in proc.stdout
    # before: the shipped config on the same car; after: the calibrated one (two figure-8s, ~25 m)
    before = _figure8(tmp_path, ROOT / "config" / "sim.yaml")
    after = _figure8(tmp_path, config)
    assert not before["collided"] and not after["collided"]
    assert after["distance_m"] > 20.0
    assert after["odometry_error_m"] < 0.1, (before["odometry_error_m"], after["odometry_error_m"])
    assert before["odometry_error_m"] > 3 * after["odometry_error_m"]


@pytest.mark.parametrize(("args", "why"), [
    (("--wall-distance", "5.0"), "the wall is not where it should be: expected 5.00 m"),
    (("--scenario-set", "faults=[{at_s: 5.5, action: disarm}]"), "the operator let go"),
    (("--scenario-set", "faults=[{at_s: 5.5, action: obstacle_ahead, distance_m: 0.25}]"),
     "the safety controller intervened"),
])
def test_calibrate_stops_the_car_and_says_why(args, why):
    proc = _calibrate(*args, timeout=300)
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert why in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
