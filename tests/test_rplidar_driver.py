"""RplidarDriver against FakeRplidar: sessions, conventions, faults, reconnects.

Most run in lockstep (:mod:`racecar_hw.runtime.lockstep`): the driver and the fake in one loop on
virtual time behind an in-memory link, as fast as the machine allows, so the scans are exactly a
revolution (0.1 s) apart. What is about the serial line itself (DTR on a pty, an unplugged pty's
reconnect) runs over a real pty in real time (``realtime=True``).
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import replace

import numpy as np
import pytest
from conftest import async_wait_for, wait_for

from lidar_drivers.base import RoomRangeSource, beam_count
from lidar_drivers.params import LidarParams
from lidar_drivers.rplidar_codec import (
    AnswerType,
    Command,
    ConfKey,
    LidarConf,
    Request,
    RplidarClient,
    SampleRate,
    ScanMode,
)
from lidar_drivers.rplidar_driver import RplidarDriver
from lidar_drivers.rplidar_fake import FakeRplidar
from lidar_drivers.rplidar_models import MODELS
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.link import SerialLink
from racecar_hw.base.messages import LaserScan
from racecar_hw.runtime import lockstep

ROOM = RoomRangeSource(8.0, 6.0, x=2.5, y=1.5, yaw=0.3)  # off-centre and turned: no symmetry


def run_driver(device_thread, tmp_path, model: str,
               scenario: Callable[[RplidarDriver, FakeRplidar, list[LaserScan]], Awaitable[None]],
               firmware: tuple[int, int] | None = None,
               device: Callable[[FakeRplidar], None] | None = None, realtime: bool = False,
               **params: object) -> None:
    """Run ``scenario`` against a driver streaming from a fake; what the scenario does before its
    first ``await`` happens before the driver's first step (set faults there). ``device`` changes
    the fake before it serves (a device that behaves unlike its model). In lockstep unless
    ``realtime``: then the fake serves a pty from ``device_thread``."""
    link = str(tmp_path / "rplidar") if realtime else f"mem://{tmp_path.name}/rplidar"
    fake = FakeRplidar(model, ROOM, link, firmware=firmware)
    if device is not None:
        device(fake)
    if realtime:
        device_thread.spawn(fake.serve())
        wait_for(lambda: fake.port.plugged)

    async def main() -> None:
        # in lockstep the fake first in the loop's queue: plugged in before the driver looks (the
        # task is held here: the loop keeps only a weak reference to it)
        serving = None if realtime else asyncio.ensure_future(fake.serve())
        if serving is not None:
            await asyncio.sleep(0)
            assert fake.port.plugged
        bus = Bus()
        scans: list[LaserScan] = []
        bus.subscribe("/scan", scans.append)
        driver = RplidarDriver(bus, LidarParams(model=model, port=fake.link, **params))
        task = asyncio.create_task(driver.run())
        try:
            await scenario(driver, fake, scans)
        finally:
            task.cancel()
            done, _ = await asyncio.wait({task}, timeout=10)
            assert done and task.cancelled()
            if serving is not None:
                serving.cancel()

    if realtime:
        asyncio.run(main())
    else:
        lockstep.run(main())


#: Range slack per answer type: standard nodes carry 1/4 mm, express and dense capsules 1 mm;
#: ultra capsules 2-8 mm steps in a room this size, and a 10-bit prediction for two of three.
TOLERANCE = {AnswerType.SCAN: 0.003, AnswerType.EXPRESS: 0.003, AnswerType.DENSE_CAPSULED: 0.003,
             AnswerType.ULTRA_CAPSULED: 0.009}


def assert_room(scan: LaserScan, tol: float = 0.003, empty: float = 0.0) -> None:
    """Every beam's range is what the room shows within half a beam of the beam's ROS angle.

    The slack covers the wire's quantisation: 1/64 degree angles (capsule sample angles are
    interpolated and truncated like the SDK's) and the distance resolution (:data:`TOLERANCE`).
    At most the fraction ``empty`` of the beams may have got no sample (nan).
    """
    got = np.isfinite(scan.ranges)
    assert np.count_nonzero(~got) <= empty * len(got)
    assert not np.any(np.isinf(scan.ranges))
    half = scan.angle_increment / 2 + math.radians(0.05)
    window = scan.angles()[:, None] + np.linspace(-half, half, 9)[None, :]
    truth = ROOM.ranges(window.ravel()).reshape(window.shape)
    lo, hi = truth.min(axis=1) - tol, truth.max(axis=1) + tol
    assert np.all((scan.ranges[got] >= lo[got]) & (scan.ranges[got] <= hi[got]))


def assert_conventions(scan: LaserScan, model: str) -> None:
    spec = MODELS[model]
    assert scan.header.frame_id == "laser"
    assert scan.angle_increment > 0
    assert len(scan.ranges) == beam_count(scan.angle_min, scan.angle_max, scan.angle_increment)
    assert scan.angle_min == pytest.approx(-math.pi)
    assert scan.angle_max == pytest.approx(math.pi - scan.angle_increment)
    # beams sweep from high to low index: negative time increment spanning one revolution
    assert scan.time_increment < 0
    assert -scan.time_increment * len(scan.ranges) == pytest.approx(scan.scan_time)
    assert scan.scan_time == pytest.approx(0.1, rel=0.05)
    assert (scan.range_min, scan.range_max) == (spec.range_min, spec.range_max)
    assert len(scan.ranges) % 2 == 0
    assert scan.ranges.dtype == np.float32


def check_mode_scans(driver: RplidarDriver, fake: FakeRplidar, scans: list[LaserScan], model: str,
                     mode: str) -> None:
    """The scans of ``mode`` show the room with the model's conventions and the mode's density."""
    assert fake.mode is not None and fake.mode.name == mode  # what the device streams
    for scan in scans:
        assert_conventions(scan, model)
        # ultra samples' angles carry a distance-dependent correction in steps (the SDK's), so
        # their spacing is uneven and the odd beam may get no sample
        ultra = fake.mode.answer_type == AnswerType.ULTRA_CAPSULED
        assert_room(scan, TOLERANCE[fake.mode.answer_type], empty=0.005 if ultra else 0.0)
    stamps = [s.header.stamp.to_ns() for s in scans]
    # a revolution (0.1 s) apart, to the sample packet a scan ends in (in lockstep no hold-up of
    # the machine stretches it)
    assert all(b - a == pytest.approx(1e8, rel=0.1) for a, b in zip(stamps[:-1], stamps[1:], strict=True))
    assert driver.info["model"] == MODELS[model].name
    assert driver.info["firmware"] == fake.info.firmware
    assert driver.info["scan_mode"] == mode
    used = driver.scan_mode
    assert used is not None and (used.id, used.name, used.us_per_sample, used.answer_type) == (
        fake.mode.id, fake.mode.name, fake.mode.us_per_sample, fake.mode.answer_type)
    assert driver.geometry is not None and driver.geometry.beams == len(scans[-1].ranges)
    samples_per_rev = fake.samples_per_rev(fake.mode)
    assert 0.9 * samples_per_rev < len(scans[-1].ranges) < samples_per_rev
    assert driver.stats.scans == len(scans)
    assert fake.scans_sent >= len(scans)


#: Every model at its own firmware, and the A1 at firmware 1.24 and 1.27 (its older tables).
FIRMWARE_TABLES = [(model, None) for model in MODELS] + [("a1", (1, 24)), ("a1", (1, 27))]


@pytest.mark.parametrize(("model", "firmware", "mode"), [
    (model, firmware, m.name) for model, firmware in FIRMWARE_TABLES
    for m in MODELS[model].for_firmware(firmware or MODELS[model].firmware).modes])
def test_every_scan_mode_of_every_model(device_thread, tmp_path, model, firmware, mode):
    """Firmware with the configuration commands: the driver reads the mode table and starts the
    mode named in the config."""
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        check_mode_scans(driver, fake, scans, model, mode)
        assert [m.name for m in driver.scan_modes] == [m.name for m in fake.spec.modes]
        assert driver.scan_modes == list(fake.spec.modes)  # ids, periods, ranges, answer types
        assert Command.GET_LIDAR_CONF in [r.command for r in fake.requests]

    run_driver(device_thread, tmp_path, model, scenario, firmware=firmware, scan_mode=mode.lower())


@pytest.mark.parametrize(("model", "mode"), [(model, name) for model in ("a1", "a2m8", "a2m7", "a2m12", "a3")
                                              for name in ("Standard", "Express")])
def test_firmware_without_configuration_commands(device_thread, tmp_path, model, mode):
    """Firmware 1.20: no GET_LIDAR_CONF; Standard and Express timed by GET_SAMPLERATE."""
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        check_mode_scans(driver, fake, scans, model, mode)
        cmds = [r.command for r in fake.requests]
        assert Command.GET_LIDAR_CONF not in cmds and Command.GET_SAMPLERATE in cmds
        assert [m.name for m in driver.scan_modes] == ["Standard", "Express"]

    run_driver(device_thread, tmp_path, model, scenario, firmware=(1, 20), scan_mode=mode)


@pytest.mark.parametrize(("model", "firmware", "typical"), [
    ("a1", None, "Sensitivity"), ("a1", (1, 27), "Standard"), ("a3", None, "Sensitivity"),
    ("s1", None, "DenseBoost"), ("c1", (1, 20), "DenseBoost"), ("a2m8", (1, 20), "Express")])
def test_default_is_the_typical_mode(device_thread, tmp_path, model, firmware, typical):
    """An A1 names Sensitivity with firmware 1.29 and Standard with 1.27, as public records of
    real units show; C/S series have the configuration commands whatever the firmware number; an
    old A-series firmware's typical mode is Express, as the SDK has it."""
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        check_mode_scans(driver, fake, scans, model, typical)
        assert f"{typical}*" in driver.info["scan_modes"]

    run_driver(device_thread, tmp_path, model, scenario, firmware=firmware)


