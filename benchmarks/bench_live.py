"""What the live view costs: the daemon at nominal load with Foxglove and the status page off, then on
with one client each, in one run (bench_daemon.py's harness: UST-10LX at 40 Hz, VESC at 50 Hz, the
figure-8 driver, the recorder writing MCAP).

The Foxglove client is a raw WebSocket client (``foxglove.sdk.v1``) that subscribes to every channel
the server advertises (more than any layout shows); the page client opens the status page's
WebSocket as a browser does and takes its pushes (10 Hz, scan and band included). Both run in a
process of their own, as a viewer on a laptop would: their CPU time is not the daemon's, and their
Python work does not delay this process's fakes, which time the round trip.

A third configuration has both on with no client (the shipped default: they listen, but send nothing).
The configurations run interleaved ``ROUNDS`` times (default 3), each leading a round in turn
(:mod:`rounds`), and each row is the median over the rounds, so a burst of load from elsewhere on a
shared machine does not land on one side only. The p99 of a run is dominated by the time the loop
thread spends off the CPU when the machine is shared; the daemon's CPU time in the scan path (its
p99) is the part the live view can add. The round trip (fake lidar to fake VESC) is also given as
one p99 over every scan of every round of a setting (:func:`rounds.pooled_p99`).

Run ``python benchmarks/bench_live.py [SECONDS] [ROUNDS]``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import bench_daemon
from rounds import interleaved, pooled_p99
from table import print_rows

ADDED_P99_TARGET = 0.05  # ms
OFF = {"foxglove": {"enabled": False}, "web": {"enabled": False}}
ON = {"foxglove": {"enabled": True, "port": 0}, "web": {"enabled": True, "port": 0}}


class Clients:
    """One Foxglove client subscribed to everything and one status-page client, in a process of their own.

    As on a laptop, their Python work (taking 430 messages a second) does not share an interpreter
    with the benchmark's fakes, whose reads time the round trip.
    """

    def __init__(self, log_path: Path) -> None:
        self.log_path = log_path
        self.foxglove_messages = 0
        self.page_messages = 0
        self.channels = 0
        self.elapsed = 1e-9
        self._proc: subprocess.Popen[str] | None = None

    def __enter__(self) -> Clients:
        self._proc = subprocess.Popen([sys.executable, __file__, "--clients", str(self.log_path)],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self._proc.stdout is not None
        ready = self._proc.stdout.readline()  # the clients give up on their own within 30 s
        if ready.strip() != "ready":
            self._proc.kill()
            raise RuntimeError(f"bench clients did not connect (exit {self._proc.wait()})")
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._proc is not None
        out, _ = self._proc.communicate("", timeout=30)  # closing stdin ends them
        counts = json.loads(out.strip().splitlines()[-1])
        self.foxglove_messages, self.page_messages = counts["foxglove"], counts["page"]
        self.channels, self.elapsed = counts["channels"], max(1e-9, counts["elapsed"])


def _ports(log_path: Path) -> tuple[int, int]:
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        text = log_path.read_text()
        fox = re.search(r"foxglove: live view on ws://[^:]+:(\d+)", text)
        web = re.search(r"web: status page on http://[^:]+:(\d+)/", text)
        if fox and web:
            return int(fox.group(1)), int(web.group(1))
        time.sleep(0.1)
    raise RuntimeError("the daemon did not log its live-view ports")


async def _clients(log_path: Path) -> dict[str, float]:
    """The clients' process: connect, say "ready", count until stdin closes, return the counts."""
    from websockets.asyncio.client import connect

    fox_port, web_port = await asyncio.to_thread(_ports, log_path)
    fox = await connect(f"ws://127.0.0.1:{fox_port}/", subprotocols=["foxglove.sdk.v1"], max_size=None)
    page = await connect(f"ws://127.0.0.1:{web_port}/ws", origin=f"http://127.0.0.1:{web_port}")
    channels: list[int] = []
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and len(channels) < 10:
        frame = await asyncio.wait_for(fox.recv(), 10)
        if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
            channels += [ch["id"] for ch in json.loads(frame)["channels"]]
    await fox.send(json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i, "channelId": c} for i, c in enumerate(channels)]}))
    counts = {"foxglove": 0, "page": 0}

    async def count(name: str, ws: object) -> None:
        async for _ in ws:  # type: ignore[attr-defined]
            counts[name] += 1

    readers = [asyncio.ensure_future(count("foxglove", fox)), asyncio.ensure_future(count("page", page))]
    print("ready", flush=True)
    started = time.monotonic()
    await asyncio.to_thread(sys.stdin.read)
    elapsed = time.monotonic() - started
    for task in readers:
        task.cancel()
    await fox.close()
    await page.close()
    return {**counts, "channels": len(channels), "elapsed": elapsed}


