"""The streaming shell every lidar driver shares (``LidarDriver._stream_from``), over a real pty."""

from __future__ import annotations

import asyncio

import pytest

from lidar_drivers.base import LidarDriver
from lidar_drivers.params import LidarParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import DeviceError, DeviceIOError, DeviceTimeout
from racecar_hw.base.link import SerialLink
from racecar_hw.base.messages import LaserScan
from racecar_hw.runtime.fakepty import PtyPort


class LineLidar(LidarDriver):
    """A toy device: every ``scan`` line is a scan, ``fault`` a device fault, ``boom`` breaks us."""

    def __init__(self, link: SerialLink, timeout_s: float) -> None:
        super().__init__(Bus(), LidarParams(model="ust-10lx", port=link.url))
        self.link = link
        self.timeout_s = timeout_s
        self.backlog_seen = False

    def on_bytes(self, data: bytes) -> None:
        for line in data.split():
            if line == b"scan":
                self.publish(LaserScan())
            elif line == b"fault":
                self._end_stream(DeviceError("status 55: hardware fault"))
            elif line == b"boom":
                raise ValueError("a bug in handling a frame")

    async def _session(self) -> None:
        def backlog() -> None:
            self.backlog_seen = True

        await self._stream_from(self.link, self.on_bytes, lambda: self.timeout_s, backlog)


def stream(tmp_path, writes: list[bytes], timeout_s: float = 30.0) -> tuple[BaseException, LineLidar]:
    """Run one stream while ``writes`` go to the device, one per published scan; what ended it."""

    async def scenario() -> tuple[BaseException, LineLidar]:
        port = PtyPort(str(tmp_path / "lidar")).open()
        link = SerialLink(port.path)
        await link.open()
        lidar = LineLidar(link, timeout_s)
        task = asyncio.ensure_future(lidar._session())
        for data in writes:
            before = lidar.stats.scans
            port.write(data)
            for _ in range(1000):
                if task.done() or lidar.stats.scans > before:
                    break
                await asyncio.sleep(0.01)
        try:
            await asyncio.wait_for(task, 30)
        except BaseException as err:  # noqa: BLE001 - what ended the stream is the result
            ended = err
        else:
            raise AssertionError("the stream returned instead of raising")
        assert not link._receiver, "the receiver must be detached when the stream ends"  # noqa: SLF001
        link.close()
        port.close()
        return ended, lidar

    return asyncio.run(scenario())


def test_scans_flow_until_the_device_reports_a_fault(tmp_path):
    ended, lidar = stream(tmp_path, [b"scan\n", b"scan\n", b"fault\n"])
    assert isinstance(ended, DeviceError) and "status 55" in str(ended)
    assert lidar.stats.scans == 2 and lidar.backlog_seen


def test_a_fault_in_handling_a_frame_becomes_a_device_error(tmp_path):
    ended, lidar = stream(tmp_path, [b"scan\n", b"boom\n"])
    assert isinstance(ended, DeviceError) and "a bug in handling a frame" in str(ended)
    assert isinstance(ended.__cause__, ValueError) and lidar.stats.scans == 1


def test_no_scan_for_the_timeout_ends_the_stream(tmp_path):
    ended, lidar = stream(tmp_path, [b"scan\n"], timeout_s=0.2)
    assert isinstance(ended, DeviceTimeout) and "no scan for 0.20 s" in str(ended)
    assert lidar.stats.scans == 1


def test_an_unplugged_device_ends_the_stream_with_its_error(tmp_path):
    async def scenario() -> BaseException:
        port = PtyPort(str(tmp_path / "lidar")).open()
        link = SerialLink(port.path)
        await link.open()
        lidar = LineLidar(link, 30.0)
        task = asyncio.ensure_future(lidar._session())
        await asyncio.sleep(0)
        port.unplug()
        with pytest.raises(DeviceIOError) as err:
            await asyncio.wait_for(task, 30)
        link.close()
        port.close()
        return err.value

    assert isinstance(asyncio.run(scenario()), DeviceIOError)
