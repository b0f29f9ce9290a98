"""Cost of the command mux's control path: one arbitration and one full output tick.

A tick (arbitrate, limit, stamp, publish on the bus) runs 50 times a second on the daemon's event
loop, next to the drivers; it should take a small fraction of the 20 ms period.

Run ``python benchmarks/bench_mux.py``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import time

from table import print_rows

from mux.node import CommandMux
from mux.params import LockParams, MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Bool

TARGET_TICK_US = 100.0


def _mux() -> tuple[Bus, CommandMux]:
    bus = Bus()
    params = MuxParams(locks=[LockParams("pause", "/pause", 50, 0.0),
                              LockParams("deadman", "/deadman", 95, 0.5)])
    mux = CommandMux(bus, params)
    bus.subscribe(params.output_topic, lambda msg: None)
    for inp in params.inputs[2:]:
        bus.publish(inp.topic, AckermannDriveStamped(drive=AckermannDrive(0.1, 0.0, 1.0)))
    bus.publish("/pause", Bool(False))
    bus.publish("/deadman", Bool(False))
    return bus, mux


def _best_us(fn, rounds: int) -> float:  # noqa: ANN001 - any zero-argument callable
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(rounds):
            fn()
        best = min(best, (time.perf_counter() - t0) / rounds)
    return best * 1e6


def run() -> list[dict]:
    """Rows: arbitration, full tick, diagnostics build (6 inputs, 2 locks)."""
    _bus, mux = _mux()
    now = monotonic_ns()  # a fixed time keeps every input fresh
    return [
        {"name": "mux_arbitrate", "value": _best_us(lambda: mux.arbitrate(now), 5000),
         "unit": "us", "target": None},
        {"name": "mux_tick", "value": _best_us(lambda: mux.step(now), 5000), "unit": "us",
         "target": TARGET_TICK_US},
        {"name": "mux_diagnostics", "value": _best_us(lambda: mux.diagnostics(now), 1000),
         "unit": "us", "target": None},
    ]


if __name__ == "__main__":
    print_rows(run())
