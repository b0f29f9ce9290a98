"""What ``/clock`` costs the simulation: the sim process's CPU share with ``/clock`` off, on with
nobody subscribed, and on with a subscriber (issue 27).

Each setting runs ``racecar-hw sim --scenario wall`` (nobody driving; the Zenoh bridge on a free
port, the Foxglove live view and the status page on free ports, nobody connected; DDS off, so no
discovery traffic leaves this benchmark on a shared host) for SECONDS after the daemon is up and
a settling second; the CPU time (utime + stime of every thread, /proc/PID/stat) over that window
divided by its wall time is the share of one core. Settings:

* ``off``: ``world.clock_rate_hz=0``;
* ``on, no subscriber``: 100 Hz (the default): the publisher task and the bus's callbacks, which
  skip a topic nobody subscribes;
* ``on, subscribed``: 100 Hz with a :class:`racecar_hw.client.Car` (``use_sim_time=True``) in this
  process following it: serialization and a Zenoh put per message, sent at once (``/clock`` is on
  the senders' urgent list).

The settings are interleaved over the rounds (rounds.py), and the per-message cost is the
difference of the medians divided by the messages per second. The last row times the publisher
alone in this process (an event loop with it against one without, the loop thread's CPU time),
finer than the whole sim process's share can show.

Run ``python benchmarks/bench_clock.py [SECONDS] [ROUNDS]`` (20 s, 3 rounds); ``run()`` returns
the rows.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from rounds import interleaved
from table import print_rows

ROOT = Path(__file__).resolve().parents[1]
TICKS_PER_S = os.sysconf("SC_CLK_TCK")
RATE_HZ = 100.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_S  # utime, stime


def _one(seconds: float, rate_hz: float, subscribe: bool) -> float:
    """The sim process's CPU share (% of one core) over ``seconds`` once running."""
    port = _free_port()
    with tempfile.TemporaryDirectory() as out:
        command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--scenario", "wall", "--no-status",
                   "--scenario-set", "drivers=[]", "--scenario-set", f"world.clock_rate_hz={rate_hz}",
                   "--duration", str(seconds + 30), "--out", out, "--set", "dds.enabled=false",
                   "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "--set", "foxglove.port=0",
                   "--set", "web.port=0"]
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                cwd=ROOT)
        running = threading.Event()
        lines: list[str] = []

        def read() -> None:  # -v: the log says when the daemon runs
            assert proc.stderr is not None
            for line in proc.stderr:
                lines.append(line)
                if "racecar-hw running" in line:
                    running.set()

        threading.Thread(target=read, daemon=True).start()
        car = None
        try:
            if not running.wait(120):
                raise RuntimeError("the sim did not start: " + "".join(lines[-20:]))
            if subscribe:
                from racecar_hw.client import Car  # noqa: PLC0415

                car = Car(f"tcp/127.0.0.1:{port}", use_sim_time=True)
                car.wait_clock(timeout=30)
            time.sleep(1.0)  # settle
            cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
            time.sleep(seconds)
            cpu1, t1 = _cpu_s(proc.pid), time.monotonic()
            return 100.0 * (cpu1 - cpu0) / (t1 - t0)
        finally:
            if car is not None:
                car.close()
            proc.send_signal(2)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _loop_cpu_s(seconds: float, rate_hz: float) -> float:
    """This thread's CPU time (s) running an event loop for ``seconds`` with the ``/clock``
    publisher at ``rate_hz`` (0: none) on a bus with one subscriber that skips, as a bridge with
    nobody subscribed does: the publisher's own cost, its wake-ups included."""
    import asyncio  # noqa: PLC0415

    from racecar_hw.base.bus import Bus  # noqa: PLC0415
    from racecar_hw.base.topics import CLOCK_TOPIC  # noqa: PLC0415
    from racecar_hw.sim.clock_topic import publish_clock  # noqa: PLC0415

    async def main() -> float:
        bus = Bus()
        skipped = [0]
        bus.subscribe(CLOCK_TOPIC, lambda msg: skipped.__setitem__(0, skipped[0] + 1))
        task = asyncio.ensure_future(publish_clock(bus, rate_hz)) if rate_hz else None
        t0 = time.thread_time()
        await asyncio.sleep(seconds)
        spent = time.thread_time() - t0
        if task is not None:
            task.cancel()
        return spent

    return asyncio.run(main())


def run(seconds: float = 20.0, rounds: int = 3) -> list[dict]:
    """The rows: CPU share per setting (median over the rounds) and the cost per message."""
    settings = {
        "off": lambda: _one(seconds, 0.0, False),
        "on, no subscriber": lambda: _one(seconds, RATE_HZ, False),
        "on, subscribed": lambda: _one(seconds, RATE_HZ, True),
    }
    results = interleaved(settings, rounds)
    med = {label: float(np.median(values)) for label, values in results.items()}
    rows = [{"name": f"sim process CPU, /clock {label}", "value": med[label], "unit": "% of a core",
             "target": None} for label in settings]
    for label in ("on, no subscriber", "on, subscribed"):
        per_msg_us = (med[label] - med["off"]) / 100.0 / RATE_HZ * 1e6
        rows.append({"name": f"CPU per /clock message, {label}", "value": per_msg_us, "unit": "us",
                     "target": None})
    # the publisher alone, in this process: one loop thread, no other timers to share wake-ups with
    alone = interleaved({"off": lambda: _loop_cpu_s(10.0, 0.0), "on": lambda: _loop_cpu_s(10.0, RATE_HZ)}, 4)
    per_tick_us = (np.median(alone["on"]) - np.median(alone["off"])) / (10.0 * RATE_HZ) * 1e6
    rows.append({"name": "event-loop CPU per /clock tick, publisher alone", "value": float(per_tick_us),
                 "unit": "us", "target": None})
    if os.environ.get("BENCH_VERBOSE"):
        print("publisher alone, CPU s per 10 s: " + ", ".join(
            f"{label} {np.median(v):.4f}" for label, v in alone.items()))
        for label, values in results.items():
            print(f"{label}: " + ", ".join(f"{v:.2f}" for v in values))
    return rows


if __name__ == "__main__":
    args = [float(a) for a in sys.argv[1:]]
    print_rows(run(*(args[:1] or [20.0]), *(int(a) for a in args[1:2])))
