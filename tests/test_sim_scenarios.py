"""Every shipped scenario on the fake-hardware loopback, checked for its physical outcome.

The real daemon runs against the fake VESC and fake lidar, moved by the world simulation, in
lockstep (:mod:`racecar_hw.runtime.lockstep`): the same bytes through in-memory links on the
simulation's virtual clock, as fast as the machine allows, so a loaded machine's hold-ups (late
scans, missed control ticks) never enter the outcome and the expectations are exact where a
real-time run needed bands. A smaller set runs in real time over real ptys and TCP
(``realtime``). Assertions are about where the car went, whether it stopped and whether it
touched anything, read from the report and the trajectory.
"""

from __future__ import annotations

import asyncio
import gc
import json
import math
import sys

import pytest
from conftest import QUIET_NET, ahead_here, set_args
from lockstep_sim import run_lockstep, shares_run, shipped_run, trajectory

from racecar_hw.cli import main
from racecar_hw.sim.loopback import Loopback, SimResult
from racecar_hw.sim.scenario import load_scenario, scenario_names
from racecar_hw.sim.trajectory import read_csv

#: A real-time run of a car that drives up to something and stops ends once it has stood this
#: long (world seconds), not at the scenario's duration: the wall clock it waits is CI's time
#: (docs/tests.md, "How the real-time tests keep their time down"). The lockstep runs of the
#: same scenarios run their whole duration.
STOOD_S = 1.5
STOOD = "stood still"


def end_when_stood(loopback: Loopback) -> None:
    """``setup`` for a real-time run: once the car has driven (over 0.5 m/s) and then stood
    (under 0.01 m/s) for :data:`STOOD_S`, end the run (``stop_reason`` :data:`STOOD`)."""
    world, daemon = loopback.world, loopback.daemon
    assert world is not None and daemon is not None

    async def watch() -> None:
        drove, since = False, None
        while True:
            await asyncio.sleep(0.05)
            drove = drove or abs(world.speed) > 0.5
            if not drove or abs(world.speed) >= 0.01:
                since = None
            elif since is None:
                since = world.sim_time
            elif world.sim_time - since >= STOOD_S:
                loopback.request_stop(STOOD)
                return

    daemon.add_task(watch())


def realtime(name: str, tmp_path, *overrides: str, duration_s: float | None = None) -> SimResult:
    """``name`` in real time: the fakes on a thread of their own behind a real pty and TCP; the
    run ends once the car has stood :data:`STOOD_S` after driving (:func:`end_when_stood`)."""
    scenario = load_scenario(name, list(overrides))
    loopback = Loopback(scenario, out_dir=tmp_path, duration_s=duration_s, overrides=[*QUIET_NET],
                        setup=end_when_stood)
    with ahead_here():
        result = asyncio.run(loopback.run())
    # shown with a failure: interventions by reason and missed control ticks tell a loaded
    # machine's hold-ups (stale_scan, missed ticks) from a wrong outcome
    r = result.report
    print(name, json.dumps({k: r.get(k) for k in ("final_pose", "distance_m", "collided",
                                                   "safety_interventions_by_reason", "interventions",
                                                   "mux_switches", "control", "vesc", "lidar")}))
    return result


def run(name: str, *overrides: str, duration_s: float | None = None) -> tuple[dict, list]:
    """``name`` in lockstep: its report and its trajectory. In lockstep the control loop never
    misses a tick and a scan is never late for the machine's load: only an unplugged lidar makes
    one stale. The shipped scenario as it is (no overrides) is its shared run
    (:func:`lockstep_sim.shipped_run`): a test of it carries ``@shares_run(name)``."""
    if not overrides and duration_s is None:
        r, samples = shipped_run(name)
    else:
        result, loopback = run_lockstep(name, *overrides, duration_s=duration_s)
        r, samples = result.report, trajectory(loopback)
    assert r["control"]["missed_ticks"] == 0, r["control"]
    if not any(a == "lidar_unplug" for _, a in r["faults"]):
        assert "stale_scan" not in r["safety_interventions_by_reason"], r["interventions"]
    return r, samples


def mean_speed(samples, t0: float, t1: float) -> float:
    """Mean speed over [t0, t1] (world time)."""
    window = [s.speed for s in samples if t0 <= s.t <= t1]
    assert window, (t0, t1)
    return sum(window) / len(window)


def fault_time(report: dict, action: str) -> float:
    return next(t for t, a in report["faults"] if a == action)


