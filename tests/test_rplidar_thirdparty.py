"""The pip ``rplidar`` package (an independent client) reads the fake A1 over a real pty."""

from __future__ import annotations

import math

import numpy as np
import rplidar
import serial
from conftest import wait_for

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.rplidar_fake import FakeRplidar


def test_pip_rplidar_reads_info_health_and_scans(device_thread, tmp_path, monkeypatch):
    room = RoomRangeSource(8.0, 6.0, x=2.5, y=1.5, yaw=0.3)
    fake = FakeRplidar("a1", room, str(tmp_path / "rplidar"))
    device_thread.spawn(fake.serve())
    wait_for(lambda: fake.port.plugged)
    # The ONE neutralised call: a pty has no DTR line, and rplidar sets it in start_motor().
    monkeypatch.setattr(serial.Serial, "setDTR", lambda self, value=True: None)

    lidar = rplidar.RPLidar(fake.link, baudrate=115200, timeout=3)
    try:
        info = lidar.get_info()
        assert info["model"] == 0x18 and info["firmware"] == (1, 29) and info["hardware"] == 7
        assert info["serialnumber"] == fake.info.serial_hex
        assert lidar.get_health() == ("Good", 0)
        scans = []
        for scan in lidar.iter_scans(max_buf_meas=False):
            scans.append(scan)
            if len(scans) == 3:
                break
    finally:
        lidar.stop()
        lidar.disconnect()

    per_rev = fake.samples_per_rev_standard
    for scan in scans[1:]:  # the first one may start mid-revolution
        quality, angle, dist = (np.array(v) for v in zip(*scan, strict=True))
        assert len(scan) == per_rev
        assert np.all(quality == 47)
        # what the fake was told to produce: the room along ROS angle -device angle
        k = np.round(angle * per_rev / 360.0)
        exact = k * 360.0 / per_rev
        np.testing.assert_allclose(angle, exact, atol=1 / 64)
        ros = np.mod(-np.radians(exact) + math.pi, 2 * math.pi) - math.pi
        np.testing.assert_allclose(dist, np.round(room.ranges(ros) * 4000) / 4, atol=1e-9)
