"""The daemon's scan path in one process, back to back and after an idle gap as at 40 Hz.

One pass is what the daemon does between a UST-10LX frame's last byte and the motor command:
decode the MD frame (1081 steps), build the LaserScan, turn it into base_link points, sweep the
footprint along the commanded arc, encode SET_RPM + SET_SERVO_POS and write them to a pty.

Run back to back, every pass finds its code and data in the CPU caches. In the daemon, 25 ms of
other work and idling pass between scans; on a shared virtual machine the caches are cold again by
then and the same pass takes several times longer. The "after 25 ms idle" rows show that cost,
which is what the daemon's in-process latency (bench_daemon.py) is made of.

Run ``python benchmarks/bench_scan_path.py``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import logging
import os
import pty
import time
import tty

import numpy as np
from table import print_rows

from lidar_drivers.params import LidarParams
from lidar_drivers.scip import ResponseDecoder, ScanCommand, SensorParams, encode_scan
from lidar_drivers.scip_driver import HokuyoDriver
from lidar_drivers.scip_models import get_model
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import AckermannDrive
from safety.controller import SafetyController
from safety.params import SafetyParams
from vesc.ackermann import AckermannConversion
from vesc.codec import SetRpm, SetServoPosition, encode_payload, frame

STAGES = ("decode", "LaserScan", "safety points", "safety sweep", "VESC write")
GAP_S = 0.025  # the scan period of a UST-10LX


def _pass(decoder: ResponseDecoder, raw: bytes, driver: HokuyoDriver, dev: SensorParams,
          safety: SafetyController, conversion: AckermannConversion, drive: AckermannDrive,
          fd: int) -> list[int]:
    clock = time.perf_counter_ns
    t = [clock()]
    decoder.receive_data(raw)
    reply = decoder.next_event()
    t.append(clock())
    scan = driver.to_laser_scan(reply, dev)  # type: ignore[arg-type]
    t.append(clock())
    safety.on_scan(scan, t[0])
    t.append(clock())
    out, _ = safety.limit(drive, "nav_0", 1.0, t[0])
    t.append(clock())
    setpoint = conversion.to_vesc(out)
    os.write(fd, frame(encode_payload(SetRpm(setpoint.erpm)))
             + frame(encode_payload(SetServoPosition(setpoint.servo))))
    t.append(clock())
    return [t[i + 1] - t[i] for i in range(len(t) - 1)]


def run(passes: int = 400) -> list[dict]:
    """Rows: p50 and p99 of the whole pass, hot and after an idle gap, and p50 per stage."""
    logging.getLogger("safety").setLevel(logging.ERROR)
    m = get_model("ust-10lx")
    dev = SensorParams.from_fields({k: str(v) for k, v in m.fields().items()})  # as PP reads
    req = ScanCommand(name="MD", start=m.amin, end=m.amax, cluster=1, interval=0, count=0)
    angles = np.linspace(-2.35, 2.35, req.values)
    distances = (2000 + 1500 * np.abs(np.cos(1.3 * angles))).astype(np.int64)  # a room, 2-3.5 m
    raw = encode_scan(req.echo(0), "99", 123456, distances)
    driver = HokuyoDriver(Bus(), LidarParams(model="ust-10lx", tcp="127.0.0.1:10940"))
    driver._rx_wall_ns = time.time_ns()  # noqa: SLF001 - the stamp the read would have set
    safety = SafetyController(SafetyParams())
    conversion = AckermannConversion()
    drive = AckermannDrive(steering_angle=0.25, speed=1.0)  # on an arc, as in the figure-8
    master, slave = pty.openpty()
    tty.setraw(slave)
    rows: list[dict] = []
    try:
        for label, gap in (("back to back", 0.0), ("after 25 ms idle", GAP_S)):
            decoder = ResponseDecoder()
            samples = []
            for k in range(passes + 20):
                stages = _pass(decoder, raw, driver, dev, safety, conversion, drive, slave)
                os.read(master, 4096)
                if k >= 20:  # the first passes fill caches and the allocator
                    samples.append(stages)
                if gap:
                    time.sleep(gap)
            us = np.asarray(samples, dtype=np.float64) / 1e3
            total = us.sum(axis=1)
            rows.append({"name": f"scan path {label} p50", "value": float(np.percentile(total, 50)),
                         "unit": "us", "target": None})
            rows.append({"name": f"scan path {label} p99", "value": float(np.percentile(total, 99)),
                         "unit": "us", "target": None})
            for j, stage in enumerate(STAGES):
                rows.append({"name": f"  {stage}, {label}, p50",
                             "value": float(np.percentile(us[:, j], 50)), "unit": "us", "target": None})
    finally:
        os.close(master)
        os.close(slave)
    return rows


if __name__ == "__main__":
    print_rows(run())