def test_the_scan_modes_are_logged_once_at_connect(device_thread, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="lidar_drivers.rplidar_driver")

    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 1, 15)
        fake.unplug()
        await async_wait_for(lambda: driver.stats.device_errors >= 1, 15)
        fake.replug()
        n = len(scans)
        await async_wait_for(lambda: len(scans) > n, 15)

    run_driver(device_thread, tmp_path, "a1", scenario, realtime=True)  # a pty's unplug and replug
    lines = [r.getMessage() for r in caplog.records if "scan modes:" in r.getMessage()]
    assert lines == [  # once: the reconnect found the same table
        f"rplidar {tmp_path / 'rplidar'}: scan modes: "
        "Standard (id 0): 2.3 k samples/s, 12 m, standard nodes (0x81); "
        "Express (id 1): 4.0 k samples/s, 12 m, express capsules (0x82); "
        "Boost (id 2): 7.9 k samples/s, 12 m, ultra capsules (0x84); "
        "Sensitivity (id 3): 7.9 k samples/s, 12 m, ultra capsules (0x84); "
        "Stability (id 4): 5.0 k samples/s, 12 m, ultra capsules (0x84); typical: Sensitivity"]


def test_a_mode_the_device_lacks_is_refused_naming_its_modes(device_thread, tmp_path):
    """An A1 with firmware 1.24 has no Sensitivity mode (the users' logs in robopeak/rplidar_ros
    #68 and Slamtec/sllidar_ros2 #42, where the launch file asked for it)."""
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: driver.last_error is not None, 15)
        assert "'Sensitivity' is not a scan mode of this A1M8" in driver.last_error
        assert "Standard (id 0): 2.0 k samples/s, 12 m" in driver.last_error
        assert "Boost (id 2): 8.0 k samples/s, 12 m, ultra capsules (0x84)" in driver.last_error
        assert "Stability" not in driver.last_error
        assert not scans and fake.scanning is None
        assert Command.EXPRESS_SCAN not in [r.command for r in fake.requests]

    run_driver(device_thread, tmp_path, "a1", scenario, firmware=(1, 24), scan_mode="Sensitivity")


