"""``racecar-hw calibrate --sim`` as a user runs it: the command line, the real daemon on the fake
hardware, a simulated car whose true gains differ from the config (scenario ``miscalibrated``).
It must find them, write them, and then a figure-8 must end where odometry says; and it must stop
the car and say why when the operator lets go, the safety controller steps in or the wall is not
where it should be.

The runs are in lockstep (``--speed max``: the daemon and the simulated car on the simulation's
clock, in this process), so what is checked is the procedure against the simulated world, never
the scheduling of a loaded machine; ``racecar-hw sim`` in real time is tested in
tests/test_sim_scenarios.py and tests/test_sim_cli.py.
"""

from __future__ import annotations

import json
import re
import shutil

import pytest
from conftest import set_args
from lockstep_sim import OFFLINE, shares_run, shipped_run
from zenoh_util import ROOT

from racecar_hw.cli import main

#: lockstep in this process, interfaces off, or pure computation: may run beside an alone test
pytestmark = pytest.mark.quiet

VALUE = re.compile(r"^(\w+): (\S+) \(true: (\S+)\)", re.MULTILINE)


def _calibrate(capsys, *args: str) -> tuple[int, str, str]:
    """``racecar-hw calibrate --sim --speed max ARGS``: its exit code, standard output and error."""
    capsys.readouterr()
    code = main(["calibrate", "--sim", "--speed", "max", *args, *set_args(*OFFLINE)])
    out, err = capsys.readouterr()
    return code, out, err


def _figure8(capsys, tmp_path, config) -> dict:
    out = tmp_path / f"fig8-{config.stem}"
    code = main(["sim", "--scenario", "miscalibrated-figure8", "--speed", "max", "--config", str(config),
                 "--no-status", "--no-plot", "--out", str(out), "--report", str(out / "report.json"),
                 *set_args(*OFFLINE)])
    assert code == 0, capsys.readouterr().err[-3000:]
    return json.loads((out / "report.json").read_text())


@pytest.mark.slow
@shares_run("miscalibrated-figure8")
def test_calibrate_finds_the_miscalibrated_cars_gains_and_odometry_closes_after(tmp_path, capsys):
    config = tmp_path / "car.yaml"
    shutil.copy(ROOT / "config" / "sim.yaml", config)
    shipped = config.read_text()
    code, stdout, stderr = _calibrate(capsys, "--config", str(config), "--write", str(config))
    assert code == 0, stdout[-3000:] + stderr[-3000:]
    found = {name: (float(a), float(b)) for name, a, b in VALUE.findall(stdout)}
    gain, offset, steer = (found[k] for k in ("speed_to_erpm_gain", "steering_angle_to_servo_offset",
                                              "steering_angle_to_servo_gain"))
    assert gain[0] == pytest.approx(gain[1], rel=0.02)
    # within its error bar (±0.0002): fitted against the unrounded servo positions it was 0.0005 off
    assert offset[0] == pytest.approx(offset[1], abs=0.00025)
    assert steer[0] == pytest.approx(steer[1], rel=0.03)
    # written into the file, its comments kept, and the diff shown
    written = config.read_text()
    assert "speed_to_erpm_gain" in written and written.startswith(shipped.splitlines()[0])
    assert f"+++ {config}" in stdout
    # before: the shipped config on the same car (the scenario as shipped: its shared lockstep run,
    # tests/lockstep_sim.py); after: the calibrated one on the command line (two figure-8s, ~25 m)
    before = shipped_run("miscalibrated-figure8")[0]
    after = _figure8(capsys, tmp_path, config)
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
def test_calibrate_stops_the_car_and_says_why(args, why, capsys):
    code, stdout, stderr = _calibrate(capsys, *args)
    assert code == 1, stdout[-2000:] + stderr[-2000:]
    assert why in stderr, stderr[-2000:]
    assert "Traceback" not in stderr


