"""The picture of a run: a matplotlib figure a person reads, written as a PNG.

Top: the map in metres (map frame, x right, y up), the driven path coloured by speed, the start and
end poses, the obstacles, interventions (orange rings) and collisions (red crosses). Under it, on one
time axis (seconds of sim time): the commanded, output, allowed and measured speed (m/s) with the
interventions and collisions as vertical marks, the steering angle (rad, + left), and the mux's active
source as a band of coloured spans.

matplotlib's Agg canvas draws without pyplot, so no global figure state is touched and the plot can be
made from any thread. The inputs are plain sequences so a report read back from JSON plots as well as a
live run: interventions and collisions may be (x, y), (t, x, y), objects with ``x``/``y`` (and ``t``)
attributes, or mappings with those keys (and ``reason``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle as CirclePatch
from matplotlib.patches import Polygon as PolygonPatch
from matplotlib.transforms import Affine2D
from mpl_toolkits.axes_grid1 import make_axes_locatable

from racecar_hw.sim.obstacles import Box, Circle, Obstacle, Polygon
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.plot_rows import ControlSample as ControlSample  # re-exported: plot rows
from racecar_hw.sim.plot_rows import Mark
from racecar_hw.sim.world import World

#: Figure width in inches; ``width_px`` sets the resolution.
FIGURE_WIDTH_IN = 8.0
FREE_GREY, OCCUPIED_GREY, UNKNOWN_GREY = 1.0, 0.16, 0.75
START_COLOUR, END_COLOUR = "#14a03c", "#8c28b4"
INTERVENTION_COLOUR, COLLISION_COLOUR, OBSTACLE_COLOUR = "#f59600", "#dc1414", "#787878"
SPEED_COLOURS = {"commanded": "#1f77b4", "output": "#17becf", "allowed": "#f59600", "measured": "#2ca02c"}
SPEED_CMAP = "viridis"
#: The figure's margins (inches): tick labels and axis labels left and below, the title above.
MARGIN_LEFT_IN, MARGIN_RIGHT_IN, MARGIN_BOTTOM_IN, MARGIN_TOP_IN = 0.85, 0.1, 0.5, 0.35
#: The gaps (inches) under the map (its x tick labels and label) and between the time panels.
MAP_GAP_IN, SERIES_GAP_IN = 0.6, 0.12
#: Room (inches) right of the map for its colour bar's tick labels and label.
COLORBAR_LABELS_IN = 0.75


def as_marks(items: Iterable[Any]) -> list[Mark]:
    """Interventions or collisions in any of the accepted shapes, as :class:`Mark` s."""
    marks = []
    for item in items:
        if isinstance(item, Mark):
            marks.append(item)
        elif isinstance(item, Mapping):
            marks.append(Mark(float(item["x"]), float(item["y"]), _opt(item.get("t")),
                              str(item.get("reason", ""))))
        elif hasattr(item, "x") and hasattr(item, "y"):
            marks.append(Mark(float(item.x), float(item.y), _opt(getattr(item, "t", None)),
                              str(getattr(item, "reason", ""))))
        elif len(item) == 2:
            marks.append(Mark(float(item[0]), float(item[1])))
        else:
            marks.append(Mark(float(item[1]), float(item[2]), float(item[0])))
    return marks


def _opt(value: Any) -> float | None:
    return None if value is None else float(value)


def image_size(occ_map: OccupancyMap, width_px: int = 800, with_series: bool = True) -> tuple[int, int]:
    """(width, height) in pixels of the picture :func:`plot_run` draws for this map."""
    w_in, h_in = _figure_inches(occ_map, with_series)
    dpi = width_px / w_in
    return round(w_in * dpi), round(h_in * dpi)


def _map_inches(occ_map: OccupancyMap) -> float:
    """Height of the map panel (inches): the map's aspect, kept between 2.5 and 8 inches."""
    w_m, h_m = occ_map.size_m
    return min(8.0, max(2.5, (FIGURE_WIDTH_IN - 1.6) * h_m / w_m + 0.8))


def _figure_inches(occ_map: OccupancyMap, with_series: bool) -> tuple[float, float]:
    return FIGURE_WIDTH_IN, _map_inches(occ_map) + (4.4 if with_series else 0.0)


def plot_run(path: str | Path, occ_map: OccupancyMap,
             trajectory: Sequence[Sequence[float]],
             interventions: Iterable[Any] = (),
             collisions: Iterable[Any] = (),
             obstacles: Iterable[tuple[float, float, float] | Obstacle] = (),
             width_px: int = 800, title: str | None = None, *,
             series: Sequence[Sequence[float]] = (),
             switches: Sequence[Sequence[Any]] = ()) -> tuple[int, int]:
    """Write :func:`run_figure` to ``path`` (PNG); returns its size in pixels (width, height)."""
    fig = run_figure(occ_map, trajectory, interventions, collisions, obstacles, width_px, title,
                     series=series, switches=switches)
    fig.savefig(path, format="png")
    width, height = fig.get_size_inches() * fig.dpi
    return round(width), round(height)