@pytest.mark.parametrize("answer_type", [AnswerType.HQ, AnswerType.ULTRA_DENSE_CAPSULED])
def test_a_mode_in_a_format_we_do_not_decode_is_refused(device_thread, tmp_path, answer_type):
    """A device listing a mode whose answer type racecar-hw does not decode (HQ 0x83, ultra-dense
    0x86): choosing it fails the session with a clear error; the scan is never started."""
    extra = ScanMode(5, "Future", 50.0, 25.0, answer_type)

    def device(fake: FakeRplidar) -> None:
        fake.spec = replace(fake.spec, modes=fake.spec.modes + (extra,))

    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: driver.last_error is not None, 15)
        assert (f"scan mode Future sends {extra.answer_name} (0x{answer_type:02x}), which "
                "racecar-hw does not decode; set lidar.scan_mode to another of: ") in driver.last_error
        assert "Sensitivity (id 3)" in driver.last_error
        assert not scans and not driver.connected
        cmds = [r.command for r in fake.requests]
        assert Command.SCAN not in cmds and Command.EXPRESS_SCAN not in cmds

    run_driver(device_thread, tmp_path, "a3", scenario, device=device, scan_mode="future")


def test_no_conf_answer_falls_back_to_the_legacy_commands(device_thread, tmp_path, caplog):
    """A unit that should have GET_LIDAR_CONF (firmware 1.29) but does not answer it: after the
    request times out the driver logs it and uses GET_SAMPLERATE and legacy express capsules."""
    caplog.set_level(logging.WARNING, logger="lidar_drivers.rplidar_driver")

    def device(fake: FakeRplidar) -> None:
        fake.conf_commands = False

    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        check_mode_scans(driver, fake, scans, "a1", "Express")
        cmds = [r.command for r in fake.requests]
        assert cmds.count(Command.GET_LIDAR_CONF) == 1  # the mode count, unanswered
        assert cmds.index(Command.GET_LIDAR_CONF) < cmds.index(Command.GET_SAMPLERATE)
        scan_requests = [r for r in fake.requests if r.command == Command.EXPRESS_SCAN]
        assert [r.payload[0] for r in scan_requests] == [0]  # legacy working mode
        assert [m.name for m in driver.scan_modes] == ["Standard", "Express"]
        assert driver.sample_rate == SampleRate(435, 250)
        assert driver.info["firmware"] == "1.29"

    run_driver(device_thread, tmp_path, "a1", scenario, device=device)
    assert sum("no GET_LIDAR_CONF answer" in r.getMessage() for r in caplog.records) == 1