def test_every_shipped_scenario_is_covered():
    # the two miscalibrated ones are run by tests/test_calibrate.py, track by tests/test_sim_env.py,
    # two-cars by tests/test_sim_fleet.py
    assert set(scenario_names()) == {"figure8", "wall", "corridor", "teleop-override", "lidar-dropout",
                                     "vesc-replug", "obstacle", "reverse-wall", "crossing-person",
                                     "sliding-box", "miscalibrated", "miscalibrated-figure8", "track",
                                     "two-cars"}


@shares_run("figure8")
def test_figure8_returns_to_the_start():
    r, samples = run("figure8")
    assert not r["collided"]
    ys = [s.y for s in samples]
    # one loop to the left (y > 0), one to the right (y < 0), each about 2 x 0.98 m across
    assert max(ys) > 1.6 and min(ys) < -1.6
    assert 11.0 < r["distance_m"] < 13.5
    end = r["final_pose"]
    assert math.hypot(end["x"], end["y"]) < 0.6
    # Open floor never makes the controller brake for an obstacle (and in lockstep no scan is late)
    assert r["safety_interventions"] == 0 and r["safety_interventions_by_reason"] == {}


def test_a_daemon_run_in_process_leaves_the_interpreter_as_it_found_it():
    # the daemon freezes its start-up objects and shortens the GIL switch interval while it runs
    interval = sys.getswitchinterval()
    r, _ = run("wall", duration_s=1.0)
    assert r["lidar"]["scans"] > 0
    assert sys.getswitchinterval() == interval
    assert gc.get_freeze_count() == 0


def test_a_scans_motor_command_is_written_before_its_summaries_are_made():
    # /scan_range and /open_space are diagnostics: they must not sit between a scan and the motor
    written_first: list[bool] = []

    def setup(loopback: Loopback) -> None:
        daemon = loopback.daemon
        assert daemon is not None and daemon.vesc is not None and daemon.lidar is not None
        vesc, lidar = daemon.vesc, daemon.lidar
        daemon.bus.subscribe("/scan_range", lambda msg: written_first.append(
            vesc.last_motor_write_ns >= lidar.frame_arrival_ns))

    _, loopback = run_lockstep("wall", duration_s=1.5, setup=setup)
    assert loopback.daemon is not None
    timed = len(loopback.daemon.stats.scan_to_command_ns)  # scans whose command the scan path wrote
    assert timed > 10 and len(written_first) >= timed
    assert written_first.count(True) == timed


#: The shipped wall scenario's speed (m/s): at it, the head-on run is the scenario's shared run.
WALL_SPEED = 2.0


@pytest.mark.parametrize("speed", [1.0, pytest.param(WALL_SPEED, marks=shares_run("wall")), 3.0, 4.0])
def test_wall_head_on_never_touched_and_stopped_close(speed):
    assert load_scenario("wall").drivers[0].speed_mps == WALL_SPEED
    r, _ = run("wall", *([] if speed == WALL_SPEED else [f"drivers.0.speed_mps={speed}"]))
    check_wall_head_on(r, speed)
    assert r["safety_interventions_by_reason"] == {"obstacle": 1}  # the wall, once, and it held


@pytest.mark.slow
def test_wall_head_on_in_real_time_over_a_pty_and_tcp(tmp_path):
    """The same run on the wall clock: the fake VESC behind a real pty, the fake UST-10LX on a
    loopback TCP port, on a thread of their own beside the daemon's loop."""
    r = realtime("wall", tmp_path, "drivers.0.speed_mps=2.0").report
    check_wall_head_on(r, 2.0)
    assert r["stop_reason"] == STOOD  # it stood at the wall before the scenario's end


