"""The report of a sim run: what happened, as JSON, with the trajectory CSV and the plot next to it.

Positions are in the map frame (m), times in sim time (s) unless a key says otherwise; every
float is rounded to 4 decimals and a non-finite one is null. See docs/sim.md for the keys.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.errors import ConfigError
from racecar_hw.sim.car import CLEARANCE_RANGE_M, CarParams, footprint
from racecar_hw.sim.obstacles import point_polygon_distance
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.plot_worker import PendingPlot, PlotWorker
from racecar_hw.sim.trajectory import TrajectorySample, rest_time, stopping_distance, write_csv
from racecar_hw.sim.world import SimRangeSource, compose
from vesc.codec import firmware_text

if TYPE_CHECKING:
    from racecar_hw.sim.loopback import Loopback
    from safety.controller import Obstacle

#: How near (m) to an intervention's point the map's cells are the wall it stopped for (its
#: ``distance_left_m``): the part of the wall around the point, not a side wall elsewhere.
WALL_NEAR_M = 0.5

#: The keys of a report that depend on where and when it ran, not on what the car did: output
#: paths, the live interfaces' ports, and the real seconds the run took. Two lockstep runs of a
#: scenario with the same seed agree on everything else (:func:`comparable`).
RUN_SPECIFIC = ("trajectory_csv", "plot_png", "bags", "live", "clock.real_time_s")


def comparable(report: dict[str, Any]) -> dict[str, Any]:
    """``report`` without its :data:`RUN_SPECIFIC` keys (dotted: a key inside a section)."""
    out = json.loads(json.dumps(report))
    for top in (out, *(out.get("cars") or {}).values()):  # a fleet's report: each car's section too
        for key in RUN_SPECIFIC:
            *path, last = key.split(".")
            section = top
            for part in path:
                section = section.get(part) or {}
            section.pop(last, None)
    return out


@dataclass
class SimResult:
    """What a run produced: the report (also written as JSON) and the files next to it."""

    report: dict[str, Any]
    report_path: Path | None = None
    trajectory_csv: Path | None = None
    plot_png: Path | None = None
    interventions_at: list[tuple[float, float]] = field(default_factory=list)


def write_report(result: SimResult, path: str | Path) -> Path:
    """Write the JSON report to ``path``."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(result.report, indent=2) + "\n")
    result.report_path = p
    return p


