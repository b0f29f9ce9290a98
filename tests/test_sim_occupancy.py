"""Occupancy maps in map_server format: images, origin, negate, thresholds, modes, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from PIL import Image

from racecar_hw.base.errors import ConfigError, RacecarError
from racecar_hw.sim.occupancy import MapError, OccupancyMap, image_to_grid, load_map, load_shipped_map

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

YAML = """image: {image}
resolution: {resolution}
origin: {origin}
negate: {negate}
occupied_thresh: 0.65
free_thresh: 0.196
"""


def write_map(tmp_path: Path, pixels: np.ndarray, image: str = "m.pgm", resolution: float = 0.1,
              origin: str = "[0.0, 0.0, 0.0]", negate: int = 0, extra: str = "",
              mode: str | None = None) -> Path:
    img_mode = {2: "L", 3: "RGB"}[pixels.ndim] if pixels.ndim != 3 or pixels.shape[2] != 4 else "RGBA"
    Image.fromarray(pixels.astype(np.uint8), mode=img_mode).save(tmp_path / image)
    text = YAML.format(image=image, resolution=resolution, origin=origin, negate=negate) + extra
    if mode:
        text += f"mode: {mode}\n"
    path = tmp_path / "m.yaml"
    path.write_text(text)
    return path


def pattern() -> np.ndarray:
    """A 4 x 6 image: black top-left pixel, grey (unknown) bottom-right, the rest white."""
    px = np.full((4, 6), 254, dtype=np.uint8)
    px[0, 0] = 0
    px[3, 5] = 205
    return px


@pytest.mark.parametrize("image", ["m.pgm", "m.png"])
def test_loads_pgm_and_png_with_rows_flipped(tmp_path: Path, image: str) -> None:
    m = load_map(write_map(tmp_path, pattern(), image=image))
    assert (m.width, m.height) == (6, 4)
    # grid row 0 is the image's bottom row
    assert m.data[3, 0] == 100 and m.image()[0, 0] == 100
    assert m.data[0, 5] == -1
    assert int((m.data == 0).sum()) == 22
    assert m.occupied[3, 0] and m.occupied[0, 5]  # unknown counts as occupied by default
    assert m.source == tmp_path / "m.yaml"


def test_unknown_can_be_free(tmp_path: Path) -> None:
    m = load_map(write_map(tmp_path, pattern()), unknown_is_occupied=False)
    assert not m.occupied[0, 5] and m.occupied[3, 0]


def test_rgb_and_alpha_images(tmp_path: Path) -> None:
    rgba = np.zeros((2, 2, 4), dtype=np.uint8)
    rgba[..., :3] = 254
    rgba[..., 3] = 255
    rgba[0, 0, :3] = (0, 0, 0)      # black: occupied
    rgba[0, 1, :3] = (254, 0, 0)    # mean 84.7 -> occ 0.67: occupied
    rgba[1, 0, :3] = (254, 254, 0)  # mean 169 -> occ 0.34: unknown in trinary
    m = load_map(write_map(tmp_path, rgba, image="m.png"))
    img = m.image()
    assert img[0, 0] == 100 and img[0, 1] == 100 and img[1, 0] == -1 and img[1, 1] == 0


def test_pixel_world_conversions_follow_map_server(tmp_path: Path) -> None:
    m = load_map(write_map(tmp_path, pattern(), origin="[-1.0, 2.0, 0.0]"))
    # the image's top-left pixel is the cell at the top of column 0
    x, y = m.pixel_to_world(0, 0)
    assert (float(x), float(y)) == pytest.approx((-1.0 + 0.05, 2.0 + 0.35))
    # the lower-left corner of the image is the origin
    x, y = m.pixel_to_world(3, 0)
    assert (float(x), float(y)) == pytest.approx((-0.95, 2.05))
    row, col = m.world_to_pixel(-0.95, 2.35)
    assert (int(row), int(col)) == (0, 0)
    assert bool(m.is_occupied(-0.95, 2.35))
    assert not bool(m.is_occupied(-0.85, 2.35))
    assert not bool(m.in_bounds(-1.01, 2.1)) and bool(m.in_bounds(-0.99, 2.01))
    assert not bool(m.is_occupied(100.0, 100.0))  # off the grid is free


def test_origin_yaw_rotates_the_grid(tmp_path: Path) -> None:
    m = load_map(write_map(tmp_path, pattern(), origin=f"[1.0, 1.0, {math.pi / 2}]"))
    # grid +x points along map +y: the cell one to the right of the origin corner is above it
    x, y = m.cell_to_world(0, 0)
    assert (float(x), float(y)) == pytest.approx((1.0 - 0.05, 1.05))
    i, j = m.world_to_cell(1.0 - 0.05, 1.0 + 0.55)
    assert (int(i), int(j)) == (5, 0)


@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-math.pi, math.pi))
def test_world_grid_round_trip(x: float, y: float, yaw: float) -> None:
    m = OccupancyMap(np.zeros((3, 3), dtype=np.int8), 0.05, (1.5, -2.0, yaw))
    gx, gy = m.world_to_grid_frame(x, y)
    bx, by = m.grid_frame_to_world(gx, gy)
    assert float(bx) == pytest.approx(x, abs=1e-9) and float(by) == pytest.approx(y, abs=1e-9)


def test_negate_inverts_colours(tmp_path: Path) -> None:
    m = load_map(write_map(tmp_path, pattern(), negate=1))
    img = m.image()
    assert img[0, 0] == 0            # black is free when negated
    assert img[1, 1] == 100          # white is occupied
    assert img[3, 5] == 100          # 205 reads as 50: occupancy (255 - 50) / 255 = 0.80


def test_thresholds_decide_each_cell(tmp_path: Path) -> None:
    px = np.array([[0, 89, 90, 204, 205, 206, 254]], dtype=np.uint8)
    # occ = (255 - p) / 255: 1.0, 0.651, 0.647, 0.2, 0.19608 (map_saver's unknown), 0.192, 0.004
    path = write_map(tmp_path, px)
    m = load_map(path)
    assert list(m.image()[0]) == [100, 100, -1, -1, -1, 0, 0]
    path.write_text(path.read_text().replace("occupied_thresh: 0.65", "occupied_thresh: 0.9"))
    assert list(load_map(path).image()[0]) == [100, -1, -1, -1, -1, 0, 0]


def test_scale_and_raw_modes(tmp_path: Path) -> None:
    px = np.array([[0, 130, 254]], dtype=np.uint8)
    scale = load_map(write_map(tmp_path, px, mode="scale")).image()[0]
    occ = (255 - 130) / 255
    assert list(scale) == [100, int(1 + 98 * (occ - 0.196) / (0.65 - 0.196)), 0]
    raw_px = np.array([[0, 40, 100, 255]], dtype=np.uint8)
    raw = load_map(write_map(tmp_path, raw_px, mode="raw"))
    assert list(raw.image()[0]) == [0, 40, 100, -1]
    assert list(raw.occupied[0]) == [False, False, True, True]


def test_absolute_image_path(tmp_path: Path) -> None:
    sub = tmp_path / "elsewhere"
    sub.mkdir()
    Image.fromarray(pattern(), mode="L").save(sub / "abs.pgm")
    path = tmp_path / "m.yaml"
    path.write_text(YAML.format(image=sub / "abs.pgm", resolution=0.05, origin="[0, 0, 0]", negate=0))
    assert load_map(path).width == 6


@pytest.mark.parametrize("key", ["image", "resolution", "origin", "negate", "occupied_thresh",
                                 "free_thresh"])
def test_missing_key_is_named(tmp_path: Path, key: str) -> None:
    path = write_map(tmp_path, pattern())
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith(key + ":")]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MapError, match=key) as info:
        load_map(path)
    assert info.value.key.endswith(key)
    assert isinstance(info.value, ConfigError) and isinstance(info.value, RacecarError)


@pytest.mark.parametrize(("key", "bad"), [
    ("resolution", "-0.05"), ("resolution", "abc"), ("origin", "[1, 2]"), ("origin", "[1, 2, nope]"),
    ("negate", "2"), ("occupied_thresh", "1.5"), ("free_thresh", "0.9"), ("mode", "fancy"),
])
def test_bad_value_is_named(tmp_path: Path, key: str, bad: str) -> None:
    path = write_map(tmp_path, pattern())
    text = "\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith(key + ":"))
    path.write_text(text + f"\n{key}: {bad}\n")
    with pytest.raises(MapError, match=key):
        load_map(path)


def test_missing_files_and_garbage(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="not found"):
        load_map(tmp_path / "nope.yaml")
    path = write_map(tmp_path, pattern())
    (tmp_path / "m.pgm").unlink()
    with pytest.raises(MapError, match="image file not found"):
        load_map(path)
    (tmp_path / "m.pgm").write_bytes(b"not an image at all")
    with pytest.raises(MapError, match="cannot read image"):
        load_map(path)
    path.write_text("image: [unclosed\n")
    with pytest.raises(MapError, match="not valid YAML"):
        load_map(path)
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(MapError, match="cannot read map YAML"):
        load_map(path)
    path.write_text("- a list\n")
    with pytest.raises(MapError, match="mapping"):
        load_map(path)


def test_shipped_maps_load() -> None:
    for name in ("track", "room", "corridor"):
        m = load_shipped_map(name)
        assert m.resolution == 0.05
        assert not bool(m.is_occupied(0.0, 0.0))  # every start pose is at the origin, in free space
        assert m.occupied.any() and (~m.occupied).any()


def reference_value(p: float, negate: bool, occ_th: float, free_th: float) -> int:
    """map_server's per-pixel rule for trinary mode, one pixel at a time."""
    if negate:
        p = 255 - p
    occ = (255 - p) / 255.0
    if occ > occ_th:
        return 100
    if occ < free_th:
        return 0
    return -1