def run_figure(occ_map: OccupancyMap, trajectory: Sequence[Sequence[float]],
               interventions: Iterable[Any] = (), collisions: Iterable[Any] = (),
               obstacles: Iterable[tuple[float, float, float] | Obstacle] = (),
               width_px: int = 800, title: str | None = None, *,
               series: Sequence[Sequence[float]] = (),
               switches: Sequence[Sequence[Any]] = ()) -> Figure:
    """The figure of a run, ``width_px`` pixels wide.

    ``trajectory`` rows start with (t, x, y, yaw, speed) in sim time, map-frame metres and m/s;
    ``obstacles`` are discs (x, y, radius), :class:`Circle`, :class:`Box` or :class:`Polygon`; ``series`` are
    :class:`ControlSample` rows; ``switches`` are the mux's (t, source) switches in sim time. Without
    ``series`` and ``switches`` only the map panel is drawn.
    """
    traj = np.asarray([row[:5] for row in trajectory], dtype=np.float64).reshape(-1, 5)
    samples = np.asarray([tuple(row)[:6] for row in series], dtype=np.float64).reshape(-1, 6)
    marks_i, marks_c = as_marks(interventions), as_marks(collisions)
    with_series = bool(len(samples) or len(switches))
    w_in, h_in = _figure_inches(occ_map, with_series)
    fig = Figure(figsize=(w_in, h_in), dpi=width_px / w_in)
    FigureCanvasAgg(fig)
    # fixed margins in inches, not a layout engine: matplotlib's constrained layout measures every
    # tick label in extra drawing passes, half the time of writing the PNG
    box = {"left": MARGIN_LEFT_IN / w_in, "right": 1.0 - MARGIN_RIGHT_IN / w_in,
           "bottom": MARGIN_BOTTOM_IN / h_in, "top": 1.0 - MARGIN_TOP_IN / h_in}
    if with_series:
        map_in = _map_inches(occ_map) - MAP_GAP_IN
        series_in = h_in - MARGIN_TOP_IN - MARGIN_BOTTOM_IN - MAP_GAP_IN - map_in
        outer = fig.add_gridspec(2, 1, height_ratios=[map_in, series_in],
                                 hspace=MAP_GAP_IN / ((map_in + series_in) / 2), **box)
        ratios = [2.0, 1.3, 0.7]
        inner = outer[1].subgridspec(3, 1, height_ratios=ratios,
                                     hspace=SERIES_GAP_IN / ((series_in - 2 * SERIES_GAP_IN) / 3))
        map_row = outer[0].subgridspec(1, 2, wspace=0.0, width_ratios=[
            w_in - MARGIN_LEFT_IN - MARGIN_RIGHT_IN - COLORBAR_LABELS_IN, COLORBAR_LABELS_IN])
        ax_map = fig.add_subplot(map_row[0])
        ax_map.set_anchor("S")  # a map shorter than its panel keeps its x labels by the panels below
        ax_speed = fig.add_subplot(inner[0])
        ax_steer = fig.add_subplot(inner[1], sharex=ax_speed)
        ax_source = fig.add_subplot(inner[2], sharex=ax_speed)
    else:
        fig.subplots_adjust(**{**box, "right": box["right"] - COLORBAR_LABELS_IN / w_in})
        ax_map = fig.add_subplot(1, 1, 1)
    _draw_map(fig, ax_map, occ_map, traj, marks_i, marks_c, obstacles)
    if title:
        ax_map.set_title(title)
    if with_series:
        ends = ([traj[-1, 0]] if len(traj) else []) + ([samples[-1, 0]] if len(samples) else [])
        end_t = float(max(ends, default=0.0))
        _draw_speeds(ax_speed, samples, marks_i, marks_c)
        _draw_steering(ax_steer, samples)
        _draw_sources(ax_source, switches, end_t)
        ax_source.set_xlim(0.0, max(end_t, 1e-3))
        ax_source.set_xlabel("sim time (s)")
        for ax in (ax_speed, ax_steer):
            ax.tick_params(labelbottom=False)
    return fig


def plot_world(path: str | Path, world: World, interventions: Iterable[Any] = (),
               width_px: int = 800, title: str | None = None) -> tuple[int, int]:
    """:func:`plot_run` with the map, path, collisions and current obstacles of a :class:`World`."""
    return plot_run(path, world.map, world.trajectory, interventions, world.collisions,
                    world.obstacles.values(), width_px, title)


# --- panels ---------------------------------------------------------------------------------------