@pytest.mark.parametrize(("key", "why", "amount"), [
    ("vesc.invert_motor", r"the car drove away from the wall when told to drive toward it \((\S+) m\)", 0.1),
    ("vesc.invert_servo", r"the car turned ([-+]\d+) deg off its heading", 6),
])
def test_a_car_going_the_other_way_stops_at_once_naming_the_key(key, why, amount, capsys):
    """The config's flag wrong for the car (set in the config, not on the simulated car): the motor
    backs it away from the wall it was told to approach, or the heading hold steers it further off.
    Stopped within 5 cm or 5 degrees, not metres later with a wall "6 cm from flat"."""
    flag = key.removeprefix("vesc.")
    code, stdout, stderr = _calibrate(capsys, "--set", f"{key}=true", "--scenario-set", f"car.{flag}=false")
    assert code == 1, stdout[-2000:] + stderr[-2000:]
    assert "Traceback" not in stderr
    line = stderr.strip().splitlines()[-1]
    m = re.search(why, line)
    assert m and f"check {key}" in line, line
    assert abs(float(m.group(1))) <= amount
    assert "ERPM gain" not in stdout  # on the first leg


def test_a_car_wired_backwards_with_a_mirrored_servo_calibrates(capsys):
    """A motor wired backwards and a mirrored servo, configured so (``invert_motor``,
    ``invert_servo``): the tachometer counts down going forward, which the ERPM fit once took for a
    wall that did not move ("is the wall flat and straight ahead?"). The gains are found, the ERPM
    gain as the magnitude the config states and the servo gains as the mirrored config states them."""
    code, stdout, stderr = _calibrate(capsys, "--set", "vesc.invert_motor=true",
                                      "--set", "vesc.invert_servo=true")
    assert code == 0, stdout[-3000:] + stderr[-3000:]
    found = {name: (float(a), float(b)) for name, a, b in VALUE.findall(stdout)}
    gain, offset, steer = (found[k] for k in ("speed_to_erpm_gain", "steering_angle_to_servo_offset",
                                              "steering_angle_to_servo_gain"))
    assert gain[0] == pytest.approx(gain[1], rel=0.02) and gain[1] > 0
    assert offset[0] == pytest.approx(offset[1], abs=0.00025)
    assert steer[0] == pytest.approx(steer[1], rel=0.03) and steer[1] > 0  # the servo's, mirrored
    snippet = dict(re.findall(r"^  (\w+): (\S+)$", stdout.split("config snippet:")[1], re.MULTILINE))
    assert float(snippet["speed_to_erpm_gain"]) == gain[0]
    assert float(snippet["steering_angle_to_servo_gain"]) == -steer[0]  # as the config with invert_servo


@pytest.mark.parametrize("how", ["read-only", "no room for the scratch file"])
def test_write_to_a_file_that_cannot_be_replaced_is_refused_before_the_car_moves(how, tmp_path, capsys):
    config = tmp_path / "car.yaml"
    shutil.copy(ROOT / "config" / "sim.yaml", config)
    shipped = config.read_text()
    if how == "read-only":
        config.chmod(0o444)
    else:
        (tmp_path / ".car.yaml.calibrate-check").mkdir()  # stops root too, as a read-only directory would not
    code, stdout, stderr = _calibrate(capsys, "--write", str(config))
    assert code == 1
    assert stderr.startswith(f"racecar-hw calibrate: --write: {config}: ") and stderr.count("\n") == 1, stderr
    assert "standing still" not in stdout  # the car never moved
    assert config.read_text() == shipped


def test_speed_is_for_the_simulated_car_only(capsys):
    assert main(["calibrate", "--speed", "max", "--yes"]) == 1
    assert capsys.readouterr().err == ("racecar-hw calibrate: --speed: the simulation's clock is for --sim; "
                                       "a real car runs in real time\n")


def test_an_imu_message_without_rates_is_not_a_rate_of_zero():
    """The driver publishes a reply without the gyro with its angular velocity "not provided"
    (covariance element 0 at -1, the rates zeros): the procedure must not take it as standing still."""
    import numpy as np

    from racecar_hw.base.bus import Bus
    from racecar_hw.base.messages import Imu, Vector3
    from racecar_hw.base.topics import TOPIC_IMU
    from racecar_hw.sources.calibration import CalibrationParams, CalibrationProcedure, CarWatch

    bus = Bus()
    proc = CalibrationProcedure(bus, CalibrationParams(), CarWatch(lambda: True, lambda: None, lambda: None))
    not_provided = np.zeros(9)
    not_provided[0] = -1.0
    bus.publish(TOPIC_IMU, Imu(angular_velocity_covariance=not_provided))
    assert proc._s.imu_ns == 0
    bus.publish(TOPIC_IMU, Imu(angular_velocity=Vector3(0.0, 0.0, 0.25)))
    assert proc._s.imu_ns != 0 and proc._s.gyro_z == 0.25
    proc.close()