@settings(max_examples=60, deadline=None)
@given(arrays(np.uint8, st.tuples(st.integers(1, 9), st.integers(1, 9))), st.booleans(),
       st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_every_pixel_follows_map_server(pixels: np.ndarray, negate: bool, a: float, b: float) -> None:
    free_th, occ_th = min(a, b), max(a, b)
    grid = image_to_grid(Image.fromarray(pixels, mode="L"), negate, occ_th, free_th)
    want = [[reference_value(float(p), negate, occ_th, free_th) for p in row] for row in pixels[::-1]]
    assert grid.tolist() == want


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=200))
def test_garbage_image_files_raise_map_error(tmp_path_factory: pytest.TempPathFactory, blob: bytes) -> None:
    tmp = tmp_path_factory.mktemp("garbage")
    (tmp / "g.pgm").write_bytes(blob)
    (tmp / "g.yaml").write_text(YAML.format(image="g.pgm", resolution=0.05, origin="[0, 0, 0]", negate=0))
    try:
        m = load_map(tmp / "g.yaml")
    except MapError:
        return
    assert m.data.ndim == 2  # some short blobs are valid images; then they load as maps


@settings(max_examples=60, deadline=None)
@given(st.text(max_size=120))
def test_garbage_yaml_raises_map_error(tmp_path_factory: pytest.TempPathFactory, text: str) -> None:
    tmp = tmp_path_factory.mktemp("yaml")
    (tmp / "g.yaml").write_text(text)
    with pytest.raises(MapError):
        load_map(tmp / "g.yaml")
