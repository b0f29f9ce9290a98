"""A scenario's drivers: what commands the mux's inputs during a sim run, on scenario time.

``setpoint`` (a :class:`~racecar_hw.sources.setpoint.SetpointRelay`), ``constant`` and ``script``
(speed in m/s and steering in rad, + left, published at ``rate_hz``), ``figure8`` and ``follow``
(a bag replayed by a :class:`~racecar_hw.bags.follow.BagFollower`). Follow drivers' bags are
loaded before the run, so a missing or damaged one is refused before anything starts.
"""

from __future__ import annotations

import asyncio
import logging

from racecar_hw.bags.follow import BagFollower, FollowerParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.config import Config
from racecar_hw.daemon import command_limits, reverse_speed_cap
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.sim.scenario import DriverSpec, Scenario
from racecar_hw.sim.timeline import ScenarioClock

log = logging.getLogger(__name__)

#: Seconds a run that lasts as long as its replay (``until_replay_ends``) goes on after the last
#: command, for the car to come to rest.
REPLAY_SETTLE_S = 1.0
#: How much later than planned such a run waits for a replay held up by a loaded machine (s).
REPLAY_LATE_MAX_S = 30.0


class ScenarioDrivers:
    """The drivers of ``scenario`` for the daemon configured by ``config``, timed by ``clock``."""

    def __init__(self, scenario: Scenario, config: Config, clock: ScenarioClock) -> None:
        self.scenario = scenario
        self.config = config
        self.clock = clock
        self._followers: dict[int, BagFollower] = {}  # follow drivers' followers, loaded before the run
        self._followed: dict[int, float] = {}  # follow drivers' fraction of their replay published

    def check(self) -> None:
        """Refuse, before anything starts, a driver on an input the mux does not have or a follow
        driver whose bag is not there (a one-line error); follow drivers' bags are loaded next, by
        :meth:`load_bags`."""
        self.scenario.check_bags()
        inputs = [inp.name for inp in self.config.mux.inputs]
        for i, spec in enumerate(self.scenario.drivers):
            if spec.input not in inputs:
                raise ConfigError(f"scenario.drivers.{i}.input",
                                  f"{spec.input!r} is not a mux input; inputs: {', '.join(inputs)}")

    async def load_bags(self) -> bool:
        """Load every follow driver's bag (off the event loop); True when there is one."""
        for spec in self.scenario.drivers:
            if spec.type == "follow":
                await asyncio.to_thread(self._follower, spec, Bus())
        return bool(self._followers)

    @property
    def replays_done(self) -> bool:
        """True when every follow driver's replay has ended."""
        return all(f.done for f in self._followers.values())

    async def drive(self, spec: DriverSpec, bus: Bus) -> None:
        """Run one driver on ``bus`` from its ``from_s`` to its ``until_s`` (scenario time)."""
        clock = self.clock
        topic = self._input_topic(spec.input)
        await clock.wait_until(spec.from_s)
        if spec.type == "setpoint":
            from racecar_hw.sources.setpoint import SetpointParams, SetpointRelay

            relay = SetpointRelay(bus, SetpointParams(topic=topic, rate_hz=spec.rate_hz,
                                                      max_speed_mps=max(2.0, abs(spec.speed_mps))))
            relay.set_velocity(spec.speed_mps)
            relay.set_steering_angle(spec.steering_rad)
            relay.start()
            try:
                await clock.until(relay.run(), spec.until_s)
            finally:
                relay.close()
        elif spec.type in ("constant", "script"):
            ticker = Ticker(spec.rate_hz)
            while spec.until_s is None or clock.scenario_time() < spec.until_s:
                await ticker.tick()
                speed, steer = spec.speed_mps, spec.steering_rad
                if spec.type == "script":
                    speed, steer = _script_at(spec.steps, clock.scenario_time() - spec.from_s)
                bus.publish(topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()),
                                                         AckermannDrive(steering_angle=steer, speed=speed)))
        elif spec.type == "figure8":
            from racecar_hw.sources.figure8 import Figure8Driver, Figure8Params

            params = Figure8Params(speed_mps=spec.speed_mps, steering_angle_rad=spec.steering_rad,
                                   wheelbase_m=self.config.vesc.wheelbase_m, figure8s=spec.figure8s,
                                   rate_hz=spec.rate_hz, topic=topic)
            await clock.until(Figure8Driver(bus, params).run(), spec.until_s)
        elif spec.type == "follow":
            await clock.until(self._follower(spec, bus).run(), spec.until_s)

    def _follower(self, spec: DriverSpec, bus: Bus) -> BagFollower:
        """The bag follower of a ``follow`` driver, loaded once (raises BagError for a bad bag)."""
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

    def replay_end_s(self) -> float:
        """Scenario time (s) at which the last follow driver's replay ends (at its ``until_s``)."""
        ends = []
        for spec in self.scenario.drivers:
            if spec.type == "follow":
                end = spec.from_s + self._replay_s(spec)
                ends.append(end if spec.until_s is None else min(end, spec.until_s))
        return max(ends, default=0.0)

    async def wait_for_replays(self, duration_s: float) -> None:
        """A replay held up by a loaded machine ends later than planned (``duration_s``): wait for
        it (at most :data:`REPLAY_LATE_MAX_S`), then :data:`REPLAY_SETTLE_S` more."""
        clock = self.clock
        late = False
        while not self.replays_done:
            if clock.scenario_time() > duration_s + REPLAY_LATE_MAX_S:
                log.warning("sim: the replay did not end %.0f s after it should have; stopping",
                            REPLAY_LATE_MAX_S)
                return
            late = True
            await asyncio.sleep(0.05)
        if late:
            log.info("sim: the replay ended %.2f s late (a held-up machine)",
                     clock.scenario_time() - duration_s + REPLAY_SETTLE_S)
            await clock.wait_until(clock.scenario_time() + REPLAY_SETTLE_S)

    def _input_topic(self, name: str) -> str:
        for inp in self.config.mux.inputs:
            if inp.name == name:
                return inp.topic
        names = ", ".join(i.name for i in self.config.mux.inputs)
        raise ConfigError("scenario", f"driver input {name!r} is not a mux input; inputs: {names}")

    def report(self) -> list[dict[str, object]]:
        """Each follow driver's replay: its length as replayed (s), the fraction of its commands
        published, and whether it was followed to the end (``complete``)."""
        out: list[dict[str, object]] = []
        for spec in self.scenario.drivers:
            if spec.type == "follow" and id(spec) in self._followers:
                followed = self._followed[id(spec)]
                out.append({"bag": str(spec.bag), "reverse": spec.reverse,
                            "replay_s": round(self._replay_s(spec), 3),
                            "speed_scale": round(self._followers[id(spec)].speed_scale, 3),
                            "followed": round(followed, 3), "complete": followed >= 1.0})
        return out


def _script_at(steps: list[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """The (speed m/s, steering rad) of the last script step at or before ``t`` (s)."""
    speed, steer = 0.0, 0.0
    for t0, v, d in steps:
        if t >= t0:
            speed, steer = v, d
    return speed, steer


__all__ = ["REPLAY_LATE_MAX_S", "REPLAY_SETTLE_S", "ScenarioDrivers"]
