"""Several cars in one world (issue 27): each car its own daemon, namespace and world, the worlds
coupled so that each lidar sees the other cars and cars collide with each other.

The acceptance: the shipped two-car scenario, each car driven by its own client over Zenoh (its
namespace, its listener), both see each other in their scans, and the follower's safety controller
stops it behind the leader when the leader brakes. And in lockstep at full speed with the
scenario's drivers: a follower without a safety controller hits the braking leader, and the report
says so in both cars' sections.
"""

from __future__ import annotations

import asyncio
import json
import math
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import QUIET_NET, reaped, set_args, wait_for
from hypothesis import given, settings
from hypothesis import strategies as st
from zenoh_util import endpoint, free_port

from racecar_hw.base.clock import SIM_EPOCH_NS, use_virtual_time
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build
from racecar_hw.cli import main
from racecar_hw.runtime import lockstep
from racecar_hw.sim.car import CarParams
from racecar_hw.sim.car_state import compose
from racecar_hw.sim.fleet import CarShadow, Fleet, FleetCar
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.scenario import Scenario, load_scenario
from racecar_hw.sim.world import World

P = CarParams()
CORRIDOR = load_shipped_map("corridor")
#: base_link -> laser in the shipped sim config (x forward, m)
LASER_X = 0.265


# --- the coupling, on bare worlds --------------------------------------------------------------


class Motor:
    """A fixed speed for a world's ERPM source, and the stall a collision calls."""

    def __init__(self, speed: float = 0.0) -> None:
        self.erpm = P.speed_to_erpm_gain * speed
        self.stalls = 0

    def stall(self) -> None:
        self.stalls += 1
        self.erpm = 0.0


def two_worlds(lead_x: float, follow_speed: float) -> tuple[World, World, Motor]:
    lead_motor, follow_motor = Motor(), Motor(follow_speed)
    # one time zero for both worlds, as a fleet in lockstep has: built on the host's clock, a busy
    # machine could put milliseconds between them, which the shadows would read as motion
    with use_virtual_time(lambda: SIM_EPOCH_NS):
        lead = World(CORRIDOR, P, (lead_x, 0.0, 0.0), lambda: lead_motor.erpm, noise_std_m=0.0)
        follow = World(CORRIDOR, P, (0.0, 0.0, 0.0), lambda: follow_motor.erpm, noise_std_m=0.0,
                       on_collision=follow_motor.stall)
    follow.add_mover(CarShadow("leader", lambda: follow, lambda: lead))
    lead.add_mover(CarShadow("follower", lambda: lead, lambda: follow))
    return lead, follow, follow_motor


def test_each_world_sees_the_other_car_where_the_other_world_has_it():
    lead, follow, _ = two_worlds(3.0, 0.0)
    # the follower's laser looks along +x at the leader's rear bumper: 3.0 - 0.1 - 0.265 m
    ahead = follow.true_ranges(np.array([0.0]))[0]
    assert ahead == pytest.approx(3.0 - P.rear_overhang - LASER_X, abs=1e-6)
    # behind the leader (a 360-degree view): the follower's front bumper, 3.265 - 0.45 m away
    behind = lead.true_ranges(np.array([math.pi]))[0]
    assert behind == pytest.approx(3.0 + LASER_X - (P.length - P.rear_overhang), abs=1e-6)
    assert follow.what_is_at(2.95, 0.0) == "leader" and lead.what_is_at(0.4, 0.0) == "follower"
    for _ in range(50):  # the leader drives away 1 m/s for 0.5 s: the follower's lidar sees it go
        lead._erpm_source = lambda: P.speed_to_erpm_gain * 1.0
        lead.step(0.01)
        follow.step(0.01)
    assert lead.pose.x == pytest.approx(3.5, abs=0.01)
    assert follow.true_ranges(np.array([0.0]))[0] == pytest.approx(3.5 - 0.1 - LASER_X, abs=0.01)


