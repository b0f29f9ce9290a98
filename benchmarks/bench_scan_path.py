"""The daemon's scan path in one process, back to back and after an idle gap as at 40 Hz.

One pass is what the daemon does between a UST-10LX frame's last byte and the motor command:
decode the MD frame (1081 steps, a 5 m x 4 m room seen from its centre), build the LaserScan,
turn it into base_link points, sweep the footprint along the commanded arc, encode SET_RPM +
SET_SERVO_POS and write them to a pty.

Run back to back, every pass finds its code and data in the CPU caches. In the daemon, 25 ms of
other work and idling pass between scans; on a shared virtual machine the caches are cold again by
then and the same pass takes several times longer. The "after 25 ms idle" rows show that cost,
which is what the daemon's in-process latency (bench_daemon.py) is made of.

Each pass runs twice, interleaved: with the obstacle memory off and on. With it on, the pass also
places the remembered points (the room all round, seen as the car turned round) next to the
scan's, and the memory takes the scan in after the write, timed on its own ("memory update", at
every scan here; the daemon updates it every fourth scan by default). The memory keeps its points
for the whole run here (max_age_s 3600), so every pass sweeps the same number of them.

On a busy shared machine a pass's wall time includes the time the thread was preempted; the "its
CPU time" rows (the thread's CPU clock over the pass) leave that out.

Run ``python benchmarks/bench_scan_path.py``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import logging
import math
import os
import pty
import time
import tty

import numpy as np
from table import print_rows

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.params import LidarParams
from lidar_drivers.scip import ResponseDecoder, ScanCommand, SensorParams, encode_scan
from lidar_drivers.scip_driver import HokuyoDriver
from lidar_drivers.scip_models import get_model
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import AckermannDrive
from safety.controller import Pose, SafetyController
from safety.params import MemoryParams, SafetyParams
from vesc.ackermann import AckermannConversion
from vesc.codec import SetRpm, SetServoPosition, encode_payload, frame

STAGES = ("decode", "LaserScan", "safety points", "safety sweep", "VESC write")
GAP_S = 0.025  # the scan period of a UST-10LX


def _pass(decoder: ResponseDecoder, raw: bytes, driver: HokuyoDriver, dev: SensorParams,
          safety: SafetyController, conversion: AckermannConversion, drive: AckermannDrive,
          fd: int, pose: Pose) -> list[int]:
    """The time of each stage (ns), then the thread's CPU time over the whole pass (ns)."""
    clock = time.perf_counter_ns
    cpu0 = time.thread_time_ns()
    t = [clock()]
    decoder.receive_data(raw)
    reply = decoder.next_event()
    t.append(clock())
    scan = driver.to_laser_scan(reply, dev)  # type: ignore[arg-type]
    t.append(clock())
    safety.on_scan(scan, t[0], pose)
    t.append(clock())
    out, _ = safety.limit(drive, "nav_0", 1.0, t[0])
    t.append(clock())
    setpoint = conversion.to_vesc(out)
    os.write(fd, frame(encode_payload(SetRpm(setpoint.erpm)))
             + frame(encode_payload(SetServoPosition(setpoint.servo))))
    t.append(clock())
    cpu = time.thread_time_ns() - cpu0
    return [t[i + 1] - t[i] for i in range(len(t) - 1)] + [cpu]


def _room_frame(heading: float) -> bytes:
    """An MD frame of a 5 m x 4 m room seen from a car at its centre facing ``heading`` (rad)."""
    m = get_model("ust-10lx")
    req = ScanCommand(name="MD", start=m.amin, end=m.amax, cluster=1, interval=0, count=0)
    angles = np.linspace(-2.35, 2.35, req.values)
    laser = 0.265  # ahead of base_link, which stays at the room's centre as the car turns
    room = RoomRangeSource(5.0, 4.0, 2.5 + laser * math.cos(heading), 2.0 + laser * math.sin(heading),
                           heading)
    distances = (np.minimum(room.ranges(angles), 30.0) * 1000).astype(np.int64)
    return encode_scan(req.echo(0), "99", 123456, distances)


