"""The fake hardware of a sim run: a fake VESC, a fake lidar and the world that moves them.

In real time the fake VESC (a pty) and the fake lidar (TCP or a pty) run in a :class:`DeviceThread`
with the :class:`~racecar_hw.sim.world.World`; in lockstep they run as tasks in the daemon's own
event loop (on virtual time, :mod:`racecar_hw.runtime.lockstep`) behind in-memory links
(``mem://CAR/vesc``, ``mem://CAR/lidar``: :mod:`racecar_hw.base.memlink`) carrying the same bytes.
Either way the world reads the fake VESC's motor ERPM and servo
position, moves the car, and the fake lidar ray-casts the map from the car's laser pose (x, y in
metres and yaw in radians in base_link, from the config's static transforms). The daemon's config
is pointed at the fakes' device paths and ports.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from lidar_drivers.params import HOKUYO_USB_MODELS
from lidar_drivers.registry import family, make_fake
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.transforms import TfTree, yaw_of
from racecar_hw.config import Config
from racecar_hw.runtime.devicethread import DeviceThread
from racecar_hw.sim.car import CarParams
from racecar_hw.sim.live import map_to_odom
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.pacer import Pacer
from racecar_hw.sim.scenario import CarSpec, FaultSpec, Scenario
from racecar_hw.sim.world import World
from vesc.codec import servo_on_wire
from vesc.fake import FakeVesc

#: Longest range the fake lidar casts, metres (UST-10LX: 10 m; others less matter little indoors).
LIDAR_MAX_RANGE_M = {"urg-04lx": 5.6, "ust-10lx": 10.0, "ust-20lx": 20.0, "utm-30lx": 30.0,
                     "utm-30lx-ew": 30.0}
#: The faults acted out on the fake devices and the world (the others reach the daemon).
DEVICE_FAULTS = frozenset(("lidar_unplug", "lidar_replug", "vesc_unplug", "vesc_replug", "vesc_garbage",
                           "obstacle_ahead", "clear_obstacles"))


class FakeRig:
    """The fakes of one run: in ``dev_dir`` on their own thread once :meth:`start` built them, or,
    with ``lockstep``, at ``mem://NAME/...`` in the running loop (``name``: the car's, unique in the
    process)."""

    def __init__(self, scenario: Scenario, occupancy: OccupancyMap, dev_dir: Path, *,
                 lockstep: bool = False, name: str = "car") -> None:
        self.scenario = scenario
        self.map = occupancy
        self.dev_dir = dev_dir
        self.lockstep = lockstep
        self.name = name
        self.devices: DeviceThread | None = None if lockstep else DeviceThread("sim-devices")
        self._tasks: list[asyncio.Future[Any]] = []
        self.vesc: FakeVesc | None = None
        self.lidar: Any = None
        self.world: World | None = None
        self.car_params: CarParams | None = None

    def start(self, config: Config) -> Config:
        """Build and start the fakes and the world for ``config``; returns it pointed at them."""
        sc = self.scenario
        model = sc.lidar.model
        if all(t.child_frame_id != "odom" for t in config.static_transforms):
            config.static_transforms.append(map_to_odom(sc.start))  # odometry drawn in the map
        laser = laser_pose(config)
        vesc = self.vesc = FakeVesc(self.device_path("vesc"), firmware=sc.firmware_version())
        self.car_params = car_params(config, sc.car)
        world = self.world = World(self.map, self.car_params, sc.start,
                                   erpm_source=lambda: vesc.erpm, servo_source=lambda: vesc.servo,
                                   laser_pose_in_base=laser, noise_std_m=sc.world.noise_std_m,
                                   seed=sc.world.seed, on_collision=vesc.stall)
        vesc.imu.motion = world.motion
        vesc.imu.mount = imu_pose(config)
        vesc.imu.errors.gyro_bias_dps = sc.car.gyro_bias_dps
        source = world.range_source(max_range=LIDAR_MAX_RANGE_M.get(model, 12.0))
        # TCP only where the real device has it: an Ethernet Hokuyo (USB models and RPLIDARs: pty)
        use_tcp = sc.lidar.transport == "tcp" and family(model) == "hokuyo" \
            and model not in HOKUYO_USB_MODELS
        lidar_path = self.device_path("lidar")
        if use_tcp and not self.lockstep:
            self.lidar = make_fake(model, source, tcp=("127.0.0.1", 0))
        else:
            self.lidar = make_fake(model, source, link=lidar_path)
        config.vesc.port = vesc.path
        if self.lockstep:  # the fakes first in the loop's queue: plugged in before a driver looks
            vesc.open()
            # the motor model stepped by the world's timer when both step on the same grid: one
            # loop timer instead of two, the motor first at each instant as when each had its own
            shared = vesc.tick_ns == Pacer(sc.world.rate_hz).period_ns
            self._tasks = [asyncio.ensure_future(c) for c in
                           (vesc.serve(motor_timer=not shared), self.lidar.serve(),
                            world.run(sc.world.rate_hz, before_step=vesc.step_motor if shared else None))]
            if use_tcp:  # the Ethernet link, in memory
                config.lidar.tcp, config.lidar.port = lidar_path, None
            else:
                config.lidar.port, config.lidar.tcp = lidar_path, None
            return config
        assert self.devices is not None
        self.devices.start()
        self.devices.spawn(vesc.serve())
        self.devices.spawn(self.lidar.serve())
        self.devices.spawn(world.run(sc.world.rate_hz))
        ready = getattr(self.lidar, "ready", None)
        if ready is not None and not ready.wait(10):
            raise RuntimeError("fake lidar did not start")
        if use_tcp:
            host, port = self.lidar.tcp_address
            config.lidar.tcp, config.lidar.port = f"{host}:{port}", None  # one set, the other null
        else:
            config.lidar.port, config.lidar.tcp = lidar_path, None
        return config

    def check(self, config: Config) -> None:
        """Build, without starting anything, what :meth:`start` builds from ``config`` that can
        refuse it: the fake VESC's firmware version, the lidar's mounting, the simulated car and its
        world at the start pose (a ConfigError naming the key)."""
        sc = self.scenario
        sc.firmware_version()
        World(self.map, car_params(config, sc.car), sc.start, laser_pose_in_base=laser_pose(config),
              noise_std_m=sc.world.noise_std_m, seed=sc.world.seed)

    def device_path(self, device: str) -> str:
        """Where the daemon finds ``device`` (vesc, lidar): a pty link in ``dev_dir``, or in
        lockstep ``mem://NAME/DEVICE``."""
        return f"mem://{self.name}/{device}" if self.lockstep else str(self.dev_dir / device)

    def stop(self) -> None:
        """Stop the device thread (the fakes and the world with it); in lockstep, cancel their
        tasks (:meth:`aclose` also waits for them)."""
        if self.devices is not None:
            self.devices.stop()
        for task in self._tasks:
            task.cancel()

    async def aclose(self) -> None:
        """:meth:`stop`, and in lockstep wait until the fakes have unplugged."""
        self.stop()
        tasks, self._tasks = self._tasks, []
        await asyncio.gather(*tasks, return_exceptions=True)
        if self.lockstep and self.vesc is not None:  # plugged in by start(), even if never served
            self.vesc.port.close()

    def apply(self, fault: FaultSpec) -> None:
        """Act out a fault of :data:`DEVICE_FAULTS` on the fakes or the world."""
        assert self.vesc is not None and self.world is not None
        action = fault.action
        tcp = getattr(self.lidar, "tcp_address", None) is not None
        if action == "lidar_unplug":
            if tcp:
                self.lidar.mute(True)
                self.lidar.drop_connection()
            else:
                self.lidar.unplug()
        elif action == "lidar_replug":
            if tcp:
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


