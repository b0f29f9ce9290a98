"""``racecar-hw sim``: the real daemon on fake hardware, moved by the world simulation.

The fake VESC (a pty) and the fake lidar (TCP or a pty) run in a :class:`DeviceThread` with the
:class:`World`: the world reads the fake VESC's motor ERPM and servo position, moves the car, and
the fake lidar ray-casts the map from the car's laser pose. The daemon runs unchanged in the main
event loop with its device paths pointed at the fakes, so every byte crosses a real pty or socket.

:class:`Loopback` runs one scenario: the fakes (:class:`~racecar_hw.sim.rig.FakeRig`), the clocks
(:class:`~racecar_hw.sim.timeline.ScenarioClock`), the drivers
(:class:`~racecar_hw.sim.drivers.ScenarioDrivers`), what is watched
(:class:`~racecar_hw.sim.observer.RunObserver`) and the report
(:class:`~racecar_hw.sim.report.RunReport`) are its parts.

Sim time is real (monotonic) time since the world started; see docs/sim.md.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mux.estop import DAEMON, Origin
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.overrides import merge
from racecar_hw.config import Config, listeners, load_config, move_to_free_ports, shipped_config
from racecar_hw.daemon import Daemon
from racecar_hw.net.ports import Listener, PortLock
from racecar_hw.runtime.panel import StatusPanel
from racecar_hw.sim.car import CarParams
from racecar_hw.sim.clock_topic import add_clock
from racecar_hw.sim.drivers import REPLAY_LATE_MAX_S, REPLAY_SETTLE_S, ScenarioDrivers
from racecar_hw.sim.live import SIM_TOPICS, log_estop_timing, publish_truth
from racecar_hw.sim.observer import MAX_SAMPLES, SAMPLE_PERIOD_S, RunObserver
from racecar_hw.sim.occupancy import load_map
from racecar_hw.sim.plot_rows import ControlSample, Mark
from racecar_hw.sim.plot_worker import PlotWorker
from racecar_hw.sim.report import RunReport, SimResult, write_report
from racecar_hw.sim.rig import DEVICE_FAULTS, LIDAR_MAX_RANGE_M, FakeRig, car_params
from racecar_hw.sim.scenario import FaultSpec, Scenario
from racecar_hw.sim.timeline import ScenarioClock
from racecar_hw.sim.world import World
from vesc.fake import FakeVesc

log = logging.getLogger(__name__)

#: The origin of a scenario's e-stop and release actions: the daemon itself.
SCENARIO = Origin(DAEMON, "scenario")

#: Settings that keep a simulated car off the network and the live views (Zenoh, DDS, Foxglove,
#: the status page, ``/rosout``), for runs nothing outside can keep pace with or take part in
#: without changing them: ``racecar-hw sim --speed max`` and the step API (docs/sim.md, "The
#: network at --speed max"). Settings given after them turn an interface back on.
OFFLINE_OVERRIDES = ("zenoh.enabled=false", "dds.enabled=false", "foxglove.enabled=false",
                     "web.enabled=false", "rosout.enabled=false")



def take_free_ports(config: Config, lock: PortLock) -> list[tuple[Listener, str]]:
    """The rule for ports (docs/live-view.md, "Ports"): a sim listens on free ports instead of
    taken ones, and says where; returns the moved ones. After every refusal, so a refused run
    touches no port. With something to listen on, it takes ``lock`` first, which the run holds
    until its daemon listens (its components run), so that another sim starting meanwhile does not
    find the same ports free."""
    if listeners(config):
        lock.acquire()
    moved = move_to_free_ports(config)
    for listener, where in moved:
        print(f"racecar-hw sim: {listener.key} {listener.address()} is taken (another racecar-hw?); "
              f"{listener.what} is on {where} instead", file=sys.stderr, flush=True)
    return moved


class Loopback:
    """One scenario on fake hardware: build with a scenario and config, then ``await run()``."""

    def __init__(self, scenario: Scenario, *, config_path: str | Path | None = None,
                 overrides: tuple[str, ...] | list[str] = (), out_dir: str | Path | None = None,
                 status: StatusPanel | None = None, duration_s: float | None = None,
                 until_replay_ends: bool = False,
                 setup: Callable[[Loopback], None] | None = None, lockstep: bool = False,
                 car_name: str = "car", plotter: PlotWorker | None = None, plot: bool = True) -> None:
        if scenario.cars:
            raise ConfigError("cars", f"scenario {scenario.name!r} has several cars: run it with "
                                      "racecar_hw.sim.fleet.Fleet")
        self.scenario = scenario
        self.duration_s = duration_s if duration_s is not None else scenario.duration_s
        #: run as long as the follow drivers' replays (stretched for the reverse cap) and
        #: :data:`REPLAY_SETTLE_S`, instead of the scenario's duration; ``duration_s`` wins
        self.until_replay_ends = until_replay_ends and duration_s is None
        self.map = load_map(scenario.map_path())  # first: a missing map leaves nothing behind
        self._tmp = tempfile.TemporaryDirectory(prefix="racecar-hw-sim-")
        self.dev_dir = Path(self._tmp.name)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.config_path = config_path if config_path is not None else shipped_config("sim")
        self.overrides = tuple(overrides)
        self.status = status
        self.setup = setup
        #: draws the run's plot in another process (started before the run); None: in this one
        self.plotter = plotter
        self.plot = plot  # False: the report and the trajectory CSV only (sweeps, batch runs)
        #: the fakes in the daemon's loop behind in-memory links, on the loop's (virtual) clock
        #: (run it with :func:`racecar_hw.runtime.lockstep.run`), instead of ptys and TCP in real time
        self.lockstep = lockstep
        self.rig = FakeRig(scenario, self.map, self.dev_dir, lockstep=lockstep, name=car_name)
        self.clock = ScenarioClock()
        self.observer = RunObserver()
        self.drivers: ScenarioDrivers | None = None
        self.daemon: Daemon | None = None
        self.config: Config | None = None
        self.fault_log: list[tuple[float, str]] = []
        self._stop: asyncio.Event | None = None
        self._real_start: float | None = None  # real monotonic s when run() began
        #: why the run ended: "duration", or what interrupted it (request_stop)
        self.stop_reason = "duration"
        #: a second stop request (hurry): the report without the roll to rest or the plot
        self.hurried = False
        #: listeners whose configured port was taken, with where they listen instead
        self.moved_ports: list[tuple[Listener, str]] = []
        self._port_lock = PortLock()  # held from taking ports until they are bound

    _car_params = staticmethod(car_params)

    # --- the parts, as the run's users see them ---------------------------------------------------

    @property
    def world(self) -> World | None:
        return self.rig.world

    @property
    def vesc(self) -> FakeVesc | None:
        return self.rig.vesc

    @property
    def lidar(self) -> Any:
        return self.rig.lidar

    @property
    def car_params(self) -> CarParams | None:
        """The simulated car (after the devices started)."""
        return self.rig.car_params

    @property
    def ready_at_s(self) -> float | None:
        """World time (s) when the car was ready to drive: the scenario's time zero."""
        return self.clock.ready_at_s

    @property
    def interventions_at(self) -> list[tuple[float, float]]:
        return self.observer.interventions_at

    @property
    def intervention_marks(self) -> list[Mark]:
        return self.observer.intervention_marks

    @property
    def control_samples(self) -> list[ControlSample]:
        return self.observer.control_samples

    def sim_time(self) -> float:
        """Seconds since the world started (the time in the report and the trajectory)."""
        return self.clock.sim_time()

    def scenario_time(self) -> float:
        """Seconds since the car was ready: drivers, faults and the duration count from there."""
        return self.clock.scenario_time()

    # --- building -------------------------------------------------------------------------------

    def _build_config(self) -> Config:
        """The sim config with the scenario's overrides, its VESC port at the fake's pty.

        The lidar endpoint is filled in once the fake lidar listens (a TCP port is only known then).
        """
        extra = merge(self.scenario.config, {
            "vesc": {"port": self.rig.device_path("vesc")},
            "lidar": {"model": self.scenario.lidar.model, "tcp": None, "port": None},
        })
        return load_config(self.config_path, self.overrides, extra=extra)

    def check(self) -> Config:
        """Refuse what :meth:`run` would refuse before its devices start, starting nothing: the
        config (the scenario's merged in), the drivers' mux inputs, that follow drivers' bags are
        there, the firmware, the lidar's mounting and the start pose on the map; returns the config.
        Bags are read by the run."""
        config = self._build_config()
        ScenarioDrivers(self.scenario, config, self.clock).check()
        self.rig.check(config)
        return config

    def discard(self) -> None:
        """Forget a loopback that will not run (its temporary directory is removed)."""
        self._tmp.cleanup()

    def _take_free_ports(self, config: Config) -> None:
        """:func:`take_free_ports` (a fleet's car claims its share of one process's ports instead)."""
        self.moved_ports = take_free_ports(config, self._port_lock)

    # --- running --------------------------------------------------------------------------------

    async def run(self) -> SimResult:
        """Run the scenario for its duration; returns (and writes, with ``out_dir``) the report."""
        self._real_start = time.monotonic()
        try:
            self.config = config = self._build_config()
            drivers = self.drivers = ScenarioDrivers(self.scenario, config, self.clock)
            drivers.check()
            # bags first: a missing or damaged one is refused before any device or the daemon starts
            if await drivers.load_bags() and self.until_replay_ends:
                self.duration_s = drivers.replay_end_s() + REPLAY_SETTLE_S
            self._take_free_ports(config)
            self.config = self.rig.start(config)
            world = self.clock.world = self.rig.world
            assert world is not None
            daemon = self.daemon = Daemon(self.config, status=self.status)
            self.clock.daemon = daemon
            daemon.state.extra_status = lambda: {
                "sim_time_s": world.sim_time, "sim_pose": tuple(world.pose),
                "clearance_m": world.clearance()}
            if self.setup is not None:
                self.setup(self)
            stop = self._stop = asyncio.Event()
            if self.stop_reason != "duration":  # asked to stop while the devices were starting
                stop.set()
            for spec in self.scenario.drivers:
                daemon.add_task(drivers.drive(spec, daemon.bus))
            daemon.add_task(self._port_lock.released())
            daemon.add_task(self._faults())
            daemon.add_task(self._place_obstacles())
            daemon.add_task(self.observer.watch(daemon, world))
            daemon.live_topics.extend(SIM_TOPICS)
            daemon.add_task(publish_truth(daemon.bus, world, self.map))
            add_clock(daemon, self.scenario.world.clock_rate_hz)
            assert self.vesc is not None
            daemon.add_task(log_estop_timing(daemon, self.vesc))

            async def timer() -> None:
                await self.clock.wait_until(self.duration_s)
                if self.until_replay_ends:
                    await drivers.wait_for_replays(self.duration_s)
                stop.set()

            daemon.add_task(timer())
            await daemon.run(stop)
            if daemon.failure is not None:
                self.request_stop(f"failure of {daemon.failure[0]}: {daemon.failure[1]}")
            await self._settle()
            return await RunReport(self).result()
        finally:
            self._port_lock.release()
            await self.rig.aclose()
            self._tmp.cleanup()

    def clock_report(self) -> dict[str, Any]:
        """The report's ``clock`` section: how time ran, and the real seconds the run took."""
        loop = asyncio.get_running_loop()
        speed = getattr(loop, "speed", 1.0) if self.lockstep else 1.0
        real = time.monotonic() - self._real_start if self._real_start is not None else None
        return {"mode": "lockstep" if self.lockstep else "real time",
                "speed": "max" if speed is None else speed,
                "real_time_s": None if real is None else round(real, 3)}

    def request_stop(self, reason: str = "request") -> None:
        """End the run now (from the event loop), as if the duration had passed; the report says
        it was ``interrupted`` and why (``stop_reason``: SIGINT, SIGTERM, ...)."""
        if self.stop_reason == "duration":
            self.stop_reason = reason
        if self._stop is not None:
            self._stop.set()

    def next_stop(self) -> asyncio.Event:
        """An event the next stop request sets: for what waits after the run ended (the plot)."""
        self._stop = asyncio.Event()
        return self._stop

    def hurry(self) -> None:
        """A second stop request: stop if not stopping yet, then write the report at once, without
        waiting for the car to roll to rest or drawing the plot (the trajectory CSV is written)."""
        self.hurried = True
        self.request_stop("hurry")

    async def _settle(self) -> None:
        """Let the car roll to rest after the daemon's final brake, for honest final numbers."""
        assert self.world is not None
        for _ in range(100):
            if abs(self.world.speed) < 0.01 or self.hurried:
                return
            await asyncio.sleep(0.02)

    async def _place_obstacles(self) -> None:
        """Put the scenario's obstacles in the world, on scenario time (which starts when ready)."""
        assert self.world is not None
        await self.clock.wait_ready()
        assert self.ready_at_s is not None
        for k, spec in enumerate(self.scenario.obstacles):
            self.world.add_mover(spec.mover(self.ready_at_s, f"obstacle {k + 1}"))

    async def _faults(self) -> None:
        for fault in sorted(self.scenario.faults, key=lambda f: f.at_s):
            await self.clock.wait_until(fault.at_s)
            self.fault_log.append((round(self.sim_time(), 3), fault.action))
            log.info("sim fault at %.2f s: %s", self.sim_time(), fault.action)
            self._apply(fault)

    def _apply(self, fault: FaultSpec) -> None:
        """Act out a fault: on the fakes and the world (:data:`~racecar_hw.sim.rig.DEVICE_FAULTS`),
        or on the daemon (an e-stop, its release, arming and disarming)."""
        assert self.vesc is not None and self.world is not None and self.daemon is not None
        action = fault.action
        if action in DEVICE_FAULTS:
            self.rig.apply(fault)
        elif action == "estop":
            self.daemon.mux.engage_estop("scenario", SCENARIO)
        elif action == "estop_release":
            self.daemon.mux.release_estop(SCENARIO)
        elif action == "disarm":  # the operator lets go: the deadman, BACK or a ground station
            self.daemon.arming.disarm("scenario", "the operator let go")
        elif action == "arm":
            self.daemon.arming.arm("scenario")


__all__ = ["LIDAR_MAX_RANGE_M", "MAX_SAMPLES", "OFFLINE_OVERRIDES", "REPLAY_LATE_MAX_S", "REPLAY_SETTLE_S",
           "SAMPLE_PERIOD_S", "SCENARIO", "Loopback", "SimResult", "write_report"]