def check_writable(path: str | Path, option: str, *, directory: bool) -> None:
    """Refuse (a one-line ConfigError naming ``option``) an output that could not be written: a
    file ``path`` that is a directory, a ``directory`` that is a file, or a place whose nearest
    existing directory is not writable. For before a run starts, so it is not lost at its end."""
    p = Path(path)
    if directory and p.exists() and not p.is_dir():
        raise ConfigError(option, f"{p} is a file, not a directory")
    if not directory:
        if p.is_dir():
            raise ConfigError(option, f"{p} is a directory, not a file")
        if p.exists() and not os.access(p, os.W_OK):
            raise ConfigError(option, f"{p} cannot be written (permission denied)")
    base = p if directory else p.parent
    while not base.exists() and base != base.parent:  # what mkdir(parents=True) would start from
        base = base.parent
    if not base.is_dir():
        raise ConfigError(option, f"{p} cannot be made: {base} is a file, not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise ConfigError(option, f"{p} cannot be written: {base} is not writable")
    # the OS's word, not the permission bits': root passes os.access on /proc, which takes no file
    # (a nameless file tried where the run would start making its own, nothing left behind)
    try:
        with tempfile.TemporaryFile(dir=base):
            pass
    except OSError as err:
        raise ConfigError(option, f"{p} cannot be written: {base} takes no file ({err.strerror or err})") \
            from None


class RunReport:
    """Reads a finished run of ``loopback`` (its world, daemon, drivers and observer) into a
    :class:`SimResult`, writing the trajectory CSV and the plot into ``out_dir`` when it has one."""

    def __init__(self, loopback: Loopback) -> None:
        self.run = loopback

    async def result(self) -> SimResult:
        run = self.run
        assert run.world is not None and run.daemon is not None and run.vesc is not None
        world, daemon = run.world, run.daemon
        pose = world.pose
        vstats = daemon.vesc.stats if daemon.vesc is not None else None
        lstats = daemon.lidar.stats if daemon.lidar is not None else None
        sim_time = world.sim_time
        ready_at_s = run.ready_at_s
        report: dict[str, Any] = {
            "scenario": run.scenario.name,
            "description": run.scenario.description,
            "sim_time_s": round(sim_time, 3),
            "interrupted": run.stop_reason != "duration",
            "stop_reason": run.stop_reason,
            "duration_s": round(run.duration_s, 3),
            "follow": run.drivers.report() if run.drivers is not None else [],
            "ready_at_s": None if ready_at_s is None else round(ready_at_s, 3),
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
            "mux_switches": [[round(world.sim_time_at(daemon.mux.start_ns + round(t * NS_PER_S)), 3), s]
                             for t, s in daemon.mux.switches],
            "faults": [[t, a] for t, a in run.fault_log],
            "vesc": {
                "frames_tx": vstats.frames_tx if vstats else 0,
                "frames_rx": vstats.frames_rx if vstats else 0,
                "crc_errors": vstats.crc_errors if vstats else 0,
                "reconnects": vstats.reconnects if vstats else 0,
                "firmware": firmware_text(run.scenario.firmware_version()),  # 6.02, as vesc-info
            },
            "lidar": {
                "model": run.scenario.lidar.model,
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
            # why the recording stopped early (a write error: the disk full or unwritable); the
            # command then exits 1
            "recording_error": daemon.recorder.stats.error if daemon.recorder is not None else None,
            # where the live view and the status page listened during the run
            "live": dict(daemon.started_live),
            # lockstep (virtual time; speed: a multiple of real time, or "max") or real time
            "clock": run.clock_report(),
        }
        result = SimResult(report, interventions_at=list(run.interventions_at))
        if run.out_dir is not None:
            run.out_dir.mkdir(parents=True, exist_ok=True)
            stem = run.scenario.name or "sim"
            csv_path = run.out_dir / f"{stem}-trajectory.csv"
            png_path = run.out_dir / f"{stem}.png"
            if run.hurried or not run.plot:  # a second Ctrl-C, --no-plot: no picture
                write_csv(csv_path, world.samples)
                report["trajectory_csv"], result.trajectory_csv = str(csv_path), csv_path
                return result
            # the plot is drawn by the run's plot worker (another process) while the CSV is written
            drawn = await self._draw(
                lambda: write_csv(csv_path, world.samples), png_path, run.map, world.trajectory,
                run.intervention_marks, world.collisions, list(world.obstacles.values()), title=stem,
                series=run.control_samples, switches=report["mux_switches"])
            report["trajectory_csv"], result.trajectory_csv = str(csv_path), csv_path
            if drawn:
                report["plot_png"], result.plot_png = str(png_path), png_path
            else:
                print("racecar-hw sim: stopped while the plot was drawn: no plot (the report and the "
                      "trajectory are written)", file=sys.stderr, flush=True)
        return result

    async def _draw(self, meanwhile: Callable[[], None], *args: Any, **kwargs: Any) -> bool:
        """Draw the plot (:func:`~racecar_hw.sim.plot.plot_run`'s arguments) while ``meanwhile()``
        runs; False when a stop request (Ctrl-C) gave it up. The plot worker's answer is awaited
        in a thread, the event loop free to act on a signal: it once held the loop, Ctrl-C and
        all, for up to RESULT_TIMEOUT_S. Drawn here (no worker, or one that could not) at once."""
        stop = self.run.next_stop()
        plotter = self.run.plotter or PlotWorker(None)

        def hand_over() -> tuple[PendingPlot, tuple[int, int] | None]:
            pending = plotter.submit(*args, **kwargs)
            return pending, pending.answer()

        answer = asyncio.get_running_loop().run_in_executor(None, hand_over)
        stopped = asyncio.ensure_future(stop.wait())
        try:
            meanwhile()
            await asyncio.wait({answer, stopped}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stopped.cancel()
            if not answer.done():
                plotter.kill()  # the thread's wait ends at once
        if not answer.done():
            return False
        pending, size = answer.result()
        if size is None:
            pending.wait()  # drawn here
        return True

    def _odometry_error(self) -> float | None:
        """How far the car truly is (m) from where its odometry says at the end, the odom frame
        being the start pose in the map (what the map -> odom transform says); None without odometry."""
        run = self.run
        assert run.world is not None and run.daemon is not None
        odom = run.daemon.bus.latest(run.daemon.config.safety.odom_topic)
        if odom is None:
            return None
        x0, y0, yaw0 = run.scenario.start
        ox, oy = float(odom.pose.pose.position.x), float(odom.pose.pose.position.y)
        mx = x0 + math.cos(yaw0) * ox - math.sin(yaw0) * oy
        my = y0 + math.sin(yaw0) * ox + math.cos(yaw0) * oy
        pose = run.world.pose
        return _num(math.hypot(pose.x - mx, pose.y - my))

    def _interventions(self) -> list[dict[str, Any]]:
        """Each intervention: when (world time), why, what caused it and where the car stopped.

        An intervention that started for something else (a late scan, the reverse cap) and then
        became a stop for an obstacle has a second entry from that moment, with ``continues`` true
        (the first then ends there): what the car stopped for, and how far from it, are in that one.

        ``source``: the live scan or the obstacle memory (None without an obstacle, e.g. a stale
        scan). ``obstacle``: the limiting point in the map frame (:meth:`_seen_at` says from which
        pose); ``object``: what the world has there (``map``, a scenario obstacle's name, or None:
        nothing, a remembered point of something that has gone or that the memory misplaced).
        ``ended_at_s``: when the controller let go (None: at the end of the run). ``stopped_at_s``:
        when the car came to rest before that (:func:`rest_time`: a car that stood at the start and
        then drove stopped where it came to rest again; None: it only slowed down);
        ``stopping_distance_m``: path driven until then; ``distance_left_m``: the gap
        between the car's footprint and that object at standstill, or when the intervention ended
        if the car only slowed (for the map: to the wall around the point, :func:`_wall_gap`; for
        nothing: to the point).
        """
        assert self.run.world is not None and self.run.daemon is not None
        world = self.run.world
        samples = world.samples
        out = []
        for event in self.run.daemon.safety.controller.events:
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
                seen_ns = self._seen_at(o, event.scan_ns, event.pose_ns)
                point = compose(world.pose_at(seen_ns), (o.x, o.y, 0.0))
                entry["source"] = o.source
                entry["obstacle"] = {"x": _num(point.x), "y": _num(point.y)}
                entry["object"] = world.what_is_at(point.x, point.y, world.sim_time_at(seen_ns))
            stopped = rest_time(samples, t, end)
            if stopped is not None:
                entry["stopped_at_s"] = round(stopped, 3)
                entry["stopping_distance_m"] = _num(stopping_distance(samples, t, stopped) or 0.0)
            when = stopped if stopped is not None else end
            if point is not None and when is not None:
                at = next((s for s in samples if s.t >= when), samples[-1])
                corners = footprint((at.x, at.y, at.yaw), world.params)
                if entry["object"] == "map":
                    gap = _wall_gap(world.scene.map, (at.x, at.y, at.yaw), world.params, point.x, point.y)
                else:
                    gap = next((shape.distance_to(corners) for label, shape in world.obstacles_at(when)
                                if label == entry["object"]),
                               point_polygon_distance(point.x, point.y, corners))
                entry["distance_left_m"] = _num(gap)
            out.append(entry)
        return out

    def _seen_at(self, obstacle: Obstacle, scan_ns: int, pose_ns: int | None) -> int:
        """When (monotonic ns) the car was where ``obstacle`` (base_link, of the scan that arrived at
        ``scan_ns``) is relative to: a return of the scan (or a ray of its blind sector), where the
        car was when the lidar measured that beam, up to a sweep before the scan arrived (at 5 m/s
        and 40 Hz, 9 cm); a remembered point, where the car was at ``pose_ns``, the time of the
        odometry pose the controller brought the memory into the scan's frame with (the sweep's
        first beam: safety.node.sweep_ns)."""
        lidar = self.run.lidar
        source = getattr(lidar, "range_source", None)
        if obstacle.source == "memory" or not isinstance(source, SimRangeSource):
            return scan_ns if pose_ns is None else pose_ns
        lx, ly, lyaw = source.laser_pose_in_base
        angle = math.atan2(obstacle.y - ly, obstacle.x - lx) - lyaw
        measured = source.measured_before(angle, scan_ns)
        return scan_ns if measured is None else measured


def _wall_gap(occupancy: OccupancyMap, pose: tuple[float, float, float], params: CarParams, x: float,
              y: float) -> float:
    """The gap (m) between the footprint at ``pose`` and the map's occupied cells within
    :data:`WALL_NEAR_M` of (``x``, ``y``): the wall there, not any wall (a side wall in a corridor is
    not what the car stopped for); measured as the world measures clearance (car.Collider). inf
    when no cell is that near."""
    res = occupancy.resolution
    reach = math.ceil(WALL_NEAR_M / res) + 1
    ci, cj = (int(v) for v in occupancy.world_to_cell(x, y))
    i0, j0 = max(ci - reach, 0), max(cj - reach, 0)
    jj, ii = occupancy.occupied[j0:cj + reach + 1, i0:ci + reach + 1].nonzero()
    cx, cy = occupancy.cell_to_world(ii + i0, jj + j0)
    near = np.hypot(cx - x, cy - y) <= WALL_NEAR_M
    if not near.any():
        return math.inf
    px, py, yaw = pose
    dx, dy = cx[near] - px, cy[near] - py
    c, s = math.cos(yaw), math.sin(yaw)
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    front = params.length - params.rear_overhang
    out_x = np.maximum(np.maximum(-params.rear_overhang - lx, lx - front), 0.0)
    out_y = np.maximum(np.abs(ly) - params.width / 2, 0.0)
    return max(float(np.sqrt(np.min(out_x * out_x + out_y * out_y))) - res / 2, 0.0)


def _speed_at(samples: list[TrajectorySample], t: float) -> float:
    """The car's speed (m/s) at the first sample at or after sim time ``t`` (0 past the end)."""
    return next((s.speed for s in samples if s.t >= t), 0.0)


def _num(x: float) -> float | None:
    return round(float(x), 4) if math.isfinite(x) else None


__all__ = ["RunReport", "SimResult", "write_report"]
