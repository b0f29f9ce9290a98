"""Decode time of RPLIDAR revolutions: every capsule format and standard nodes, bytes to samples.

Each revolution's bytes are fed to the codec as one chunk (the driver sees a few chunks per
revolution); the value is the median time per revolution, bytes in to Measurements out.

Run ``python benchmarks/bench_lidar_rplidar.py``; :func:`run` returns the rows for run_all.py.
"""

from __future__ import annotations

import math
import time

import numpy as np
from table import print_rows

from lidar_drivers import rplidar_capsules
from lidar_drivers.base import RoomRangeSource
from lidar_drivers.rplidar_codec import (
    AnswerType,
    Command,
    Measurements,
    Request,
    RplidarClient,
    encode_capsules,
    encode_nodes,
    encode_scan_descriptor,
)
from lidar_drivers.rplidar_scan import ScanAssembler

TARGET_MS = 0.2


def _revolutions(express: bool, per_rev: int, revs: int) -> tuple[bytes, list[bytes]]:
    k = np.arange(per_rev * revs)
    theta = (k % per_rev) * 360.0 / per_rev
    ros = np.mod(-np.radians(theta) + math.pi, 2 * math.pi) - math.pi
    dist = RoomRangeSource(8.0, 6.0, x=2.5, y=1.5).ranges(ros) * 1000.0
    if express:
        data = encode_capsules(theta[::32], dist, first=True)
        step = per_rev // 32 * 84
    else:
        data = encode_nodes((k % per_rev) == 0, np.full(len(k), 47), theta, dist)
        step = per_rev * 5
    return encode_scan_descriptor(express), [data[i:i + step] for i in range(0, len(data), step)]


def _time_decode(express: bool, per_rev: int, revs: int = 200) -> float:
    head, chunks = _revolutions(express, per_rev, revs)
    client = RplidarClient()
    client.send(Request.express_scan() if express else Request.simple(Command.SCAN))
    client.receive_data(head)
    client.events()
    times = []
    n = 0
    for chunk in chunks:
        t0 = time.perf_counter()
        client.receive_data(chunk)
        n += sum(len(e) for e in client.events() if isinstance(e, Measurements))
        times.append(time.perf_counter() - t0)
    assert n >= per_rev * (revs - 1)
    return float(np.median(times)) * 1e3  # median: robust to other processes on the machine


def _room_mm(theta: np.ndarray) -> np.ndarray:
    ros = np.mod(-np.radians(theta) + math.pi, 2 * math.pi) - math.pi
    return RoomRangeSource(8.0, 6.0, x=2.5, y=1.5).ranges(ros) * 1000.0


def _time_decode_newer(kind: AnswerType, per_rev: int, revs: int = 200) -> float:
    """Like :func:`_time_decode` for ultra (96 samples a capsule) or dense (40) capsules."""
    group = rplidar_capsules.ULTRA_SAMPLES if kind == AnswerType.ULTRA_CAPSULED else \
        rplidar_capsules.DENSE_SAMPLES
    n = per_rev * revs // group * group
    theta = (np.arange(n + group) % per_rev) * 360.0 / per_rev
    dist = _room_mm(theta)
    if kind == AnswerType.ULTRA_CAPSULED:
        data = rplidar_capsules.encode_ultra(theta[:n:group], dist[:n], dist[n], first=True)
        size = rplidar_capsules.ULTRA_LEN
    else:
        data = rplidar_capsules.encode_dense(theta[:n:group], dist[:n], first=True)
        size = rplidar_capsules.DENSE_LEN
    step = max(per_rev // group, 1) * size
    client = RplidarClient()
    client.send(Request.express_scan(3), kind)
    client.receive_data(encode_scan_descriptor(True, kind))
    client.events()
    times, got = [], 0
    for i in range(0, len(data), step):
        t0 = time.perf_counter()
        client.receive_data(data[i:i + step])
        got += sum(len(e) for e in client.events() if isinstance(e, Measurements))
        times.append(time.perf_counter() - t0)
    assert got >= n - 2 * per_rev
    return float(np.median(times)) * 1e3


def _time_assemble(per_rev: int, revs: int = 200) -> float:
    head, chunks = _revolutions(True, per_rev, revs)
    client = RplidarClient()
    client.send(Request.express_scan())
    client.receive_data(head + b"".join(chunks))
    batches = [e for e in client.events() if isinstance(e, Measurements)]
    asm = ScanAssembler(range_min=0.15, range_max=12.0, sample_period_s=1e-4)
    t0 = time.perf_counter()
    scans = 0
    for i, m in enumerate(batches):
        scans += len(asm.add(m, i * 1_000_000))
    dt = time.perf_counter() - t0
    return dt / max(scans, 1) * 1e3


def _time_noise(size: int = 2048, rounds: int = 20) -> float:
    """Median time (ms) to skip ``size`` bytes of line noise in the standard node stream, fed at
    once (the driver's reader callback, on the daemon's event loop)."""
    noise = np.random.default_rng(7).integers(0, 256, size, dtype=np.uint8).tobytes()
    times = []
    for _ in range(rounds):
        client = RplidarClient()
        client.send(Request.simple(Command.SCAN))
        client.receive_data(encode_scan_descriptor(False))
        t0 = time.perf_counter()
        client.receive_data(noise)
        client.events()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3


def run() -> list[dict]:
    """Benchmark rows: name, value, unit, target."""
    return [
        {"name": "rplidar express revolution decode (A2, 800 samples)",
         "value": _time_decode(True, 800), "unit": "ms", "target": TARGET_MS},
        {"name": "rplidar express revolution decode (S1, 928 samples)",
         "value": _time_decode(True, 928), "unit": "ms", "target": TARGET_MS},
        {"name": "rplidar ultra capsule revolution decode (A3 Sensitivity, 1587 samples)",
         "value": _time_decode_newer(AnswerType.ULTRA_CAPSULED, 1587), "unit": "ms",
         "target": TARGET_MS},
        {"name": "rplidar dense capsule revolution decode (S1 DenseBoost, 920 samples)",
         "value": _time_decode_newer(AnswerType.DENSE_CAPSULED, 920), "unit": "ms",
         "target": TARGET_MS},
        {"name": "rplidar standard revolution decode (A1, 200 samples)",
         "value": _time_decode(False, 200), "unit": "ms", "target": None},
        {"name": "rplidar standard nodes: 2 KiB of line noise skipped",
         "value": _time_noise(), "unit": "ms", "target": 1.0},
        {"name": "rplidar revolution -> LaserScan (800 samples)",
         "value": _time_assemble(800), "unit": "ms", "target": None},
    ]


if __name__ == "__main__":
    print_rows(run())
