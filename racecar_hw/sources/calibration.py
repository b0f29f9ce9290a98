"""``racecar-hw calibrate``'s procedure: the car measures its own gains with its lidar and IMU.

It drives through a mux input like any navigation source, so the operator's deadman, higher
priority sources and the safety controller stay in charge; it only watches them and gives up
(brakes, says why) the moment one of them takes the car. The steps, with the car on a clear floor
facing a flat wall ``wall_distance_m`` ahead of the lidar:

1. **Stand still** (``still_s``): the gyro's z offset is the mean rate.
2. **Toward the wall** at ``speed_mps``, holding the heading with the gyro (a PI on the integrated
   yaw, so a wrong servo offset does not bend the path), until the wall is ``stop_distance_m``
   away; then **back** at ``reverse_speed_mps`` the same way. Each scan's fitted wall distance
   against the tachometer gives the ERPM gain (:func:`~racecar_hw.sources.calibration_fit.fit_erpm_gain`).
3. **Arcs**: for each steering command of ``arc_steering_rad``, left and right, forward for
   ``arc_s`` then back along the same arc. The steady part of each gives the servo position sent
   and the curvature, the gyro's yaw rate over the speed (from the ERPM and the new gain): the
   servo offset and the gain of each side (:func:`~racecar_hw.sources.calibration_fit.fit_steering`).

Aborts (:class:`CalibrationAborted`, the car braked first): the car disarmed or another source
(or a deadman lock, or an e-stop) took over; the safety controller intervened; no flat wall where
it should be, or the wall stops agreeing with the distance driven; the lidar, the IMU or the VESC's
telemetry went quiet. On the straight legs, before any of those could tell (:class:`StraightLeg`): the
wall moving ``WRONG_WAY_M`` the wrong way (the motor turns the other way: ``vesc.invert_motor``)
or the heading ``MAX_HEADING_DEG`` off (the heading hold steers the wrong way:
``vesc.invert_servo`` or the steering gain's sign).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Float64,
    Imu,
    LaserScan,
    VescStateStamped,
    stamp_now,
)
from racecar_hw.base.params import param
from racecar_hw.base.topics import TOPIC_CORE, TOPIC_IMU, TOPIC_SERVO
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.sources.calibration_fit import (
    Estimate,
    SteeringFit,
    WallFit,
    fit_erpm_gain,
    fit_steering,
    fit_wall,
)

#: Sensors silent for this long abort the procedure (s).
SILENT_S = 0.5
#: On a straight leg, the wall this much (m) farther when driving toward it (or nearer when backing):
#: the car drives the other way. The fitted distance varies by millimetres from scan to scan.
WRONG_WAY_M = 0.05
#: On a straight leg, the heading this far off (deg): the heading hold steers the wrong way. The sim's
#: car with its servo offset 0.15 off (0.11 rad of steering) peaks at 3.7 deg, then comes back.
MAX_HEADING_DEG = 5.0


class CalibrationAborted(Exception):
    """The procedure stopped the car; ``str()`` says why, for the operator."""


@dataclass
class CalibrationParams:
    """The procedure's set-up: where the wall is, how fast and how far to drive."""

    wall_distance_m: float = param(3.0, "distance from the lidar to the flat wall straight ahead "
                                   "at the start", unit="m", min=1.5, max=20.0)
    wall_tolerance_m: float = param(0.3, "how far the wall may be from wall_distance_m", unit="m",
                                    min=0.05, max=2.0)
    stop_distance_m: float = param(1.2, "the approach ends with the wall this close to the lidar",
                                   unit="m", min=0.5, max=10.0)
    speed_mps: float = param(0.5, "speed toward the wall and on the arcs", unit="m/s", min=0.1, max=2.0)
    reverse_speed_mps: float = param(0.4, "speed back from the wall and along the arcs", unit="m/s",
                                     min=0.1, max=2.0)
    still_s: float = param(3.0, "standing still for the gyro bias", unit="s", min=0.5, max=60.0)
    arc_steering_rad: list[float] = param([0.08, 0.15, 0.22], "steering commands of the arcs, each "
                                          "driven left and right", unit="rad")
    arc_s: float = param(1.6, "each arc's drive forward (and back)", unit="s", min=0.5, max=10.0)
    settle_s: float = param(0.6, "the start of each arc left out of its average", unit="s", min=0.1,
                            max=5.0)
    wheelbase_m: float = param(0.25, "the measured wheelbase (curvature to steering angle)", unit="m",
                               min=0.05, max=2.0)
    input_topic: str = param("/vesc/high_level/ackermann_cmd_mux/input/nav_0",
                             "mux input the procedure drives")
    input_name: str = param("nav_0", "that input's name, to tell when another source takes over")
    rate_hz: float = param(50.0, "command rate", unit="Hz", min=10.0, max=200.0)
    configured_erpm_gain: float = param(4614.0, "the config's ERPM gain: a wall whose distance changes "
                                        "by far more or less than the distance driven says so is not "
                                        "a wall to trust", unit="ERPM/(m/s)", min=1.0, max=100000.0)
    invert_motor: bool = param(False, "the config's vesc.invert_motor: the motor's ERPM and tachometer "
                                      "count backwards as the car drives forward")