def test_front_left_is_positive_angle(device_thread, tmp_path):
    """The wall 1.5 m to the right (y=0) and 4.5 m to the left: CW device data became CCW."""
    room = RoomRangeSource(8.0, 6.0, x=4.0, y=1.5, yaw=0.0)

    async def scenario(driver, fake, scans):
        fake.range_source = room
        await async_wait_for(lambda: len(scans) >= 4, 15)
        scan = scans[-1]
        left = scan.ranges[np.argmin(np.abs(scan.angles() - math.pi / 2))]
        right = scan.ranges[np.argmin(np.abs(scan.angles() + math.pi / 2))]
        ahead = scan.ranges[len(scan.ranges) // 2]
        assert scan.angles()[len(scan.ranges) // 2] == pytest.approx(0.0, abs=1e-9)
        assert (left, right, ahead) == pytest.approx((4.5, 1.5, 4.0), abs=0.02)

    run_driver(device_thread, tmp_path, "a1", scenario)


def test_session_requests_and_motor_control(device_thread, tmp_path, caplog):
    caplog.set_level(logging.WARNING)

    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 1, 15)
        cmds = [r.command for r in fake.requests]
        assert cmds[:4] == [Command.STOP, Command.GET_INFO, Command.GET_HEALTH, Command.GET_LIDAR_CONF]
        assert Command.GET_ACC_BOARD_FLAG in cmds
        assert cmds.index(Command.SET_MOTOR_PWM) < cmds.index(Command.EXPRESS_SCAN)
        assert fake.motor_pwm == 700
        assert driver.info["motor"] == "pwm 700"
        assert driver.baudrate == 256000
        assert driver.health is not None and driver.health.status == 0
        assert driver.sample_rate is None  # the mode table times the samples
        assert driver.scan_mode is not None and driver.scan_mode.us_per_sample == 63

    run_driver(device_thread, tmp_path, "a2m7", scenario, motor_pwm=700)


def test_s_series_motor_gets_the_speed_it_asks_for(device_thread, tmp_path):
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 1, 15)
        assert fake.motor_rpm == MODELS["s1"].desired_rpm == 600
        assert driver.info["motor"] == "rpm 600"
        cmds = [r.command for r in fake.requests]
        assert cmds.index(Command.SET_MOTOR_RPM) < cmds.index(Command.EXPRESS_SCAN)

    run_driver(device_thread, tmp_path, "s1", scenario)


