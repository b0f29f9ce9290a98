"""Bag benchmarks: recorder throughput per format, recorder CPU at the daemon's nominal message mix,
follower inter-command jitter at 20 Hz.

The nominal mix is what ``racecar-hw run`` publishes with a UST-10LX at 40 Hz and the VESC at 50 Hz
(about 430 msg/s, see :func:`nominal_mix`). "CPU per nominal second" records 20 s of it as fast as
possible (process CPU / 20 s: the work alone); "writer thread at nominal load" publishes it in real
time from an asyncio loop for a few seconds and reads the writer thread's CPU from /proc, wakeups
and all (Linux only).

Run: ``python benchmarks/bench_bags.py``. ``run()`` returns the rows for benchmarks/run_all.py.
"""

from __future__ import annotations

import asyncio
import os
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from table import print_rows

from racecar_hw.bags.follow import BagFollower, FollowerParams
from racecar_hw.bags.record import Recorder, record_params
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Bool,
    DiagnosticArray,
    DiagnosticStatus,
    Float64,
    Header,
    KeyValue,
    LaserScan,
    Message,
    Odometry,
    OpenSpace,
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    ScanRange,
    TFMessage,
    Time,
    Transform,
    TransformStamped,
    Twist,
    TwistWithCovariance,
    Vector3,
    VescState,
    VescStateStamped,
)
from racecar_hw.base.topics import NAV0_TOPIC, TELEOP_TOPIC
from racecar_hw.rosmsg.typestore import ros1_types, ros2_types

FORMATS = ("mcap", "sqlite3", "ros1")
RECORDER_CPU_TARGET = 1.5  # percent of one core at the nominal mix


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


