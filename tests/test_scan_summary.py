"""The seeds' /scan_range and /open_space for every /scan."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lidar_drivers.base import RandomRangeSource, ScanGeometry
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import LaserScan, OpenSpace, ScanRange, stamp_now
from racecar_hw.sources.scan_summary import ScanSummaryParams, ScanSummaryPublisher, open_space, scan_range

#: The MIT lab 1C fake scan: -2/3 pi .. 2/3 pi every pi/300, ranges 1..10 m, a beam at both ends.
SEED = ScanGeometry(angle_min=-2 / 3 * math.pi, angle_max=2 / 3 * math.pi, angle_increment=math.pi / 300,
                    range_min=1.0, range_max=10.0, scan_time=0.05, time_increment=0.0)


def make_scan(ranges: np.ndarray, stamp_ns: int = 1_700_000_000_250_000_000,
              geometry: ScanGeometry = SEED) -> LaserScan:
    return LaserScan(stamp_now("laser", stamp_ns), geometry.angle_min, geometry.angle_max,
                     geometry.angle_increment, geometry.time_increment, geometry.scan_time,
                     geometry.range_min, geometry.range_max, np.asarray(ranges, dtype=np.float32))


def test_seed_fake_scan() -> None:
    assert SEED.beams == 401
    ranges = RandomRangeSource(seed=7).ranges(SEED.angles())
    scan = make_scan(ranges)
    r = scan_range(scan)
    assert r.closest == pytest.approx(float(np.float32(ranges.min())))
    assert r.farthest == pytest.approx(float(np.float32(ranges.max())))
    assert r.header == scan.header and r.header is not scan.header
    o = open_space(scan)
    i = int(np.argmax(scan.ranges))
    assert o.distance == r.farthest
    assert o.angle == pytest.approx(SEED.angle_min + i * SEED.angle_increment)


def test_invalid_readings_are_ignored() -> None:
    ranges = np.full(SEED.beams, 5.0)
    ranges[0] = math.inf          # no return
    ranges[1] = math.nan          # device error
    ranges[2] = 0.5               # below range_min
    ranges[3] = 12.0              # beyond range_max
    ranges[-1] = 9.5              # the longest valid return, at angle_max
    ranges[200] = 1.25            # the closest, straight ahead
    scan = make_scan(ranges)
    assert (scan_range(scan).closest, scan_range(scan).farthest) == (1.25, 9.5)
    o = open_space(scan)
    assert o.distance == 9.5
    assert o.angle == pytest.approx(SEED.angle_max)


def test_scan_without_valid_beams_gives_nan() -> None:
    scan = make_scan(np.full(SEED.beams, math.inf))
    assert math.isnan(scan_range(scan).closest) and math.isnan(scan_range(scan).farthest)
    assert math.isnan(open_space(scan).angle) and math.isnan(open_space(scan).distance)


@settings(deadline=None)
@given(arrays(np.float32, st.integers(1, 300),
              elements=st.one_of(st.floats(0.0, 40.0, width=32),
                                 st.sampled_from([math.inf, -math.inf, math.nan]))))
def test_summary_matches_a_direct_search(ranges: np.ndarray) -> None:
    geometry = ScanGeometry(-math.pi, math.pi, 2 * math.pi / 300, 0.1, 30.0, 0.1, 0.0)
    scan = make_scan(ranges, geometry=geometry)
    valid = [(float(r), i) for i, r in enumerate(ranges) if math.isfinite(r) and 0.1 <= r <= 30.0]
    r, o = scan_range(scan), open_space(scan)
    if not valid:
        assert math.isnan(r.closest) and math.isnan(o.distance)
        return
    assert r.closest == min(valid)[0]
    assert r.farthest == o.distance == max(v for v, _ in valid)
    index = round((o.angle - geometry.angle_min) / geometry.angle_increment)
    assert float(ranges[index]) == o.distance


def test_publisher_answers_every_scan_on_the_bus() -> None:
    bus = Bus()
    ranges_got: list[ScanRange] = []
    spaces_got: list[OpenSpace] = []
    bus.subscribe("/scan_range", ranges_got.append)
    bus.subscribe("/open_space", spaces_got.append)
    source = RandomRangeSource(seed=3)
    with ScanSummaryPublisher(bus) as node:
        for k in range(20):
            bus.publish("/scan", make_scan(source.ranges(SEED.angles()), stamp_ns=k * 50_000_000))
        bus.publish("/scan", make_scan(np.full(SEED.beams, math.nan)))
    bus.publish("/scan", make_scan(np.full(SEED.beams, 2.0)))  # after close: ignored
    assert len(ranges_got) == len(spaces_got) == node.summarized == 21
    assert node.empty_scans == 1
    assert [m.header.stamp.to_ns() for m in ranges_got[:20]] == [k * 50_000_000 for k in range(20)]
    assert all(m.header.frame_id == "laser" for m in ranges_got)
    assert all(1.0 <= m.closest <= m.farthest <= 10.0 for m in ranges_got[:20])
    assert bus.topics()["/scan_range"] is ScanRange and bus.topics()["/open_space"] is OpenSpace
    assert bus.callback_errors == 0


def test_publisher_topics_are_configurable() -> None:
    bus = Bus()
    got: list[OpenSpace] = []
    bus.subscribe("/summary/open", got.append)
    node = ScanSummaryPublisher(bus, ScanSummaryParams("/fake_scan", "/summary/range", "/summary/open"))
    node.start()
    node.start()
    bus.publish("/fake_scan", make_scan(np.linspace(1.0, 9.0, SEED.beams)))
    node.close()
    node.close()
    assert len(got) == 1 and got[0].distance == pytest.approx(9.0)
    assert got[0].angle == pytest.approx(SEED.angle_max)
