"""The report of a run with several cars: a section per car, the contacts and gaps between cars.

Each car's section is its single-car report (:mod:`racecar_hw.sim.report`: its world's times, its
CSV and plot named SCENARIO-CAR) with what a fleet adds: ``namespace``, ``zenoh_listen``,
``world_start_s`` (when its world started, in fleet time: seconds since the first car's world
started; 0 when they started together, as they do) and ``car_collisions`` (the contacts it was in).
Top level: ``car_collisions`` (every contact between two cars, fleet time) and ``gaps`` (for each
pair, the smallest gap between the footprints over the run and the gap at the end, m).
See docs/sim.md, "Several cars".
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.sim.car import CarParams, Pose2D, footprint
from racecar_hw.sim.car_state import compose
from racecar_hw.sim.fleet_plot import plot_fleet
from racecar_hw.sim.obstacles import Box, polygon_distance
from racecar_hw.sim.report import SimResult
from racecar_hw.sim.world import World

if TYPE_CHECKING:
    from racecar_hw.sim.fleet import CarContact, Fleet


def footprint_box(pose: Pose2D | tuple[float, float, float], params: CarParams) -> Box:
    """The car's footprint at ``pose`` (rear axle, map frame) as a :class:`Box` obstacle."""
    centre = compose(pose, (params.length / 2 - params.rear_overhang, 0.0, 0.0))
    return Box(centre.x, centre.y, params.length, params.width, centre.yaw)


def start_ns(world: World) -> int:
    """The monotonic time (ns) of ``world``'s sim time zero."""
    now_ns = world.time_ns
    return now_ns - round(world.sim_time_at(now_ns) * NS_PER_S)


class FleetReport:
    """Reads a finished :class:`~racecar_hw.sim.fleet.Fleet` and its cars' results."""

    def __init__(self, fleet: Fleet, results: dict[str, SimResult]) -> None:
        self.fleet = fleet
        self.results = results

    def result(self) -> SimResult:
        fleet = self.fleet
        sc = fleet.scenario
        contacts = [_contact(c) for c in fleet.contacts]
        ref = fleet._reference()
        cars: dict[str, Any] = {}
        for name, car in fleet.cars.items():
            report = dict(self.results[name].report)
            z = car.config.zenoh if car.config is not None else None
            report["car"] = name
            report["namespace"] = (z.namespace or "/") if z is not None else None
            report["zenoh_listen"] = list(z.listen) if z is not None and z.enabled else []
            report["world_start_s"] = (round((start_ns(car.world) - start_ns(ref)) / NS_PER_S, 6)
                                       if car.world is not None and ref is not None else None)
            report["car_collisions"] = [c for c in contacts if name in (c["car"], c["other"])]
            cars[name] = report
        worlds = {name: car.world for name, car in fleet.cars.items() if car.world is not None}
        names = list(worlds)
        gaps = [pair_gaps(a, worlds[a], b, worlds[b], cars[a]["world_start_s"] or 0.0)
                for i, a in enumerate(names) for b in names[i + 1:]]
        reports = list(cars.values())
        interrupted = fleet.stop_reason != "duration" or any(r["interrupted"] for r in reports)
        report: dict[str, Any] = {
            "scenario": sc.name,
            "description": sc.description,
            "sim_time_s": max((r["sim_time_s"] for r in reports), default=0.0),
            "interrupted": interrupted,
            "stop_reason": fleet.stop_reason if fleet.stop_reason != "duration" else next(
                (r["stop_reason"] for r in reports if r["interrupted"]), "duration"),
            "car_names": list(cars),
            "car_collisions": contacts,
            "gaps": gaps,
            "cars": cars,
            "plot_png": None,
            # how time ran (every car's is the same loop's) and the longest car's real seconds
            "clock": {**reports[0]["clock"],
                      "real_time_s": max((r["clock"]["real_time_s"] or 0.0 for r in reports), default=0.0)}
            if reports and "clock" in reports[0] else None,
        }
        result = SimResult(report)
        out = fleet.out_dir
        if out is not None and ref is not None and fleet.plot:
            out.mkdir(parents=True, exist_ok=True)
            ends = {name: footprint_box(world.pose, world.params) for name, world in worlds.items()}
            png = plot_fleet(out / f"{sc.name or 'sim'}.png", ref.map,
                             {name: world.trajectory for name, world in worlds.items()}, ends,
                             [(c["x"], c["y"]) for c in contacts], title=sc.name or None)
            report["plot_png"] = str(png)
            result.plot_png = png
        return result


def pair_gaps(a: str, world_a: World, b: str, world_b: World, offset_s: float = 0.0) -> dict[str, Any]:
    """The gap (m) between car ``a``'s and car ``b``'s footprints: the smallest at ``a``'s steps
    (with ``b`` where its world had it at the same instant) and when (``a``'s sim time plus
    ``offset_s``: fleet time), and at the end."""
    t0_ns = start_ns(world_a)
    best, best_t = math.inf, None
    for s in world_a.samples:
        corners_b = footprint(world_b.pose_at(t0_ns + round(s.t * NS_PER_S)), world_b.params)
        gap = polygon_distance(footprint((s.x, s.y, s.yaw), world_a.params), corners_b)
        if gap < best:
            best, best_t = gap, s.t
    final = polygon_distance(footprint(world_a.pose, world_a.params), footprint(world_b.pose, world_b.params))
    return {"cars": [a, b], "min_gap_m": _num(best),
            "min_gap_at_s": None if best_t is None else round(best_t + offset_s, 3),
            "final_gap_m": _num(final)}


def _contact(contact: CarContact) -> dict[str, Any]:
    d = dataclasses.asdict(contact)
    t = d.pop("t")
    return {"t_s": round(t, 3), **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}}


def _num(x: float) -> float | None:
    return round(float(x), 4) if math.isfinite(x) else None


__all__ = ["FleetReport", "footprint_box", "pair_gaps", "start_ns"]