def _draw_map(fig: Figure, ax: Any, occ_map: OccupancyMap, traj: np.ndarray, interventions: list[Mark],
              collisions: list[Mark], obstacles: Iterable[Any]) -> None:
    grey = np.full(occ_map.data.shape, FREE_GREY)
    grey[occ_map.data < 0] = UNKNOWN_GREY
    grey[occ_map.occupied] = OCCUPIED_GREY
    ox, oy, oyaw = occ_map.origin
    w_m, h_m = occ_map.size_m
    image = ax.imshow(grey, cmap="gray", vmin=0.0, vmax=1.0, origin="lower", interpolation="nearest",
                      extent=(ox, ox + w_m, oy, oy + h_m), zorder=0)
    if oyaw:
        image.set_transform(Affine2D().rotate_around(ox, oy, oyaw) + ax.transData)
    corners = np.array([occ_map.grid_frame_to_world(gx, gy)
                        for gx, gy in ((0, 0), (occ_map.width, 0), (0, occ_map.height),
                                       (occ_map.width, occ_map.height))])
    ax.set_xlim(corners[:, 0].min(), corners[:, 0].max())
    ax.set_ylim(corners[:, 1].min(), corners[:, 1].max())
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    for obstacle in obstacles:
        if isinstance(obstacle, (Box, Polygon)):
            ax.add_patch(PolygonPatch(obstacle.corners(), closed=True, color=OBSTACLE_COLOUR, zorder=1))
            continue
        x, y, r = ((obstacle.x, obstacle.y, obstacle.radius) if isinstance(obstacle, Circle) else obstacle)
        ax.add_patch(CirclePatch((x, y), r, color=OBSTACLE_COLOUR, zorder=1))
    handles: list[Any] = []
    if len(traj) >= 2:
        segments, speed = path_segments(traj)
        lines = LineCollection(segments, cmap=colormaps[SPEED_CMAP], linewidths=2.5, zorder=2, gid="path")
        lines.set_array(speed)
        lines.set_clim(0.0, max(float(np.abs(traj[1:, 4]).max()), 0.1))
        ax.add_collection(lines)
        # beside the map as drawn (its aspect kept), as tall as it: axes_grid1's divider, since the
        # figure has no layout engine to size a colorbar to the map
        divider = make_axes_locatable(ax)
        divider.set_anchor(ax.get_anchor())
        cax = divider.append_axes("right", size="3%", pad=0.1)
        cax.set_label("<colorbar>")  # the name matplotlib gives the axes of fig.colorbar(ax=...)
        fig.colorbar(lines, cax=cax, label="speed (m/s)")
    if len(traj):
        _pose_marker(ax, traj[0], START_COLOUR, 13)
        _pose_marker(ax, traj[-1], END_COLOUR, 9)
        handles += [_handle("^", START_COLOUR, "start"), _handle("^", END_COLOUR, "end")]
    if interventions:
        ax.scatter([m.x for m in interventions], [m.y for m in interventions], s=110, facecolors="none",
                   edgecolors=INTERVENTION_COLOUR, linewidths=2.2, zorder=4, gid="interventions")
        handles.append(_handle("o", INTERVENTION_COLOUR, f"intervention ({len(interventions)})", hollow=True))
    if collisions:
        ax.scatter([m.x for m in collisions], [m.y for m in collisions], s=120, marker="x",
                   color=COLLISION_COLOUR, linewidths=2.8, zorder=5, gid="collisions")
        handles.append(_handle("x", COLLISION_COLOUR, f"collision ({len(collisions)})"))
    if handles:
        ax.legend(handles=handles, loc="upper right", fontsize="small", framealpha=0.85)


