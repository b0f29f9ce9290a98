"""Slamtec's own SDK (pyrplidarsdk, wrapping rplidar_sdk) reads our fake RPLIDAR, every model.

The SDK decides from the model and firmware whether the device has the configuration commands,
asks GET_LIDAR_CONF for the typical scan mode and its answer type, sets the motor speed, starts
that mode and decodes its measurement format. With firmware 1.20 an A-series unit has no
configuration commands: the SDK falls back to GET_SAMPLERATE and legacy express capsules. C- and
S-series units always have them, whatever their firmware number. An A1 lists three modes with
firmware 1.24 and four with 1.27 (typical Standard: the SDK sends SCAN), five with 1.29 (typical
Sensitivity).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import wait_for
from rplidar_sdk_peer import sdk_scan

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.params import RPLIDAR_MODELS
from lidar_drivers.rplidar_codec import AnswerType, Command
from lidar_drivers.rplidar_fake import FakeRplidar
from racecar_hw.runtime.devicethread import DeviceThread

ROOM = RoomRangeSource(8.0, 6.0, x=2.5, y=1.5, yaw=0.3)
REVOLUTIONS = 4


#: Every model at its own firmware and at 1.20; the A1 also at 1.24 and 1.27 (its older tables;
#: 1.27's typical mode is Standard, which the SDK starts with SCAN).
CASES = [pytest.param(model, firmware, id=f"{model}-{name}") for model in RPLIDAR_MODELS
         for firmware, name in ((None, "current-firmware"), ((1, 20), "firmware-1.20"))]
CASES[1:1] = [pytest.param("a1", (1, 24), id="a1-firmware-1.24"),
              pytest.param("a1", (1, 27), id="a1-firmware-1.27")]


#: Each case is a fake on a pty of its own and the SDK in a process of its own, and most of a run
#: is waiting (the SDK's own time-outs for commands an old firmware does not answer, the
#: revolutions, its exit): the runs are independent, so this many go at once, all started by the
#: module's first test; each test then checks its own run. The module's tests are one
#: pytest-xdist group (one worker makes the runs, once).
AT_ONCE = 4

pytestmark = pytest.mark.xdist_group("rplidar-sdk")


class SdkRuns:
    """The SDK against a fake for each selected case, :data:`AT_ONCE` at a time."""

    def __init__(self, folder: Path, cases: list[tuple[str, tuple[int, int] | None]]) -> None:
        self.folder = folder
        self.thread = DeviceThread().start()
        self.pool = ThreadPoolExecutor(AT_ONCE)
        self.runs: dict[tuple[str, tuple[int, int] | None], tuple[FakeRplidar, Future]] = {}
        for k, (model, firmware) in enumerate(cases):
            fake = FakeRplidar(model, ROOM, str(folder / f"rplidar{k}"), firmware=firmware)
            self.runs[(model, firmware)] = (fake, self.pool.submit(self._scan, fake))

    def _scan(self, fake: FakeRplidar) -> dict[str, Any]:
        served = self.thread.spawn(fake.serve())
        try:
            wait_for(lambda: fake.port.plugged)
            return sdk_scan(fake.link, fake.spec.baudrate, REVOLUTIONS)
        finally:
            served.cancel()  # what the device saw stays in the fake (its requests) for the test

    def get(self, model: str, firmware: tuple[int, int] | None) -> tuple[FakeRplidar, dict[str, Any]]:
        """The fake of a case and the SDK's report of its run (raised: the run's failure or skip)."""
        fake, future = self.runs[(model, firmware)]
        return fake, future.result()

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.thread.stop()


@pytest.fixture(scope="module")
def sdk_runs(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[SdkRuns]:
    """The runs of this session's cases of this module (those selected, in their order)."""
    cases = [(item.callspec.params["model"], item.callspec.params["firmware"])
             for item in request.session.items
             if item.module is request.module and hasattr(item, "callspec")
             and "model" in item.callspec.params]
    runs = SdkRuns(tmp_path_factory.mktemp("rplidar-sdk"), cases)
    try:
        yield runs
    finally:
        runs.close()


@pytest.mark.parametrize(("model", "firmware"), CASES)
def test_the_sdk_scans_the_fake_in_its_default_mode(model, firmware, sdk_runs):
    fake, report = sdk_runs.get(model, firmware)

    assert report["connected"], report["stderr"]
    info = report["info"]
    assert info["model"] == fake.spec.model_id
    assert info["firmware"] == (fake.info.firmware_major << 8) | fake.info.firmware_minor
    assert info["serial"] == fake.info.serial_hex.lower()
    assert report["health"] == {"status": 0, "error_code": 0}
    assert report["started"], report["stderr"]

    # the SDK asks A2-C units their accessory board flag (PWM or, without it, DTR)
    flag_asked = any(r.command == Command.GET_ACC_BOARD_FLAG for r in fake.requests)
    assert flag_asked == (2 <= fake.spec.model_id >> 4 <= 5)

    # the mode the SDK chose, as the device saw it
    conf_asked = any(r.command == Command.GET_LIDAR_CONF for r in fake.requests)
    if fake.conf_commands:
        mode = fake.spec.mode(fake.spec.typical)
        assert conf_asked
    else:
        mode = fake.spec.mode(1)  # legacy express capsules at the GET_SAMPLERATE rate
        assert any(r.command == Command.GET_SAMPLERATE for r in fake.requests)
    assert mode is not None
    scan_requests = [r for r in fake.requests if r.command == Command.EXPRESS_SCAN]
    if mode.answer_type != AnswerType.SCAN:
        assert scan_requests and scan_requests[-1].payload[0] == (mode.id if fake.conf_commands else 0)
    else:  # a standard-node typical mode: the SDK starts it with SCAN
        assert not scan_requests and any(r.command == Command.SCAN for r in fake.requests)
    per_rev = mode.samples_per_s / fake.scan_hz

    scans = report["scans"]
    assert len(scans) == REVOLUTIONS and all(s is not None for s in scans)
    for angles, ranges, _quality in scans[-3:]:  # full revolutions, as the SDK assembles them
        order = np.argsort(angles)
        angles, ranges = np.asarray(angles)[order], np.asarray(ranges)[order]
        assert abs(len(angles) - per_rev) <= max(2.0, 0.005 * per_rev), (len(angles), per_rev)
        # the whole circle, with no hole wider than a few samples
        gaps = np.diff(np.concatenate([angles, [angles[0] + 2 * math.pi]]))
        assert gaps.max() < 4 * 2 * math.pi / per_rev
        assert angles.min() >= 0 and angles.max() < 2 * math.pi
        # the room, seen along ROS angle -device angle
        expected = ROOM.ranges(np.mod(-angles + math.pi, 2 * math.pi) - math.pi)
        error = np.abs(ranges - expected)
        assert np.percentile(error, 99) < 0.01, np.percentile(error, 99)
        assert np.median(error) < 0.003
