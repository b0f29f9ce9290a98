"""Several cars in one world: a scenario with ``cars``, each car a whole loopback of its own.

Each car is a :class:`FleetCar`: a :class:`~racecar_hw.sim.loopback.Loopback` with its own fakes
(``mem://NAME/vesc``, ``mem://NAME/lidar``), its own :class:`~racecar_hw.sim.world.World` on the
scenario's map, and its own daemon, whose config is the sim config with the scenario's ``config``,
then the car's, and the namespace ``/NAME`` on the network interfaces (``zenoh.namespace``, which
DDS shares) unless the car's config names one. Its listeners (Zenoh, the live view, the status
page) move to free ports where another car of the fleet has them.

All the cars run in ONE event loop, in lockstep (:mod:`racecar_hw.runtime.lockstep`): one virtual
clock, so every world and every daemon agree on what time it is. The worlds are coupled through
that clock: in each car's world every other car is a :class:`CarShadow`, a moving obstacle that
is the other car's footprint (a box, map frame) where the other world has that car at the same
instant (monotonic ns, :meth:`World.pose_at <racecar_hw.sim.world.World.pose_at>`). So each lidar
sees the other cars, each safety controller stops for them, and a car that drives into another
collides with it; :class:`Fleet` names the car it hit (:class:`CarContact`).

The report (:mod:`racecar_hw.sim.fleet_report`) has a section per car (the single-car report of
each) and the contacts between cars. See docs/sim.md, "Several cars".
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.overrides import merge
from racecar_hw.config import Config, listeners, move_to_free_ports
from racecar_hw.daemon import Daemon
from racecar_hw.runtime.lockstep import VirtualTimeLoop
from racecar_hw.sim.car import CarParams, Collider, footprint
from racecar_hw.sim.fleet_report import FleetReport, footprint_box, start_ns
from racecar_hw.sim.loopback import Loopback
from racecar_hw.sim.movers import Mover
from racecar_hw.sim.obstacles import Box, Obstacle, polygon_distance
from racecar_hw.sim.report import SimResult
from racecar_hw.sim.rig import car_params
from racecar_hw.sim.scenario import Scenario, ScenarioCar
from racecar_hw.sim.timeline import ScenarioClock
from racecar_hw.sim.world import World

log = logging.getLogger(__name__)

#: Two cars' worlds that find the same pair in contact this close in time (s) report one contact.
SAME_CONTACT_S = 1.0


class CarShadow(Mover):
    """Another car, as an obstacle in one car's world: its footprint where its own world has it.

    ``observer`` and ``source`` give the two worlds (None until they exist: the shadow is absent).
    Sim time ``t`` of the observing world is turned into the monotonic instant, and the source world
    says where its car was then (interpolated between its steps, extrapolated at most
    :data:`~racecar_hw.sim.history.MAX_EXTRAPOLATION_S` past its last one).
    """

    def __init__(self, name: str, observer: Callable[[], World | None],
                 source: Callable[[], World | None]) -> None:
        super().__init__(Box(0.0, 0.0, 1.0, 1.0), (0.0, 0.0), name=name)
        self._observer = observer
        self._source = source

    def at(self, t: float) -> Obstacle | None:
        observer, source = self._observer(), self._source()
        if observer is None or source is None:
            return None
        stamp_ns = start_ns(observer) + round(t * NS_PER_S)
        return footprint_box(source.pose_at(stamp_ns), source.params)

    def present(self, t: float) -> bool:
        return self.at(t) is not None

    def position(self, t: float) -> tuple[float, float]:
        shape = self.at(t)
        return (shape.x, shape.y) if isinstance(shape, Box) else self.start


@dataclass(frozen=True)
class CarContact:
    """Two cars touched: ``car`` drove into ``other`` (its world found the contact) at fleet time
    ``t`` (s), at map point (``x``, ``y``) (``car``'s contact side's centre); ``mutual``: ``other``'s
    world found it too (both were moving)."""

    t: float
    car: str
    other: str
    x: float
    y: float
    mutual: bool = False


def car_scenario(scenario: Scenario, entry: ScenarioCar, index: int) -> Scenario:
    """The single-car scenario of car ``entry`` (the ``index``-th): the scenario's map, duration,
    world and obstacles with the car's start, lidar, drivers, faults, true gains and config (over the
    scenario's, with the namespace /NAME unless the car's config gives a ``zenoh.namespace``, and
    DDS off unless a config turns it on)."""
    # DDS off unless a config turns it on: Cyclone opens a domain once per process (docs/sim.md)
    config = merge(merge({"dds": {"enabled": False}}, scenario.config), entry.config)
    if "namespace" not in (entry.config.get("zenoh") or {}):
        config = merge(config, {"zenoh": {"namespace": f"/{entry.name}"}})
    seed = scenario.world.seed
    world = dataclasses.replace(scenario.world, seed=None if seed is None else seed + index)
    return dataclasses.replace(
        scenario, name=f"{scenario.name or 'sim'}-{entry.name}",
        description=f"{entry.name} in: {scenario.description}" if scenario.description else entry.name,
        start=entry.start, lidar=entry.lidar or scenario.lidar, drivers=list(entry.drivers),
        faults=list(entry.faults), config=config, car=entry.car, world=world, cars=[])


class FleetClock(ScenarioClock):
    """A car's clocks in a fleet: its scenario time starts when EVERY car is ready to drive (each
    car's VESC answered and its first scan is in), so drivers, faults and obstacles keep one
    schedule for the whole fleet."""

    def __init__(self, fleet: Fleet) -> None:
        super().__init__()
        self.fleet = fleet

    async def wait_ready(self, timeout_s: float = 15.0) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while self.ready_at_s is None:
            cars = list(self.fleet.cars.values())
            ready = all(car.daemon is not None and devices_ready(car.daemon) for car in cars)
            if ready or loop.time() > deadline:
                if not ready:
                    log.warning("sim: not every car's devices are ready after %.0f s; starting anyway",
                                timeout_s)
                for car in cars:  # one instant for all: the loop's clock is theirs
                    if car.clock.ready_at_s is None:
                        car.clock.ready_at_s = car.clock.sim_time()
                return
            await asyncio.sleep(0.01)


def devices_ready(daemon: Daemon) -> bool:
    """Whether a car's daemon can drive: its VESC answered and its first scan is in."""
    return ((daemon.vesc is None or daemon.vesc.connected)
            and (daemon.lidar is None or daemon.lidar.stats.scans > 0))


