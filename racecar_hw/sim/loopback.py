"""``racecar-hw sim``: the real daemon on fake hardware, moved by the world simulation.

The fake VESC (a pty) and the fake lidar (TCP or a pty) run in a :class:`DeviceThread` with the
:class:`World`: the world reads the fake VESC's motor ERPM and servo position, moves the car, and
the fake lidar ray-casts the map from the car's laser pose. The daemon runs unchanged in the main
event loop with its device paths pointed at the fakes, so every byte crosses a real pty or socket.

Sim time is real (monotonic) time since the world started; see docs/sim.md.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lidar_drivers.params import HOKUYO_USB_MODELS
from lidar_drivers.registry import family, make_fake
from mux.estop import DAEMON, Origin
from racecar_hw.bags.follow import BagFollower, FollowerParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.base.overrides import merge
from racecar_hw.base.transforms import TfTree, yaw_of
from racecar_hw.config import Config, load_config, move_to_free_ports, shipped_config
from racecar_hw.daemon import Daemon, command_limits, reverse_speed_cap
from racecar_hw.net.ports import Listener
from racecar_hw.runtime.devicethread import DeviceThread
from racecar_hw.runtime.status import StatusPanel
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.sim.car import CLEARANCE_RANGE_M, CarParams, footprint
from racecar_hw.sim.live import SIM_TOPICS, log_estop_timing, map_to_odom, publish_truth
from racecar_hw.sim.obstacles import point_polygon_distance
from racecar_hw.sim.occupancy import load_map
from racecar_hw.sim.plot import ControlSample, Mark, plot_run
from racecar_hw.sim.scenario import CarSpec, DriverSpec, FaultSpec, Scenario
from racecar_hw.sim.trajectory import TrajectorySample, rest_time, stopping_distance, write_csv
from racecar_hw.sim.world import World, compose
from vesc.codec import servo_on_wire
from vesc.fake import FakeVesc

log = logging.getLogger(__name__)

#: The origin of a scenario's e-stop and release actions: the daemon itself.
SCENARIO = Origin(DAEMON, "scenario")

#: How often the control path is sampled for the plot (s of sim time), and at most how many samples.
SAMPLE_PERIOD_S = 0.05
MAX_SAMPLES = 200_000

#: Seconds a run that lasts as long as its replay (``until_replay_ends``) goes on after the last
#: command, for the car to come to rest.
REPLAY_SETTLE_S = 1.0
#: How much later than planned such a run waits for a replay held up by a loaded machine (s).
REPLAY_LATE_MAX_S = 30.0

#: Longest range the fake lidar casts, metres (UST-10LX: 10 m; others less matter little indoors).
LIDAR_MAX_RANGE_M = {"urg-04lx": 5.6, "ust-10lx": 10.0, "ust-20lx": 20.0, "utm-30lx": 30.0,
                     "utm-30lx-ew": 30.0}


@dataclass
class SimResult:
    """What a run produced: the report (also written as JSON) and the files next to it."""

    report: dict[str, Any]
    report_path: Path | None = None
    trajectory_csv: Path | None = None
    plot_png: Path | None = None
    interventions_at: list[tuple[float, float]] = field(default_factory=list)


class Loopback:
    """One scenario on fake hardware: build with a scenario and config, then ``await run()``."""

    def __init__(self, scenario: Scenario, *, config_path: str | Path | None = None,
                 overrides: tuple[str, ...] | list[str] = (), out_dir: str | Path | None = None,
                 status: StatusPanel | None = None, duration_s: float | None = None,
                 until_replay_ends: bool = False,
                 setup: Callable[[Loopback], None] | None = None) -> None:
        self.scenario = scenario
        self.duration_s = duration_s if duration_s is not None else scenario.duration_s
        #: run as long as the follow drivers' replays (stretched for the reverse cap) and
        #: :data:`REPLAY_SETTLE_S`, instead of the scenario's duration; ``duration_s`` wins
        self.until_replay_ends = until_replay_ends and duration_s is None
        self._tmp = tempfile.TemporaryDirectory(prefix="racecar-hw-sim-")
        self.dev_dir = Path(self._tmp.name)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.config_path = config_path if config_path is not None else shipped_config("sim")
        self.overrides = tuple(overrides)
        self.status = status
        self.setup = setup
        self.devices = DeviceThread("sim-devices")
        self.map = load_map(scenario.map_path())
        self.vesc: FakeVesc | None = None
        self.lidar: Any = None
        self.world: World | None = None
        self.daemon: Daemon | None = None
        self.config: Config | None = None
        self.interventions_at: list[tuple[float, float]] = []
        #: the interventions with their sim time, for the plot
        self.intervention_marks: list[Mark] = []
        #: the control path sampled every :data:`SAMPLE_PERIOD_S`, for the plot
        self.control_samples: list[ControlSample] = []
        self.fault_log: list[tuple[float, str]] = []
        self._stop: asyncio.Event | None = None
        #: why the run ended: "duration", or what interrupted it (request_stop)
        self.stop_reason = "duration"
        #: world time (s) when the car was ready to drive: the scenario's time zero
        self.ready_at_s: float | None = None
        self._mux_offset_s = 0.0
        self._followers: dict[int, BagFollower] = {}  # follow drivers' followers, loaded before the run
        self._followed: dict[int, float] = {}  # follow drivers' fraction of their replay published
        #: listeners whose configured port was taken, with where they listen instead
        self.moved_ports: list[tuple[Listener, str]] = []

    # --- building -------------------------------------------------------------------------------

    def _build_config(self) -> Config:
        """The sim config with the scenario's overrides, its VESC port at the fake's pty.

        The lidar endpoint is filled in once the fake lidar listens (a TCP port is only known then).
        """
        extra = merge(self.scenario.config, {
            "vesc": {"port": str(self.dev_dir / "vesc")},
            "lidar": {"model": self.scenario.lidar.model, "tcp": None, "port": None},
        })
        return load_config(self.config_path, self.overrides, extra=extra)

    def _take_free_ports(self, config: Config) -> None:
        """The rule for ports (docs/live-view.md, "Ports"): a sim listens on free ports instead of
        taken ones, and says where. After every refusal, so a refused run touches no port."""
        self.moved_ports = move_to_free_ports(config)
        for listener, where in self.moved_ports:
            print(f"racecar-hw sim: {listener.key} {listener.address()} is taken (another racecar-hw?); "
                  f"{listener.what} is on {where} instead", file=sys.stderr, flush=True)

    @staticmethod
    def _car_params(config: Config, true: CarSpec | None = None) -> CarParams:
        """The simulated car: calibrated for the daemon's config, so it drives straight at the
        servo position that reaches the VESC for steering 0 (the offset in thousandths, as the
        wire carries it: 0.5304 is sent as 0.530, and a car "straight" at 0.5304 would drift),
        except where the scenario's ``car`` gives its true values."""
        v, fp = config.vesc, config.safety.footprint
        t = true if true is not None else CarSpec()

        def pick(value: float | None, configured: float | None) -> float | None:
            return configured if value is None else value

        right = (t.steering_angle_to_servo_gain_right if t.steering_angle_to_servo_gain is not None
                 else pick(t.steering_angle_to_servo_gain_right, v.steering_angle_to_servo_gain_right))
        return CarParams(speed_to_erpm_gain=pick(t.speed_to_erpm_gain, v.speed_to_erpm_gain),
                         speed_to_erpm_offset=v.speed_to_erpm_offset,
                         steering_angle_to_servo_gain=pick(t.steering_angle_to_servo_gain,
                                                           v.steering_angle_to_servo_gain),
                         steering_angle_to_servo_gain_right=right,
                         steering_angle_to_servo_offset=pick(t.steering_angle_to_servo_offset,
                                                             servo_on_wire(v.steering_angle_to_servo_offset)),
                         wheelbase=pick(t.wheelbase_m, v.wheelbase_m), length=fp.length_m,
                         width=fp.width_m, rear_overhang=fp.rear_overhang_m)

    def _check(self, config: Config) -> None:
        """Refuse, before anything starts, a driver on an input the mux does not have (a one-line
        error); follow drivers' bags are loaded next, by :meth:`_follower`."""
        inputs = [inp.name for inp in config.mux.inputs]
        for i, spec in enumerate(self.scenario.drivers):
            if spec.input not in inputs:
                raise ConfigError(f"scenario.drivers.{i}.input",
                                  f"{spec.input!r} is not a mux input; inputs: {', '.join(inputs)}")

    def _start_devices(self, config: Config) -> Config:
        sc = self.scenario
        model = sc.lidar.model
        if all(t.child_frame_id != "odom" for t in config.static_transforms):
            config.static_transforms.append(map_to_odom(sc.start))  # odometry drawn in the map
        laser = self._laser_pose(config)
        vesc = self.vesc = FakeVesc(str(self.dev_dir / "vesc"), firmware=sc.firmware_version())
        self.car_params = self._car_params(config, sc.car)
        self.world = World(self.map, self.car_params, sc.start,
                           erpm_source=lambda: vesc.erpm, servo_source=lambda: vesc.servo,
                           laser_pose_in_base=laser, noise_std_m=sc.world.noise_std_m,
                           seed=sc.world.seed, on_collision=vesc.stall)
        vesc.imu.motion = self.world.motion
        vesc.imu.mount = self._imu_pose(config)
        vesc.imu.errors.gyro_bias_dps = sc.car.gyro_bias_dps
        source = self.world.range_source(max_range=LIDAR_MAX_RANGE_M.get(model, 12.0))
        # TCP only where the real device has it: an Ethernet Hokuyo (USB models and RPLIDARs: pty)
        use_tcp = sc.lidar.transport == "tcp" and family(model) == "hokuyo" \
            and model not in HOKUYO_USB_MODELS
        if use_tcp:
            self.lidar = make_fake(model, source, tcp=("127.0.0.1", 0))
        else:
            self.lidar = make_fake(model, source, link=str(self.dev_dir / "lidar"))
        self.devices.start()
        self.devices.spawn(self.vesc.serve())
        self.devices.spawn(self.lidar.serve())
        self.devices.spawn(self.world.run(sc.world.rate_hz))
        ready = getattr(self.lidar, "ready", None)
        if ready is not None and not ready.wait(10):
            raise RuntimeError("fake lidar did not start")
        if use_tcp:
            host, port = self.lidar.tcp_address
            config.lidar.tcp = f"{host}:{port}"
        else:
            config.lidar.port = str(self.dev_dir / "lidar")
        return config

    @staticmethod
    def _laser_pose(config: Config) -> tuple[float, float, float]:
        """The laser's (x, y, yaw) in base_link, from the static transforms."""
        tree = TfTree.from_params(config.static_transforms)
        frame = config.lidar.frame_id
        if not tree.can_transform("base_link", frame):
            raise ConfigError("static_transforms", f"no transform from base_link to the lidar frame "
                                                   f"{frame!r}: the simulated lidar needs one")
        m = tree.lookup("base_link", frame)
        return float(m[0, 3]), float(m[1, 3]), yaw_of(m)

    @staticmethod
    def _imu_pose(config: Config) -> tuple[float, float, float]:
        """The IMU's (x, y, yaw) in base_link from the static transforms; base_link itself when the
        config gives no ``base_link -> imu_frame_id``."""
        tree = TfTree.from_params(config.static_transforms)
        frame = config.vesc.imu_frame_id
        if not tree.can_transform("base_link", frame):
            return (0.0, 0.0, 0.0)
        m = tree.lookup("base_link", frame)
        return float(m[0, 3]), float(m[1, 3]), yaw_of(m)

    # --- running --------------------------------------------------------------------------------

    def sim_time(self) -> float:
        """Seconds since the world started (the time in the report and the trajectory)."""
        return self.world.sim_time if self.world is not None else 0.0

    def scenario_time(self) -> float:
        """Seconds since the car was ready: drivers, faults and the duration count from there."""
        return self.sim_time() - (self.ready_at_s if self.ready_at_s is not None else math.inf)

    async def _wait_until(self, t_s: float) -> None:
        """Wait until scenario time ``t_s`` (after the car is ready)."""
        await self._wait_ready()
        while (left := t_s - self.scenario_time()) > 0:
            await asyncio.sleep(min(0.02, max(0.001, left)))

    async def _wait_ready(self, timeout_s: float = 15.0) -> None:
        """Wait until the car is ready to drive: the VESC answered and the first scan is in.

        A driver on a real car waits for the same; commanding earlier only makes the safety
        controller hold the car (no scan yet), which would count as an intervention.
        """
        assert self.daemon is not None
        daemon = self.daemon
        deadline = asyncio.get_running_loop().time() + timeout_s
        while self.ready_at_s is None:
            vesc_ok = daemon.vesc is None or daemon.vesc.connected
            lidar_ok = daemon.lidar is None or daemon.lidar.stats.scans > 0
            if (vesc_ok and lidar_ok) or asyncio.get_running_loop().time() > deadline:
                if not (vesc_ok and lidar_ok):
                    log.warning("sim: devices not ready after %.0f s; starting anyway", timeout_s)
                self.ready_at_s = self.sim_time()
                return
            await asyncio.sleep(0.01)

    async def _drive(self, spec: DriverSpec) -> None:
        assert self.config is not None and self.daemon is not None
        topic = self._input_topic(spec.input)
        await self._wait_until(spec.from_s)
        bus = self.daemon.bus
        if spec.type == "setpoint":
            from racecar_hw.sources.setpoint import SetpointParams, SetpointRelay

            relay = SetpointRelay(bus, SetpointParams(topic=topic, rate_hz=spec.rate_hz,
                                                      max_speed_mps=max(2.0, abs(spec.speed_mps))))
            relay.set_velocity(spec.speed_mps)
            relay.set_steering_angle(spec.steering_rad)
            relay.start()
            try:
                await self._until(relay.run(), spec.until_s)
            finally:
                relay.close()
        elif spec.type in ("constant", "script"):
            ticker = Ticker(spec.rate_hz)
            while spec.until_s is None or self.scenario_time() < spec.until_s:
                await ticker.tick()
                speed, steer = spec.speed_mps, spec.steering_rad
                if spec.type == "script":
                    speed, steer = _script_at(spec.steps, self.scenario_time() - spec.from_s)
                bus.publish(topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()),
                                                         AckermannDrive(steering_angle=steer, speed=speed)))
        elif spec.type == "figure8":
            from racecar_hw.sources.figure8 import Figure8Driver, Figure8Params

            params = Figure8Params(speed_mps=spec.speed_mps, steering_angle_rad=spec.steering_rad,
                                   wheelbase_m=self.config.vesc.wheelbase_m, figure8s=spec.figure8s,
                                   rate_hz=spec.rate_hz, topic=topic)
            await self._until(Figure8Driver(bus, params).run(), spec.until_s)
        elif spec.type == "follow":
            await self._until(self._follower(spec, bus).run(), spec.until_s)

    def _follower(self, spec: DriverSpec, bus: Bus) -> BagFollower:
        """The bag follower of a ``follow`` driver, loaded once (raises BagError for a bad bag)."""
        assert self.config is not None
        follower = self._followers.get(id(spec))
        if follower is None:
            params = FollowerParams(bag=spec.bag, topic=spec.topic, input_topic=self._input_topic(spec.input),
                                    rate_hz=spec.rate_hz, use_timestamps=spec.use_timestamps,
                                    reverse=spec.reverse)
            follower = BagFollower(bus, params, wheelbase_m=self.config.vesc.wheelbase_m,
                                   reverse_speed_cap_mps=reverse_speed_cap(self.config),
                                   limits=command_limits(self.config))
            self._followers[id(spec)] = follower
            self._followed[id(spec)] = 0.0
            follower.progress = lambda fraction, _eta: self._followed.__setitem__(id(spec), fraction)
        follower.bus = bus
        follower.load()
        return follower

    def _replay_s(self, spec: DriverSpec) -> float:
        """Seconds from a follow driver's first command to its last, as replayed (stretched when
        the reverse cap slows it down)."""
        steps = self._followers[id(spec)].load()
        return steps[-1].offset_ns / NS_PER_S if steps else 0.0

    def _replay_end_s(self) -> float:
        """Scenario time (s) at which the last follow driver's replay ends (at its ``until_s``)."""
        ends = []
        for spec in self.scenario.drivers:
            if spec.type == "follow":
                end = spec.from_s + self._replay_s(spec)
                ends.append(end if spec.until_s is None else min(end, spec.until_s))
        return max(ends, default=0.0)

    async def _until(self, coro: Any, until_s: float | None) -> None:
        task = asyncio.ensure_future(coro)
        if until_s is None:
            await task
            return
        waiter = asyncio.ensure_future(self._wait_until(until_s))
        await asyncio.wait([task, waiter], return_when=asyncio.FIRST_COMPLETED)
        for t in (task, waiter):
            t.cancel()
        await asyncio.gather(task, waiter, return_exceptions=True)

    def _input_topic(self, name: str) -> str:
        assert self.config is not None
        for inp in self.config.mux.inputs:
            if inp.name == name:
                return inp.topic
        names = ", ".join(i.name for i in self.config.mux.inputs)
        raise ConfigError("scenario", f"driver input {name!r} is not a mux input; inputs: {names}")

    async def _faults(self) -> None:
        for fault in sorted(self.scenario.faults, key=lambda f: f.at_s):
            await self._wait_until(fault.at_s)
            self.fault_log.append((round(self.sim_time(), 3), fault.action))
            log.info("sim fault at %.2f s: %s", self.sim_time(), fault.action)
            self._apply(fault)

    async def _place_obstacles(self) -> None:
        """Put the scenario's obstacles in the world, on scenario time (which starts when ready)."""
        assert self.world is not None
        await self._wait_ready()
        assert self.ready_at_s is not None
        for k, spec in enumerate(self.scenario.obstacles):
            self.world.add_mover(spec.mover(self.ready_at_s, f"obstacle {k + 1}"))

    def _apply(self, fault: FaultSpec) -> None:
        assert self.vesc is not None and self.world is not None and self.daemon is not None
        action = fault.action
        if action == "lidar_unplug":
            if getattr(self.lidar, "tcp_address", None) is not None:
                self.lidar.mute(True)
                self.lidar.drop_connection()
            else:
                self.lidar.unplug()
        elif action == "lidar_replug":
            if getattr(self.lidar, "tcp_address", None) is not None:
                self.lidar.mute(False)
            else:
                self.lidar.replug()
        elif action == "vesc_unplug":
            self.vesc.unplug()
        elif action == "vesc_replug":
            self.vesc.replug()
        elif action == "vesc_garbage":
            self.vesc.inject_garbage(fault.bytes)
        elif action == "obstacle_ahead":
            self.world.add_obstacle_ahead(fault.distance_m, fault.radius_m)
        elif action == "clear_obstacles":
            self.world.clear_obstacles()
        elif action == "estop":
            self.daemon.mux.engage_estop("scenario", SCENARIO)
        elif action == "estop_release":
            self.daemon.mux.release_estop(SCENARIO)
        elif action == "disarm":  # the operator lets go: the deadman, BACK or a ground station
            self.daemon.arming.disarm("scenario", "the operator let go")
        elif action == "arm":
            self.daemon.arming.arm("scenario")

    async def _watch_interventions(self) -> None:
        """Note where and when interventions start, and sample the control path for the plot."""
        assert self.daemon is not None and self.world is not None
        daemon, world = self.daemon, self.world
        seen = 0
        next_sample = 0.0
        while True:
            await asyncio.sleep(0.02)
            n = daemon.safety.interventions
            t = world.sim_time
            if n > seen:
                pose = world.pose
                self.interventions_at.extend([(pose.x, pose.y)] * (n - seen))
                self.intervention_marks.extend([Mark(pose.x, pose.y, t)] * (n - seen))
                seen = n
            if t >= next_sample and len(self.control_samples) < MAX_SAMPLES:
                next_sample = t + SAMPLE_PERIOD_S
                self.control_samples.append(self._control_sample(t))

    def _control_sample(self, t: float) -> ControlSample:
        assert self.daemon is not None
        daemon = self.daemon
        out = daemon.mux.last_output
        odom = daemon.bus.latest(daemon.config.safety.odom_topic)
        asked = daemon.mux.last_command(daemon.mux.source)
        return ControlSample(t, float(asked.speed) if asked is not None else 0.0,
                             float(out.drive.speed) if out is not None else 0.0,
                             float(daemon.safety.state.allowed_speed),
                             float(odom.twist.twist.linear.x) if odom is not None else 0.0,
                             float(out.drive.steering_angle) if out is not None else 0.0)

    async def run(self) -> SimResult:
        """Run the scenario for its duration; returns (and writes, with ``out_dir``) the report."""
        try:
            self.config = config = self._build_config()
            self._check(config)
            # bags first: a missing or damaged one is refused before any device or the daemon starts
            for spec in self.scenario.drivers:
                if spec.type == "follow":
                    await asyncio.to_thread(self._follower, spec, Bus())
            if self.until_replay_ends and self._followers:
                self.duration_s = self._replay_end_s() + REPLAY_SETTLE_S
            self._take_free_ports(config)
            self.config = self._start_devices(config)
            assert self.world is not None
            created_ns = monotonic_ns()
            self.daemon = Daemon(self.config, status=self.status)
            world = self.world
            self.daemon.state.extra_status = lambda: {
                "sim_time_s": world.sim_time, "sim_pose": tuple(world.pose),
                "clearance_m": world.clearance()}
            # world time at which the mux started counting (its switch times are relative to it)
            self._mux_offset_s = self.world.sim_time - (monotonic_ns() - created_ns) / NS_PER_S
            if self.setup is not None:
                self.setup(self)
            stop = self._stop = asyncio.Event()
            if self.stop_reason != "duration":  # asked to stop while the devices were starting
                stop.set()
            for spec in self.scenario.drivers:
                self.daemon.add_task(self._drive(spec))
            self.daemon.add_task(self._faults())
            self.daemon.add_task(self._place_obstacles())
            self.daemon.add_task(self._watch_interventions())
            self.daemon.live_topics.extend(SIM_TOPICS)
            self.daemon.add_task(publish_truth(self.daemon.bus, self.world, self.map))
            assert self.vesc is not None
            self.daemon.add_task(log_estop_timing(self.daemon, self.vesc))

            async def timer() -> None:
                await self._wait_until(self.duration_s)
                if self.until_replay_ends:
                    await self._wait_for_replays()
                stop.set()

            self.daemon.add_task(timer())
            await self.daemon.run(stop)
            await self._settle()
            return self._result()
        finally:
            self.devices.stop()
            self._tmp.cleanup()

    async def _wait_for_replays(self) -> None:
        """A replay held up by a loaded machine ends later than planned: wait for it (at most
        :data:`REPLAY_LATE_MAX_S`), then :data:`REPLAY_SETTLE_S` more."""
        late = False
        while not all(f.done for f in self._followers.values()):
            if self.scenario_time() > self.duration_s + REPLAY_LATE_MAX_S:
                log.warning("sim: the replay did not end %.0f s after it should have; stopping",
                            REPLAY_LATE_MAX_S)
                return
            late = True
            await asyncio.sleep(0.05)
        if late:
            log.info("sim: the replay ended %.2f s late (a held-up machine)",
                     self.scenario_time() - self.duration_s + REPLAY_SETTLE_S)
            await self._wait_until(self.scenario_time() + REPLAY_SETTLE_S)

    def request_stop(self, reason: str = "request") -> None:
        """End the run now (from the event loop), as if the duration had passed; the report says
        it was ``interrupted`` and why (``stop_reason``: SIGINT, SIGTERM, ...)."""
        if self.stop_reason == "duration":
            self.stop_reason = reason
        if self._stop is not None:
            self._stop.set()

    async def _settle(self) -> None:
        """Let the car roll to rest after the daemon's final brake, for honest final numbers."""
        assert self.world is not None
        for _ in range(100):
            if abs(self.world.speed) < 0.01:
                return
            await asyncio.sleep(0.02)

    # --- report ---------------------------------------------------------------------------------

    def _result(self) -> SimResult:
        assert self.world is not None and self.daemon is not None and self.vesc is not None
        world, daemon = self.world, self.daemon
        pose = world.pose
        vstats = daemon.vesc.stats if daemon.vesc is not None else None
        lstats = daemon.lidar.stats if daemon.lidar is not None else None
        sim_time = world.sim_time
        report: dict[str, Any] = {
            "scenario": self.scenario.name,
            "description": self.scenario.description,
            "sim_time_s": round(sim_time, 3),
            "interrupted": self.stop_reason != "duration",
            "stop_reason": self.stop_reason,
            "duration_s": round(self.duration_s, 3),
            "follow": self._follow_report(),
            "ready_at_s": None if self.ready_at_s is None else round(self.ready_at_s, 3),
            "collided": world.collided,
            "collisions": [[round(c.t, 3), round(c.x, 3), round(c.y, 3)] for c in world.collisions],
            "min_clearance_m": _num(world.min_clearance),
            "clearance_cap_m": CLEARANCE_RANGE_M,
            "final_clearance_m": _num(world.clearance()),
            "distance_m": _num(world.distance_travelled),
            "final_pose": {"x": _num(pose.x), "y": _num(pose.y), "yaw": _num(pose.yaw)},
            "final_speed_mps": _num(world.speed),
            "max_speed_mps": _num(max((abs(s[4]) for s in world.trajectory), default=0.0)),
            "safety_interventions": daemon.safety.interventions,
            "safety_interventions_by_reason": dict(daemon.safety.controller.interventions_by_reason),
            "mux_switches": [[round(t + self._mux_offset_s, 3), s] for t, s in daemon.mux.switches],
            "faults": [[t, a] for t, a in self.fault_log],
            "vesc": {
                "frames_tx": vstats.frames_tx if vstats else 0,
                "frames_rx": vstats.frames_rx if vstats else 0,
                "crc_errors": vstats.crc_errors if vstats else 0,
                "reconnects": vstats.reconnects if vstats else 0,
                "firmware": self.scenario.firmware,
            },
            "lidar": {
                "model": self.scenario.lidar.model,
                "scans": lstats.scans if lstats else 0,
                "rate_hz": _num(lstats.scans / sim_time if lstats and sim_time > 0 else 0.0),
                "reconnects": lstats.reconnects if lstats else 0,
            },
            "control": {"ticks": daemon.stats.ticks, "missed_ticks": daemon.stats.missed_ticks,
                        "scan_cuts": daemon.stats.scan_cuts},
            "interventions": self._interventions(),
            "safety_memory": daemon.config.safety.memory.enabled,
            "odometry_error_m": self._odometry_error(),
            "trajectory_csv": None,
            "plot_png": None,
            # the bags --record wrote (ROS 2: the bag directory)
            "bags": ([str(f) for f in daemon.recorder.stats.files] if daemon.recorder is not None
                     else []),
            # where the live view and the status page listened during the run
            "live": dict(daemon.started_live),
        }
        result = SimResult(report, interventions_at=list(self.interventions_at))
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            stem = self.scenario.name or "sim"
            csv_path = self.out_dir / f"{stem}-trajectory.csv"
            write_csv(csv_path, world.samples)
            png_path = self.out_dir / f"{stem}.png"
            plot_run(png_path, self.map, world.trajectory, self.intervention_marks, world.collisions,
                     world.obstacles.values(), title=stem, series=self.control_samples,
                     switches=report["mux_switches"])
            report["trajectory_csv"] = str(csv_path)
            report["plot_png"] = str(png_path)
            result.trajectory_csv, result.plot_png = csv_path, png_path
        return result


    def _odometry_error(self) -> float | None:
        """How far the car truly is (m) from where its odometry says at the end, the odom frame
        being the start pose in the map (what the map -> odom transform says); None without odometry."""
        assert self.world is not None and self.daemon is not None
        odom = self.daemon.bus.latest(self.daemon.config.safety.odom_topic)
        if odom is None:
            return None
        x0, y0, yaw0 = self.scenario.start
        ox, oy = float(odom.pose.pose.position.x), float(odom.pose.pose.position.y)
        mx = x0 + math.cos(yaw0) * ox - math.sin(yaw0) * oy
        my = y0 + math.sin(yaw0) * ox + math.cos(yaw0) * oy
        pose = self.world.pose
        return _num(math.hypot(pose.x - mx, pose.y - my))

    def _follow_report(self) -> list[dict[str, Any]]:
        """Each follow driver's replay: its length as replayed (s), the fraction of its commands
        published, and whether it was followed to the end (``complete``)."""
        out = []
        for spec in self.scenario.drivers:
            if spec.type == "follow" and id(spec) in self._followers:
                followed = self._followed[id(spec)]
                out.append({"bag": str(spec.bag), "reverse": spec.reverse,
                            "replay_s": round(self._replay_s(spec), 3),
                            "speed_scale": round(self._followers[id(spec)].speed_scale, 3),
                            "followed": round(followed, 3), "complete": followed >= 1.0})
        return out

    def _interventions(self) -> list[dict[str, Any]]:
        """Each intervention: when (world time), why, what caused it and where the car stopped.

        An intervention that started for something else (a late scan, the reverse cap) and then
        became a stop for an obstacle has a second entry from that moment, with ``continues`` true
        (the first then ends there): what the car stopped for, and how far from it, are in that one.

        ``source``: the live scan or the obstacle memory (None without an obstacle, e.g. a stale
        scan). ``obstacle``: the limiting point in the map frame; ``object``: what the world has
        there (``map``, a scenario obstacle's name, or None: nothing, a remembered point of
        something that has gone). ``ended_at_s``: when the controller let go (None: at the end of
        the run). ``stopped_at_s``: when the car came to rest before that (:func:`rest_time`: a car
        that stood at the start and then drove stopped where it came to rest again; None: it only
        slowed down); ``stopping_distance_m``: path driven until then; ``distance_left_m``: the gap
        between the car's footprint and that object at standstill, or when the intervention ended
        if the car only slowed (for the map or nothing: the gap to the point).
        """
        assert self.world is not None and self.daemon is not None
        world = self.world
        samples = world.samples
        out = []
        for event in self.daemon.safety.controller.events:
            t = world.sim_time_at(event.t_ns)
            end = world.sim_time_at(event.end_ns) if event.end_ns is not None else None
            entry: dict[str, Any] = {
                "t_s": round(t, 3), "reason": event.reason, "continues": event.continues,
                "source": None, "obstacle": None, "object": None, "speed_mps": _num(_speed_at(samples, t)),
                "allowed_mps": _num(event.allowed_speed),
                "ended_at_s": None if end is None else round(end, 3), "stopped_at_s": None,
                "stopping_distance_m": None, "distance_left_m": None,
            }
            point = None
            if event.obstacle is not None and event.scan_ns is not None:
                o = event.obstacle
                scan_t = world.sim_time_at(event.scan_ns)
                point = compose(world.pose_at(event.scan_ns), (o.x, o.y, 0.0))
                entry["source"] = o.source
                entry["obstacle"] = {"x": _num(point.x), "y": _num(point.y)}
                entry["object"] = world.what_is_at(point.x, point.y, scan_t)
            stopped = rest_time(samples, t, end)
            if stopped is not None:
                entry["stopped_at_s"] = round(stopped, 3)
                entry["stopping_distance_m"] = _num(stopping_distance(samples, t, stopped) or 0.0)
            when = stopped if stopped is not None else end
            if point is not None and when is not None:
                at = next((s for s in samples if s.t >= when), samples[-1])
                corners = footprint((at.x, at.y, at.yaw), world.params)
                gap = next((shape.distance_to(corners) for label, shape in world.obstacles_at(when)
                            if label == entry["object"]),
                           point_polygon_distance(point.x, point.y, corners))
                entry["distance_left_m"] = _num(gap)
            out.append(entry)
        return out


def write_report(result: SimResult, path: str | Path) -> Path:
    """Write the JSON report to ``path``."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(result.report, indent=2) + "\n")
    result.report_path = p
    return p


def _speed_at(samples: list[TrajectorySample], t: float) -> float:
    """The car's speed (m/s) at the first sample at or after sim time ``t`` (0 past the end)."""
    return next((s.speed for s in samples if s.t >= t), 0.0)


def _script_at(steps: list[tuple[float, float, float]], t: float) -> tuple[float, float]:
    speed, steer = 0.0, 0.0
    for t0, v, d in steps:
        if t >= t0:
            speed, steer = v, d
    return speed, steer


def _num(x: float) -> float | None:
    return round(float(x), 4) if math.isfinite(x) else None

