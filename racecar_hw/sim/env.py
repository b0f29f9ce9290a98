"""A step API for learning and sweeps: the real daemon on the fakes, in lockstep, one control period
per step.

:class:`RaceEnv` owns a :class:`~racecar_hw.runtime.lockstep.VirtualTimeLoop` (as fast as the
machine allows) and drives it from the caller's thread. ``reset(scenario, seed=...)`` starts a
:class:`~racecar_hw.sim.loopback.Loopback` of the scenario in that loop (the fakes, the world and
the unchanged daemon, network interfaces off) and returns once the car is ready to drive;
``step((speed, steering))`` publishes the command on a mux input (``nav_0``) and runs the loop
until one control period (``1 / mux.rate_hz``: 20 ms by default) of virtual time has passed and
nothing is left to do at that instant. The shapes are Gymnasium's (``reset -> (observation,
info)``, ``step -> (observation, reward, terminated, truncated, info)``) without depending on it;
docs/sim.md ("Step API") compares it with f1tenth_gym.

Units and frames: speed in m/s, steering in rad (+ left); the scan in metres in the lidar's frame
(``laser``), counter-clockwise from ``angle_min``; odometry (x, y, yaw, forward speed, yaw rate) in
the ``odom`` frame, which starts where the car starts; the true pose (``info["pose"]``) in the map
frame; times in seconds of virtual time since the episode began.

The process's clock (:mod:`racecar_hw.base.clock`) follows the env's loop from construction to
:meth:`RaceEnv.close`: one env per process at a time (run envs side by side in processes).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from racecar_hw.base.clock import NS_PER_S, use_virtual_time, wall_ns
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.base.topics import TOPIC_ODOM
from racecar_hw.daemon import Daemon
from racecar_hw.runtime import lockstep
from racecar_hw.runtime.lockstep import VirtualTimeLoop
from racecar_hw.sim.laps import LapProgress, infield_centre
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.report import SimResult
from racecar_hw.sim.scenario import Scenario, load_scenario
from racecar_hw.sim.world import World

log = logging.getLogger(__name__)

#: The scenario an env runs unless told otherwise: the track map with nobody else driving.
DEFAULT_SCENARIO = "track"
#: Config overrides an env applies before the caller's: no network interfaces (speed, and many
#: envs on one machine without port clashes) and no /rosout records.
ENV_OVERRIDES = ("zenoh.enabled=false", "dds.enabled=false", "foxglove.enabled=false",
                 "web.enabled=false", "rosout.enabled=false")
#: How long (virtual s) :meth:`RaceEnv.reset` waits for the car to be ready and the first odometry.
READY_TIMEOUT_S = 30.0
#: How often (virtual s) reset looks whether the car is ready.
READY_POLL_S = 0.001


class RaceEnv:
    """One simulated car stepped one control period at a time; see the module docstring.

    ``scenario``: what :meth:`reset` runs when not told (a shipped name, a scenario file, or a
    :class:`Scenario`). ``config_path``, ``overrides``: the daemon's config (default the sim's)
    and ``key=value`` settings after :data:`ENV_OVERRIDES` (turn an interface back on here).
    ``mux_input``: the mux input the actions go to. ``max_episode_s``: virtual seconds after which an
    episode is truncated. ``max_laps``: an episode ends (terminated) after this many laps; None:
    never. ``lap_centre``: the point in the infield laps are counted round (map frame, m); None:
    :func:`~racecar_hw.sim.laps.infield_centre` of the scenario's map.
    """

    def __init__(self, scenario: str | Path | Scenario = DEFAULT_SCENARIO, *,
                 config_path: str | Path | None = None, overrides: Sequence[str] = (),
                 mux_input: str = "nav_0", max_episode_s: float = 60.0, max_laps: int | None = None,
                 lap_centre: tuple[float, float] | None = None, car_name: str = "env") -> None:
        if not (max_episode_s > 0):
            raise ValueError(f"max_episode_s must be positive, got {max_episode_s!r}")
        self.scenario = scenario
        self.config_path = config_path
        self.overrides = (*ENV_OVERRIDES, *overrides)
        self.mux_input = mux_input
        self.max_episode_s = float(max_episode_s)
        self.max_laps = max_laps
        self.lap_centre = lap_centre
        self.car_name = car_name
        self.loop = VirtualTimeLoop(None)
        self._clock = use_virtual_time(self.loop.now_ns)
        try:
            self._clock.__enter__()  # left in close()
        except BaseException:
            self.loop.close()
            raise
        self._closed = False
        #: the episode running now (None before the first reset)
        self.loopback: Loopback | None = None
        self._task: asyncio.Task[SimResult] | None = None
        #: what the last episode's run returned when it was torn down (its report)
        self.last_result: SimResult | None = None
        self._topic = ""
        self._scan_topic = ""
        self.period_ns = 0
        self._t0_ns = 0
        self.steps = 0
        self._laps: LapProgress | None = None

    # --- the parts of the episode ---------------------------------------------------------------

    @property
    def daemon(self) -> Daemon:
        """The episode's daemon (after :meth:`reset`)."""
        if self.loopback is None or self.loopback.daemon is None:
            raise RuntimeError("no episode: call reset() first")
        return self.loopback.daemon

    @property
    def world(self) -> World:
        """The episode's world (after :meth:`reset`)."""
        if self.loopback is None or self.loopback.world is None:
            raise RuntimeError("no episode: call reset() first")
        return self.loopback.world

    @property
    def period_s(self) -> float:
        """One step: the daemon's control period (``1 / mux.rate_hz``), s (after :meth:`reset`)."""
        return self.period_ns / NS_PER_S

    @property
    def scan_angles(self) -> np.ndarray:
        """The angle (rad, counter-clockwise, 0 ahead, lidar frame) of each of the observation's
        scan ranges (after :meth:`reset`)."""
        scan = self.daemon.bus.latest(self._scan_topic)
        if scan is None:
            return np.zeros(0)
        return np.asarray(scan.angles(), dtype=np.float64)

    @property
    def time_s(self) -> float:
        """Virtual seconds since the episode began (reset returned)."""
        return (self.loop.now_ns() - self._t0_ns) / NS_PER_S

    # --- the API --------------------------------------------------------------------------------

    def reset(self, scenario: str | Path | Scenario | None = None, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """End the running episode (its daemon stopped, its fakes unplugged) and start ``scenario``
        (default: the env's) with the world's random seed ``seed`` (None: the scenario's
        ``world.seed``); returns once the car is ready to drive: ``(observation, info)``.
        ``options``: Gymnasium's reset options; ``{"scenario": ...}`` is the same as ``scenario``."""
        self._check_open()
        options = dict(options or {})
        if scenario is None:
            scenario = options.pop("scenario", None)
        if set(options) - {"scenario"}:
            raise ValueError(f"unknown reset options {sorted(set(options) - {'scenario'})}; "
                             "the one option is 'scenario'")
        self._end_episode()
        self.loop.run_until_time(self.loop.now_ns())  # what the teardown left to do at this instant
        self.loop.rewind()  # every episode from the same virtual time: the same seed, the same run
        sc = self._scenario(scenario if scenario is not None else self.scenario)
        if seed is not None:
            sc = dataclasses.replace(sc, world=dataclasses.replace(sc.world, seed=int(seed)))
        loopback = Loopback(sc, config_path=self.config_path, overrides=self.overrides,
                            lockstep=True, car_name=self.car_name, duration_s=math.inf)
        self.loopback = loopback
        task = self._task = self.loop.create_task(loopback.run())
        try:
            self.loop.run_until_complete(self._until_ready(loopback, task))
        except BaseException:
            self._end_episode()
            raise
        if task.done():  # refused or failed while starting: nothing of it is left running
            self._task = self.loopback = None
            task.result()  # raises what refused the scenario (a ConfigError naming the key)
            raise RuntimeError(f"the scenario {sc.name or sc.map!r} ended while it started")
        config = loopback.config
        assert config is not None
        topics = {inp.name: inp.topic for inp in config.mux.inputs}
        if self.mux_input not in topics:
            self._end_episode()
            raise ValueError(f"{self.mux_input!r} is not a mux input; inputs: {', '.join(topics)}")
        self._topic = topics[self.mux_input]
        self._scan_topic = config.safety.scan_topic
        self.period_ns = round(NS_PER_S / config.mux.rate_hz)
        self._t0_ns = self.loop.now_ns()
        self.steps = 0
        centre = self.lap_centre if self.lap_centre is not None else infield_centre(loopback.map)
        self._laps = LapProgress(centre, tuple(self.world.pose)) if centre is not None else None
        return self._observation(), self._info()

    def step(self, action: Sequence[float]) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        """Send ``action`` = (speed m/s, steering rad, + left) on the env's mux input and run one
        control period: ``(observation, reward, terminated, truncated, info)``.

        The reward is the lap progress of this step (laps; 0 without a lap centre). Terminated: the
        car collided (the world's contact, latched), or ``max_laps`` laps are done. Truncated: the
        episode reached ``max_episode_s``. Stepping on after either is allowed; reset to start over.
        """
        self._check_open()
        task = self._task
        if task is None or self.loopback is None:
            raise RuntimeError("no episode: call reset() first")
        if task.done():
            task.result()
            raise RuntimeError("the episode's simulation ended by itself (see the log)")
        speed, steering = _action(action)
        drive = AckermannDrive(steering_angle=steering, speed=speed)
        self.daemon.bus.publish(self._topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()), drive))
        before = self._laps.progress if self._laps is not None else 0.0
        self.steps += 1
        self.loop.run_until_time(self._t0_ns + self.steps * self.period_ns)
        obs, info = self._observation(), self._info()
        reward = info["lap_progress"] - before if self._laps is not None else 0.0
        terminated = bool(info["collided"]) or (self.max_laps is not None and info["laps"] >= self.max_laps)
        truncated = not terminated and self.time_s >= self.max_episode_s - 1e-9
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        """End the episode, close the loop and give the process its real clock back (safe twice)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._end_episode()
        finally:
            try:
                lockstep.close(self.loop)
            finally:
                self._clock.__exit__(None, None, None)

    def __enter__(self) -> RaceEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- inside ---------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("the env is closed")

    @staticmethod
    def _scenario(scenario: str | Path | Scenario) -> Scenario:
        return scenario if isinstance(scenario, Scenario) else load_scenario(str(scenario))

    async def _until_ready(self, loopback: Loopback, task: asyncio.Task[SimResult]) -> None:
        """Until the car is ready to drive (the VESC answered, a scan is in) and odometry came."""
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

    def _end_episode(self) -> None:
        """Stop the running episode (the daemon brakes and stops, the fakes unplug), if any."""
        task, loopback = self._task, self.loopback
        self._task = None
        if task is None or loopback is None:
            return
        loopback.request_stop("reset")
        self.loop.run_until_complete(asyncio.wait([task]))
        if task.cancelled():
            return
        err = task.exception()
        if err is not None:
            log.warning("sim env: the episode's run failed: %r", err)
        else:
            self.last_result = task.result()

    def _observation(self) -> dict[str, Any]:
        daemon = self.daemon
        bus = daemon.bus
        scan = bus.latest(self._scan_topic)
        odom = bus.latest(TOPIC_ODOM)
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
            "scan_time_s": (self._episode_time(scan.header.stamp.to_ns()) if scan is not None
                            else math.nan),
            "odom": odometry,
            "safety": {"reason": state.reason, "intervening": bool(state.intervening),
                       "allowed_speed_mps": float(state.allowed_speed),
                       "interventions": int(daemon.safety.interventions)},
        }

    def _info(self) -> dict[str, Any]:
        world = self.world
        pose = world.pose
        progress = self._laps.update(pose.x, pose.y) if self._laps is not None else 0.0
        last = self.daemon.mux.last_output
        return {
            "time_s": self.time_s,
            "steps": self.steps,
            "pose": np.array([pose.x, pose.y, pose.yaw], dtype=np.float64),
            "speed_mps": world.speed,
            "steering_rad": world.steering,
            "collided": world.collided,
            "distance_m": world.distance_travelled,
            "lap_progress": progress,
            "laps": self._laps.laps if self._laps is not None else 0,
            "mux_source": self.daemon.mux.source or "idle",
            "command": ((float(last.drive.speed), float(last.drive.steering_angle)) if last is not None
                        else (0.0, 0.0)),
        }

    def _episode_time(self, stamp_ns: int) -> float:
        return (stamp_ns - self._t0_ns) / NS_PER_S


def _action(action: Sequence[float]) -> tuple[float, float]:
    """(speed, steering) from an action; refuses a wrong shape or a value that is not finite."""
    try:
        speed, steering = (float(v) for v in np.asarray(action, dtype=np.float64).reshape(-1))
    except (TypeError, ValueError) as err:
        raise ValueError(f"an action is (speed m/s, steering rad), got {action!r}") from err
    if not (math.isfinite(speed) and math.isfinite(steering)):
        raise ValueError(f"an action must be finite, got speed {speed!r}, steering {steering!r}")
    return speed, steering


__all__ = ["DEFAULT_SCENARIO", "ENV_OVERRIDES", "READY_TIMEOUT_S", "RaceEnv"]