class FleetCar(Loopback):
    """One car of a :class:`Fleet`: a lockstep :class:`Loopback` named ``name`` whose listeners also
    keep off the ports its fleet promised to the other cars."""

    def __init__(self, fleet: Fleet, name: str, scenario: Scenario, **kwargs: Any) -> None:
        super().__init__(scenario, lockstep=True, car_name=name, setup=fleet._set_up, **kwargs)
        self.fleet = fleet
        self.name = name
        self.clock = FleetClock(fleet)

    async def run(self) -> SimResult:
        try:
            return await super().run()
        except ConfigError as err:  # say which car's config it is
            raise self.named(err) from None

    def named(self, err: ConfigError) -> ConfigError:
        """``err`` saying it is this car's."""
        named = ConfigError("", f"car {self.name}: {err}")
        named.key = err.key
        return named

    def footprint_params(self) -> CarParams:
        """The simulated car with its own config's footprint (sizes in m), before anything starts;
        refuses (ConfigError naming the car) a config that does not load."""
        try:
            return car_params(self._build_config(), self.scenario.car)
        except ConfigError as err:
            raise self.named(err) from None

    def _take_free_ports(self, config: Config) -> None:
        """Between building the config and starting anything: claim this car's share of what the
        cars of one process share (a namespace, the DDS interface, ports), refusing a clash."""
        namespaces = self.fleet.namespaces
        if config.zenoh.enabled or config.dds.enabled:
            holder = namespaces.get(config.zenoh.namespace)
            if holder is not None:
                raise ConfigError("zenoh.namespace", f"cars {holder} and {self.name} both have "
                                  f"{config.zenoh.namespace or '/'}: each car needs its own (the "
                                  "default is /NAME; a --set applies to every car)")
            namespaces[config.zenoh.namespace] = self.name
        if config.dds.enabled:
            if self.fleet.dds_car is not None:
                raise ConfigError("dds.enabled", f"cars {self.fleet.dds_car} and {self.name} both have "
                                  "DDS: in a fleet (one process) one car at most can (it is off unless "
                                  "a config turns it on; docs/sim.md, \"Several cars\")")
            self.fleet.dds_car = self.name
        promised = self.fleet.promised_ports
        self.moved_ports = move_to_free_ports(config, avoid=set(promised))
        for listener, where in self.moved_ports:
            holder = promised.get(listener.port)
            why = f"is car {holder}'s" if holder is not None else "is taken (another racecar-hw?)"
            print(f"racecar-hw sim: car {self.name}: {listener.key} {listener.address()} {why}; "
                  f"{listener.what} is on {where} instead", file=sys.stderr, flush=True)
        for item in listeners(config):
            promised[item.port] = self.name


