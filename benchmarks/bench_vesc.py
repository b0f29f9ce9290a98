"""VESC benchmarks: codec encode/decode rates and driver command-to-wire latency over a pty.

Run: ``python benchmarks/bench_vesc.py``. ``run()`` returns the rows for ``benchmarks/run_all.py``.

Latency is measured from the ``VescDriver.command()`` call to the moment its SET_RPM and
SET_SERVO_POS bytes are readable at the pty master (what a USB VESC would receive), with the
driver running in its event loop and polling telemetry at 50 Hz.
"""

from __future__ import annotations

import asyncio
import os
import select
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from table import print_rows

from racecar_hw.base.bus import Bus  # noqa: E402
from racecar_hw.base.messages import AckermannDrive  # noqa: E402
from racecar_hw.runtime.fakepty import PtyPort  # noqa: E402
from vesc.codec import (  # noqa: E402
    FwVersion,
    FwVersionRequest,
    GetValuesRequest,
    Role,
    SetRpm,
    SetServoPosition,
    Values,
    VescCodec,
)
from vesc.driver import VescDriver  # noqa: E402
from vesc.params import VescParams  # noqa: E402


def _rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    fn(n)
    return n / (time.perf_counter() - t0)


def bench_codec(n: int = 50_000) -> list[dict]:
    host = VescCodec(Role.HOST, firmware=(6, 2))
    dev = VescCodec(Role.DEVICE, firmware=(6, 2))
    sample = Values(temp_fet=30.0, erpm=12345, v_in=16.2, tachometer=999, status=1)

    def encode_commands(k: int) -> None:
        for i in range(k):
            host.send(SetRpm(i))

    def encode_values(k: int) -> None:
        for _ in range(k):
            dev.send(sample)

    commands = b"".join(host.send(SetRpm(i)) + host.send(SetServoPosition(0.5)) for i in range(n // 2))
    replies = dev.send(sample) * n

    def decode_commands(k: int) -> None:
        d = VescCodec(Role.DEVICE)
        d.receive_data(commands[: len(commands) * k // n])
        while d.next_event() is not None:
            pass

    def decode_values(k: int) -> None:
        h = VescCodec(Role.HOST, firmware=(6, 2))
        for i in range(0, k, 100):  # 100 replies per read, like a busy serial buffer
            h.receive_data(replies[i * 79:(i + 100) * 79])
            while h.next_event() is not None:
                pass

    return [
        {"name": "codec encode SET_RPM", "value": _rate(encode_commands, n), "unit": "frames/s",
         "target": 100_000},
        {"name": "codec encode GET_VALUES reply (6.x)", "value": _rate(encode_values, n // 5),
         "unit": "frames/s", "target": None},
        {"name": "codec decode commands", "value": _rate(decode_commands, n), "unit": "frames/s",
         "target": 100_000},
        {"name": "codec decode GET_VALUES replies (6.x)", "value": _rate(decode_values, n // 5),
         "unit": "frames/s", "target": 10_000},
    ]


async def _latency(samples: int) -> list[float]:
    with tempfile.TemporaryDirectory() as tmp, PtyPort(os.path.join(tmp, "vesc")) as port:
        assert port.master_fd is not None
        fd = port.master_fd
        dev = VescCodec(Role.DEVICE, firmware=(6, 2))

        def answer(data: bytes) -> None:
            dev.receive_data(data)
            for p in dev.events():
                if isinstance(p, FwVersionRequest):
                    port.write(dev.send(FwVersion(6, 2, "60", bytes(12))))
                elif isinstance(p, GetValuesRequest):
                    port.write(dev.send(Values(v_in=16.0)))

        loop = asyncio.get_running_loop()
        loop.add_reader(fd, lambda: answer(port.read()))
        driver = VescDriver(Bus(), VescParams(port=port.path))
        out: list[float] = []
        async with driver:
            while not driver.connected:
                await asyncio.sleep(0.01)
            for i in range(samples):
                answer(port.read())  # drain what the poll loop wrote
                drive = AckermannDrive(speed=0.5 + (i % 10) * 0.1, steering_angle=0.05)
                t0 = time.perf_counter_ns()
                driver.command(drive)
                ready, _, _ = select.select([fd], [], [], 1.0)
                t1 = time.perf_counter_ns()
                if ready:
                    out.append((t1 - t0) / 1e3)
                answer(port.read())
                await asyncio.sleep(0.004)
        loop.remove_reader(fd)
        return out


def bench_latency(samples: int = 2000) -> list[dict]:
    lat = sorted(asyncio.run(_latency(samples)))
    p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))]
    return [
        {"name": "driver command() -> bytes at pty master p50", "value": statistics.median(lat),
         "unit": "us", "target": 1000},
        {"name": "driver command() -> bytes at pty master p99", "value": p99, "unit": "us",
         "target": 5000},
    ]


def run() -> list[dict]:
    """Every VESC benchmark row."""
    return bench_codec() + bench_latency()


if __name__ == "__main__":
    print_rows(run())
