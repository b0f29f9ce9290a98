"""Helpers for the Zenoh tests: free ports, ``racecar-hw sim`` in a process of its own, its report."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A TCP port nobody listens on now (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


@contextlib.asynccontextmanager
async def bridge_with_peer(bus: Any) -> AsyncIterator[tuple[Any, Any]]:
    """A :class:`~racecar_hw.net.zenoh_bridge.ZenohBridge` with the daemon's topic table, listening
    on a free loopback port with its loop bound to ``bus``, and a client Zenoh session connected
    to it: ``(bridge, peer)``, both closed on leaving."""
    import zenoh  # noqa: PLC0415

    from mux.params import MuxParams  # noqa: PLC0415
    from racecar_hw.net.topics import topic_table  # noqa: PLC0415
    from racecar_hw.net.zenoh_bridge import ZenohBridge  # noqa: PLC0415
    from racecar_hw.net.zenoh_config import ZenohParams, session_config  # noqa: PLC0415
    from safety.params import SafetyParams  # noqa: PLC0415

    port = free_port()
    bridge = ZenohBridge(bus, ZenohParams(listen=[endpoint(port)]), topic_table(MuxParams(), SafetyParams()))
    loop = asyncio.get_running_loop()
    bus.bind_loop(loop)
    await loop.run_in_executor(None, bridge.open, loop)
    peer = zenoh.open(session_config("client", [], [endpoint(port)]))
    try:
        yield bridge, peer
    finally:
        peer.close()
        await loop.run_in_executor(None, bridge.close)


@dataclass
class SimProcess:
    """``racecar-hw sim`` running in a subprocess; :meth:`report` waits for it and reads the report."""

    proc: subprocess.Popen
    out: Path
    started: float

    def report(self, timeout: float = 120) -> dict:
        try:
            _, err = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
            raise AssertionError(f"sim did not finish: {err[-3000:]}") from None
        assert self.proc.returncode == 0, err[-3000:]
        self.log = err
        return json.loads((self.out / "report.json").read_text())

    def interrupt(self, timeout: float = 120) -> dict:
        """End the run now as Ctrl-C does (the report is written, marked interrupted) and read it."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        return self.report(timeout)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


def start_sim(out: Path, listen_port: int | None, *sets: str, scenario: str = "wall",
              scenario_sets: tuple[str, ...] = ("drivers=[]",), duration: float = 12.0,
              preexec_fn: Callable[[], None] | None = None, speed: float | None = None) -> SimProcess:
    """Start ``racecar-hw sim`` with its Zenoh bridge listening on ``listen_port`` (None: ``sets`` say).

    The live view and the status page listen on free ports (never the defaults 8765 and 8080).
    ``speed``: lockstep paced at that many times real time (``--speed``), every interface still on;
    None: real time.
    """
    out.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--no-plot", "--scenario", scenario,
               "--duration", str(duration), "--no-status", "--out", str(out),
               "--report", str(out / "report.json"), "--set", "foxglove.port=0", "--set", "web.port=0"]
    if speed is not None:
        command += ["--speed", f"{speed:g}"]
    for item in scenario_sets:
        command += ["--scenario-set", item]
    if listen_port is not None:
        command += ["--set", f'zenoh.listen=["{endpoint(listen_port)}"]']
    for item in sets:
        command += ["--set", item]
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            preexec_fn=preexec_fn)
    return SimProcess(proc, out, time.monotonic())


def wait_standing(car: Any, timeout: float = 60.0) -> None:
    """Until three odometry messages in a row that ``car`` (a :class:`racecar_hw.client.Car`)
    receives after the call say the car stands still (50 Hz odometry: 60 ms)."""
    deadline = time.monotonic() + timeout
    still = 0
    while still < 3:
        if time.monotonic() > deadline:
            raise AssertionError(f"the car still moves after {timeout} s: {car.odom}")
        still = still + 1 if abs(car.next_odom(timeout=30).speed) < 0.005 else 0


def wait_until_stopped(port: int, timeout: float = 60.0, **car: Any) -> None:
    """:func:`wait_standing` through a client session of its own to the sim's Zenoh port (``car``:
    more for :class:`racecar_hw.client.Car`, such as ``profile`` or ``ros_distro``).

    A test whose driver has finished ends the sim then (SIGINT: :meth:`SimProcess.interrupt`) instead
    of waiting out a fixed ``--duration``; its report's final speed is zero however late a loaded
    machine ran the mux's timeout and the braking. The session only listens: it sends nothing that
    the mux would see as a source."""
    from racecar_hw.client import Car  # noqa: PLC0415 - the client (and Zenoh) only where used

    with Car(endpoint(port), **car) as watcher:
        wait_standing(watcher, timeout)


def switches(report: dict) -> list[str]:
    """The mux's sources in the order they became active."""
    return [source for _, source in report["mux_switches"]]


def switch_times(report: dict, source: str) -> list[float]:
    """World times (s) at which ``source`` became active."""
    return [t for t, s in report["mux_switches"] if s == source]
