"""A PNG picture of a run: the map, the driven path, start and end poses, interventions, collisions.

Pillow only. The map is scaled to ``width_px`` wide (nearest neighbour, so cells stay crisp), north
(map +y) up when the map's origin yaw is 0; a legend band sits under the map. Points are map-frame
metres.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from racecar_hw.sim.obstacles import Box, Circle, Obstacle, Polygon
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.world import Collision, World

LEGEND_PX = 30
FREE_RGB, OCCUPIED_RGB, UNKNOWN_RGB = (255, 255, 255), (40, 40, 40), (190, 190, 190)
PATH_RGB = (30, 90, 220)
START_RGB, END_RGB = (20, 160, 60), (140, 40, 180)
INTERVENTION_RGB, COLLISION_RGB, OBSTACLE_RGB = (245, 150, 0), (220, 20, 20), (120, 120, 120)


def image_size(occ_map: OccupancyMap, width_px: int = 800) -> tuple[int, int]:
    """(width, height) in pixels of the picture :func:`plot_run` draws for this map."""
    scale = width_px / occ_map.width
    return width_px, max(1, round(occ_map.height * scale)) + LEGEND_PX


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):
        return ImageFont.load_default()


def plot_run(path: str | Path, occ_map: OccupancyMap,
             trajectory: Sequence[Sequence[float]],
             interventions: Iterable[tuple[float, float]] = (),
             collisions: Iterable[tuple[float, float] | Collision] = (),
             obstacles: Iterable[tuple[float, float, float] | Obstacle] = (),
             width_px: int = 800, title: str | None = None) -> tuple[int, int]:
    """Write the picture to ``path`` (PNG). ``trajectory`` rows start with (t, x, y, yaw, ...);
    ``collisions`` are (x, y) points or :class:`~racecar_hw.sim.world.Collision`; ``obstacles`` are
    discs (x, y, radius), :class:`Circle`, :class:`Box` or :class:`Polygon`. Returns the image size
    (width, height)."""
    width, height = image_size(occ_map, width_px)
    map_h = height - LEGEND_PX
    scale = width / occ_map.width  # pixels per cell

    rgb = np.empty(occ_map.data.shape + (3,), dtype=np.uint8)
    img_data = occ_map.image()
    rgb[:] = FREE_RGB
    rgb[img_data < 0] = UNKNOWN_RGB
    rgb[occ_map.occupied[::-1]] = OCCUPIED_RGB
    base = Image.fromarray(rgb, mode="RGB").resize((width, map_h), Image.Resampling.NEAREST)
    img = Image.new("RGB", (width, height), (250, 250, 250))
    img.paste(base, (0, 0))
    draw = ImageDraw.Draw(img)

    def px(x: float, y: float) -> tuple[float, float]:
        gx, gy = occ_map.world_to_grid_frame(x, y)
        return float(gx) * scale, map_h - float(gy) * scale

    unit = max(4.0, width / 110)  # marker size in pixels
    for obstacle in obstacles:
        if isinstance(obstacle, (Box, Polygon)):
            draw.polygon([px(x, y) for x, y in obstacle.corners()], fill=OBSTACLE_RGB)
            continue
        ox, oy, r = ((obstacle.x, obstacle.y, obstacle.radius) if isinstance(obstacle, Circle)
                     else obstacle)
        cx, cy = px(ox, oy)
        rp = max(r / occ_map.resolution * scale, 2.0)
        draw.ellipse((cx - rp, cy - rp, cx + rp, cy + rp), fill=OBSTACLE_RGB)

    points = [px(row[1], row[2]) for row in trajectory]
    if len(points) >= 2:
        draw.line(points, fill=PATH_RGB, width=max(2, round(unit / 2.5)), joint="curve")
    if trajectory:
        # the start marker is the larger one, so it still shows when a run ends where it began
        _pose_marker(draw, points[0], trajectory[0][3] - occ_map.origin[2], unit * 2.2, START_RGB)
        _pose_marker(draw, points[-1], trajectory[-1][3] - occ_map.origin[2], unit * 1.3, END_RGB)
    for x, y in interventions:
        cx, cy = px(x, y)
        draw.ellipse((cx - unit, cy - unit, cx + unit, cy + unit), outline=INTERVENTION_RGB,
                     width=max(2, round(unit / 3)))
    for collision in collisions:
        cx, cy = px(*((collision.x, collision.y) if isinstance(collision, Collision) else collision))
        w = max(3, round(unit / 2))
        draw.line((cx - unit, cy - unit, cx + unit, cy + unit), fill=COLLISION_RGB, width=w)
        draw.line((cx - unit, cy + unit, cx + unit, cy - unit), fill=COLLISION_RGB, width=w)

    _legend(draw, width, map_h, occ_map, title)
    img.save(path, format="PNG")
    return width, height


def plot_world(path: str | Path, world: World, interventions: Iterable[tuple[float, float]] = (),
               width_px: int = 800, title: str | None = None) -> tuple[int, int]:
    """:func:`plot_run` with the map, path, collisions and current obstacles of a :class:`World`."""
    return plot_run(path, world.map, world.trajectory, interventions, world.collisions,
                    world.obstacles.values(), width_px, title)


def _pose_marker(draw: ImageDraw.ImageDraw, at: tuple[float, float], yaw: float, size: float,
                 colour: tuple[int, int, int]) -> None:
    """A triangle pointing along ``yaw`` (image y points down, so the angle is mirrored)."""
    x, y = at
    c, s = math.cos(yaw), -math.sin(yaw)
    tip = (x + c * size, y + s * size)
    left = (x - c * size * 0.6 - s * size * 0.6, y - s * size * 0.6 + c * size * 0.6)
    right = (x - c * size * 0.6 + s * size * 0.6, y - s * size * 0.6 - c * size * 0.6)
    draw.polygon([tip, left, right], fill=colour, outline=(0, 0, 0))


def _legend(draw: ImageDraw.ImageDraw, width: int, top: int, occ_map: OccupancyMap,
            title: str | None) -> None:
    font = _font(14)
    y = top + LEGEND_PX // 2
    x = 8
    entries = [("path", PATH_RGB), ("start", START_RGB), ("end", END_RGB),
               ("intervention", INTERVENTION_RGB), ("collision", COLLISION_RGB)]
    for label, colour in entries:
        draw.rectangle((x, y - 5, x + 10, y + 5), fill=colour)
        draw.text((x + 14, y), label, fill=(0, 0, 0), font=font, anchor="lm")
        x += 24 + int(draw.textlength(label, font=font))
    # a 1 m scale bar
    bar = 1.0 / occ_map.resolution * (width / occ_map.width)
    right = width - 8
    draw.line((right - bar, y + 6, right, y + 6), fill=(0, 0, 0), width=3)
    draw.text((right - bar - 6, y), "1 m", fill=(0, 0, 0), font=font, anchor="rm")
    if title:
        draw.text((x + 10, y), title, fill=(0, 0, 0), font=font, anchor="lm")