async def _raw_answers(link: SerialLink, requests: list[Request], size: int) -> bytes:
    """Send ``requests`` and return the first ``size`` bytes the device answers."""
    for request in requests:
        link.write(request.encode())
    data = b""
    while len(data) < size:
        data += await link.read_within(10.0)
    return data


@pytest.mark.parametrize("model", ["s1", "a1", "a3", "c1"])
def test_motor_speed_range_as_the_sdks_get_motor_info_asks_it(device_thread, tmp_path, model):
    """GET_LIDAR_CONF MIN_ROT_FREQ / MAX_ROT_FREQ (0x04 / 0x05, u16 rpm), the SDK's getMotorInfo:
    the S1 answers them; models without a public record of them answer nothing, as unknown keys
    (the next request's answer comes first)."""
    fake = FakeRplidar(model, ROOM, str(tmp_path / "rplidar"))
    device_thread.spawn(fake.serve())
    wait_for(lambda: fake.port.plugged)
    info = Request.simple(Command.GET_INFO)

    async def main() -> None:
        link = SerialLink(fake.link, fake.spec.baudrate)
        await link.open()
        try:
            if fake.spec.rot_freq_range is None:
                data = await _raw_answers(link, [Request.get_lidar_conf(ConfKey.MIN_ROT_FREQ),
                                                 Request.get_lidar_conf(ConfKey.MAX_ROT_FREQ), info],
                                          7 + 20)
                assert data[:7] == bytes.fromhex("a55a1400000004")  # GET_INFO's, nothing before
                return
            client = RplidarClient()
            got = []
            for key in (ConfKey.MIN_ROT_FREQ, ConfKey.MAX_ROT_FREQ):
                link.write(client.send(Request.get_lidar_conf(key)))
                while (ev := client.next_event()) is None:
                    client.receive_data(await link.read_within(10.0))
                assert isinstance(ev, LidarConf) and ev.key == key
                got.append(ev.number(2))
            assert tuple(got) == fake.spec.rot_freq_range == (300, 900)
            assert got[0] <= fake.spec.desired_rpm <= got[1]
        finally:
            link.close()

    asyncio.run(main())


def test_a1_dtr_refused_by_the_pty_is_not_fatal(device_thread, tmp_path, caplog):
    caplog.set_level(logging.WARNING)

    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        assert driver.info["motor"] == "dtr"
        assert driver.baudrate == 115200

    run_driver(device_thread, tmp_path, "a1", scenario, realtime=True)  # DTR on a real pty
    assert sum("cannot set DTR" in r.getMessage() for r in caplog.records) == 1


