"""Sockets cannot exhaust the daemon: floods of half-open connections against the status page and the
Foxglove relay, on ``racecar-hw sim`` run with its open-file limit lowered to 1,024.

The sim drives the car in a circle (a constant command on nav_0) on the loopback: fake VESC on a pty,
fake lidar, real daemon. This test opens 1,100 TCP connections to the status page, sends each a request
head that never ends and keeps them open for 15 s; then the same against the relay's port for 8 s.
Meanwhile a new browser (an HTTP GET of the page, then a Foxglove WebSocket client) must be served
within 1 s each time it tries, the daemon's open files stay far below the limit, and the log grows by
a few summary lines, and the control loop misses at most 1 % of its ticks during each flood (its
counters read from the page's ``/api/state`` before and after). At the end the sim's report (written on
SIGTERM) must show the lidar stream uninterrupted: no stale-scan or no-scan intervention, no reconnect.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import os
import queue
import resource
import threading
import time
import urllib.request
from pathlib import Path

import pytest
from conftest import ahead_of_other_load
from live_sim import SimProcess
from websockets.sync.client import connect

#: The daemon's open-file limit in this test (soft and hard), and the half-open connections per flood.
FILE_LIMIT = 1024
CONNECTIONS = 1100
WEB_FLOOD_S = 15.0
RELAY_FLOOD_S = 8.0
#: The quiet window before the floods: what the loaded machine alone costs the control loop, printed
#: beside the floods' counts to read a failure by (not asserted on). 150 ticks at 50 Hz are enough.
QUIET_S = 3.0
#: A new browser must be served within this (s), as the issue asks.
SERVE_WITHIN_S = 1.0
PROBE_EVERY_S = 2.0
#: The log may grow by fewer lines than this during one flood.
MAX_LOG_LINES = 100
PARTIAL_HEAD = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUser-Agent: slow\r\n"  # never finished


def _lower_file_limit() -> None:  # in the sim's process, before it starts
    resource.setrlimit(resource.RLIMIT_NOFILE, (FILE_LIMIT, FILE_LIMIT))
    # The tests share a small machine: what is measured is the flood's effect on the daemon (on a car
    # the attacker's CPU is elsewhere), not other processes', so the daemon runs ahead of them when
    # this test may arrange it; a quiet window before the floods shows what the machine alone costs.
    ahead_of_other_load()


@pytest.fixture
def many_files():
    """This process opens 1,100 sockets at once (and the sim's pipes): raise its own soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = CONNECTIONS + 1000
    if hard != resource.RLIM_INFINITY and hard < need:
        pytest.skip(f"the hard open-file limit {hard} is below the {need} this test needs")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, need), hard))
    yield
    resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


class Flood:
    """``count`` connections to ``port``, each sending ``head`` and then holding on until ``hold_s``
    after the start (or until the server closes it). Runs in a process of its own (forked), with its
    own event loop: in this one, its 1,100 connections' callbacks would hold the interpreter's lock
    that the probes of a new browser wait for, and the probes would measure this test, not the
    daemon."""

    def __init__(self, port: int, count: int, hold_s: float, head: bytes = PARTIAL_HEAD) -> None:
        self.port, self.count, self.hold_s, self.head = port, count, hold_s, head
        self.opened = self.failed = self.closed_by_server = self.held = 0
        context = multiprocessing.get_context("fork")
        self.all_opened = context.Event()
        self._counts = context.Queue()
        self._process = context.Process(target=self._flood, daemon=True)

    def start(self) -> Flood:
        self._process.start()
        return self

    def join(self) -> None:
        try:
            self.opened, self.failed, self.closed_by_server, self.held = self._counts.get(
                timeout=self.hold_s + 60)
        except queue.Empty:
            raise AssertionError(f"the flood did not end (exit code {self._process.exitcode})") from None
        finally:
            self._process.join(30)
            if self._process.is_alive():
                self._process.kill()

    def _flood(self) -> None:  # in the forked process
        asyncio.run(self._run())
        self._counts.put((self.opened, self.failed, self.closed_by_server, self.held))

    async def _run(self) -> None:
        end = time.monotonic() + self.hold_s
        connecting = asyncio.Semaphore(200)
        tried = 0

        async def one() -> None:
            nonlocal tried
            try:
                async with connecting:
                    reader, writer = await asyncio.wait_for(
                        asyncio.open_connection("127.0.0.1", self.port), 30)
                    writer.write(self.head)
            except (OSError, TimeoutError):
                self.failed += 1
                return
            finally:
                tried += 1
                if tried == self.count:
                    self.all_opened.set()
            self.opened += 1
            try:
                async with asyncio.timeout(max(0.0, end - time.monotonic())):
                    while await reader.read(4096):
                        pass
                self.closed_by_server += 1
            except TimeoutError:
                self.held += 1
            except OSError:
                self.closed_by_server += 1
            finally:
                writer.transport.abort()

        await asyncio.gather(*(one() for _ in range(self.count)))


class FileWatch:
    """Samples how many files the process ``pid`` has open, every 50 ms, until stopped."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.most = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            try:
                self.most = max(self.most, len(os.listdir(f"/proc/{self.pid}/fd")))
            except OSError:
                return

    def stop(self) -> int:
        self._stop.set()
        self._thread.join(5)
        return self.most


def probe_page(port: int) -> float:
    """Seconds a new browser waits for the whole status page."""
    start = time.monotonic()
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as res:
        body = res.read()
    elapsed = time.monotonic() - start
    assert res.status == 200 and b"E-STOP" in body
    return elapsed


def probe_foxglove(port: int) -> float:
    """Seconds a new Foxglove client waits for the WebSocket handshake and the server's hello."""
    start = time.monotonic()
    with connect(f"ws://127.0.0.1:{port}/", subprotocols=["foxglove.sdk.v1"], open_timeout=10,
                 max_size=None) as ws:
        info = json.loads(ws.recv(timeout=10))
        elapsed = time.monotonic() - start
    assert info["op"] == "serverInfo"
    return elapsed