def test_a_car_driving_into_another_collides_with_it():
    lead, follow, motor = two_worlds(1.5, 2.0)
    for _ in range(200):
        follow.step(0.01)
        lead.step(0.01)
    assert follow.collided and motor.stalls == 1
    (hit,) = follow.collisions
    # stopped at the leader's rear bumper (1.4 m), within the sweep's half-cell steps
    front = compose(follow.pose, (P.length - P.rear_overhang, 0.0, 0.0))
    assert 1.4 - 0.03 < front.x <= 1.4
    assert hit.x == pytest.approx(front.x)
    assert follow.min_clearance == 0.0 and lead.pose.x == 1.5  # the leader stood still


# --- the scenario format ---------------------------------------------------------------------


def test_a_scenario_with_cars_refuses_what_belongs_to_each_car():
    with pytest.raises(ConfigError, match=r"cars\[1\]\.name: 'a': two cars"):
        load_scenario("two-cars", ["cars=[{name: a}, {name: a, start: [2, 0, 0]}]"])
    with pytest.raises(ConfigError, match="drivers: with cars, each car has its own drivers"):
        load_scenario("two-cars", ["drivers=[{type: constant}]"])
    with pytest.raises(ConfigError, match="start: with cars"):
        load_scenario("two-cars", ["start=[1, 0, 0]"])
    with pytest.raises(ConfigError, match=r"scenario.cars\[0\]: name: 'car 1'"):
        load_scenario("two-cars", ["cars.0.name=car 1"])
    with pytest.raises(ConfigError, match="overlaps car leader"):
        Fleet(load_scenario("two-cars", ["cars.1.start=[3.3, 0.0, 0.0]"]))._check_starts()
    with pytest.raises(ConfigError, match="several cars: run it with"):
        Loopback(load_scenario("two-cars"))


def test_overlapping_starts_are_checked_with_each_cars_own_footprint():
    """A car whose config makes its footprint 2 m long overlaps a car 1 m ahead, where two cars of
    the default footprint (0.55 m) would not; a car's config that does not load names the car."""
    apart = ["cars=[{name: a, start: [0, 0, 0]}, {name: b, start: [1, 0, 0]}]"]
    Fleet(load_scenario("two-cars", apart))._check_starts()
    long_a = ["cars.0.config={safety: {footprint: {length_m: 2.0}}}"]
    with pytest.raises(ConfigError, match=r"^scenario\.cars\[1\]\.start: car b's .* overlaps car a's"):
        Fleet(load_scenario("two-cars", apart + long_a))._check_starts()
    bad_b = "cars.1.config={safety: {footprint: {nope: 1}}}"
    with pytest.raises(ConfigError, match=r"^car b: safety\.footprint\.nope: unknown key"):
        Fleet(load_scenario("two-cars", [*apart, bad_b]))._check_starts()


CAR_ENTRY = st.fixed_dictionaries(
    {"name": st.one_of(st.sampled_from(["a", "b", "car_1"]), st.text(max_size=6))},
    optional={"start": st.lists(st.floats(allow_nan=True), max_size=4),
              "drivers": st.lists(st.fixed_dictionaries({"type": st.sampled_from(["constant", "nope"])}),
                                  max_size=2),
              "lidar": st.one_of(st.none(), st.fixed_dictionaries({"model": st.text(max_size=8)})),
              "config": st.one_of(st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
                                  st.integers()),
              "bogus": st.integers()})
SCENARIO_DATA = st.fixed_dictionaries(
    {"cars": st.one_of(st.lists(CAR_ENTRY, max_size=4), st.text(max_size=3))},
    optional={"drivers": st.lists(st.fixed_dictionaries({"type": st.just("constant")}), max_size=1),
              "start": st.lists(st.floats(-5, 5), min_size=3, max_size=3),
              "obstacles": st.lists(st.fixed_dictionaries({"name": st.sampled_from(["a", "box"])}),
                                    max_size=1)})