def test_c1_motor_runs_by_itself_and_dtr_is_no_warning(device_thread, tmp_path, caplog):
    """As the SDK: the C1 is asked its accessory board flag (no PWM) and DTR is cleared; the C1
    ignores DTR, so a port without modem lines is normal and not warned about."""
    caplog.set_level(logging.DEBUG, logger="lidar_drivers.rplidar_driver")

    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        assert driver.info["motor"] == "self-driven"
        cmds = [r.command for r in fake.requests]
        assert Command.GET_ACC_BOARD_FLAG in cmds
        assert Command.SET_MOTOR_PWM not in cmds and Command.SET_MOTOR_RPM not in cmds

    run_driver(device_thread, tmp_path, "c1", scenario, realtime=True)  # DTR on a real pty
    dtr = [r for r in caplog.records if "cannot set DTR" in r.getMessage()]
    assert dtr and all(r.levelno == logging.DEBUG for r in dtr)


def test_default_baud_rates_and_config_errors():
    bus = Bus()
    expected = {"a1": 115200, "a2m8": 115200, "a2m7": 256000, "a2m12": 256000, "a3": 256000,
                "s1": 256000, "c1": 460800}
    for model, baud in expected.items():
        assert RplidarDriver(bus, LidarParams(model=model, port="/dev/null")).baudrate == baud
    assert RplidarDriver(bus, LidarParams(model="a1", port="/dev/null", baudrate=9600)).baudrate == 9600
    with pytest.raises(ConfigError, match="port"):
        RplidarDriver(bus, LidarParams(model="a1"))


def test_crop_and_intensities(device_thread, tmp_path):
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        scan = scans[-1]
        assert scan.angle_min >= -math.pi / 2 - 1e-6 and scan.angle_max <= math.pi / 2 + 1e-6
        assert scan.angle_min - scan.angle_increment < -math.pi / 2
        assert len(scan.intensities) == len(scan.ranges)
        assert np.all(scan.intensities == 47)
        assert_room(scan)
        # the stamp is beam 0's time: later crops start later in the sweep, so earlier stamps
        assert len(scan.ranges) == beam_count(scan.angle_min, scan.angle_max, scan.angle_increment)

    run_driver(device_thread, tmp_path, "a1", scenario, angle_min=-math.pi / 2, angle_max=math.pi / 2,
               intensities=True, scan_mode="Standard")


def test_out_of_range_is_inf(device_thread, tmp_path):
    big = RoomRangeSource(60.0, 60.0, x=30.0, y=5.0)

    async def scenario(driver, fake, scans):
        fake.range_source = big
        await async_wait_for(lambda: len(scans) >= 3, 15)
        scan = scans[-1]
        half = scan.angle_increment / 2 + math.radians(0.05)
        window = scan.angles()[:, None] + np.linspace(-half, half, 9)[None, :]
        truth = big.ranges(window.ravel()).reshape(window.shape)
        far = (truth > MODELS["a1"].range_max).all(axis=1)
        near = (truth < MODELS["a1"].range_max).all(axis=1)
        assert far.sum() > 10 and near.sum() > 10
        assert np.all(np.isinf(scan.ranges[far]))
        assert np.all(np.isfinite(scan.ranges[near]))
        assert np.all((scan.ranges[near] >= truth[near].min(axis=1) - 0.003)
                      & (scan.ranges[near] <= truth[near].max(axis=1) + 0.003))

    run_driver(device_thread, tmp_path, "a1", scenario, scan_mode="Standard")


