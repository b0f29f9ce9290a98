"""Decode time of SCIP 2.0 scans: a UST-10LX MD frame (1081 steps) and an ME frame.

Run ``python benchmarks/bench_lidar_scip.py``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import time

import numpy as np
from table import print_rows

from lidar_drivers.scip import ResponseDecoder, ScanCommand, ScanReply, SensorParams, encode_scan
from lidar_drivers.scip_driver import ranges_m
from lidar_drivers.scip_models import get_model

TARGET_MS = 0.2


def _frame(kind: str) -> tuple[bytes, ScanCommand]:
    m = get_model("ust-10lx")
    req = ScanCommand(name=kind, start=m.amin, end=m.amax, cluster=1, interval=0, count=0)
    rng = np.random.default_rng(1)
    dist = rng.integers(20, 30000, size=req.values)
    inten = rng.integers(0, 5000, size=req.values) if req.intensities else None
    return encode_scan(req.echo(0), "99", 123456, dist, inten), req


def _decode_ms(raw: bytes, rounds: int) -> float:
    decoder = ResponseDecoder()
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(rounds):
            decoder.receive_data(raw)
            event = decoder.next_event()
        best = min(best, (time.perf_counter() - t0) / rounds)
        assert isinstance(event, ScanReply)
    return best * 1000.0


def run() -> list[dict]:
    """Rows: decode time per scan (MD, ME), decode + metres conversion, frame size."""
    m = get_model("ust-10lx")
    dev = SensorParams.from_fields({k: str(v) for k, v in m.fields().items()})  # as PP reads
    md, _ = _frame("MD")
    me, _ = _frame("ME")
    rows = [
        {"name": "scip_decode_md_1081", "value": _decode_ms(md, 400), "unit": "ms/scan",
         "target": TARGET_MS},
        {"name": "scip_decode_me_1081", "value": _decode_ms(me, 200), "unit": "ms/scan",
         "target": None},
    ]
    decoder = ResponseDecoder()
    t0 = time.perf_counter()
    n = 400
    for _ in range(n):
        decoder.receive_data(md)
        event = decoder.next_event()
        assert isinstance(event, ScanReply)
        ranges_m(dev, event.distances)
    rows.append({"name": "scip_decode_md_to_metres", "value": (time.perf_counter() - t0) / n * 1000,
                 "unit": "ms/scan", "target": None})
    rows.append({"name": "scip_md_frame_size", "value": len(md), "unit": "bytes", "target": None})
    return rows


if __name__ == "__main__":
    print_rows(run())