def _remembering(driver: HokuyoDriver, dev: SensorParams) -> SafetyController:
    """A controller whose memory saw the room while the car turned round to face +x."""
    safety = SafetyController(SafetyParams(memory=MemoryParams(max_age_s=3600.0, update_period_s=0.0)))
    for k in range(37):
        heading = math.pi * (1.0 - k / 36)  # from facing away to facing ahead, 5 deg a scan
        decoder = ResponseDecoder()
        decoder.receive_data(_room_frame(heading))
        scan = driver.to_laser_scan(decoder.next_event(), dev)  # type: ignore[arg-type]
        safety.on_scan(scan, time.monotonic_ns(), (0.0, 0.0, heading))
        safety.remember()
    return safety


def run(passes: int = 1000) -> list[dict]:
    """Rows: p50 and p99 of the whole pass, hot and after an idle gap, memory off and on, p50 per
    stage, and the memory update after the write."""
    logging.getLogger("safety").setLevel(logging.ERROR)
    m = get_model("ust-10lx")
    dev = SensorParams.from_fields({k: str(v) for k, v in m.fields().items()})  # as PP reads
    raw = _room_frame(0.0)  # walls 1.7-3.2 m away
    driver = HokuyoDriver(Bus(), LidarParams(model="ust-10lx", tcp="127.0.0.1:10940"))
    driver._rx_wall_ns = time.time_ns()  # noqa: SLF001 - the stamp the read would have set
    pose = (0.0, 0.0, 0.0)
    variants = {"memory off": SafetyController(SafetyParams(memory=MemoryParams(enabled=False))),
                "memory on": _remembering(driver, dev)}
    conversion = AckermannConversion()
    drive = AckermannDrive(steering_angle=0.25, speed=1.0)  # on an arc, as in the figure-8
    master, slave = pty.openpty()
    tty.setraw(slave)
    rows: list[dict] = []
    try:
        for label, gap in (("back to back", 0.0), ("after 25 ms idle", GAP_S)):
            decoder = ResponseDecoder()
            samples: dict[str, list[list[int]]] = {name: [] for name in variants}
            updates: list[int] = []
            for k in range(passes + 20):
                for name, safety in variants.items():  # interleaved: both see the same machine
                    stages = _pass(decoder, raw, driver, dev, safety, conversion, drive, slave, pose)
                    os.read(master, 4096)
                    t0 = time.perf_counter_ns()
                    safety.remember()  # after the write, as the daemon does
                    if k >= 20:  # the first passes fill caches and the allocator
                        samples[name].append(stages)
                        if safety.memory is not None:
                            updates.append(time.perf_counter_ns() - t0)
                    if gap:
                        time.sleep(gap)
            for name, got in samples.items():
                us = np.asarray(got, dtype=np.float64) / 1e3
                total = us[:, :-1].sum(axis=1)
                for q in (50, 99):
                    rows.append({"name": f"scan path {label}, {name}, p{q}",
                                 "value": float(np.percentile(total, q)), "unit": "us", "target": None})
                rows.append({"name": f"  its CPU time, {label}, {name}, p99",
                             "value": float(np.percentile(us[:, -1], 99)), "unit": "us", "target": None})
                for j, stage in enumerate(STAGES):
                    rows.append({"name": f"  {stage}, {label}, {name}, p50",
                                 "value": float(np.percentile(us[:, j], 50)), "unit": "us", "target": None})
            remembered = variants["memory on"].memory
            assert remembered is not None
            for q in (50, 99):
                rows.append({"name": f"memory update after the write, {label}, p{q} "
                                     f"({remembered.points().size} remembered points)",
                             "value": float(np.percentile(np.asarray(updates) / 1e3, q)), "unit": "us",
                             "target": None})
    finally:
        os.close(master)
        os.close(slave)
    return rows


if __name__ == "__main__":
    print_rows(run())