@settings(max_examples=300, deadline=None)
@given(SCENARIO_DATA)
def test_any_cars_section_is_a_scenario_or_refused_naming_the_key(data):
    try:
        scenario = build(Scenario, data, "scenario")
    except ConfigError as err:
        assert str(err).startswith("scenario"), err
        return
    names = [c.name for c in scenario.cars]
    assert len(set(names)) == len(names) and all(n.isidentifier() for n in names)
    assert not (scenario.cars and (scenario.drivers or scenario.start != (0.0, 0.0, 0.0)))
    assert not {o.name for o in scenario.obstacles} & set(names)


def test_each_car_gets_its_namespace_its_ports_and_its_scenario():
    scenario = load_scenario("two-cars")
    assert [c.name for c in scenario.cars] == ["leader", "follower"]
    port = free_port()
    fleet = Fleet(scenario, overrides=[f'zenoh.listen=["{endpoint(port)}"]', "foxglove.port=0", "web.port=0"])
    leader, follower = fleet.cars["leader"], fleet.cars["follower"]
    assert (leader.scenario.name, follower.scenario.name) == ("two-cars-leader", "two-cars-follower")
    assert leader.scenario.lidar.model == "a2m8" and follower.scenario.lidar.model == "ust-10lx"
    configs = []
    for car in (leader, follower):
        config = car._build_config()
        car._take_free_ports(config)
        configs.append(config)
    assert [c.zenoh.namespace for c in configs] == ["/leader", "/follower"]
    assert [c.dds.enabled for c in configs] == [False, False]  # one Cyclone domain per process
    # the same --set for both: the follower's listener moves off the port promised to the leader
    assert configs[0].zenoh.listen == [endpoint(port)]
    assert configs[1].zenoh.listen != [endpoint(port)]
    assert [c.vesc.port for c in configs] == ["mem://leader/vesc", "mem://follower/vesc"]
    same = Fleet(scenario, overrides=["zenoh.namespace=/car", f'zenoh.listen=["{endpoint(free_port())}"]',
                                      "foxglove.port=0", "web.port=0", "dds.enabled=false"])
    for k, car in enumerate(same.cars.values()):
        config = car._build_config()
        if k == 0:
            car._take_free_ports(config)
        else:
            with pytest.raises(ConfigError, match="zenoh.namespace: cars leader and follower both have /car"):
                car._take_free_ports(config)
    both = Fleet(scenario, overrides=["dds.enabled=true", f'zenoh.listen=["{endpoint(free_port())}"]',
                                      "foxglove.port=0", "web.port=0"])
    leader, follower = both.cars.values()
    leader._take_free_ports(leader._build_config())
    with pytest.raises(ConfigError, match="dds.enabled: cars leader and follower both have DDS"):
        follower._take_free_ports(follower._build_config())


# --- lockstep at full speed: a car-car collision ---------------------------------------------


