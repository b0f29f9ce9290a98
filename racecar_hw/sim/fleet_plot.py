"""The picture of a run with several cars: every car's path on the map, one colour per car.

The map as in :mod:`racecar_hw.sim.plot` (map frame, metres), each car's driven path as a line in
its colour, named in the legend, its start and end poses, its footprint where it ended (a box in its
colour), and the contacts between cars (red crosses). Each car's own plot, with its speeds and
sources, is the single-car picture next to this one.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Polygon as PolygonPatch

from racecar_hw.sim.obstacles import Box
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.plot import (
    COLLISION_COLOUR,
    FIGURE_WIDTH_IN,
    _draw_map,
    _map_inches,
    _pose_marker,
)


def plot_fleet(path: str | Path, occ_map: OccupancyMap, paths: Mapping[str, Sequence[Sequence[float]]],
               footprints: Mapping[str, Box], contacts: Iterable[tuple[float, float]] = (),
               title: str | None = None, width_px: int = 800) -> Path:
    """Write the picture to ``path`` (PNG): ``paths`` are each car's (t, x, y, yaw, ...) rows,
    ``footprints`` where each car ended, ``contacts`` (x, y) points of car-car contacts."""
    height = _map_inches(occ_map) + 0.6
    fig = Figure(figsize=(FIGURE_WIDTH_IN, height), dpi=width_px / FIGURE_WIDTH_IN, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    _draw_map(fig, ax, occ_map, np.zeros((0, 5)), [], [], ())
    colours = colormaps["tab10"]
    handles = []
    for k, (name, rows) in enumerate(paths.items()):
        colour = colours(k % 10)
        traj = np.asarray([row[:4] for row in rows], dtype=np.float64).reshape(-1, 4)
        if name in footprints:
            ax.add_patch(PolygonPatch(footprints[name].corners(), closed=True, facecolor=colour,
                                      edgecolor="black", alpha=0.5, zorder=3))
        if len(traj):
            # each later car's line thinner, so paths on one lane all show
            ax.plot(traj[:, 1], traj[:, 2], color=colour, linewidth=max(4.5 - 1.5 * k, 1.5), zorder=2,
                    gid=f"path-{name}")
            _pose_marker(ax, traj[0], colour, 11)
            _pose_marker(ax, traj[-1], colour, 8)
        handles.append(Line2D([], [], color=colour, linewidth=2.5, label=name))
    points = list(contacts)
    if points:
        ax.scatter([x for x, _ in points], [y for _, y in points], s=120, marker="x", color=COLLISION_COLOUR,
                   linewidths=2.8, zorder=5, gid="contacts")
        handles.append(Line2D([], [], marker="x", linestyle="none", color=COLLISION_COLOUR,
                              markeredgewidth=2, label=f"car-car contact ({len(points)})"))
    ax.legend(handles=handles, loc="upper right", fontsize="small", framealpha=0.85)
    if title:
        ax.set_title(title)
    out = Path(path)
    fig.savefig(out, format="png")
    return out


__all__ = ["plot_fleet"]