def page_state(port: int) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=10) as res:
        return json.loads(res.read())


def wait_until_driving(port: int, timeout_s: float = 60.0) -> None:
    """Until the page says the car drives (the floods must meet a moving car)."""
    deadline = time.monotonic() + timeout_s
    while (state := page_state(port))["speed"]["output"] is None or state["speed"]["output"] < 0.5:
        assert time.monotonic() < deadline, state
        time.sleep(0.2)


def cpu_s(pid: int) -> float:
    """CPU time (user + system, s) the process ``pid`` used so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def quiet_window(sim: SimProcess, web_port: int, seconds: float) -> dict:
    """The control loop's ticks and the daemon's CPU over ``seconds`` without a flood, to compare."""
    before, cpu = page_state(web_port)["control"], cpu_s(sim.proc.pid)
    time.sleep(seconds)
    after = page_state(web_port)["control"]
    return {"ticks": after["ticks"] - before["ticks"],
            "missed_ticks": after["missed_ticks"] - before["missed_ticks"],
            "cpu_s": round(cpu_s(sim.proc.pid) - cpu, 3)}


def flood_while_probing(sim: SimProcess, web_port: int, port: int, seconds: float, probe) -> dict:
    """Flood ``port`` for ``seconds``; probe a new client every PROBE_EVERY_S once the connections are
    open. What happened, for the assertions (and printed with a failure); the control loop's ticks
    are read from the status page on ``web_port`` before and after."""
    before, cpu = page_state(web_port)["control"], cpu_s(sim.proc.pid)
    lines_before = len(sim.lines)
    files = FileWatch(sim.proc.pid)
    flood = Flood(port, CONNECTIONS, seconds).start()
    assert flood.all_opened.wait(60), "the flood could not even try every connection"
    waits = []
    end = time.monotonic() + seconds
    while time.monotonic() < end - 0.5:
        waits.append(probe(port))
        time.sleep(PROBE_EVERY_S)
    flood.join()
    most_files = files.stop()
    log = sim.lines[lines_before:]
    after = page_state(web_port)["control"]
    out = {"cpu_s": round(cpu_s(sim.proc.pid) - cpu, 3), "ticks": after["ticks"] - before["ticks"],
           "missed_ticks": after["missed_ticks"] - before["missed_ticks"], "opened": flood.opened,
           "failed": flood.failed, "closed_by_server": flood.closed_by_server,
           "held_to_the_end": flood.held, "probe_waits_s": [round(w, 3) for w in waits],
           "most_open_files": most_files, "log_lines": len(log)}
    print(json.dumps(out), *log, sep="\n")
    return out | {"log": log}


@pytest.mark.slow
@pytest.mark.alone  # it measures the pace of the machine (docs/tests.md, "Alone")
def test_half_open_floods_leave_the_lidar_the_control_loop_and_new_clients_alone(tmp_path: Path,
                                                                                 many_files):
    out = tmp_path / "sim"
    sim = SimProcess(["--scenario", "wall", "--scenario-set",
                      "drivers=[{type: constant, input: nav_0, speed_mps: 1.0, steering_rad: 0.25}]",
                      "--duration", "300", "--set", "web.port=0", "--set", "foxglove.port=0",
                      "--out", str(out)], preexec_fn=_lower_file_limit)
    try:
        sim.wait_for("racecar-hw running")
        assert sim.wait_for(r"open files: limit (\d+)").group(1) == str(FILE_LIMIT)
        web_port, fox_port = sim.port("web"), sim.port("foxglove")
        wait_until_driving(web_port)

        quiet = quiet_window(sim, web_port, QUIET_S)
        print("quiet", json.dumps(quiet))
        web = flood_while_probing(sim, web_port, web_port, WEB_FLOOD_S, probe_page)
        relay = flood_while_probing(sim, web_port, fox_port, RELAY_FLOOD_S, probe_foxglove)
        assert sim.proc.poll() is None, "the sim ended during the floods"
    finally:
        sim.stop()

    for flood in (web, relay):
        assert flood["opened"] >= CONNECTIONS // 2, flood  # the floods reached the daemon
        assert flood["closed_by_server"] >= flood["opened"] - 40, flood  # and it let go of them
        assert len(flood["probe_waits_s"]) >= 3 and max(flood["probe_waits_s"]) < SERVE_WITHIN_S, flood
        assert flood["most_open_files"] < FILE_LIMIT // 2, flood  # room left for the devices
        assert flood["log_lines"] < MAX_LOG_LINES, flood
        # the control loop kept its rate through the flood
        assert flood["ticks"] > 0 and flood["missed_ticks"] <= 0.01 * flood["ticks"], flood
        assert not [line for line in flood["log"] if "Traceback" in line or "Too many open files" in line]

    report = json.loads((out / "wall.json").read_text())  # the sim names its report after the scenario
    control, lidar = report["control"], report["lidar"]
    print(json.dumps({k: report[k] for k in ("control", "lidar", "safety_interventions_by_reason",
                                             "distance_m")}))
    assert report["distance_m"] > 10.0  # the car drove through both floods
    assert lidar["reconnects"] == 0
    by_reason = report["safety_interventions_by_reason"]
    assert "stale_scan" not in by_reason and "no_scan" not in by_reason, by_reason
    assert control["ticks"] >= web["ticks"] + relay["ticks"]
