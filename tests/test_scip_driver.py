"""HokuyoDriver against the fake Hokuyo over real ptys and TCP, with faults injected."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable

import numpy as np
import pytest
from conftest import async_wait_for

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.params import LidarParams
from lidar_drivers.registry import DEFAULT_BAUD, make_driver, make_fake
from lidar_drivers.scip import ScanCommand, SensorParams, encode_scan
from lidar_drivers.scip_driver import HokuyoDriver, crop_steps, ranges_m
from lidar_drivers.scip_fake import FakeHokuyo
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.link import SerialLink, TcpLink
from racecar_hw.base.messages import LaserScan

ROOM = RoomRangeSource(8, 6)
FAST = {"reconnect_backoff_min_s": 0.05, "reconnect_backoff_max_s": 0.2}


def start_fake(device_thread, model: str, tmp_path, tcp: bool) -> FakeHokuyo:
    fake = FakeHokuyo(model, ROOM, link=None if tcp else str(tmp_path / "lidar"),
                      tcp=("127.0.0.1", 0) if tcp else None, seed=7)
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)
    return fake


def params_for(fake: FakeHokuyo, **kw) -> LidarParams:
    where = ({"tcp": "{}:{}".format(*fake.tcp_address)} if fake.tcp_address else {"port": fake.path})
    return LidarParams(model=fake.model.name, **where, **{**FAST, **kw})


def drive(params: LidarParams, scenario: Callable[[HokuyoDriver, list[LaserScan]], Awaitable[None]]
          ) -> None:
    async def main() -> None:
        bus = Bus()
        scans: list[LaserScan] = []
        bus.subscribe(params.topic, scans.append)
        driver = make_driver(bus, params)
        assert isinstance(driver, HokuyoDriver)
        task = asyncio.create_task(driver.run())
        try:
            await scenario(driver, scans)
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task

    asyncio.run(main())


async def more_scans(scans: list, n: int, timeout: float = 15.0) -> None:
    target = len(scans) + n
    await async_wait_for(lambda: len(scans) >= target, timeout)


def expected_ranges(scan: LaserScan) -> np.ndarray:
    return np.rint(ROOM.ranges(scan.angles()) * 1000) / 1000


@pytest.mark.parametrize(("model", "tcp"), [("ust-10lx", True), ("urg-04lx", False),
                                            ("utm-30lx", False), ("utm-30lx-ew", True)])
def test_streams_laser_scans_in_ros_conventions(device_thread, tmp_path, model, tcp):
    fake = start_fake(device_thread, model, tmp_path, tcp)
    m = fake.model

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 3)
        scan = scans[-1]
        assert driver.connected and driver.info["product"] == m.model
        assert driver.info["firmware"] == m.firmware and driver.info["serial"] == fake.serial
        step = 2 * math.pi / m.ares
        assert scan.angle_min == pytest.approx((m.amin - m.afrt) * step)
        assert scan.angle_max == pytest.approx((m.amax - m.afrt) * step)
        assert scan.angle_increment == pytest.approx(step)
        beams = round((scan.angle_max - scan.angle_min) / scan.angle_increment) + 1
        assert len(scan.ranges) == beams == m.steps
        assert scan.range_min == pytest.approx(m.dmin / 1000) and scan.range_max == m.dmax / 1000
        assert scan.scan_time == pytest.approx(m.scan_period_s)
        assert scan.time_increment == pytest.approx(m.scan_period_s / m.ares)
        assert scan.header.frame_id == "laser" and scan.ranges.dtype == np.float32
        want = expected_ranges(scan)
        want[want > m.dmax / 1000] = np.inf
        np.testing.assert_allclose(scan.ranges, want, atol=1e-6)
        # CCW: +90 deg (left) sees the wall 3 m away, straight ahead 4 m
        ahead = int(round(-scan.angle_min / scan.angle_increment))
        assert scan.ranges[ahead] == pytest.approx(4.0)
        # the stamp is the first beam's time: before arrival by at least the sweep
        assert scan.header.stamp.to_ns() < wall_ns()
        assert driver.stats.checksum_errors == 0 and driver.stats.reconnects == 0
        assert list(fake.received)[:5] == ["QT", "RS", "VV", "PP", "II"]

    drive(params_for(fake), scenario)


def test_crop_cluster_skip_and_intensities(device_thread, tmp_path):
    fake = start_fake(device_thread, "ust-20lx", tmp_path, tcp=True)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        scan = scans[-1]
        req = driver.request
        assert req is not None and req.name == "ME" and req.cluster == 4 and req.interval == 1
        assert (req.start, req.end) == (540 - 360, 540 + 360)  # +-90 deg at 0.25 deg a step
        assert scan.angle_min == pytest.approx(-math.pi / 2)
        assert scan.angle_increment == pytest.approx(4 * 2 * math.pi / 1440)
        assert len(scan.ranges) == req.values == 181
        assert scan.angle_max == pytest.approx(scan.angle_min + 180 * scan.angle_increment)
        assert len(scan.intensities) == 181 and (scan.intensities > 0).all()
        assert scan.scan_time == pytest.approx(0.05)  # every second scan
        # a cluster reports the nearest of its 4 steps
        steps = scan.angle_min + np.arange(181 * 4) * (2 * math.pi / 1440)
        nearest = (np.rint(ROOM.ranges(steps) * 1000) / 1000).reshape(181, 4).min(axis=1)
        np.testing.assert_allclose(scan.ranges[:180], nearest[:180], atol=1e-6)

    drive(params_for(fake, angle_min=-math.pi / 2, angle_max=math.pi / 2, cluster=4, skip=1,
                     intensities=True, frame_id="base_laser"), scenario)


def test_garbage_bad_checksums_and_split_writes_over_a_pty(device_thread, tmp_path):
    fake = start_fake(device_thread, "urg-04lx", tmp_path, tcp=False)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        fake.corrupt_next_checksum()
        await async_wait_for(lambda: driver.stats.checksum_errors >= 1, 15)
        fake.inject_garbage(500)
        await async_wait_for(lambda: driver.stats.resyncs >= 1, 15)
        fake.split_writes(True)
        await more_scans(scans, 5)
        fake.split_writes(False)
        np.testing.assert_allclose(scans[-1].ranges, expected_ranges(scans[-1]), atol=1e-6)
        assert driver.stats.reconnects == 0

    drive(params_for(fake), scenario)


def test_unplug_and_replug_reconnects(device_thread, tmp_path):
    fake = start_fake(device_thread, "urg-04lx", tmp_path, tcp=False)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        fake.unplug()
        await async_wait_for(lambda: not driver.connected, 15)
        assert driver.stats.device_errors >= 1 and driver.last_error
        fake.replug()
        await async_wait_for(lambda: driver.connected, 15)
        await more_scans(scans, 3)
        assert driver.stats.reconnects >= 1

    drive(params_for(fake), scenario)


@pytest.mark.parametrize("fault", ["unplug", "hardware-fault"])
def test_last_error_clears_once_a_new_session_streams(device_thread, tmp_path, fault):
    """The error that ended a session stands until a reconnected session publishes a scan; a
    healthy device then shows no error (the daemon's status reports it)."""
    fake = start_fake(device_thread, "urg-04lx" if fault == "unplug" else "ust-10lx", tmp_path,
                      tcp=fault != "unplug")

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        assert driver.last_error is None
        if fault == "unplug":
            fake.unplug()
            await async_wait_for(lambda: not driver.connected and driver.last_error, 15)
            error = driver.last_error
            fake.replug()
        else:
            fake.fail_next_frame("55")
            await async_wait_for(lambda: "hardware fault" in (driver.last_error or ""), 15)
            error = driver.last_error
        await async_wait_for(lambda: driver.stats.reconnects >= 1, 15)
        published = driver.stats.scans
        await async_wait_for(lambda: driver.stats.scans > published and driver.connected, 15)
        assert driver.last_error is None, error

    drive(params_for(fake), scenario)


def test_dropped_tcp_connection_reconnects(device_thread, tmp_path):
    fake = start_fake(device_thread, "ust-10lx", tmp_path, tcp=True)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        fake.drop_connection()
        await async_wait_for(lambda: driver.stats.reconnects >= 1, 15)
        await more_scans(scans, 3)
        assert "closed" in (driver.last_error or "") or driver.stats.device_errors >= 1

    drive(params_for(fake), scenario)


@pytest.mark.parametrize(("field", "value"), [("scan_rpm", 0), ("ares", 0), ("amin", 2000)])
def test_a_pp_reply_that_describes_no_sensor_is_a_device_error_without_a_traceback(
        device_thread, tmp_path, caplog, field, value):
    """A damaged or hostile PP (no motor speed, no steps, AMIN past AMAX) is said in one line and
    retried; it once raised ZeroDivisionError or blamed lidar.angle_min, with a traceback each time."""
    import dataclasses
    import logging

    fake = FakeHokuyo("ust-10lx", ROOM, tcp=("127.0.0.1", 0), seed=7)
    fake.model = dataclasses.replace(fake.model, **{field: value})
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await async_wait_for(lambda: driver.stats.reconnects >= 2, 15)
        assert "PP reply describes no sensor" in (driver.last_error or ""), driver.last_error
        assert not scans

    with caplog.at_level(logging.DEBUG):
        drive(params_for(fake), scenario)
    assert not [r for r in caplog.records if r.exc_info], [r.getMessage() for r in caplog.records]


def test_silent_device_is_detected_and_recovered(device_thread, tmp_path):
    fake = start_fake(device_thread, "ust-10lx", tmp_path, tcp=True)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        fake.mute(True)
        await async_wait_for(lambda: driver.stats.reconnects >= 1, 15)
        assert "no scan" in (driver.last_error or "")
        fake.mute(False)
        await more_scans(scans, 3)

    drive(params_for(fake, stale_timeout_s=0.3), scenario)


@pytest.mark.parametrize("length", ["half", "100 too many"])
def test_scans_of_the_wrong_length_are_named_once_in_the_reconnect_warning(device_thread, tmp_path, caplog,
                                                                           length):
    """A device streaming scans of the wrong length is reconnected for want of scans; the warning
    said only "no scan for 0.30 s" (the reason went to DEBUG, and the codec had dropped it), and
    its repeats were silent. It now names the malformed replies and why, once while it repeats."""
    import logging

    fake = start_fake(device_thread, "ust-10lx", tmp_path, tcp=True)
    asked: list[int] = []

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        assert driver.request is not None
        n = driver.request.values
        asked.append(n)
        fake.wrong_length(n // 2 - n if length == "half" else 100)
        await async_wait_for(lambda: driver.stats.reconnects >= 3 and driver.last_error, 30)
        assert "replies were malformed" in (driver.last_error or "")

    with caplog.at_level(logging.WARNING):
        drive(params_for(fake, stale_timeout_s=0.3), scenario)
    n = asked[0]
    why = f"{n // 2 if length == 'half' else n + 100} readings, expected {n}"
    lost = [r.getMessage() for r in caplog.records if "reconnecting" in r.getMessage()]
    named = [line for line in lost if why in line and "replies were malformed" in line]
    assert len(named) == 1, lost  # three losses or more, one line


def test_a_loss_after_the_device_worked_again_is_logged_again(device_thread, tmp_path, caplog):
    """Repeats of one cause are logged once while the device does not recover; once it published
    scans again, the next loss is news whatever its cause (a second dropout a minute after the first
    went unlogged when the once-a-minute rule outlived the recovery)."""
    import logging

    fake = start_fake(device_thread, "ust-10lx", tmp_path, tcp=True)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        for k in range(2):
            fake.mute(True)
            await async_wait_for(lambda k=k: driver.stats.reconnects >= k + 1
                                 and "no scan" in (driver.last_error or ""), 15)
            fake.mute(False)
            await more_scans(scans, len(scans) + 5)  # working again
            assert driver.last_error is None, driver.last_error

    with caplog.at_level(logging.WARNING):
        drive(params_for(fake, stale_timeout_s=0.3), scenario)
    lost = [r.getMessage() for r in caplog.records if "reconnecting" in r.getMessage()]
    assert len(lost) >= 2, lost


def test_hardware_fault_status_is_surfaced_with_its_meaning(device_thread, tmp_path):
    fake = start_fake(device_thread, "ust-10lx", tmp_path, tcp=True)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        fake.fail_next_frame("55")
        await async_wait_for(lambda: "hardware fault" in (driver.last_error or ""), 15)
        assert "status 55" in (driver.last_error or "")
        await more_scans(scans, 3)  # the session restarts and streams again
        assert driver.stats.reconnects >= 1

    drive(params_for(fake), scenario)


def test_two_frames_in_one_read_each_keep_their_own_stamp(device_thread, tmp_path):
    # a loaded host reads late and gets two frames in one read: the earlier one must not be
    # stamped as the later one (it was complete a scan period before the read)
    fake = start_fake(device_thread, "ust-10lx", tmp_path, tcp=True)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        arrivals: list[tuple[int, int]] = []  # (stamp, monotonic ns of the read that completed it)
        driver.bus.subscribe(driver.params.topic,
                             lambda s: arrivals.append((s.header.stamp.to_ns(), driver.frame_arrival_ns)))
        await more_scans(scans, 2)
        fake.bunch_next_frames(2)
        await async_wait_for(lambda: fake._bunch == 0, 15)
        await more_scans(scans, 2)
        pairs = [i for i in range(len(arrivals) - 1) if arrivals[i][1] == arrivals[i + 1][1]]
        assert pairs, "no two frames came in one read"
        stamps = [stamp for stamp, _ in arrivals]
        assert all(a < b for a, b in zip(stamps[:-1], stamps[1:], strict=True)), np.diff(stamps)
        period_ns = fake.model.scan_period_s * 1e9
        for i in pairs:
            assert stamps[i + 1] - stamps[i] == pytest.approx(period_ns, abs=2e6)

    drive(params_for(fake), scenario)


def test_frames_of_one_read_are_stamped_back_from_the_last_by_the_device_clock():
    from lidar_drivers.scip import ResponseDecoder
    from lidar_drivers.scip_driver import frame_stamps

    req = ScanCommand(name="MD", start=0, end=1080)

    d = ResponseDecoder()
    for ts in (0xFFFFF0, 9, 34):  # the 24-bit device clock wraps between the first two
        d.receive_data(encode_scan(req.echo(0), "99", ts, np.full(1081, 1000)))
    frames = [d.next_event() for _ in range(3)]
    assert frame_stamps(frames, 10**9, 0.025) == [10**9 - 50_000_000, 10**9 - 25_000_000, 10**9]
    # a device-clock gap that is not plausible: the frames are a scan period apart
    assert frame_stamps(frames[::-1][1:], 10**9, 0.025) == [10**9 - 25_000_000, 10**9]


def test_error_codes_become_inf_or_nan():
    dev = SensorParams("UTM-30LX", 23, 60000, 1440, 0, 1080, 540, 2400)
    r = ranges_m(dev, np.array([0, 1, 2, 3, 22, 23, 1234, 60000, 65533]))
    assert np.isinf(r[0]) and np.isinf(r[1])
    assert np.isnan(r[2:5]).all()
    assert r[5] == pytest.approx(0.023) and r[6] == pytest.approx(1.234) and r[7] == 60.0
    assert r.dtype == np.float32
    assert np.isinf(r[8])


def test_crop_steps_clamps_to_the_device_and_refuses_an_empty_crop():
    dev = SensorParams("URG-04LX", 20, 5600, 1024, 44, 725, 384, 600)
    assert crop_steps(dev, None, None) == (44, 725)
    assert crop_steps(dev, -10.0, 10.0) == (44, 725)
    assert crop_steps(dev, 0.0, 0.0) == (384, 384)
    with pytest.raises(ConfigError):
        crop_steps(dev, 1.0, -1.0)


def test_stamp_subtracts_sweep_and_serial_transfer_time():
    driver = HokuyoDriver(Bus(), LidarParams(model="urg-04lx", port="/dev/null"))
    dev = SensorParams("URG-04LX", 20, 5600, 1024, 44, 725, 384, 600)
    req = ScanCommand(name="MD", start=44, end=725)
    from lidar_drivers.scip import ResponseDecoder

    d = ResponseDecoder()
    d.receive_data(encode_scan(req.echo(0), "99", 0, np.full(682, 1000)))
    frame = d.next_event()
    driver._rx_wall_ns = 10_000_000_000
    over_tcp = driver.to_laser_scan(frame, dev)
    sweep = (725 - 44) * 0.1 / 1024
    assert over_tcp.header.stamp.to_ns() == pytest.approx(10e9 - sweep * 1e9, abs=1)
    driver._link = driver._make_link()  # a serial link (not opened): transfer time counts
    over_serial = driver.to_laser_scan(frame, dev)
    transfer = frame.nbytes * 10 / 115200
    assert over_serial.header.stamp.to_ns() == pytest.approx(10e9 - (sweep + transfer) * 1e9, abs=1)


def test_registry_picks_the_family_and_default_bauds():
    assert isinstance(make_driver(Bus(), LidarParams(model="utm-30lx")), HokuyoDriver)
    assert isinstance(make_fake("UST-10LX", ROOM, tcp=("127.0.0.1", 0)), FakeHokuyo)
    assert DEFAULT_BAUD["a1"] == 115200 and DEFAULT_BAUD["a2m8"] == 115200
    assert DEFAULT_BAUD["a3"] == DEFAULT_BAUD["s1"] == DEFAULT_BAUD["a2m12"] == 256000
    assert DEFAULT_BAUD["c1"] == 460800 and DEFAULT_BAUD["urg-04lx"] == 115200
    with pytest.raises(ConfigError):
        make_fake("a1", ROOM, tcp=("127.0.0.1", 0))


def test_every_reading_becomes_its_metres_or_the_error_policy():
    dev = SensorParams("UST-10LX", 20, 30000, 1440, 0, 1080, 540, 2400)
    readings = np.arange(1 << 18)  # every reading of 3 SCIP characters
    for dtype in (np.uint32, np.int64, np.float64):
        r = ranges_m(dev, readings.astype(dtype))
        assert r.dtype == np.float32
        valid = slice(20, 30001)
        assert np.array_equal(r[valid], (readings[valid] / 1000.0).astype(np.float32))
        assert np.isinf(r[:2]).all() and np.isnan(r[2:20]).all() and np.isinf(r[30001:]).all()
    assert np.array_equal(ranges_m(dev, np.array([-3, 1 << 20])), [np.inf, np.inf])


def test_urg04lx_refuses_me_and_the_driver_falls_back_to_md(device_thread, tmp_path, caplog):
    fake = start_fake(device_thread, "urg-04lx", tmp_path, tcp=False)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        await more_scans(scans, 2)
        assert driver.request is not None and driver.request.name == "MD"
        assert len(scans[-1].intensities) == 0
        np.testing.assert_allclose(scans[-1].ranges, expected_ranges(scans[-1]), atol=1e-6)
        sent = list(fake.received)
        assert sent.index("ME0044072501000") < sent.index("MD0044072501000")

    drive(params_for(fake, intensities=True), scenario)
    assert any("ME refused" in r.getMessage() and "unknown command" in r.getMessage()
               for r in caplog.records)


def test_classic_urg04lx_in_scip11_is_switched_to_scip20(device_thread, tmp_path):
    fake = FakeHokuyo("urg-04lx", ROOM, link=str(tmp_path / "urg"), scip1=True)
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)

    async def scenario(driver: HokuyoDriver, scans: list[LaserScan]) -> None:
        started = time.monotonic()
        await more_scans(scans, 2)
        # the SCIP 1.1 answer is recognised at once, not after the 2 s QT timeout
        assert time.monotonic() - started < 1.9
        assert list(fake.received)[:4] == ["QT", "SCIP2.0", "QT", "RS"]
        assert not fake.scip1 and driver.info["protocol"] == "SCIP 2.0"
        np.testing.assert_allclose(scans[-1].ranges, expected_ranges(scans[-1]), atol=1e-6)

    drive(params_for(fake), scenario)


def test_default_links_follow_the_model():
    usb = ("urg-04lx", "utm-30lx")
    for model in ("urg-04lx", "ust-10lx", "ust-20lx", "utm-30lx", "utm-30lx-ew"):
        link = make_driver(Bus(), LidarParams(model=model))._make_link()  # type: ignore[attr-defined]
        if model in usb:
            assert isinstance(link, SerialLink) and link.name.startswith("/dev/ttyACM0")
        else:
            assert isinstance(link, TcpLink) and "192.168.0.10:10940" in link.name