def car_params(config: Config, true: CarSpec | None = None) -> CarParams:
    """The simulated car: calibrated for the daemon's config, so it drives straight at the
    servo position that reaches the VESC for steering 0 (the offset in thousandths, as the
    wire carries it: 0.5304 is sent as 0.530, and a car "straight" at 0.5304 would drift) and
    wired as its ``invert_motor`` and ``invert_servo`` say, except where the scenario's ``car``
    gives its true values."""
    v, fp = config.vesc, config.safety.footprint
    t = true if true is not None else CarSpec()

    def pick(value: Any, configured: Any) -> Any:
        return configured if value is None else value

    right = (t.steering_angle_to_servo_gain_right if t.steering_angle_to_servo_gain is not None
             else pick(t.steering_angle_to_servo_gain_right, v.steering_angle_to_servo_gain_right))
    # the car's true signs: a motor wired backwards, a mirrored servo (as the config's flags say
    # unless the scenario's car says otherwise)
    motor = -1.0 if pick(t.invert_motor, v.invert_motor) else 1.0
    servo = -1.0 if pick(t.invert_servo, v.invert_servo) else 1.0
    return CarParams(speed_to_erpm_gain=motor * pick(t.speed_to_erpm_gain, v.speed_to_erpm_gain),
                     speed_to_erpm_offset=v.speed_to_erpm_offset,
                     steering_angle_to_servo_gain=servo * pick(t.steering_angle_to_servo_gain,
                                                               v.steering_angle_to_servo_gain),
                     steering_angle_to_servo_gain_right=None if right is None else servo * right,
                     steering_angle_to_servo_offset=pick(t.steering_angle_to_servo_offset,
                                                         servo_on_wire(v.steering_angle_to_servo_offset)),
                     wheelbase=pick(t.wheelbase_m, v.wheelbase_m), length=fp.length_m,
                     width=fp.width_m, rear_overhang=fp.rear_overhang_m)


def laser_pose(config: Config) -> tuple[float, float, float]:
    """The laser's (x, y, yaw) in base_link, from the static transforms."""
    tree = TfTree.from_params(config.static_transforms)
    frame = config.lidar.frame_id
    if not tree.can_transform("base_link", frame):
        raise ConfigError("static_transforms", f"no transform from base_link to the lidar frame "
                                               f"{frame!r}: the simulated lidar needs one")
    m = tree.lookup("base_link", frame)
    return float(m[0, 3]), float(m[1, 3]), yaw_of(m)


def imu_pose(config: Config) -> tuple[float, float, float]:
    """The IMU's (x, y, yaw) in base_link from the static transforms; base_link itself when the
    config gives no ``base_link -> imu_frame_id``."""
    tree = TfTree.from_params(config.static_transforms)
    frame = config.vesc.imu_frame_id
    if not tree.can_transform("base_link", frame):
        return (0.0, 0.0, 0.0)
    m = tree.lookup("base_link", frame)
    return float(m[0, 3]), float(m[1, 3]), yaw_of(m)


__all__ = ["DEVICE_FAULTS", "LIDAR_MAX_RANGE_M", "FakeRig", "car_params", "imu_pose", "laser_pose"]