@dataclass
class CarWatch:
    """What the procedure watches besides the sensors (the daemon's state): each is a callable."""

    armed: Callable[[], bool]
    source: Callable[[], str | None]            #: the mux's active source
    intervention: Callable[[], str | None]      #: why the safety controller limits, or None


@dataclass
class Arc:
    """One arc's steady part: the servo position sent, the gyro's yaw rate and the motor's ERPM."""

    steering_cmd_rad: float
    servo: float
    yaw_rate: float
    erpm: float

    def curvature(self, erpm_gain: float) -> float:
        """1/m, positive left: yaw rate over speed."""
        return self.yaw_rate / (self.erpm / erpm_gain)


@dataclass
class CalibrationResult:
    """What the procedure found."""

    gyro_bias: Estimate                       #: rad/s
    erpm_gain: Estimate                       #: ERPM per m/s
    steering: SteeringFit
    arcs: list[Arc] = field(default_factory=list)
    #: the straight legs' samples: (tachometer, wall distance m, wall normal rad) per scan
    legs: list[list[tuple[float, float, float]]] = field(default_factory=list)


@dataclass
class _Sensors:
    """The latest of each sensor, with its monotonic arrival time (ns)."""

    tach: list[tuple[int, float]] = field(default_factory=list)  # the last two (t, tachometer)
    erpm: float = 0.0
    core_ns: int = 0
    gyro_z: float = 0.0
    imu_ns: int = 0
    servo: float = math.nan
    wall: WallFit | None = None
    scan_ns: int = 0


