"""One episode of the step API (:mod:`racecar_hw.sim.env`): a scenario's run in the env's loop, from
the car being ready to its teardown, and what a policy sees of it.

Units and frames: the scan in metres in the lidar's frame, odometry in the ``odom`` frame (x, y in
m, yaw in rad, forward speed in m/s, yaw rate in rad/s), the true pose in the map frame, times in
seconds of virtual time since the episode began (:attr:`Episode.t0_ns`).
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from racecar_hw.base.clock import NS_PER_S, wall_ns
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.base.topics import TOPIC_ODOM
from racecar_hw.config import Config
from racecar_hw.daemon import Daemon
from racecar_hw.runtime.lockstep import VirtualTimeLoop
from racecar_hw.sim.laps import LapProgress, infield_centre
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.report import SimResult
from racecar_hw.sim.scenario import Scenario
from racecar_hw.sim.world import World

log = logging.getLogger(__name__)

#: How long (virtual s) an episode waits for the car to be ready and the first odometry.
READY_TIMEOUT_S = 30.0
#: How often (virtual s) it looks whether the car is ready.
READY_POLL_S = 0.001


class Episode:
    """``scenario`` run by a :class:`~racecar_hw.sim.loopback.Loopback` in lockstep in ``loop``
    (not running: the caller drives it), with its duration unbounded; commands go to the mux input
    ``mux_input``. Laps are counted round ``lap_centre`` (None: the map's infield, if it has one).
    :meth:`start`, then :meth:`drive` and the observations, then :meth:`end`."""

    def __init__(self, loop: VirtualTimeLoop, scenario: Scenario, *,
                 config_path: str | Path | None, overrides: Sequence[str], car_name: str,
                 mux_input: str, lap_centre: tuple[float, float] | None) -> None:
        self.loop = loop
        self.scenario = scenario
        self.mux_input = mux_input
        self.lap_centre = lap_centre
        self.loopback = Loopback(scenario, config_path=config_path, overrides=tuple(overrides),
                                 lockstep=True, car_name=car_name, duration_s=math.inf)
        self._task: asyncio.Task[SimResult] | None = None
        self._topic = ""
        self._scan_topic = ""
        #: one step: the daemon's control period (``1 / mux.rate_hz``), ns
        self.period_ns = 0
        #: virtual time (ns) when the car was ready: the episode's time zero
        self.t0_ns = 0
        self.laps: LapProgress | None = None

    # --- life ------------------------------------------------------------------------------------

    def check(self) -> None:
        """Refuse, starting nothing, what :meth:`start` would refuse before its devices start (the
        scenario's config, drivers, firmware and start pose: :meth:`Loopback.check`) and a
        ``mux_input`` the config does not have; the map and a scenario with ``cars`` were refused
        when the episode was made. For while another episode runs, so a bad one leaves it running."""
        self._input_topic(self.loopback.check())

    def discard(self) -> None:
        """Forget an episode that will not start (after a refusal by :meth:`check`)."""
        self.loopback.discard()

    def start(self) -> None:
        """Start the run and the loop until the car is ready to drive (the VESC answered, a scan is
        in, odometry came). Raises what refused the scenario (a ConfigError naming the key), or
        ValueError for a ``mux_input`` the config does not have; then nothing of it runs."""
        task = self._task = self.loop.create_task(self.loopback.run())
        try:
            self.loop.run_until_complete(self._until_ready(task))
        except BaseException:
            self.end()
            raise
        if task.done():  # refused or failed while starting: nothing of it is left running
            self._task = None
            task.result()
            raise RuntimeError(f"the scenario {self.scenario.name or self.scenario.map!r} ended "
                               "while it started")
        config = self.loopback.config
        assert config is not None
        try:
            self._topic = self._input_topic(config)
        except ValueError:
            self.end()
            raise
        self._scan_topic = config.safety.scan_topic
        self.period_ns = round(NS_PER_S / config.mux.rate_hz)
        self.t0_ns = self.loop.now_ns()
        centre = self.lap_centre if self.lap_centre is not None else infield_centre(self.loopback.map)
        self.laps = LapProgress(centre, tuple(self.world.pose)) if centre is not None else None

    def check_running(self) -> None:
        """Raise if the run ended by itself (a component failed; the log says which)."""
        task = self._task
        if task is None:
            raise RuntimeError("the episode has ended: call reset()")
        if task.done():
            task.result()
            raise RuntimeError("the episode's simulation ended by itself (see the log)")

    def end(self) -> SimResult | None:
        """Stop the run as a run ends (the daemon brakes, centres and stops, the car rolls to rest,
        the fakes unplug); returns its report, or None if it failed (logged) or never ran."""
        task, self._task = self._task, None
        if task is None:
            return None
        self.loopback.request_stop("reset")
        self.loop.run_until_complete(asyncio.wait([task]))
        if task.cancelled():
            return None
        err = task.exception()
        if err is not None:
            log.warning("sim env: the episode's run failed: %r", err)
            return None
        return task.result()

    def _input_topic(self, config: Config) -> str:
        """The topic of the episode's mux input in ``config`` (ValueError: no such input)."""
        topics = {inp.name: inp.topic for inp in config.mux.inputs}
        if self.mux_input not in topics:
            raise ValueError(f"{self.mux_input!r} is not a mux input; inputs: {', '.join(topics)}")
        return topics[self.mux_input]

    async def _until_ready(self, task: asyncio.Task[SimResult]) -> None:
        loopback = self.loopback
        loop = asyncio.get_running_loop()
        deadline = loop.time() + READY_TIMEOUT_S
        while not task.done():
            daemon = loopback.daemon
            if (loopback.ready_at_s is not None and daemon is not None
                    and daemon.bus.latest(TOPIC_ODOM) is not None):
                return
            if loop.time() > deadline:
                raise RuntimeError(f"the simulated car was not ready after {READY_TIMEOUT_S:g} s "
                                   "of sim time")
            await asyncio.sleep(READY_POLL_S)

    # --- the parts -------------------------------------------------------------------------------

    @property
    def daemon(self) -> Daemon:
        daemon = self.loopback.daemon
        assert daemon is not None, "the episode has not started"
        return daemon

    @property
    def world(self) -> World:
        world = self.loopback.world
        assert world is not None, "the episode has not started"
        return world

    def drive(self, speed: float, steering: float) -> None:
        """Publish (speed m/s, steering rad) on the episode's mux input, as a navigation node would."""
        drive = AckermannDrive(steering_angle=steering, speed=speed)
        self.daemon.bus.publish(self._topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()), drive))

    def time_s(self, now_ns: int) -> float:
        """Episode time (s) of virtual time ``now_ns``."""
        return (now_ns - self.t0_ns) / NS_PER_S

    def scan_angles(self) -> np.ndarray:
        """The angle (rad, counter-clockwise, 0 ahead, lidar frame) of each scan range."""
        scan = self.daemon.bus.latest(self._scan_topic)
        return np.zeros(0) if scan is None else np.asarray(scan.angles(), dtype=np.float64)

    # --- what a policy sees ------------------------------------------------------------------------

    def observation(self) -> dict[str, Any]:
        """The latest scan, odometry and the safety controller's state (docs/sim.md, "Step API")."""
        daemon = self.daemon
        scan = daemon.bus.latest(self._scan_topic)
        odom = daemon.bus.latest(TOPIC_ODOM)
        if odom is not None:
            pose, twist = odom.pose.pose, odom.twist.twist
            odometry = np.array([pose.position.x, pose.position.y, pose.orientation.yaw(),
                                 twist.linear.x, twist.angular.z], dtype=np.float64)
        else:
            odometry = np.zeros(5)
        state = daemon.safety.state
        return {
            "scan": (np.array(scan.ranges, dtype=np.float32) if scan is not None
                     else np.zeros(0, dtype=np.float32)),
            "scan_time_s": self.time_s(scan.header.stamp.to_ns()) if scan is not None else math.nan,
            "odom": odometry,
            "safety": {"reason": state.reason, "intervening": bool(state.intervening),
                       "allowed_speed_mps": float(state.allowed_speed),
                       "interventions": int(daemon.safety.interventions)},
        }

    def info(self, now_ns: int, steps: int) -> dict[str, Any]:
        """The truth and the bookkeeping at virtual time ``now_ns`` after ``steps`` steps; counts
        the lap progress up to the car's position now."""
        world, mux = self.world, self.daemon.mux
        pose = world.pose
        progress = self.laps.update(pose.x, pose.y) if self.laps is not None else 0.0
        last = mux.last_output
        return {
            "time_s": self.time_s(now_ns),
            "steps": steps,
            "pose": np.array([pose.x, pose.y, pose.yaw], dtype=np.float64),
            "speed_mps": world.speed,
            "steering_rad": world.steering,
            "collided": world.collided,
            "distance_m": world.distance_travelled,
            "lap_progress": progress,
            "laps": self.laps.laps if self.laps is not None else 0,
            "mux_source": mux.source or "idle",
            "command": ((float(last.drive.speed), float(last.drive.steering_angle)) if last is not None
                        else (0.0, 0.0)),
        }


__all__ = ["READY_POLL_S", "READY_TIMEOUT_S", "Episode"]
