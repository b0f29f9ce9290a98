"""The MAVLink ground station under a flood (issue 24): ``racecar-hw sim`` in this process with the
MAVLink link signed, a pymavlink ground station driving the car back and forth (heartbeats at
2 Hz, MANUAL_CONTROL at 10 Hz), first for ``SECONDS`` alone, then for ``SECONDS`` while another
process (tests/mavlink_flood.py) sends forged datagrams to the link's port as fast as it can, and
for ``SECONDS`` while the same flood goes to a port nobody reads (a control: what the flooding
process's own CPU and the kernel's loopback work cost this process on this machine); these two
twice each, in the order A B B A, each kind's windows pooled.

For each window: the control ticks missed (of the mux's 50 Hz), the longest gap between two of the
station's heartbeats the link accepted (the station sends every 0.5 s; the link drops the station
after 2 s), the station's time-outs, the scan-to-command p99, the CPU time of this process (daemon,
sim and station: the flood's process is not counted), and the datagrams the flood sent and the
link read (and how often a socket had to rest).

Run ``python benchmarks/bench_mavlink.py [SECONDS]``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from table import print_rows

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from racecar_hw.base.clock import NS_PER_S  # noqa: E402
from racecar_hw.sim.loopback import Loopback  # noqa: E402
from racecar_hw.sim.scenario import load_scenario  # noqa: E402
from racecar_hw.teleop.mavlink_gcs import write_signing_key  # noqa: E402

FLOOD = Path(__file__).resolve().parents[1] / "tests" / "mavlink_flood.py"
mav = mavutil.mavlink


class _Station:
    """A signed pymavlink ground station on an ephemeral loopback port."""

    def __init__(self, key: bytes) -> None:
        self.conn: Any = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                                    source_component=190)
        self.conn.setup_signing(key, sign_outgoing=True)
        self.z = 0

    @property
    def port(self) -> int:
        return int(self.conn.port.getsockname()[1])

    def heard_from_car(self) -> bool:
        while (msg := self.conn.recv_msg()) is not None:
            if msg.get_type() == "HEARTBEAT" and msg.type == mav.MAV_TYPE_GROUND_ROVER:
                return True
        return False

    async def beat(self) -> None:
        while True:
            self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            await asyncio.sleep(0.5)

    async def drive(self) -> None:
        while True:
            self.conn.mav.manual_control_send(1, 0, 0, self.z, 0, 0)
            await asyncio.sleep(0.1)


def _p99(values: list[int]) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] / 1e6


async def _window(lb: Loopback, station: _Station, seconds: float, port: int | None) -> dict[str, Any]:
    """Drive for ``seconds``, with the flood at ``port`` (None: no flood)."""
    daemon = lb.daemon
    assert daemon is not None and daemon.mavlink is not None
    link = daemon.mavlink
    proc = None
    if port is not None:
        proc = await asyncio.create_subprocess_exec(sys.executable, str(FLOOD), str(port), str(seconds),
                                                    stdout=asyncio.subprocess.PIPE)
        assert proc.stdout is not None
        await asyncio.wait_for(proc.stdout.readline(), 60)  # "ready"
    stats = daemon.stats
    ticks, missed = stats.ticks, stats.missed_ticks
    timeouts, datagrams = link.counters["gcs_timeouts"], link.counters["datagrams"]
    latencies = len(stats.scan_to_command_ns)
    rests = link.counters["drain_rests"]
    link.heartbeat_gap_max_ns = 0
    loop = asyncio.get_running_loop()
    cpu0, wall0 = time.process_time(), time.monotonic()
    end = loop.time() + seconds
    forward = True
    while loop.time() < end:  # back and forth, 2 s each way, at 1 m/s
        station.z = 500 if forward else -500
        forward = not forward
        await asyncio.sleep(min(2.0, max(0.0, end - loop.time())))
    station.z = 0
    cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - wall0)
    out: dict[str, Any] = {
        "cpu_pct": cpu, "rests": link.counters["drain_rests"] - rests,
        "ticks": stats.ticks - ticks, "missed": stats.missed_ticks - missed,
        "gap_s": link.heartbeat_gap_max_ns / NS_PER_S, "timeouts": link.counters["gcs_timeouts"] - timeouts,
        "read": link.counters["datagrams"] - datagrams,
        "latencies": list(stats.scan_to_command_ns)[latencies:], "sent": 0, "flood_s": seconds,
        "seconds": seconds}
    if proc is not None:
        stdout, _ = await asyncio.wait_for(proc.communicate(), 60)
        report = json.loads(stdout.decode().strip().splitlines()[-1])
        out["sent"], out["flood_s"] = report["sent"], report["seconds"]
    return out


def _pooled(windows: list[dict[str, Any]]) -> dict[str, Any]:
    """Windows of one kind as one: counts added, the worst gap, CPU averaged, p99 over them all."""
    out = {key: sum(w[key] for w in windows)
           for key in ("rests", "ticks", "missed", "timeouts", "read", "sent", "flood_s", "seconds")}
    out["gap_s"] = max(w["gap_s"] for w in windows)
    out["cpu_pct"] = sum(w["cpu_pct"] for w in windows) / len(windows)
    out["p99_ms"] = _p99([v for w in windows for v in w["latencies"]])
    return out


def measure(seconds: float = 10.0) -> dict[str, dict[str, Any]]:
    """The calm window, then the flood at a port nobody reads and at the link in the order A B B A
    (so a load that grows or shrinks during the run falls on both alike), each kind pooled."""
    with tempfile.TemporaryDirectory() as tmp:
        key_file = Path(tmp) / "mavlink.key"
        station = _Station(write_signing_key(key_file))
        scenario = load_scenario("wall", ["drivers=[]", f"duration_s={10 * seconds + 60}"])
        overrides = ["mavlink.enabled=true", "mavlink.bind_port=0",
                     f"mavlink.gcs_address=127.0.0.1:{station.port}", f"mavlink.signing_key_file={key_file}",
                     "zenoh.enabled=false", "foxglove.enabled=false", "web.enabled=false"]
        windows: dict[str, list[dict[str, Any]]] = {"calm": [], "elsewhere": [], "flood": []}

        async def script(lb: Loopback) -> None:
            tasks = [asyncio.ensure_future(station.beat()), asyncio.ensure_future(station.drive())]
            try:
                while not station.heard_from_car():
                    await asyncio.sleep(0.05)
                assert lb.daemon is not None
                while not (lb.daemon.lidar is not None and lb.daemon.lidar.stats.scans > 0):
                    await asyncio.sleep(0.05)
                await asyncio.sleep(1.0)
                assert lb.daemon.mavlink is not None
                windows["calm"].append(await _window(lb, station, seconds, None))
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as nobody:
                    nobody.bind(("127.0.0.1", 0))
                    ports = {"elsewhere": nobody.getsockname()[1], "flood": lb.daemon.mavlink.port}
                    for kind in ("elsewhere", "flood", "flood", "elsewhere"):
                        windows[kind].append(await _window(lb, station, seconds, ports[kind]))
            finally:
                for task in tasks:
                    task.cancel()
                lb.request_stop()

        def setup(lb: Loopback) -> None:
            assert lb.daemon is not None
            lb.daemon.add_task(script(lb))

        asyncio.run(Loopback(scenario, overrides=overrides, setup=setup).run())
        return {kind: _pooled(ws) for kind, ws in windows.items()}


def run(seconds: float = 10.0) -> list[dict]:
    """Rows: missed ticks, heartbeat gaps, time-outs, scan-to-command p99, calm and flooded; the
    flood's rate and what the link read of it."""
    r = measure(seconds)
    flood = r["flood"]
    rows = [
        {"name": "mavlink_flood_sent_per_s", "value": flood["sent"] / flood["flood_s"], "unit": "datagrams/s",
         "target": None},
        {"name": "mavlink_flood_read_per_s", "value": flood["read"] / flood["seconds"], "unit": "datagrams/s",
         "target": None},
    ]
    for name, w in r.items():
        missed_pct = 100.0 * w["missed"] / max(1, w["ticks"] + w["missed"])
        rows += [
            {"name": f"mavlink_{name}_missed_ticks_pct", "value": missed_pct, "unit": "%", "target": 1.0},
            {"name": f"mavlink_{name}_heartbeat_gap_max", "value": w["gap_s"], "unit": "s", "target": 2.0},
            {"name": f"mavlink_{name}_gcs_timeouts", "value": w["timeouts"], "unit": "", "target": 0},
            {"name": f"mavlink_{name}_scan_to_command_p99", "value": w["p99_ms"], "unit": "ms",
             "target": None},
            {"name": f"mavlink_{name}_process_cpu", "value": w["cpu_pct"], "unit": "% of a core",
             "target": None},
        ]
    rows.append({"name": "mavlink_flood_socket_rests", "value": flood["rests"], "unit": "", "target": None})
    return rows


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 10.0
    print_rows(run(seconds))


if __name__ == "__main__":
    main()