def test_a_stream_of_bad_checksums_is_named_once_in_the_reconnect_warning(device_thread, tmp_path, caplog):
    """Every capsule damaged: the driver reconnects for want of scans (after 0.5 s, then 3 s, the
    start-up timeout), and the warning says why (as the Hokuyo driver's does,
    tests/test_scip_driver.py), once while it repeats."""
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        fake.corrupt_checksums(True)
        await async_wait_for(lambda: driver.stats.device_errors >= 3, 30)
        assert "packets were malformed: bad checksum" in (driver.last_error or ""), driver.last_error

    with caplog.at_level(logging.WARNING):
        run_driver(device_thread, tmp_path, "a2m8", scenario, scan_mode="express")
    lost = [r.getMessage() for r in caplog.records if "reconnecting" in r.getMessage()]
    assert len([line for line in lost if "packets were malformed: bad checksum" in line]) == 1, lost


@pytest.mark.parametrize(("model", "mode"), [("a2m8", "standard"), ("a2m8", "express"),
                                              ("a2m8", "sensitivity"), ("c1", "denseboost")])
def test_garbage_bad_checksums_and_split_writes(device_thread, tmp_path, model, mode):
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        fake.split_writes(True)
        n = len(scans)
        await async_wait_for(lambda: len(scans) >= n + 3, 15)
        fake.split_writes(False)
        for _ in range(3):
            fake.inject_garbage(37)
            fake.corrupt_next_checksum()
            await asyncio.sleep(0.15)
        await async_wait_for(lambda: driver.stats.resyncs >= 3 and driver.stats.checksum_errors >= 3, 15)
        n = len(scans)
        await async_wait_for(lambda: len(scans) >= n + 3, 15)
        ultra = fake.mode.answer_type == AnswerType.ULTRA_CAPSULED
        for scan in scans[-2:]:
            assert_conventions(scan, model)
            assert_room(scan, TOLERANCE[fake.mode.answer_type], empty=0.005 if ultra else 0.0)
        assert driver.stats.reconnects == 0

    run_driver(device_thread, tmp_path, model, scenario, scan_mode=mode)


def test_unplug_replug_reconnects_and_streams_again(device_thread, tmp_path):
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        fake.unplug()
        await async_wait_for(lambda: not driver.connected and driver.stats.device_errors >= 1, 15)
        await asyncio.sleep(0.3)
        fake.replug()
        n = len(scans)
        await async_wait_for(lambda: len(scans) >= n + 3, 20)
        assert driver.stats.reconnects >= 1
        assert driver.connected
        assert_room(scans[-1])

    run_driver(device_thread, tmp_path, "a2m8", scenario, scan_mode="express")


def test_health_error_is_reset_and_the_banner_skipped(device_thread, tmp_path):
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 1, 15)
        assert fake.resets == 1
        assert driver.health is not None and driver.health.status == 0
        assert driver.stats.reconnects == 0
        assert_room(scans[-1])

    async def scenario_with_fault(driver, fake, scans):
        fake.set_health(status=2, error_code=0x8001)
        await scenario(driver, fake, scans)

    run_driver(device_thread, tmp_path, "a1", scenario_with_fault, scan_mode="Express")


def test_health_error_that_persists_is_surfaced(device_thread, tmp_path):
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: driver.last_error is not None, 15)
        assert "0x8001" in driver.last_error and "protection stop" in driver.last_error
        assert not scans

    async def with_fault(driver, fake, scans):
        fake.set_health(2, 0x8001, clears_on_reset=False)
        await scenario(driver, fake, scans)

    run_driver(device_thread, tmp_path, "a1", with_fault)


def test_device_reset_mid_stream_banner_then_recovery(device_thread, tmp_path):
    """A device that reboots (banner, scanning stopped) goes stale; the driver reconnects."""
    async def scenario(driver, fake, scans):
        await async_wait_for(lambda: len(scans) >= 2, 15)
        fake.reboot()
        await async_wait_for(lambda: driver.stats.device_errors >= 1, 15)
        assert driver.last_error is not None and "no scan" in driver.last_error
        n = len(scans)
        await async_wait_for(lambda: len(scans) >= n + 2, 15)
        assert_room(scans[-1])
        assert driver.last_error is None  # streaming again: the old error no longer stands

    run_driver(device_thread, tmp_path, "a1", scenario, stale_timeout_s=0.3, scan_mode="Standard")