def test_a_follower_without_safety_hits_the_braking_leader_and_both_sections_say_so(tmp_path):
    scenario = load_scenario("two-cars", ["duration_s=5", "cars.1.config={safety: {mode: 'off'}}",
                                          "cars.0.drivers.0.steps=[[0, 1.5, 0], [1.5, 0, 0]]"])
    fleet = Fleet(scenario, overrides=QUIET_NET, out_dir=tmp_path)
    r = lockstep.run(fleet.run(), None).report
    leader, follower = r["cars"]["leader"], r["cars"]["follower"]
    assert r["car_names"] == ["leader", "follower"]
    (contact,) = r["car_collisions"]
    assert (contact["car"], contact["other"], contact["mutual"]) == ("follower", "leader", False)
    assert follower["collided"] and not leader["collided"]
    assert follower["car_collisions"] == leader["car_collisions"] == [contact]
    assert follower["safety_interventions"] == 0
    # the contact is where the leader's rear bumper was when it stood
    rear = leader["final_pose"]["x"] - P.rear_overhang
    assert contact["x"] == pytest.approx(rear, abs=0.05)
    assert follower["collisions"][0][0] == contact["t_s"]  # one clock for both worlds
    assert leader["world_start_s"] == follower["world_start_s"] == 0.0
    assert leader["ready_at_s"] == follower["ready_at_s"]  # one scenario time
    (gap,) = r["gaps"]
    assert gap["cars"] == ["leader", "follower"] and gap["min_gap_m"] == pytest.approx(0.0, abs=0.03)
    for name in ("leader", "follower"):
        car = r["cars"][name]
        assert Path(car["trajectory_csv"]).name == f"two-cars-{name}-trajectory.csv"
        assert Path(car["plot_png"]).stat().st_size > 0
        assert car["namespace"] == f"/{name}"
    assert Path(r["plot_png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # every path in one picture
    assert Path(r["plot_png"]).name == "two-cars.png"
    json.dumps(r)  # the report is JSON


def test_two_cars_head_on_without_safety_make_one_mutual_contact(tmp_path):
    scenario = load_scenario("two-cars", [
        "duration_s=3", "cars.0.start=[3.0, 0.0, 3.14159265]", "cars.0.config.safety.mode=off",
        "cars.1.config={safety: {mode: 'off'}}", "cars.0.drivers.0.steps=[[0, 1.0, 0]]",
        "cars.1.drivers.0.speed_mps=1.0"])
    r = lockstep.run(Fleet(scenario, overrides=QUIET_NET).run(), None).report
    (contact,) = r["car_collisions"]  # both worlds found it: one contact, mutual
    assert contact["mutual"] is True and {contact["car"], contact["other"]} == {"leader", "follower"}
    assert r["cars"]["leader"]["collided"] and r["cars"]["follower"]["collided"]
    # they met halfway, bumper to bumper: 3.0 m between the rear axles less two 0.45 m noses
    assert contact["x"] == pytest.approx(1.5, abs=0.1)
    assert r["gaps"][0]["final_gap_m"] == pytest.approx(0.0, abs=0.03)


def test_three_cars_each_with_a_section_and_every_pair_measured(tmp_path):
    cars = [{"name": name, "start": [x, 0.0, 0.0],
             "drivers": [{"type": "constant", "input": "nav_0", "speed_mps": speed}]}
            for name, x, speed in (("a", 4.5, 0.3), ("b", 3.0, 1.0), ("c", 0.0, 1.0))]
    scenario = load_scenario("two-cars", ["duration_s=3", f"cars={json.dumps(cars)}"])
    r = lockstep.run(Fleet(scenario, overrides=QUIET_NET).run(), None).report
    assert r["car_names"] == ["a", "b", "c"] and r["car_collisions"] == []
    assert [g["cars"] for g in r["gaps"]] == [["a", "b"], ["a", "c"], ["b", "c"]]
    assert [r["cars"][n]["namespace"] for n in "abc"] == ["/a", "/b", "/c"]
    # b closes on the slower a and brakes for it: the car it stopped for is named
    assert any(i["object"] == "a" for i in r["cars"]["b"]["interventions"]), r["cars"]["b"]["interventions"]
    for gap in r["gaps"]:
        assert gap["min_gap_m"] > 0.1


# --- the acceptance: two clients over Zenoh ----------------------------------------------------


class Driver(threading.Thread):
    """A client program driving one car over Zenoh at 20 Hz: ``speed`` until told otherwise."""

    def __init__(self, car, speed: float) -> None:  # noqa: ANN001
        super().__init__(daemon=True)
        self.car = car
        self.speed = speed
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(0.05):
            self.car.drive(self.speed, 0.0)


def listening(port: int) -> bool:
    """Whether something accepts TCP connections on 127.0.0.1:``port``."""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
    except OSError:
        return False
    return True


def reading_at(scan, bearing: float) -> float:  # noqa: ANN001
    """The range of the beam nearest ``bearing`` (rad, laser frame)."""
    off = np.abs((scan.angles - bearing + math.pi) % (2 * math.pi) - math.pi)
    return float(scan.ranges[int(np.argmin(off))])


def laser_to(world_from: World, point: tuple[float, float]) -> tuple[float, float]:
    """(bearing rad in the laser frame, distance m) from ``world_from``'s laser to a map point."""
    laser = compose(world_from.pose, (LASER_X, 0.0, 0.0))
    dx, dy = point[0] - laser.x, point[1] - laser.y
    bearing = math.atan2(dy, dx) - laser.yaw
    return math.atan2(math.sin(bearing), math.cos(bearing)), math.hypot(dx, dy)


def test_two_cars_driven_by_their_own_clients_see_each_other_and_the_follower_stops_behind(tmp_path):
    from racecar_hw.client import Car

    ports = {"leader": free_port(), "follower": free_port()}
    sets = [f"cars.{k}.config.zenoh.listen=[\"{endpoint(ports[name])}\"]"
            for k, name in enumerate(ports)]
    # the clients drive: no scenario drivers; the run ends when the test has seen what it wants
    scenario = load_scenario("two-cars", ["duration_s=300", "cars.0.drivers=[]", "cars.1.drivers=[]", *sets])
    fleet = Fleet(scenario, overrides=["dds.enabled=false", "foxglove.port=0", "web.port=0"],
                  out_dir=tmp_path)
    loops: list[asyncio.AbstractEventLoop] = []

    def set_up(car: FleetCar) -> None:
        loops.append(asyncio.get_running_loop())

    fleet.setup = set_up
    outcome: dict = {}

    def run() -> None:
        try:
            outcome["result"] = lockstep.run(fleet.run(), 1.0)  # paced at real time: clients keep up
        except BaseException as err:  # noqa: BLE001 - reported by the test thread
            outcome["error"] = err

    runner = threading.Thread(target=run, daemon=True)
    runner.start()
    drivers: list[Driver] = []
    try:
        wait_for(lambda: len(loops) == 2 or not runner.is_alive(), timeout=120)
        assert "error" not in outcome, outcome
        for port in ports.values():  # each daemon's Zenoh listener is up (it opens in daemon.run)
            wait_for(lambda port=port: listening(port) or not runner.is_alive(), timeout=120)
        assert "error" not in outcome, outcome
        leader_world = fleet.cars["leader"].world
        follower_world = fleet.cars["follower"].world
        with Car(endpoint(ports["leader"]), namespace="/leader") as leader, \
                Car(endpoint(ports["follower"]), namespace="/follower") as follower:
            leader.wait_ready(timeout=120)
            follower.wait_ready(timeout=120)
            drivers = [Driver(leader, 1.0), Driver(follower, 1.0)]
            for d in drivers:
                d.start()
            # both drive; once the leader is 2 m on, its client brakes (and the follower's does not)
            wait_for(lambda: leader_world.pose.x > 5.0, timeout=180)
            assert follower_world.speed > 0.5  # really driving when the leader braked
            drivers[0].speed = 0.0
            wait_for(lambda: abs(follower_world.speed) < 0.01 and abs(leader_world.speed) < 0.01
                     and follower.safety is not None and follower.safety.values.get("intervening") is True,
                     timeout=180)
            # at rest: what each car's lidar sees at the other car's bearing is the other car
            leader_rear = compose(leader_world.pose, (-P.rear_overhang, 0.0, 0.0))
            follower_front = compose(follower_world.pose, (P.length - P.rear_overhang, 0.0, 0.0))
            bearing, distance = laser_to(follower_world, (leader_rear.x, leader_rear.y))
            assert abs(bearing) < 0.01 and 0.2 < distance < 1.0
            assert reading_at(follower.next_scan(timeout=30), bearing) == pytest.approx(distance, abs=0.05)
            bearing, distance = laser_to(leader_world, (follower_front.x, follower_front.y))
            assert abs(abs(bearing) - math.pi) < 0.01
            assert reading_at(leader.next_scan(timeout=30), bearing) == pytest.approx(distance, abs=0.05)
            follower_still_commanded = drivers[1].is_alive()
            for d in drivers:
                d.done.set()
                d.join(5)
        assert follower_still_commanded
        loops[0].call_soon_threadsafe(fleet.request_stop, "test")
        runner.join(120)
        assert not runner.is_alive() and "error" not in outcome, outcome
    finally:
        for d in drivers:
            d.done.set()
        if runner.is_alive() and loops:
            loops[0].call_soon_threadsafe(fleet.request_stop, "test")
            runner.join(60)
    r = outcome["result"].report
    leader_r, follower_r = r["cars"]["leader"], r["cars"]["follower"]
    assert r["car_collisions"] == [] and not leader_r["collided"] and not follower_r["collided"]
    assert follower_r["safety_interventions"] > 0
    assert any(i["object"] == "leader" for i in follower_r["interventions"]), follower_r["interventions"]
    (gap,) = r["gaps"]
    assert gap["final_gap_m"] > 0.1 and gap["min_gap_m"] > 0.1
    assert leader_r["zenoh_listen"] == [endpoint(ports["leader"])]
    assert follower_r["zenoh_listen"] == [endpoint(ports["follower"])]
    assert (leader_r["namespace"], follower_r["namespace"]) == ("/leader", "/follower")
    assert r["stop_reason"] == "test"


# --- the command line ------------------------------------------------------------------------


def test_the_command_line_runs_two_cars_and_ctrl_c_ends_both_with_the_report(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--scenario", "two-cars", "--speed", "max",
         "--duration", "600", "--no-status", *set_args(*QUIET_NET), "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        assert proc.stderr is not None
        running = 0
        for line in proc.stderr:  # both daemons run, then the follower stops behind the leader
            running += "racecar-hw running" in line
            if running == 2 and "safety: intervening (obstacle)" in line:
                break
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    report = json.loads((tmp_path / "two-cars.json").read_text())
    assert report["interrupted"] is True and report["stop_reason"] == "SIGINT"
    assert set(report["cars"]) == {"leader", "follower"} and report["car_collisions"] == []
    assert report["cars"]["follower"]["safety_interventions"] >= 1
    assert Path(report["plot_png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for name in ("leader", "follower"):
        assert Path(report["cars"][name]["plot_png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"car {name} (namespace /{name}):" in out
        assert f"two-cars-{name}: interrupted by SIGINT after" in out
    assert "no car hit another" in out


@pytest.mark.parametrize("option", [["--follow", "x.bag"], ["--keyboard"]], ids=["follow", "keyboard"])
def test_the_command_line_refuses_to_drive_one_of_several_cars(capsys, option):
    assert main(["sim", "--scenario", "two-cars", *option, *set_args(*QUIET_NET)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"racecar-hw sim: {option[0]}: scenario two-cars has several cars")
    assert "\n" not in err


def test_a_bad_config_of_one_car_is_refused_in_one_line_naming_the_car(capsys, tmp_path):
    code = main(["sim", "--scenario", "two-cars", "--speed", "max", "--no-status", "--out", str(tmp_path),
                 "--scenario-set", 'cars.1.config={zenoh: {namespace: "bad ns"}}',
                 *set_args("zenoh.enabled=true", 'zenoh.listen=["tcp/127.0.0.1:0"]', "dds.enabled=false",
                           "foxglove.port=0", "web.port=0")])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "racecar-hw sim: car follower: zenoh.namespace: '/bad ns' is not a valid ROS 2 topic name" in err
    assert "Traceback" not in err and not (tmp_path / "two-cars.json").exists()