def check_wall_head_on(r: dict, speed: float) -> None:
    assert not r["collided"], r["collisions"]
    assert r["min_clearance_m"] > 0.0
    assert r["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
    assert r["final_clearance_m"] <= 1.0
    assert r["max_speed_mps"] > speed * 0.9  # it really drove at that speed before braking
    assert r["safety_interventions"] >= 1


@pytest.mark.slow
def test_wall_with_an_rplidar_a1_on_a_pty(tmp_path):
    # in real time: the lidar's pty and the sweep's timing on the wall clock
    scenario = load_scenario("wall", ["lidar.model=a1", "lidar.transport=pty"])
    loopback = Loopback(scenario, out_dir=tmp_path, setup=end_when_stood,
                        overrides=["safety.scan_timeout_s=0.3", "safety.scan_period_s=0.1", *QUIET_NET])
    with ahead_here():
        r = asyncio.run(loopback.run()).report
    assert r["stop_reason"] == STOOD  # it stood at the wall before the scenario's end
    assert r["lidar"]["model"] == "a1" and 5.0 < r["lidar"]["rate_hz"] < 12.0  # ~10 Hz revolutions
    assert not r["collided"], r["collisions"]
    assert r["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
    assert r["final_clearance_m"] <= 1.0


@pytest.mark.parametrize(("firmware", "written"), [("'6.2'", "6.02"), ("'3.40'", "3.40")])
def test_the_report_writes_the_firmware_as_vesc_info_does(firmware, written):
    """The report wrote "6.2" for the fake that vesc-info and the fake-vesc banner call 6.02."""
    result, loopback = run_lockstep("wall", f"firmware={firmware}", duration_s=0.5)
    assert loopback.vesc is not None and result.report["vesc"]["firmware"] == written


def test_a_usb_hokuyo_is_reached_on_a_pty_even_with_transport_tcp():
    """The URG-04LX has no Ethernet port: the scenario's default transport (tcp) does not make
    the fake listen on one; the daemon opens its serial port as it would /dev/ttyACM0 (in lockstep,
    the in-memory link in the pty's place)."""
    assert load_scenario("wall", ["lidar.model=urg-04lx"]).lidar.transport == "tcp"
    result, loopback = run_lockstep("wall", "lidar.model=urg-04lx",
                                    overrides=["safety.scan_timeout_s=0.3", "safety.scan_period_s=0.1"])
    r = result.report
    assert loopback.lidar.tcp is None and loopback.lidar.tcp_address is None
    assert loopback.config is not None and loopback.config.lidar.tcp is None
    assert loopback.config.lidar.port == loopback.rig.device_path("lidar")
    # 10 Hz scans, from the first one (before it: the start-up, under a tenth of a second)
    assert r["lidar"]["model"] == "urg-04lx" and 9.9 < r["lidar"]["rate_hz"] <= 10.0
    assert not r["collided"], r["collisions"]
    assert r["final_speed_mps"] == pytest.approx(0.0, abs=0.02)


@shares_run("corridor")
def test_corridor_at_3_mps_without_intervention():
    r, _ = run("corridor")
    assert not r["collided"]
    # The corridor's walls never make the controller brake (and in lockstep no scan is late)
    assert r["safety_interventions"] == 0 and r["safety_interventions_by_reason"] == {}
    assert r["distance_m"] > 14.0
    assert r["max_speed_mps"] == pytest.approx(3.0, abs=0.1)
    # straight down the centre line (docs/sim.md: (1.5 - 0.30) / 2 = 0.6 m from each wall): the
    # simulated car and the daemon agree on which servo position is straight
    assert r["min_clearance_m"] == pytest.approx(0.6, abs=0.02)
    assert abs(r["final_pose"]["y"]) < 0.02


@shares_run("obstacle")
def test_obstacle_appearing_ahead_stops_the_car():
    r, _ = run("obstacle")
    assert not r["collided"], r["collisions"]
    assert r["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
    assert r["safety_interventions_by_reason"] == {"obstacle": 1}
    (stop,) = r["interventions"]
    assert stop["object"] == "obstacle 1" and stop["source"] == "scan" and stop["stopped_at_s"] is not None
    assert r["final_clearance_m"] > 0.0


def obstacle_stops(report: dict) -> list[dict]:
    """The report's entries for an obstacle: interventions that started for one, and those that
    became one after starting for a late scan (``continues``)."""
    return [i for i in report["interventions"] if i["reason"] == "obstacle"]


@shares_run("reverse-wall")
def test_reversing_into_a_wall_seen_before_a_u_turn_stops_with_the_memory():
    r, samples = run("reverse-wall")
    assert r["safety_memory"] is True
    assert not r["collided"], r["collisions"]
    assert r["final_pose"]["yaw"] == pytest.approx(0.0, abs=0.15)  # the U-turn was made
    stops = obstacle_stops(r)
    assert stops, r["interventions"]
    stop = stops[-1]
    # the wall is behind the car, outside the lidar's view: the memory stopped it, in one
    # intervention (in lockstep no late scan starts it as a stale_scan)
    assert stops == r["interventions"] and len(stops) == 1 and not stop["continues"]
    assert stop["source"] == "memory"
    # What the memory holds is placed by odometry, which drifts a few % of the distance driven
    # (docs/safety.md; a loaded machine that missed control ticks once placed it 0.16 m off in real
    # time): the remembered point is the wall's face (x = -3.95 m; "map" when within 0.15 m of
    # it) to within that drift, which over the 4 m driven is under 0.1 m
    assert stop["object"] == "map" and abs(stop["obstacle"]["x"] + 3.95) < 0.1, stop
    assert stop["stopped_at_s"] is not None and 0.05 < stop["distance_left_m"] < 0.5
    # it reversed at the cap (the script asks for -0.5 m/s until the end of the run, which the cap
    # alone would let it drive into the wall, as the run without the memory shows), up to the stop
    reversing = [s.speed for s in samples if s.t <= stop["stopped_at_s"] and s.speed < 0.0]
    assert min(reversing) == pytest.approx(-0.5, abs=0.05)
    assert r["final_pose"]["x"] > -3.95 + 0.10  # the rear bumper short of the wall's face


def test_a_stop_that_starts_for_a_late_scan_and_ends_for_a_wall_reports_the_wall():
    # the car waits 0.7 m from the far wall (face at x = 8.0 m) with the lidar unplugged; asked
    # for 2 m/s it is held for stale_scan; once scans are back the wall cuts the command, and the
    # report's entry that continues the intervention says what it stopped for and how far from it
    r, _ = run("wall", "start=[6.85, 0.0, 0.0]", "duration_s=5.0",
               "drivers=[{type: script, input: nav_0, steps: [[0.0, 0.0, 0.0], [1.0, 2.0, 0.0]]}]",
               "faults=[{at_s: 0.2, action: lidar_unplug}, {at_s: 1.5, action: lidar_replug}]")
    assert not r["collided"], r["collisions"]
    assert r["safety_interventions_by_reason"] == {"stale_scan": 1}  # one intervention throughout
    start, stop = r["interventions"]
    assert start["reason"] == "stale_scan" and not start["continues"] and start["source"] is None
    assert 1.0 <= start["t_s"] - r["ready_at_s"] < 1.5 and start["stopping_distance_m"] == 0.0
    assert stop["continues"] and stop["reason"] == "obstacle" and stop["t_s"] == start["ended_at_s"]
    assert stop["t_s"] - r["ready_at_s"] >= 1.5 and stop["ended_at_s"] is None
    assert stop["source"] == "scan" and stop["object"] == "map" and 0.0 < stop["allowed_mps"] < 2.0
    # it crept up to the wall at what the controller allowed, and stopped short of it there
    assert stop["stopped_at_s"] > stop["t_s"] and stop["stopping_distance_m"] > 0.1
    assert 0.1 < stop["distance_left_m"] < 0.5
    assert r["final_pose"]["x"] + 0.45 == pytest.approx(8.0 - stop["distance_left_m"], abs=0.01)


def test_reversing_into_the_same_wall_without_the_memory_collides():
    r, _ = run("reverse-wall", "config.safety.memory.enabled=false")
    assert r["safety_memory"] is False
    assert r["collided"]  # capped at 0.5 m/s, as before the memory: the cap does not see the wall
    assert obstacle_stops(r) == []
    assert r["final_pose"]["yaw"] == pytest.approx(0.0, abs=0.15)


@shares_run("crossing-person")
def test_a_person_crossing_at_1_mps_is_not_hit_at_2_mps():
    r, _ = run("crossing-person")
    assert not r["collided"], r["collisions"]
    assert r["max_speed_mps"] == pytest.approx(2.0, abs=0.05)
    # the car braked for the person (seen by the live scan) and drove on once they had passed
    person = [i for i in obstacle_stops(r) if i["object"] == "person"]
    assert person and person[0]["source"] == "scan"
    assert person == r["interventions"] and person[-1]["ended_at_s"] is not None  # it drove on
    assert r["min_clearance_m"] > 0.1
    assert r["distance_m"] > 4.0


@shares_run("sliding-box")
def test_a_box_sliding_into_the_path_is_not_hit_at_2_mps():
    r, _ = run("sliding-box")
    assert not r["collided"], r["collisions"]
    assert r["max_speed_mps"] == pytest.approx(2.0, abs=0.05)
    box = [i for i in obstacle_stops(r) if i["object"] == "box"]
    assert box and box[0]["source"] == "scan" and box == r["interventions"]
    assert box[-1]["stopped_at_s"] is not None and box[-1]["distance_left_m"] > 0.1
    assert r["final_speed_mps"] == pytest.approx(0.0, abs=0.02)


def test_the_memory_update_comes_after_the_scans_motor_command():
    after_write: list[bool] = []

    def setup(loopback: Loopback) -> None:
        daemon = loopback.daemon
        assert daemon is not None and daemon.vesc is not None and daemon.lidar is not None
        memory = daemon.safety.controller.memory
        assert memory is not None
        vesc, lidar, update = daemon.vesc, daemon.lidar, memory.update

        def checked(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            after_write.append(vesc.last_motor_write_ns >= lidar.frame_arrival_ns)
            return update(*args, **kwargs)

        memory.update = checked  # type: ignore[method-assign]

    # the memory takes every scan in here (by default every other one)
    _, loopback = run_lockstep("wall", "config.safety.memory.update_period_s=0", duration_s=1.5, setup=setup)
    assert loopback.daemon is not None
    timed = len(loopback.daemon.stats.scan_to_command_ns)  # scans whose command the scan path wrote
    assert timed > 10 and len(after_write) >= timed
    assert after_write.count(True) >= timed


@shares_run("teleop-override")
def test_teleop_overrides_navigation_then_hands_back():
    r, samples = run("teleop-override")
    sources = [s for _, s in r["mux_switches"] if s != "idle"]
    assert sources[:3] == ["nav_0", "teleop", "nav_0"]
    teleop_at = next(t for t, s in r["mux_switches"] if s == "teleop")
    # while teleop drives, the car steers right (negative steering) at 0.5 m/s
    mid = [s for s in samples if teleop_at + 0.8 < s.t < teleop_at + 1.8]
    assert mid and all(s.steering < 0 for s in mid)
    assert abs(mean_speed(samples, teleop_at + 0.8, teleop_at + 1.8) - 0.5) < 0.1
    assert not r["collided"]


@shares_run("lidar-dropout")
def test_lidar_unplugged_stops_the_car_and_it_drives_on_when_back():
    r, samples = run("lidar-dropout")
    unplug_at, replug_at = fault_time(r, "lidar_unplug"), fault_time(r, "lidar_replug")
    assert mean_speed(samples, unplug_at - 0.4, unplug_at) > 1.2
    # within a scan timeout plus braking from 1.5 m/s, the car stands still until the lidar is back
    assert max(abs(s.speed) for s in samples if unplug_at + 1.0 <= s.t <= replug_at) < 0.05
    assert r["lidar"]["reconnects"] >= 1
    assert mean_speed(samples, r["sim_time_s"] - 0.8, r["sim_time_s"] - 0.3) > 1.0
    assert not r["collided"]


@shares_run("vesc-replug")
def test_vesc_replug_reconnects_and_drives_on():
    r, samples = run("vesc-replug")
    assert r["vesc"]["reconnects"] >= 1
    unplug_at = fault_time(r, "vesc_unplug")
    assert mean_speed(samples, unplug_at - 0.5, unplug_at) > 0.8
    assert mean_speed(samples, r["sim_time_s"] - 0.8, r["sim_time_s"] - 0.3) > 0.8
    assert not r["collided"]


def test_cli_sim_writes_report_csv_and_plot(tmp_path, capsys):
    # the command in this process (its outputs are the subject; tests/test_sim_cli.py runs it as one)
    report = tmp_path / "out" / "report.json"
    code = main(["sim", "--scenario", "wall", "--duration", "3", "--speed", "max", "--no-status",
                 *set_args(*QUIET_NET), "--report", str(report)])
    assert code == 0, capsys.readouterr().err
    data = json.loads(report.read_text())
    for key in ("scenario", "sim_time_s", "collided", "min_clearance_m", "distance_m", "final_pose",
                "safety_interventions", "mux_switches", "vesc", "lidar", "trajectory_csv"):
        assert key in data
    assert set(data["final_pose"]) == {"x", "y", "yaw"}
    assert set(data["vesc"]) >= {"frames_tx", "frames_rx", "crc_errors", "reconnects"}
    assert set(data["lidar"]) >= {"scans", "rate_hz", "reconnects"}
    assert data["vesc"]["frames_rx"] > 0 and data["lidar"]["scans"] > 0
    assert read_csv(data["trajectory_csv"])
    png = data["plot_png"]
    with open(png, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
