"""2D occupancy maps in the ROS map_server format: a YAML file next to a PGM or PNG image.

The YAML keys are those of map_server (ROS 1) and nav2_map_server::

    image: track.pgm            # path, relative to the YAML file unless absolute
    resolution: 0.05            # metres per cell
    origin: [-4.0, -1.25, 0.0]  # pose (x, y, yaw) of the LOWER-LEFT corner of the image in the map frame
    negate: 0                   # 1: black is free, white is occupied
    occupied_thresh: 0.65       # occupancy probability above which a cell is occupied
    free_thresh: 0.196          # occupancy probability below which a cell is free
    mode: trinary               # optional: trinary (default), scale or raw

Every key but ``mode`` is required, as in map_server; other keys are ignored (map tools add their
own). A pixel's value follows map_server exactly: ``p`` is the mean of its colour channels (alpha
excluded), ``p = 255 - p`` when ``negate``, ``occ = (255 - p) / 255``; ``occ > occupied_thresh`` is
occupied (100), ``occ < free_thresh`` free (0), otherwise unknown (-1) in trinary mode (and for a
fully transparent pixel) or ``1 + 98 * (occ - free) / (occupied - free)`` in scale mode. In raw
mode the (negated) pixel value is the cell value itself.

Frames: image row 0 is the TOP of the picture; the grid (as in nav_msgs/OccupancyGrid) has row 0 at
the BOTTOM, so grid row ``j`` is image row ``height - 1 - j``. Grid cell (column ``i``, row ``j``)
covers ``[i, i+1) x [j, j+1)`` cells from the origin corner, rotated by the origin yaw (map_server
records the yaw; most ROS consumers ignore it, racecar-hw applies it). The map frame is REP-103:
x east/forward, y north/left, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.resources import config_file

MODES = ("trinary", "scale", "raw")
OCCUPIED, FREE, UNKNOWN = 100, 0, -1


class MapError(ConfigError):
    """A map file is missing, unreadable, or has a bad key; the message names the file and key."""


@dataclass(frozen=True)
class OccupancyMap:
    """An occupancy grid in the map frame.

    ``data`` holds nav_msgs/OccupancyGrid values (int8: 0 free, 100 occupied, -1 unknown, 1..99 in
    scale mode) with shape (height, width) in grid order (row 0 at the bottom). ``occupied`` is the
    boolean grid the simulator collides with and ray-casts against: occupied cells (100; in raw mode
    values of at least ``occupied_thresh * 100``) and, when ``unknown_is_occupied``, unknown cells.
    """

    data: np.ndarray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    negate: bool = False
    mode: str = "trinary"
    unknown_is_occupied: bool = True
    source: Path | None = None

    def __post_init__(self) -> None:
        data = np.ascontiguousarray(self.data, dtype=np.int8)
        if data.ndim != 2 or data.size == 0:
            raise MapError("data", f"expected a non-empty 2D grid, got shape {data.shape}")
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise MapError("resolution", f"must be a positive number of metres, got {self.resolution!r}")
        data.setflags(write=False)
        object.__setattr__(self, "data", data)
        if self.mode == "raw":
            occ = data >= math.ceil(self.occupied_thresh * 100 - 1e-9)
        else:
            occ = data == OCCUPIED
        if self.unknown_is_occupied:
            occ |= data < 0
        occ.setflags(write=False)
        object.__setattr__(self, "_occupied", occ)

    @classmethod
    def from_occupied(cls, occupied: np.ndarray, resolution: float,
                      origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
                      image_order: bool = True) -> OccupancyMap:
        """A map from a boolean array (True = occupied), in image order (row 0 = top) by default."""
        occ = np.asarray(occupied, dtype=bool)
        if image_order:
            occ = occ[::-1]
        return cls(np.where(occ, OCCUPIED, FREE).astype(np.int8), float(resolution),
                   tuple(float(v) for v in origin))  # type: ignore[arg-type]

    @property
    def occupied(self) -> np.ndarray:
        """Boolean grid, shape (height, width), grid order (row 0 at the bottom); read-only."""
        return self._occupied  # type: ignore[attr-defined,no-any-return]

    @property
    def width(self) -> int:
        """Cells along the grid x axis (image columns)."""
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        """Cells along the grid y axis (image rows)."""
        return int(self.data.shape[0])

    @property
    def size_m(self) -> tuple[float, float]:
        """Extent (width, height) in metres."""
        return self.width * self.resolution, self.height * self.resolution

    def image(self) -> np.ndarray:
        """``data`` in image order (row 0 = top), a view."""
        return self.data[::-1]

    # --- frames ---------------------------------------------------------------------------------

    def world_to_grid_frame(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame metres to continuous grid coordinates in cells (0, 0 = the lower-left corner)."""
        ox, oy, oyaw = self.origin
        dx, dy = np.asarray(x, dtype=np.float64) - ox, np.asarray(y, dtype=np.float64) - oy
        c, s = math.cos(oyaw), math.sin(oyaw)
        return (c * dx + s * dy) / self.resolution, (-s * dx + c * dy) / self.resolution

    def grid_frame_to_world(self, gx: Any, gy: Any) -> tuple[np.ndarray, np.ndarray]:
        """Continuous grid coordinates in cells to map-frame metres."""
        ox, oy, oyaw = self.origin
        gx = np.asarray(gx, dtype=np.float64) * self.resolution
        gy = np.asarray(gy, dtype=np.float64) * self.resolution
        c, s = math.cos(oyaw), math.sin(oyaw)
        return ox + c * gx - s * gy, oy + s * gx + c * gy

    def world_to_cell(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Grid indices (column i, row j from the bottom) of the cell holding a point; may be outside."""
        gx, gy = self.world_to_grid_frame(x, y)
        return np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)

    def cell_to_world(self, i: Any, j: Any) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame centre of grid cell (column i, row j from the bottom)."""
        return self.grid_frame_to_world(np.asarray(i) + 0.5, np.asarray(j) + 0.5)

    def world_to_pixel(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Image (row, column) of the pixel holding a map-frame point (row 0 = top); may be outside."""
        i, j = self.world_to_cell(x, y)
        return self.height - 1 - j, i

    def pixel_to_world(self, row: Any, col: Any) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame centre of image pixel (row, column), row 0 being the top of the image."""
        return self.cell_to_world(np.asarray(col), self.height - 1 - np.asarray(row))

    def in_bounds(self, x: Any, y: Any) -> np.ndarray:
        """Whether map-frame points lie on the grid."""
        i, j = self.world_to_cell(x, y)
        return (i >= 0) & (i < self.width) & (j >= 0) & (j < self.height)

    def is_occupied(self, x: Any, y: Any) -> np.ndarray:
        """Whether map-frame points fall in occupied cells (points off the grid are free)."""
        i, j = self.world_to_cell(x, y)
        inside = (i >= 0) & (i < self.width) & (j >= 0) & (j < self.height)
        out = np.zeros(np.shape(i), dtype=bool)
        out[inside] = self.occupied[j[inside], i[inside]]
        return out


# --- loading --------------------------------------------------------------------------------------


def load_map(yaml_path: str | Path, unknown_is_occupied: bool = True) -> OccupancyMap:
    """Load a map_server YAML and its image. Raises :class:`MapError` naming the file and key."""
    path = Path(yaml_path)
    where = str(path)
    try:
        text = path.read_text()
    except FileNotFoundError as err:
        raise MapError(where, "map YAML file not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise MapError(where, f"cannot read map YAML: {err}") from err
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise MapError(where, f"not valid YAML: {err}") from err
    if not isinstance(doc, dict):
        raise MapError(where, "expected a mapping of map_server keys")

    def key(name: str) -> str:
        return f"{where}: {name}"

    def required(name: str) -> Any:
        if name not in doc:
            raise MapError(key(name), "required map_server key is missing")
        return doc[name]

    def number(name: str) -> float:
        value = required(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise MapError(key(name), f"expected a finite number, got {value!r}")
        return float(value)

    image = required("image")
    if not isinstance(image, str) or not image:
        raise MapError(key("image"), f"expected an image file name, got {image!r}")
    resolution = number("resolution")
    if resolution <= 0:
        raise MapError(key("resolution"), f"must be > 0 metres per cell, got {resolution}")
    origin = required("origin")
    if (not isinstance(origin, (list, tuple)) or len(origin) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                       for v in origin)):
        raise MapError(key("origin"), f"expected [x, y, yaw] (metres, metres, radians), got {origin!r}")
    negate = required("negate")
    if negate not in (0, 1) or isinstance(negate, float):
        raise MapError(key("negate"), f"expected 0 or 1, got {negate!r}")
    occupied_thresh = number("occupied_thresh")
    free_thresh = number("free_thresh")
    if not 0.0 <= free_thresh <= occupied_thresh <= 1.0:
        raise MapError(key("free_thresh"), f"need 0 <= free_thresh ({free_thresh}) <= occupied_thresh "
                                           f"({occupied_thresh}) <= 1")
    mode = doc.get("mode", "trinary")
    if mode not in MODES:
        raise MapError(key("mode"), f"{mode!r} is not allowed; allowed values: {', '.join(MODES)}")

    image_path = Path(image) if Path(image).is_absolute() else path.parent / image
    data = image_to_grid(read_image(image_path, key("image")), bool(negate), occupied_thresh,
                         free_thresh, mode)
    return OccupancyMap(data, resolution, (float(origin[0]), float(origin[1]), float(origin[2])),
                        occupied_thresh, free_thresh, bool(negate), mode, unknown_is_occupied, path)


def load_shipped_map(name: str) -> OccupancyMap:
    """One of the maps shipped in ``config/maps`` by name: ``track``, ``room`` or ``corridor``."""
    return load_map(config_file("maps", f"{name}.yaml"))


def read_image(path: Path, key: str = "image") -> Image.Image:
    """Open a map image fully, translating file errors to :class:`MapError`."""
    try:
        with Image.open(path) as img:
            img.load()
            return img
    except FileNotFoundError as err:
        raise MapError(key, f"image file not found: {path}") from err
    except (UnidentifiedImageError, OSError, SyntaxError) as err:
        raise MapError(key, f"cannot read image {path}: {err}") from err


def image_to_grid(img: Image.Image, negate: bool, occupied_thresh: float, free_thresh: float,
                  mode: str = "trinary") -> np.ndarray:
    """Cell values (int8, grid order: row 0 at the bottom) from a map image, as map_server computes them."""
    colour, alpha = _channels(img)
    if negate:
        colour = 255.0 - colour
    if mode == "raw":
        values = colour.astype(np.int64).astype(np.int8)  # map_server stores the byte: 255 reads as -1
        return np.ascontiguousarray(values[::-1])
    occ = (255.0 - colour) / 255.0
    values = np.full(colour.shape, UNKNOWN, dtype=np.int8)
    if mode == "scale":
        ratio = (occ - free_thresh) / max(occupied_thresh - free_thresh, 1e-12)
        scaled = (1 + 98 * ratio).astype(np.int64).clip(1, 99).astype(np.int8)
        values = np.where(alpha == 0, np.int8(UNKNOWN), scaled).astype(np.int8)
    values[occ > occupied_thresh] = OCCUPIED
    values[occ < free_thresh] = FREE
    return np.ascontiguousarray(values[::-1])


def _channels(img: Image.Image) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the colour channels (0..255 float) and alpha (255 when none), image order."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        peak = 65535.0 if arr.max(initial=0) > 255 or img.mode.startswith("I;16") else 255.0
        return arr * (255.0 / peak), np.full(arr.shape, 255.0)
    if img.mode == "P":
        img = img.convert("RGBA")
    elif img.mode not in ("L", "LA", "RGB", "RGBA"):
        img = img.convert("RGBA" if "A" in img.mode else "RGB")
    arr = np.asarray(img, dtype=np.float64)
    if arr.ndim == 2:
        return arr, np.full(arr.shape, 255.0)
    if img.mode in ("LA", "RGBA"):
        return arr[..., :-1].mean(axis=2), arr[..., -1]
    return arr.mean(axis=2), np.full(arr.shape[:2], 255.0)