class CalibrationProcedure:
    """Drives the steps on ``bus`` and returns a :class:`CalibrationResult` from :meth:`run`."""

    def __init__(self, bus: Bus, params: CalibrationParams, watch: CarWatch,
                 say: Callable[[str], None] = lambda text: None) -> None:
        self.bus = bus
        self.params = params
        self.watch = watch
        self.say = say
        self.step = "waiting for the sensors"
        self._s = _Sensors()
        self._ticker = Ticker(params.rate_hz)
        self._bias = 0.0
        self._heading = 0.0
        self._recording: list[tuple[float, float, float]] | None = None  # (tach, distance, normal)
        self._subs = [bus.subscribe("/scan", self._on_scan), bus.subscribe(TOPIC_IMU, self._on_imu),
                      bus.subscribe(TOPIC_CORE, self._on_core), bus.subscribe(TOPIC_SERVO, self._on_servo)]
        bus.declare(params.input_topic, AckermannDriveStamped)

    def close(self) -> None:
        """Stop listening."""
        for sub in self._subs:
            sub.close()
        self._subs = []

    # --- sensors ----------------------------------------------------------------------------------

    def _on_scan(self, scan: LaserScan) -> None:
        now = monotonic_ns()
        s = self._s
        s.scan_ns = now
        s.wall = fit_wall(scan.ranges, scan.angle_min, scan.angle_increment, range_max=scan.range_max)
        if self._recording is not None and s.wall is not None and len(s.tach) == 2:
            (t0, k0), (t1, k1) = s.tach
            tach = k1 if t1 == t0 else k0 + (k1 - k0) * (now - t0) / (t1 - t0)
            self._recording.append((tach, s.wall.distance_m, s.wall.normal_rad))

    def _on_imu(self, msg: Imu) -> None:
        if msg.angular_velocity_covariance[0] == -1.0:
            return  # a reply without the gyro (sensor_msgs/Imu: not provided), not a rate of 0
        now = monotonic_ns()
        s = self._s
        if s.imu_ns:
            self._heading += (msg.angular_velocity.z - self._bias) * (now - s.imu_ns) / NS_PER_S
        s.gyro_z, s.imu_ns = float(msg.angular_velocity.z), now

    def _on_core(self, msg: VescStateStamped) -> None:
        now = monotonic_ns()
        s = self._s
        # counted the way the car drives: a motor wired backwards (vesc.invert_motor) counts its
        # tachometer down and its ERPM negative going forward, and the ERPM gain is a magnitude
        sign = -1.0 if self.params.invert_motor else 1.0
        s.tach = [*s.tach[-1:], (now, sign * float(msg.state.displacement))]
        s.erpm, s.core_ns = sign * float(msg.state.speed), now

    def _on_servo(self, msg: Float64) -> None:
        self._s.servo = float(msg.data)

    # --- the steps --------------------------------------------------------------------------------

    async def run(self) -> CalibrationResult:
        """Every step; the car is stopped when this returns or raises."""
        p = self.params
        try:
            await self._wait_for_sensors()
            self._check_wall_at_start()
            bias = await self._stand_still()
            self._bias = bias.value
            self.step = "toward the wall"
            self.say(f"gyro bias {bias.value:.4f} rad/s; driving toward the wall at {p.speed_mps} m/s")
            start_distance = self._wall().distance_m
            approach = await self._straight(p.speed_mps, lambda d: d <= p.stop_distance_m)
            self.step = "back from the wall"
            back = await self._straight(-p.reverse_speed_mps, lambda d: d >= start_distance - 0.1)
            gain = fit_erpm_gain([_leg(approach), _leg(back)])
            if not math.isfinite(gain.value):
                raise CalibrationAborted("the wall distance did not change with the distance driven: "
                                         "is the wall flat and straight ahead?")
            self.say(f"ERPM gain {gain.value:.0f} per m/s; now the arcs")
            arcs = []
            for steering in [s * side for s in p.arc_steering_rad for side in (1.0, -1.0)]:
                self.step = f"arc at {steering:+.2f} rad"
                arcs.append(await self._arc(steering, p.speed_mps))
                arcs.append(await self._arc(steering, -p.reverse_speed_mps))
                self.say(f"arc at {steering:+.2f} rad: curvature {arcs[-2].curvature(gain.value):+.3f} "
                         f"and {arcs[-1].curvature(gain.value):+.3f} 1/m (forward, back)")
            curvature = np.array([a.curvature(gain.value) for a in arcs])
            steering_fit = fit_steering(np.array([a.servo for a in arcs]), curvature, p.wheelbase_m)
            self.step = "done"
            return CalibrationResult(bias, gain, steering_fit, arcs, [approach, back])
        finally:
            await self._brake()

    async def _wait_for_sensors(self, timeout_s: float = 15.0) -> None:
        deadline = monotonic_ns() + int(timeout_s * NS_PER_S)
        while not (self._s.scan_ns and self._s.imu_ns and self._s.core_ns):
            if monotonic_ns() > deadline:
                missing = [name for name, t in (("a scan", self._s.scan_ns), ("the IMU", self._s.imu_ns),
                                                ("the VESC's telemetry", self._s.core_ns)) if not t]
                raise CalibrationAborted(f"no {', no '.join(missing)} after {timeout_s:.0f} s (the IMU "
                                         "needs VESC firmware 3.52 or later and vesc.imu on)")
            await asyncio.sleep(0.05)
        if not self.watch.armed():
            self.say("waiting for the operator to arm the car")
        while not self.watch.armed():
            await asyncio.sleep(0.05)

    def _wall(self) -> WallFit:
        wall = self._s.wall
        if wall is None or wall.rms_m > 0.05:
            why = "no flat surface" if wall is None else f"a surface {wall.rms_m * 100:.0f} cm from flat"
            raise CalibrationAborted(f"the wall is not where it should be: {why} straight ahead")
        return wall

    def _check_wall_at_start(self) -> None:
        p = self.params
        wall = self._wall()
        if abs(wall.distance_m - p.wall_distance_m) > p.wall_tolerance_m:
            raise CalibrationAborted(f"the wall is not where it should be: expected "
                                     f"{p.wall_distance_m:.2f} m ahead of the lidar, found "
                                     f"{wall.distance_m:.2f} m")
        if abs(wall.normal_rad) > 0.3:
            raise CalibrationAborted(f"the wall is {math.degrees(wall.normal_rad):.0f} deg off square: "
                                     "face it squarely (within 15 deg)")
        if p.stop_distance_m >= wall.distance_m - 0.5:
            raise CalibrationAborted(f"the wall ({wall.distance_m:.2f} m) is too close for an approach to "
                                     f"{p.stop_distance_m:.2f} m")

    def _check(self, driving: bool) -> None:
        """Raise :class:`CalibrationAborted` if the operator, the safety controller or a sensor says stop."""
        if not self.watch.armed():
            raise CalibrationAborted(f"stopped during {self.step}: the operator let go "
                                     "(the car was disarmed)")
        source = self.watch.source()
        if driving and source not in (self.params.input_name, None):
            raise CalibrationAborted(f"stopped during {self.step}: the operator took over "
                                     f"(the mux's source is {source})")
        why = self.watch.intervention()
        if why is not None:
            raise CalibrationAborted(f"stopped during {self.step}: the safety controller intervened ({why})")
        now = monotonic_ns()
        silent = [name for name, t in (("lidar", self._s.scan_ns), ("IMU", self._s.imu_ns),
                                       ("VESC telemetry", self._s.core_ns))
                  if now - t > SILENT_S * NS_PER_S]
        if silent:
            raise CalibrationAborted(f"stopped during {self.step}: no {', '.join(silent)} for "
                                     f"{SILENT_S} s")

    def _send(self, speed: float, steering: float) -> None:
        self.bus.publish(self.params.input_topic, AckermannDriveStamped(
            stamp_now("base_link", wall_ns()), AckermannDrive(steering_angle=steering, speed=speed)))

    async def _hold(self, seconds: float, speed: float = 0.0, steering: float = 0.0,
                    driving: bool = False) -> None:
        end = monotonic_ns() + int(seconds * NS_PER_S)
        while (await self._ticker.tick()) < end:
            self._check(driving)
            self._send(speed, steering)

    async def _stop_and_settle(self) -> None:
        """Zero speed until the motor stands still (and 0.3 s more)."""
        deadline = monotonic_ns() + 5 * NS_PER_S
        while abs(self._s.erpm) > 0 and monotonic_ns() < deadline:
            await self._hold(0.05)
        await self._hold(0.3)

    async def _stand_still(self) -> Estimate:
        self.step = "standing still"
        self.say(f"standing still {self.params.still_s:.0f} s for the gyro bias")
        await self._stop_and_settle()
        rates: list[float] = []
        last = self._s.imu_ns
        end = monotonic_ns() + int(self.params.still_s * NS_PER_S)
        while (await self._ticker.tick()) < end:
            self._check(False)
            self._send(0.0, 0.0)
            if self._s.imu_ns != last:
                last = self._s.imu_ns
                rates.append(self._s.gyro_z)
        if len(rates) < 10:
            raise CalibrationAborted("the IMU gave fewer than 10 readings while standing still")
        r = np.array(rates)
        return Estimate(float(r.mean()), float(r.std(ddof=1) / math.sqrt(len(r))), float(r.std()), len(r))

    async def _straight(self, speed: float,
                        done: Callable[[float], bool]) -> list[tuple[float, float, float]]:
        """Drive at ``speed`` holding the heading until ``done(wall distance)``; the leg's samples."""
        await self._stop_and_settle()
        self._heading = 0.0
        steer_bias = 0.0
        samples: list[tuple[float, float, float]] = []
        direction = 1.0 if speed > 0 else -1.0
        leg = StraightLeg(self.step, direction, self._wall().distance_m, self.params.configured_erpm_gain)
        started = monotonic_ns()
        max_s = 3.0 * abs(self.params.wall_distance_m) / abs(speed) + 5.0
        while True:
            now = await self._ticker.tick()
            self._check(driving=now - started > 0.3 * NS_PER_S)
            distance = self._wall().distance_m
            if now - started > 0.8 * NS_PER_S and self._recording is None:  # at speed: record
                self._recording = samples
                leg.first = (self._s.tach[-1][1], distance)
            leg.check(distance, self._heading, self._s.tach[-1][1])
            if done(distance) or now - started > max_s * NS_PER_S:
                break
            # a PI on the heading: the integral learns the steering that truly drives straight
            steer_bias -= direction * 0.8 * self._heading / self.params.rate_hz
            steering = steer_bias - direction * 1.5 * self._heading
            self._send(speed, max(-0.2, min(0.2, steering)))
        self._recording = None
        await self._stop_and_settle()
        return samples

    async def _arc(self, steering: float, speed: float) -> Arc:
        """Drive an arc; the averages over its steady part."""
        p = self.params
        await self._hold(p.settle_s, speed, steering, driving=False)
        servo, yaw, erpm = [], [], []
        last = self._s.imu_ns
        end = monotonic_ns() + int(max(p.arc_s - p.settle_s, 0.3) * NS_PER_S)
        while (await self._ticker.tick()) < end:
            self._check(True)
            self._send(speed, steering)
            if self._s.imu_ns != last:
                last = self._s.imu_ns
                servo.append(self._s.servo)
                yaw.append(self._s.gyro_z - self._bias)
                erpm.append(self._s.erpm)
        await self._stop_and_settle()
        if len(yaw) < 5:
            raise CalibrationAborted(f"too few IMU readings on the arc at {steering:+.2f} rad")
        return Arc(steering, float(np.median(servo)), float(np.mean(yaw)), float(np.mean(erpm)))

    async def _brake(self) -> None:
        """Zero commands for a moment, whatever happened (the mux times the input out after that)."""
        for _ in range(int(self.params.rate_hz * 0.3)):
            self._send(0.0, 0.0)
            await asyncio.sleep(1.0 / self.params.rate_hz)