class Fleet:
    """The cars of a scenario with ``cars`` in one world: build, then ``await run()`` in a
    :class:`~racecar_hw.runtime.lockstep.VirtualTimeLoop` (:func:`racecar_hw.runtime.lockstep.run`).

    ``config_path`` and ``overrides`` (``--set``) apply to every car; ``out_dir``: where each car's
    trajectory CSV and plot go (named SCENARIO-CAR; ``plot=False``: no plot); ``record_dir``: record
    each car's topics to a bag in ``record_dir/CAR``; ``setup``: called with each car once its
    daemon exists (tests).
    """

    def __init__(self, scenario: Scenario, *, config_path: str | Path | None = None,
                 overrides: tuple[str, ...] | list[str] = (), out_dir: str | Path | None = None,
                 duration_s: float | None = None, record_dir: str | Path | None = None,
                 setup: Callable[[FleetCar], None] | None = None, plot: bool = True) -> None:
        if not scenario.cars:
            raise ConfigError("cars", f"scenario {scenario.name!r} has no cars: it runs one car "
                                      "(racecar_hw.sim.loopback.Loopback)")
        self.scenario = scenario
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.plot = plot  # False: no plot of the fleet or of a car (the CSVs are written)
        self.setup = setup
        #: port -> the car whose daemon listens (or will listen) there
        self.promised_ports: dict[int, str] = {}
        #: namespace on the network interfaces -> the car whose daemon has it
        self.namespaces: dict[str, str] = {}
        #: the car whose daemon has the DDS interface (one at most)
        self.dds_car: str | None = None
        self.contacts: list[CarContact] = []
        self.cars: dict[str, FleetCar] = {}
        for k, entry in enumerate(scenario.cars):
            sub = car_scenario(scenario, entry, k)
            if record_dir is not None:
                sub.config = merge(sub.config, {"recorder": {"enabled": True,
                                                             "path": str(Path(record_dir) / entry.name)}})
            self.cars[entry.name] = FleetCar(self, entry.name, sub, config_path=config_path,
                                             overrides=overrides, out_dir=out_dir, duration_s=duration_s,
                                             plot=plot)
        self.stop_reason = "duration"

    # --- time -----------------------------------------------------------------------------------

    def _reference(self) -> World | None:
        """The first car's world: fleet time is its sim time."""
        return next(iter(self.cars.values())).world

    def fleet_time(self, world: World, t: float) -> float:
        """Sim time ``t`` (s) of ``world`` as fleet time (s since the first car's world started)."""
        ref = self._reference()
        if ref is None or ref is world:
            return t
        return t + (start_ns(world) - start_ns(ref)) / NS_PER_S

    # --- running --------------------------------------------------------------------------------

    async def run(self) -> SimResult:
        """Run every car for the scenario's duration; returns the fleet's report (written into
        ``out_dir`` with each car's CSV and plot, as the single-car run does)."""
        if not isinstance(asyncio.get_running_loop(), VirtualTimeLoop):
            raise RuntimeError("a fleet runs in lockstep: "
                               "racecar_hw.runtime.lockstep.run(fleet.run(), speed)")
        self._check_starts()
        tasks = {name: asyncio.ensure_future(car.run()) for name, car in self.cars.items()}
        try:
            await asyncio.wait(tasks.values(), return_when=asyncio.FIRST_EXCEPTION)
            failed = [t for t in tasks.values() if t.done() and not t.cancelled() and t.exception()]
            if failed:
                self.request_stop("error")
            results = await asyncio.gather(*tasks.values(), return_exceptions=True)
        except asyncio.CancelledError:
            for task in tasks.values():
                task.cancel()
            await asyncio.gather(*tasks.values(), return_exceptions=True)
            raise
        for result in results:
            if isinstance(result, BaseException):
                raise result
        return FleetReport(self, dict(zip(tasks, results, strict=True))).result()

    def hurry(self) -> None:
        """A second stop request, for every car (see :meth:`Loopback.hurry`)."""
        for car in self.cars.values():
            car.hurry()

    def request_stop(self, reason: str = "request") -> None:
        """End every car's run now (see :meth:`Loopback.request_stop`)."""
        if self.stop_reason == "duration":
            self.stop_reason = reason
        for car in self.cars.values():
            car.request_stop(reason)

    def _check_starts(self) -> None:
        """Refuse cars whose footprints overlap at the start, each car's footprint as its own
        config gives it (the sim config, the scenario's, the car's and the ``--set``s)."""
        boxes = [(entry.name, footprint(entry.start, self.cars[entry.name].footprint_params()))
                 for entry in self.scenario.cars]
        for i, (name, corners) in enumerate(boxes):
            for other, other_corners in boxes[:i]:
                if polygon_distance(corners, other_corners) <= 0.0:
                    raise ConfigError(f"scenario.cars[{i}].start", f"car {name}'s footprint at "
                                      f"{tuple(self.scenario.cars[i].start)} overlaps car {other}'s")

    def _set_up(self, car: Loopback) -> None:
        """Couple a car's world to the others (when its daemon exists): the others as shadows in
        it, and its collisions checked for a car it hit."""
        assert isinstance(car, FleetCar) and car.world is not None and car.config is not None
        world = car.world
        for name, other in self.cars.items():
            if other is not car:
                world.add_mover(CarShadow(name, lambda car=car: car.world, lambda other=other: other.world))
        stall = world.on_collision

        def on_collision() -> None:
            if stall is not None:
                stall()
            self._contact(car)

        world.on_collision = on_collision
        z = car.config.zenoh
        if z.enabled:
            print(f"racecar-hw sim: car {car.name}: namespace {z.namespace or '/'}, Zenoh on "
                  f"{', '.join(z.listen)}", file=sys.stderr, flush=True)
        if self.setup is not None:
            self.setup(car)

    def _contact(self, car: FleetCar) -> None:
        """``car``'s world found a contact: if the nearest thing to its footprint is another car,
        note the contact (once per pair, :data:`SAME_CONTACT_S`)."""
        world = car.world
        assert world is not None
        collision = world.collisions[-1]
        pose = world.pose
        corners = footprint(pose, world.params)
        nearest, gap = "map", Collider(world.map, world.params).clearance(pose)
        for name, shape in world.obstacles_at(collision.t):
            d = shape.distance_to(corners)
            if d < gap:
                nearest, gap = name, d
        if nearest not in self.cars or nearest == car.name:
            return
        t = self.fleet_time(world, collision.t)
        for k, seen in enumerate(self.contacts):
            if {seen.car, seen.other} == {car.name, nearest} and abs(seen.t - t) <= SAME_CONTACT_S:
                self.contacts[k] = dataclasses.replace(seen, mutual=True)
                return
        log.warning("sim: car %s hit car %s at t=%.3f s", car.name, nearest, t)
        self.contacts.append(CarContact(t, car.name, nearest, collision.x, collision.y))


__all__ = ["SAME_CONTACT_S", "CarContact", "CarShadow", "Fleet", "FleetCar", "car_scenario",
           "footprint_box", "start_ns"]