def nominal_mix() -> list[tuple[float, str, Message]]:
    """One second of the daemon's topics at nominal load: (offset s, topic, message), in time order."""
    rng = np.random.default_rng(1)
    out: list[tuple[float, str, Message]] = []
    base_ns = 1_700_000_000 * NS_PER_S

    def stamp(k: int, rate: int) -> Header:
        return Header(Time.from_ns(base_ns + k * NS_PER_S // rate), "")

    for k in range(40):  # lidar: scan, its summaries
        ranges = rng.uniform(0.02, 30.0, 1081).astype(np.float32)
        ranges[::50] = np.inf
        h = stamp(k, 40)
        h.frame_id = "laser"
        out.append((k / 40, "/scan", LaserScan(h, -2.356, 2.356, 0.00436, 1.7e-5, 0.025, 0.02, 30.0, ranges,
                                               rng.uniform(0, 5000, 1081).astype(np.float32))))
        out.append((k / 40, "/scan_range", ScanRange(h, 0.3, 9.5)))
        out.append((k / 40, "/open_space", OpenSpace(0.3, 9.5)))
    cov = np.zeros(36)
    cov[0] = cov[7] = 0.01
    for k in range(50):  # VESC telemetry, odometry, tf, servo and mux output; servo echo at 90 Hz
        h = stamp(k, 50)
        q = Quaternion.from_yaw(0.1 * k)
        out.append((k / 50, "/vesc/sensors/core", VescStateStamped(h, VescState(
            temp_fet=31.5, current_motor=1.2, speed=1234.0, voltage_input=12.1, displacement=k))))
        out.append((k / 50, "/odom", Odometry(Header(h.stamp, "odom"), "base_link", PoseWithCovariance(
            Pose(Point(1.0 + k, 2.0, 0.0), q), cov), TwistWithCovariance(Twist(Vector3(0.5, 0, 0)), cov))))
        out.append((k / 50, "/tf", TFMessage([TransformStamped(Header(h.stamp, "odom"), "base_link",
                                                               Transform(Vector3(1.0 + k, 2.0), q))])))
        out.append((k / 50, "/vesc/low_level/ackermann_cmd_mux/output",
                    AckermannDriveStamped(Header(h.stamp, "base_link"), AckermannDrive(0.25, 0.0, 0.5))))
    for k in range(90):
        out.append((k / 90, "/vesc/sensors/servo_position_command", Float64(0.5 + k * 1e-3)))
    for k in range(20):
        out.append((k / 20, NAV0_TOPIC, AckermannDriveStamped(stamp(k, 20), AckermannDrive(0.25, 0.0, 0.5))))
    for k in range(2):
        out.append((k / 2, "/diagnostics", DiagnosticArray(stamp(k, 2), [DiagnosticStatus(
            0, "ackermann_cmd_mux", "running", "", [KeyValue("state", "running"),
                                                    KeyValue("active", "nav_0")])])))
        out.append((k / 2, "/safety/engaged", Bool(False)))
    out.sort(key=lambda entry: entry[0])
    return out


def record_cpu_per_nominal_second(fmt: str, seconds: int = 20) -> float:
    """Process CPU to record ``seconds`` of the nominal mix as fast as possible, % of one core."""
    mix = nominal_mix()
    with tempfile.TemporaryDirectory() as tmp:
        bus = Bus()
        rec = Recorder(bus, record_params(tmp, fmt, name="bench", queue_size=len(mix) * seconds + 1))
        rec.start()
        cpu0 = time.process_time()
        for _ in range(seconds):
            for _, topic, msg in mix:
                bus.publish(topic, msg)
        stats = rec.stop()
        cpu = time.process_time() - cpu0
        assert stats.written == len(mix) * seconds and stats.dropped == 0
    return 100.0 * cpu / seconds


def _thread_cpu_s(native_id: int) -> float:
    fields = Path(f"/proc/self/task/{native_id}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def writer_thread_cpu_at_nominal_load(fmt: str = "mcap", seconds: float = 8.0,
                                      warmup_s: float = 2.0) -> float:
    """The writer thread's CPU while the nominal mix is published in real time, % of one core."""
    mix = nominal_mix()

    async def main(rec: Recorder, bus: Bus, native_id: int) -> float:
        start = time.monotonic()
        i, base, cpu0, t0 = 0, start, None, 0.0
        while True:
            now = time.monotonic()
            if cpu0 is None and now - start >= warmup_s:
                cpu0, t0 = _thread_cpu_s(native_id), now
            if now - start >= warmup_s + seconds:
                assert cpu0 is not None
                return 100.0 * (_thread_cpu_s(native_id) - cpu0) / (now - t0)
            offset, topic, msg = mix[i]
            delay = base + offset - now
            if delay > 0:
                await asyncio.sleep(delay)
            bus.publish(topic, msg)
            i += 1
            if i == len(mix):
                i, base = 0, base + 1.0

    interval = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)  # as in the daemon
    with tempfile.TemporaryDirectory() as tmp:
        bus = Bus()
        rec = Recorder(bus, record_params(tmp, fmt, name="bench"))
        rec.start()
        assert rec._outbox._thread is not None and rec._outbox._thread.native_id is not None
        try:
            return asyncio.run(main(rec, bus, rec._outbox._thread.native_id))
        finally:
            rec.stop()
            sys.setswitchinterval(interval)


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


def chunk_crc_ms(repeats: int = 200) -> float:
    """The CRC-32 of one full MCAP chunk (rosbags closes a chunk past 1 MiB), ms: what writing chunks
    with their checksum costs the recorder's writer thread per chunk (and the follower per chunk read)."""
    data = np.random.default_rng(2).integers(0, 256, 1 << 20, dtype=np.uint8).tobytes()
    best = float("inf")
    for _ in range(5):  # the least of five batches: the cost itself, not the machine's other load
        start = time.perf_counter()
        for _ in range(repeats // 5):
            zlib.crc32(data)
        best = min(best, (time.perf_counter() - start) / (repeats // 5))
    return best * 1e3


def nominal_bytes_per_second() -> int:
    """Serialized bytes the nominal mix records per second (what the chunk CRCs cover)."""
    types = ros2_types()
    return sum(len(types.serialize(msg)) for _t, _topic, msg in nominal_mix())


def run() -> list[dict]:
    rows: list[dict] = []
    crc_ms = chunk_crc_ms()
    rows.append({"name": "MCAP chunk CRC-32, per 1 MiB chunk", "value": round(crc_ms, 3), "unit": "ms",
                 "target": 10.0})
    rows.append({"name": "MCAP chunk CRC-32 at the nominal mix, share of a core",
                 "value": round(100 * crc_ms * nominal_bytes_per_second() / (1 << 20) / 1e3, 3),
                 "unit": "%", "target": RECORDER_CPU_TARGET})
    scan = _scan()
    cmd = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(0.1, 0.0, 1.0))
    for fmt in FORMATS:
        rows.append({"name": f"record LaserScan 1081 beams, {fmt}",
                     "value": round(record_throughput(fmt, scan, 3000)), "unit": "msg/s",
                     "target": 40})
        rows.append({"name": f"record AckermannDriveStamped, {fmt}",
                     "value": round(record_throughput(fmt, cmd, 20000)), "unit": "msg/s",
                     "target": 1000})
    for fmt in FORMATS:
        rows.append({"name": f"recorder CPU per nominal second (~430 msg/s), {fmt}",
                     "value": round(record_cpu_per_nominal_second(fmt), 2), "unit": "%",
                     "target": RECORDER_CPU_TARGET})
    if Path("/proc/self/task").is_dir():
        rows.append({"name": "recorder writer thread at nominal load, mcap",
                     "value": round(writer_thread_cpu_at_nominal_load(), 2), "unit": "%",
                     "target": RECORDER_CPU_TARGET})
    rows.append({"name": "follower jitter p99 at 20 Hz", "value": round(follower_jitter_p99_ms(), 3),
                 "unit": "ms", "target": 5.0})
    return rows


if __name__ == "__main__":
    print_rows(run())
