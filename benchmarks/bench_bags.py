"""Bag benchmarks: recorder throughput per format, follower inter-command jitter at 20 Hz.

Run: ``python benchmarks/bench_bags.py``. ``run()`` returns the rows for benchmarks/run_all.py.
"""

from __future__ import annotations

import asyncio
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1

from racecar_hw.bag_follow import NAV0_TOPIC, TELEOP_TOPIC, BagFollower, FollowerParams
from racecar_hw.bag_record import Recorder, record_params
from racecar_hw.bagtypes import ros1_types
from racecar_hw.bus import Bus
from racecar_hw.clock import NS_PER_S, monotonic_ns
from racecar_hw.messages import AckermannDrive, AckermannDriveStamped, Header, LaserScan, Time

FORMATS = ("mcap", "sqlite3", "ros1")


def _scan() -> LaserScan:
    r = np.linspace(0.5, 10.0, 1081, dtype=np.float32)
    return LaserScan(Header(Time(1, 0), "laser"), -2.35, 2.35, 0.00436, 0.0, 0.025, 0.02, 30.0, r, r)


def record_throughput(fmt: str, msg: object, count: int) -> float:
    """Messages per second from the first publish until the bag is closed."""
    with tempfile.TemporaryDirectory() as tmp:
        bus = Bus()
        rec = Recorder(bus, record_params(tmp, fmt, name="bench", queue_size=count + 1))
        rec.start()
        start = time.perf_counter()
        for _ in range(count):
            bus.publish("/x", msg)  # type: ignore[arg-type]
        stats = rec.stop()
        elapsed = time.perf_counter() - start
        assert stats.written == count and stats.dropped == 0
    return count / elapsed


def follower_jitter_p99_ms(n: int = 60, rate_hz: float = 20.0) -> float:
    """p99 of |gap - period| between published commands, in ms."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cmds.bag"
        types = ros1_types()
        with Writer1(path) as writer:
            conn = writer.add_connection(TELEOP_TOPIC, AckermannDriveStamped.ROS_TYPE,
                                         typestore=types.store)
            for i in range(n):
                msg = AckermannDriveStamped(drive=AckermannDrive(speed=1.0, steering_angle=0.1))
                writer.write(conn, NS_PER_S + i * NS_PER_S // 20, types.serialize(msg))

        async def main() -> list[int]:
            bus = Bus()
            times: list[int] = []
            bus.subscribe(NAV0_TOPIC, lambda _m: times.append(monotonic_ns()))
            await BagFollower(bus, FollowerParams(bag=str(path), rate_hz=rate_hz,
                                                  stop_at_end=False)).run()
            return times

        times = asyncio.run(main())
    gaps = np.diff(np.array(times, dtype=np.int64)) / 1e6
    return float(np.percentile(np.abs(gaps - 1000.0 / rate_hz), 99))


def run() -> list[dict]:
    rows: list[dict] = []
    scan = _scan()
    cmd = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(0.1, 0.0, 1.0))
    for fmt in FORMATS:
        rows.append({"name": f"record LaserScan 1081 beams, {fmt}",
                     "value": round(record_throughput(fmt, scan, 3000)), "unit": "msg/s",
                     "target": 40})
        rows.append({"name": f"record AckermannDriveStamped, {fmt}",
                     "value": round(record_throughput(fmt, cmd, 20000)), "unit": "msg/s",
                     "target": 1000})
    rows.append({"name": "follower jitter p99 at 20 Hz", "value": round(follower_jitter_p99_ms(), 3),
                 "unit": "ms", "target": 5.0})
    return rows


def main() -> None:
    rows = run()
    width = max(len(r["name"]) for r in rows)
    print(f"{'name':<{width}}  {'value':>10}  unit   target")
    for r in rows:
        target = "" if r["target"] is None else r["target"]
        print(f"{r['name']:<{width}}  {r['value']:>10}  {r['unit']:<5}  {target}")


if __name__ == "__main__":
    main()
