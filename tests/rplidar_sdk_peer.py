"""Slamtec's own RPLIDAR SDK (the ``pyrplidarsdk`` wheel wraps ``rplidar_sdk``) as a test peer.

The SDK's calls block without releasing the GIL, so a fake lidar served by a thread of the test
process would stall while the SDK waits for it. The SDK therefore runs in a subprocess: it connects
at the given port and baud rate, reads device info and health, starts the default (typical) scan
as ``pyrplidarsdk`` does (``startScan(false, true)``), grabs full revolutions and prints JSON.
"""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any

import pytest

_CLIENT = r'''
import json, sys, time
import pyrplidarsdk
port, baud, revolutions = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
driver = pyrplidarsdk.RplidarDriver(port=port, baudrate=baud)
out = {"connected": driver.connect()}
if out["connected"]:
    info, health = driver.get_device_info(), driver.get_health()
    out["info"] = info and {"model": info.model, "firmware": info.firmware_version,
                            "hardware": info.hardware_version, "serial": info.serial_number}
    out["health"] = health and {"status": health.status, "error_code": health.error_code}
    out["started"] = driver.start_scan()
    scans = []
    for _ in range(revolutions if out["started"] else 0):
        scan = driver.get_scan_data()  # angles (rad, clockwise), ranges (m), qualities
        scans.append(scan and [list(scan[0]), list(scan[1]), list(scan[2])])
    out["scans"] = scans
    driver.stop_scan()
    driver.disconnect()
print(json.dumps(out))
'''


def sdk_scan(port: str, baudrate: int, revolutions: int, timeout: float = 60.0) -> dict[str, Any]:
    """Run the SDK client against ``port``; its JSON report (skips if pyrplidarsdk is absent)."""
    pytest.importorskip("pyrplidarsdk", reason="Slamtec's SDK (pip pyrplidarsdk) is not installed")
    proc = subprocess.run([sys.executable, "-c", _CLIENT, port, str(baudrate), str(revolutions)],
                          capture_output=True, text=True, timeout=timeout, check=False)
    if proc.returncode != 0 or not proc.stdout.strip():
        raise AssertionError(f"the SDK client failed ({proc.returncode}): {proc.stderr[-2000:]}")
    report: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    report["stderr"] = proc.stderr
    return report