def run(seconds: float = 20.0, rounds: int = 3) -> list[dict]:
    clients: list[Clients] = []

    @contextlib.contextmanager
    def attach(log_path: Path) -> Iterator[Clients]:
        with Clients(log_path) as c:
            clients.append(c)
            yield c

    raw = interleaved({"off": lambda: bench_daemon.run(seconds, config_extra=OFF),
                       "on": lambda: bench_daemon.run(seconds, config_extra=ON, attach=attach),
                       "idle": lambda: bench_daemon.run(seconds, config_extra=ON)}, rounds)
    off, on, idle = ([_numbers(rows) for rows in raw[label]] for label in ("off", "on", "idle"))

    def median(runs: list[dict[str, float]], key: str) -> float:
        return statistics.median(r[key] for r in runs)

    rows = []
    for key, label, unit in (("cpu", "daemon CPU share of one core", "%"),
                             ("p50", "scan to VESC command p50 (in daemon)", "ms"),
                             ("p99", "scan to VESC command p99 (in daemon)", "ms"),
                             ("cpu_p99", "  the daemon's CPU time in it, p99", "ms")):
        rows.append({"name": f"{label}, live view off", "value": median(off, key), "unit": unit,
                     "target": None})
        rows.append({"name": f"{label}, on with one client each", "value": median(on, key), "unit": unit,
                     "target": None})
        rows.append({"name": f"{label}, on with no client", "value": median(idle, key), "unit": unit,
                     "target": None})
    rows.append({"name": "p99 added by the live view", "value": median(on, "p99") - median(off, "p99"),
                 "unit": "ms", "target": ADDED_P99_TARGET})
    rows.append({"name": "  of it the daemon's CPU time on the scan path, p99",
                 "value": median(on, "cpu_p99") - median(off, "cpu_p99"), "unit": "ms", "target": None})
    for label, key in (("live view off", "off"), ("on with one client each", "on"),
                       ("on with no client", "idle")):
        rows.append({"name": f"round trip lidar to VESC, p99 of all rounds' scans, {label}",
                     "value": pooled_p99(raw[key]), "unit": "ms", "target": None})
    rows.append({"name": "round-trip p99 of all rounds added by the live view", "unit": "ms",
                 "target": ADDED_P99_TARGET, "value": pooled_p99(raw["on"]) - pooled_p99(raw["off"])})
    rows.append({"name": "CPU share added by the live view", "value": median(on, "cpu") - median(off, "cpu"),
                 "unit": "%", "target": None})
    rows.append({"name": "Foxglove messages received per second (all channels)",
                 "value": statistics.median(c.foxglove_messages / c.elapsed for c in clients),
                 "unit": "msg/s", "target": None})
    rows.append({"name": "status page pushes received per second",
                 "value": statistics.median(c.page_messages / c.elapsed for c in clients),
                 "unit": "msg/s", "target": None})
    rows.append({"name": "host: CPU time stolen by the hypervisor (median)",
                 "value": statistics.median([r["steal"] for r in off + on + idle]), "unit": "% of busy",
                 "target": None})
    return rows


def _numbers(rows: list[dict]) -> dict[str, float]:
    by_name = {row["name"]: row["value"] for row in rows}
    return {"cpu": by_name["daemon CPU share of one core"],
            "p50": by_name["scan to VESC command p50 (in daemon)"],
            "p99": by_name["scan to VESC command p99 (in daemon)"],
            "cpu_p99": by_name["  the daemon's CPU time in it, p99"],
            "steal": by_name["host: CPU time stolen by the hypervisor"]}


def main() -> None:
    if sys.argv[1:2] == ["--clients"]:
        print(json.dumps(asyncio.run(_clients(Path(sys.argv[2])))), flush=True)
        return
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 20.0
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    print_rows(run(seconds, rounds))


if __name__ == "__main__":
    main()