def path_segments(traj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The driven path as line segments ((n, 2, 2): map-frame metres) and the |speed| (m/s) each is
    coloured by, from trajectory rows (t, x, y, yaw, speed) with at least two rows.

    A segment joins each row to the next and takes the later row's speed. Segments of zero length
    (the car standing: most rows of a run that waits) are left out: a zero-length line strokes no
    pixel, and each segment costs the plot a path of its own to build and draw.
    """
    points = traj[:, 1:3]
    moved = np.any(points[1:] != points[:-1], axis=1)
    segments = np.stack([points[:-1][moved], points[1:][moved]], axis=1)
    return segments, np.abs(traj[1:, 4][moved])


def _pose_marker(ax: Any, row: np.ndarray, colour: str, size: float) -> None:
    """A triangle at (x, y) pointing along yaw."""
    marker = (3, 0, math.degrees(float(row[3])) - 90.0)
    ax.plot(row[1], row[2], marker=marker, markersize=size, color=colour, markeredgecolor="black",
            linestyle="none", zorder=6)


def _handle(marker: str, colour: str, label: str, hollow: bool = False) -> Line2D:
    return Line2D([], [], marker=marker, linestyle="none", label=label, markersize=8,
                  color=colour, markerfacecolor="none" if hollow else colour,
                  markeredgewidth=2 if marker in ("x", "o") else 1)


def _event_lines(ax: Any, interventions: list[Mark], collisions: list[Mark]) -> None:
    for mark in interventions:
        if mark.t is not None:
            ax.axvline(mark.t, color=INTERVENTION_COLOUR, linewidth=1.0, alpha=0.8)
    for mark in collisions:
        if mark.t is not None:
            ax.axvline(mark.t, color=COLLISION_COLOUR, linewidth=1.5)


def _draw_speeds(ax: Any, samples: np.ndarray, interventions: list[Mark], collisions: list[Mark]) -> None:
    ax.set_ylabel("speed (m/s)")
    ax.grid(True, alpha=0.3)
    _event_lines(ax, interventions, collisions)
    if not len(samples):
        return
    t = samples[:, 0]
    columns = {"commanded": 1, "output": 2, "allowed": 3, "measured": 4}
    shown = [samples[:, columns[name]] for name in ("commanded", "output", "measured")]
    top = max(0.5, float(np.nanmax(np.concatenate(shown))) * 1.3)
    bottom = min(0.0, float(np.nanmin(np.concatenate(shown))) * 1.3)
    if bottom < 0.0:
        bottom = min(bottom, -0.5)
    allowed = allowed_series(samples, top, bottom)
    styles = {"commanded": "-", "output": "--", "allowed": "-", "measured": "-"}
    for name, col in columns.items():
        values = allowed if name == "allowed" else samples[:, col]
        wide = name == "allowed"
        ax.step(t, values, where="post", label=ALLOWED_LABEL if wide else name,
                color=SPEED_COLOURS[name], linestyle=styles[name], linewidth=1.8 if wide else 1.3)
    ax.set_ylim(bottom, top)
    ax.legend(loc="upper right", fontsize="small", ncols=2, framealpha=0.85)


#: The legend's name of the safety controller's allowed speed.
ALLOWED_LABEL = "allowed by safety (at the edge: no limit)"


def allowed_series(samples: np.ndarray, top: float, bottom: float) -> np.ndarray:
    """The safety controller's allowed speed as drawn (m/s), one value per :class:`ControlSample`.

    The allowed speed is a magnitude (the largest permitted |speed|); it is drawn on the side of the
    direction the car is asked to go (the commanded speed's sign, else the output's, else the
    measured), so in reverse it sits below zero with the measured speed. Where it does not limit
    (inf, or beyond the axis) it runs along that side's edge (``top``, ``bottom``). While idle (no
    speed commanded or sent) the controller's value says nothing about the drive: the line keeps
    the last driving value instead of dropping to 0 for single idle ticks.
    """
    out = np.empty(len(samples))
    magnitude, sign = math.inf, 1.0
    for i, row in enumerate(samples):
        commanded, output, allowed, measured = (float(v) for v in row[1:5])
        if commanded != 0.0 or output != 0.0:
            magnitude = allowed if math.isfinite(allowed) else math.inf
            ref = commanded if commanded != 0.0 else output
            sign = -1.0 if ref < 0.0 else 1.0
        elif i == 0 and measured < 0.0:
            sign = -1.0
        edge = top if sign > 0 else -bottom
        out[i] = sign * min(magnitude, edge * 0.985)
    return out


def _draw_steering(ax: Any, samples: np.ndarray) -> None:
    ax.set_ylabel("steering (rad)")
    ax.grid(True, alpha=0.3)
    if len(samples):
        ax.step(samples[:, 0], samples[:, 5], where="post", color="#9467bd", linewidth=1.3)
        ax.axhline(0.0, color="black", linewidth=0.6)


def _draw_sources(ax: Any, switches: Sequence[Sequence[Any]], end_t: float) -> None:
    """The active mux source over time, one coloured span per stretch, labelled when wide enough."""
    ax.set_yticks([])
    ax.set_ylabel("source", rotation=0, ha="right", va="center")
    spans = [(float(t), str(source)) for t, source in switches]
    names = list(dict.fromkeys(source for _, source in spans))
    palette = colormaps["tab10"]
    colours = {name: ("#bbbbbb" if name == "idle" else "#222222" if name in ("estop", "fault")
                      else palette(i % 10)) for i, name in enumerate(names)}
    for k, (start, source) in enumerate(spans):
        stop = spans[k + 1][0] if k + 1 < len(spans) else end_t
        if stop <= start:
            continue
        ax.broken_barh([(start, stop - start)], (0, 1), color=colours[source], gid=f"source:{source}")
        if end_t > 0 and (stop - start) / end_t > 0.06:
            ax.text((start + stop) / 2, 0.5, source, ha="center", va="center", fontsize="small",
                    color="white" if source not in ("idle",) else "black")
    ax.set_ylim(0, 1)
