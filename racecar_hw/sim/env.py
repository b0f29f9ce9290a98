"""A step API for learning and sweeps: the real daemon on the fakes, in lockstep, one control period
per step.

:class:`RaceEnv` owns a :class:`~racecar_hw.runtime.lockstep.VirtualTimeLoop` (as fast as the
machine allows) and drives it from the caller's thread. ``reset(scenario, seed=...)`` starts an
:class:`~racecar_hw.sim.episode.Episode` of the scenario in that loop (the fakes, the world and the
unchanged daemon, network interfaces off) and returns once the car is ready to drive;
``step((speed, steering))`` publishes the command on a mux input (``nav_0``) and runs the loop
until one control period (``1 / mux.rate_hz``: 20 ms by default) of virtual time has passed and
nothing is left to do at that instant. The shapes are Gymnasium's (``reset -> (observation,
info)``, ``step -> (observation, reward, terminated, truncated, info)``) without depending on it;
docs/sim.md ("Step API") lists the observation and compares it with f1tenth_gym.

Units and frames: speed in m/s, steering in rad (+ left); the scan in metres in the lidar's frame
(``laser``), counter-clockwise from ``angle_min``; odometry (x, y, yaw, forward speed, yaw rate) in
the ``odom`` frame, which starts where the car starts; the true pose (``info["pose"]``) in the map
frame; times in seconds of virtual time since the episode began.

Virtual time restarts at every reset, so an episode with a seed runs the same whatever ran before
it. The process's clock (:mod:`racecar_hw.base.clock`) follows the env's loop from construction to
:meth:`RaceEnv.close`: one env per process at a time (run envs side by side in processes).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import reprlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from racecar_hw.base.clock import NS_PER_S, use_virtual_time
from racecar_hw.daemon import Daemon
from racecar_hw.runtime import lockstep
from racecar_hw.runtime.lockstep import VirtualTimeLoop
from racecar_hw.sim.episode import READY_TIMEOUT_S, Episode
from racecar_hw.sim.loopback import OFFLINE_OVERRIDES, Loopback
from racecar_hw.sim.report import SimResult
from racecar_hw.sim.scenario import Scenario, load_scenario
from racecar_hw.sim.world import World
from vesc.ackermann import AckermannConversion

#: The scenario an env runs unless told otherwise: the track map with nobody else driving.
DEFAULT_SCENARIO = "track"
#: Config overrides an env applies before the caller's: no network interfaces (speed, and many
#: envs on one machine without port clashes) and no /rosout records.
ENV_OVERRIDES = OFFLINE_OVERRIDES


class RaceEnv:
    """One simulated car stepped one control period at a time; see the module docstring.

    ``scenario``: what :meth:`reset` runs when not told (a shipped name, a scenario file, or a
    :class:`Scenario`). ``config_path``, ``overrides``: the daemon's config (default the sim's)
    and ``key=value`` settings after :data:`ENV_OVERRIDES` (turn an interface back on here).
    ``mux_input``: the mux input the actions go to. ``max_episode_s``: virtual seconds after which
    an episode is truncated. ``max_laps``: an episode ends (terminated) after this many laps; None:
    never. ``lap_centre``: the point in the infield laps are counted round (map frame, m); None:
    :func:`~racecar_hw.sim.laps.infield_centre` of the scenario's map. ``car_name``: the name of
    the in-memory device links (``mem://NAME/vesc``).
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
        self.max_laps = _max_laps(max_laps)
        self.lap_centre = _lap_centre(lap_centre)
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
        self.episode: Episode | None = None
        #: what the last episode's run returned when it was torn down (its report)
        self.last_result: SimResult | None = None
        #: steps since the last reset
        self.steps = 0

    # --- the parts of the episode ---------------------------------------------------------------

    def _running(self) -> Episode:
        if self._closed:
            raise RuntimeError("the env is closed")
        if self.episode is None:
            raise RuntimeError("no episode: call reset() first")
        return self.episode

    @property
    def loopback(self) -> Loopback:
        """The episode's run: its fakes, world and daemon (after :meth:`reset`)."""
        return self._running().loopback

    @property
    def daemon(self) -> Daemon:
        """The episode's daemon (after :meth:`reset`)."""
        return self._running().daemon

    @property
    def world(self) -> World:
        """The episode's world (after :meth:`reset`)."""
        return self._running().world

    @property
    def period_s(self) -> float:
        """One step: the daemon's control period (``1 / mux.rate_hz``), s (after :meth:`reset`)."""
        return self._running().period_ns / NS_PER_S

    @property
    def scan_angles(self) -> np.ndarray:
        """The angle (rad, counter-clockwise, 0 ahead, lidar frame) of each of the observation's
        scan ranges (after :meth:`reset`)."""
        return self._running().scan_angles()

    @property
    def action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)``, each ``[speed m/s, steering rad]``: what the car can be commanded at most
        either way, from the episode's config (after :meth:`reset`): the VESC conversion's
        ``vesc.speed_max_mps`` and its steering range (``vesc.steering_max_rad``, 0.26 rad in the
        shipped configs, or less on a side the servo range clips). An action beyond is clamped,
        silently; the safety controller may allow less (``observation["safety"]``)."""
        config = self.loopback.config
        assert config is not None  # a running episode's
        conversion = AckermannConversion.from_params(config.vesc)
        right, left = conversion.steering_range()
        return (np.array([-conversion.speed_max_mps, right]), np.array([conversion.speed_max_mps, left]))

    @property
    def time_s(self) -> float:
        """Virtual seconds since the episode began (reset returned)."""
        return self._running().time_s(self.loop.now_ns())

    # --- the API --------------------------------------------------------------------------------

    def reset(self, scenario: str | Path | Scenario | None = None, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """End the running episode (its daemon stopped, its fakes unplugged) and start ``scenario``
        (default: the env's) with the world's random seed ``seed`` (None: the scenario's
        ``world.seed``); returns once the car is ready to drive: ``(observation, info)``.
        ``options``: Gymnasium's reset options; ``{"scenario": ...}`` is the same as ``scenario``
        (both at once is refused, ValueError, even when they agree).
        What refuses the new scenario before its devices start (a bad option, seed, map, config,
        driver input, firmware or start pose, a scenario with ``cars``) is raised before the
        running episode ends: that one steps on."""
        if self._closed:
            raise RuntimeError("the env is closed")
        options = dict(options or {})
        if scenario is not None and "scenario" in options:
            raise ValueError(f"a scenario both as the argument ({scenario!r}) and in options "
                             f"({options['scenario']!r}): give it once")
        if scenario is None:
            scenario = options.pop("scenario", None)
        if set(options) - {"scenario"}:
            raise ValueError(f"unknown reset options {sorted(set(options) - {'scenario'})}; "
                             "the one option is 'scenario'")
        # the arguments first: a bad one leaves the running episode as it is
        sc = self._scenario(scenario if scenario is not None else self.scenario)
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
            sc = dataclasses.replace(sc, world=dataclasses.replace(sc.world, seed=int(seed)))
        # then the scenario (its map, config, drivers, firmware, start), starting nothing of it yet
        episode = Episode(self.loop, sc, config_path=self.config_path, overrides=self.overrides,
                          car_name=self.car_name, mux_input=self.mux_input, lap_centre=self.lap_centre)
        try:
            episode.check()
        except BaseException:
            episode.discard()
            raise
        self._end_episode()
        self.loop.run_until_time(self.loop.now_ns())  # what the teardown left to do at this instant
        self.loop.rewind()  # every episode from the same virtual time: the same seed, the same run
        episode.start()  # raises what refused the scenario; then nothing of it runs
        self.episode, self.steps = episode, 0
        return episode.observation(), episode.info(self.loop.now_ns(), 0)

    def step(self, action: Sequence[float]) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        """Send ``action`` = (speed m/s, steering rad, + left) on the env's mux input and run one
        control period: ``(observation, reward, terminated, truncated, info)``. The action is two
        real numbers, a tuple or list of two or an array of shape (2,); anything else (f1tenth_gym's
        (num_agents, 2) ``[[steering, speed]]``, text, bools, NaN) is refused with ValueError.

        The reward is the lap progress of this step (laps; 0 without a lap centre). Terminated: the
        car collided (the world's contact, latched), or ``max_laps`` laps are done. Truncated: the
        episode reached ``max_episode_s``. Stepping on after either is allowed; reset to start over.
        """
        episode = self._running()
        episode.check_running()
        speed, steering = _action(action)
        episode.drive(speed, steering)
        before = episode.laps.progress if episode.laps is not None else 0.0
        self.steps += 1
        self.loop.run_until_time(episode.t0_ns + self.steps * episode.period_ns)
        obs, info = episode.observation(), episode.info(self.loop.now_ns(), self.steps)
        reward = info["lap_progress"] - before
        terminated = bool(info["collided"]) or (self.max_laps is not None and info["laps"] >= self.max_laps)
        truncated = not terminated and info["time_s"] >= self.max_episode_s - 1e-9
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

    @staticmethod
    def _scenario(scenario: str | Path | Scenario) -> Scenario:
        return scenario if isinstance(scenario, Scenario) else load_scenario(str(scenario))

    def _end_episode(self) -> None:
        episode, self.episode = self.episode, None
        if episode is not None:
            result = episode.end()
            if result is not None:
                self.last_result = result


def _max_laps(max_laps: int | None) -> int | None:
    """``max_laps`` if it is None or a whole number of laps from 1 (ValueError otherwise)."""
    if max_laps is None:
        return None
    if isinstance(max_laps, bool) or not isinstance(max_laps, (int, np.integer)) or max_laps < 1:
        raise ValueError(f"max_laps must be a whole number of laps from 1, or None, got {max_laps!r}")
    return int(max_laps)


def _lap_centre(lap_centre: Sequence[float] | None) -> tuple[float, float] | None:
    """``lap_centre`` as (x m, y m) if it is None or two finite numbers (ValueError otherwise)."""
    if lap_centre is None:
        return None
    try:
        x, y = (float(v) for v in np.asarray(lap_centre, dtype=np.float64).reshape(-1))
    except (TypeError, ValueError) as err:
        raise ValueError(f"lap_centre must be (x m, y m) in the map frame, or None, got {lap_centre!r}") \
            from err
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"lap_centre must be finite, got {lap_centre!r}")
    return x, y


#: What :func:`_action` says an action is, in every refusal: the order, and f1tenth_gym's other one.
ACTION_FORM = ("an action is (speed m/s, steering rad): two real numbers, as a tuple or list of two or "
               "an array of shape (2,); f1tenth_gym's [[steering, speed]] per agent is the other way round")


def _action(action: Sequence[float]) -> tuple[float, float]:
    """(speed, steering) from an action: exactly two real numbers (a tuple or list of two, or an
    array of shape (2,)); refuses (ValueError) another shape, text, bools and values not finite."""
    if isinstance(action, (tuple, list)):
        values = list(action)
        real = len(values) == 2 and all(_real(v) for v in values)
    elif isinstance(action, np.ndarray):
        values = action.tolist() if action.shape == (2,) else []
        real = action.shape == (2,) and action.dtype.kind in "iuf"
    else:
        real = False
    if not real:
        got = f"an array of shape {action.shape} ({action.dtype})" if isinstance(action, np.ndarray) \
            else reprlib.repr(action)
        raise ValueError(f"{ACTION_FORM}; got {got}")
    speed, steering = float(values[0]), float(values[1])
    if not (math.isfinite(speed) and math.isfinite(steering)):
        raise ValueError(f"an action must be finite, got speed {speed!r}, steering {steering!r}")
    return speed, steering


def _real(value: object) -> bool:
    """A real number: an int or float (numpy's too), not a bool or text."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


__all__ = ["DEFAULT_SCENARIO", "ENV_OVERRIDES", "READY_TIMEOUT_S", "RaceEnv"]