@dataclass
class StraightLeg:
    """A straight leg's checks, each scan: which way the car goes, whether its heading holds, whether
    the wall keeps agreeing with the distance driven (once ``first`` is set)."""

    step: str
    direction: float            #: +1 toward the wall, -1 back
    start_m: float              #: the wall's distance at the start
    erpm_gain: float            #: the config's, for the distance driven
    first: tuple[float, float] | None = None  #: (tachometer, wall distance) from where it is compared

    def check(self, distance: float, heading: float, tach: float) -> None:
        """Raise :class:`CalibrationAborted` naming the likely config key (or the wall) if wrong."""
        wrong_way = (distance - self.start_m) * self.direction
        if wrong_way > WRONG_WAY_M:
            told, went = ("toward", "away from") if self.direction > 0 else ("away from", "toward")
            raise CalibrationAborted(f"stopped during {self.step}: the car drove {went} the wall when told "
                                     f"to drive {told} it ({wrong_way:.2f} m): the motor turns the other "
                                     "way; check vesc.invert_motor")
        if abs(deg := math.degrees(heading)) > MAX_HEADING_DEG:
            raise CalibrationAborted(f"stopped during {self.step}: the car turned {deg:+.0f} "
                                     "deg off its heading while the heading hold steered against it: the "
                                     "steering goes the other way; check vesc.invert_servo (or the sign of "
                                     "vesc.steering_angle_to_servo_gain)")
        if self.first is not None:  # the wall's distance changed far more or less than the car drove
            driven = abs(tach - self.first[0]) * 10.0 / self.erpm_gain
            moved = abs(distance - self.first[1])
            if abs(moved - driven) > 0.3 * driven + 0.3:
                raise CalibrationAborted(f"stopped during {self.step}: the wall is not where it should be "
                                         f"(it moved {moved:.2f} m while the car drove about {driven:.2f} m)")


def _leg(samples: list[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.array(samples, dtype=np.float64).reshape(-1, 3)
    return a[:, 0], a[:, 1], a[:, 2]
