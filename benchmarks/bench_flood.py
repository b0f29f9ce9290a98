"""Inbound floods against ``racecar-hw sim``: missed control ticks and e-stop latency, and what the
network inbox costs without a flood, in one invocation.

(a) **Floods.** For each rate (1,000/s, 10,000/s, and as fast as one Python process can send), a
    fresh ``racecar-hw sim`` (wall scenario, no driver: the flood drives the car at 0.25 m/s) with
    its Zenoh bridge on a free loopback port; one process (tests/zenoh_flood.py, normal priority)
    floods ``/cmd_vel`` for 5 s; 3 s into it a second Zenoh session sends ``/estop``. Measured: the
    rate the flooder reached, what the daemon's inbox received and handed over, the control ticks
    and missed ticks within the flood (from the daemon's ``/diagnostics``), the time from the
    e-stop's send to its latch and to the brake read by the fake VESC (from the sim's log), and the
    sim process's CPU share during the flood (daemon, fake devices and world together).
(b) **No flood.** A well-behaved client (the same script at 50 messages/s) drives the car for 10 s;
    the scan-to-command p50/p99 (the daemon's own summary at exit) and the sim process's CPU share,
    with this tree's inbox and with the old path (``main``'s per-message ``call_soon_threadsafe``,
    from ``git archive`` of the ref given as OLD, default ``main``), alternating, ``ROUNDS`` times
    (default 2); each row is the median over the rounds.

``python benchmarks/bench_flood.py [ROUNDS [OLD]]``; prints the table and the rows as JSON.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from table import print_rows

ROOT = Path(__file__).resolve().parents[1]
FLOOD = ROOT / "tests" / "zenoh_flood.py"
RATES = (1000, 10_000, 0)
FLOOD_S = 5.0
ESTOP_AT_S = 3.0
CALM_S = 10.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Sim:
    """``racecar-hw sim`` from ``src`` (None: this tree) on ``port``, its log kept as it comes."""

    def __init__(self, port: int, out: Path, src: Path | None = None) -> None:
        env = dict(os.environ)
        if src is not None:
            env["PYTHONPATH"] = str(src)
        command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--scenario", "wall",
                   "--scenario-set", "drivers=[]", "--duration", "600", "--no-status", "--out", str(out),
                   "--report", str(out / "report.json"),
                   "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]']
        self.proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     text=True, cwd=src or ROOT, env=env)
        self.out = out
        self.log: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.append(line)

    def cpu_s(self) -> float:
        """The process's CPU time so far (s)."""
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> dict:
        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(120)
        self._reader.join(10)
        return json.loads((self.out / "report.json").read_text())


def _session(port: int):  # noqa: ANN202 - a zenoh.Session
    import zenoh  # noqa: PLC0415

    from racecar_hw.net.zenoh_config import session_config  # noqa: PLC0415

    deadline = time.monotonic() + 120
    while True:
        try:
            return zenoh.open(session_config("client", [], [f"tcp/127.0.0.1:{port}"]))
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def _key(topic: str, cls: type) -> str:
    from racecar_hw.net import rmw  # noqa: PLC0415

    return rmw.topic_key(0, topic, cls.ROS_TYPE, rmw.type_hash(cls.ROS_TYPE))


def _flooder(port: int, rate: int, seconds: float) -> subprocess.Popen:
    command = [sys.executable, str(FLOOD), str(port), "--rate", str(rate), "--seconds", str(seconds),
               "--speed", "0.25"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "flooding"
    return proc


def flood_case(rate: int) -> dict:
    """One flood at ``rate`` (0: as fast as it can) against a fresh sim; the measurements."""
    from racecar_hw.base.messages import Bool, DiagnosticArray  # noqa: PLC0415
    from racecar_hw.net import rmw  # noqa: PLC0415
    from racecar_hw.rosmsg.typestore import ros2_types  # noqa: PLC0415

    types = ros2_types()
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        sim = _Sim(port, Path(tmp))
        session = _session(port)
        control: list[tuple[float, int, int]] = []
        inbox: dict[str, str] = {}

        def on_diag(sample) -> None:  # noqa: ANN001
            for status in types.deserialize(sample.payload.to_bytes(), DiagnosticArray).status:
                values = {kv.key: kv.value for kv in status.values}
                if status.name == "racecar_hw: control loop":
                    control.append((time.monotonic(), int(values["ticks"]), int(values["missed ticks"])))
                elif status.name == "racecar_hw: network inbox":
                    inbox.update(values)

        sub = session.declare_subscriber(_key("/diagnostics", DiagnosticArray), on_diag)
        estop = session.declare_publisher(_key("/estop", Bool))
        while not control:
            time.sleep(0.1)
        calm_from = time.monotonic()
        time.sleep(FLOOD_S)  # the same sim without a flood: what the machine itself costs the loop
        calm_to = time.monotonic()
        flood = _flooder(port, rate, FLOOD_S)
        started, cpu0 = time.monotonic(), sim.cpu_s()
        time.sleep(ESTOP_AT_S)
        sent_wall = time.time()
        attachment = rmw.encode_attachment(1, time.time_ns(), bytes(16))
        estop.put(types.serialize(Bool(True)), attachment=attachment)
        assert flood.stdout is not None
        result = json.loads(flood.stdout.readline())
        ended, cpu1 = time.monotonic(), sim.cpu_s()
        flood.wait(30)
        time.sleep(1.0)
        sub.undeclare()
        session.close()
        sim.stop()
    first = next(c for c in control if c[0] > started)
    last = [c for c in control if c[0] <= ended][-1]
    calm0 = next(c for c in control if c[0] > calm_from)
    calm1 = [c for c in control if c[0] <= calm_to][-1]
    text = "".join(sim.log)
    m = re.search(r"e-stop from network topic /estop \(zenoh\) at wall ([\d.]+); fake VESC: brake "
                  r"[^\n]* at wall ([\d.]+) \(\+[\d.]+ ms\), ([^\n]*)", text)
    counts = inbox.get("/cmd_vel", "")
    received = int(re.match(r"received (\d+)", counts).group(1)) if counts else 0
    handed = int(re.search(r"handed over (\d+)", counts).group(1)) if counts else 0
    return {"rate": result["rate"], "received": received, "handed_over": handed,
            "ticks": last[1] - first[1], "missed": last[2] - first[2],
            "calm_ticks": calm1[1] - calm0[1], "calm_missed": calm1[2] - calm0[2],
            "latch_ms": 1e3 * (float(m.group(1)) - sent_wall) if m else float("nan"),
            "brake_ms": 1e3 * (float(m.group(2)) - sent_wall) if m else float("nan"),
            "brake_first": bool(m and m.group(3).startswith("the first")),
            "cpu_pct": 100 * (cpu1 - cpu0) / (ended - started)}


def calm_case(src: Path | None) -> dict:
    """A 50/s client for ``CALM_S`` against a sim from ``src``: scan-to-command p50/p99, CPU share."""
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        sim = _Sim(port, Path(tmp), src)
        _session(port).close()  # the bridge is up
        time.sleep(2.0)
        client = _flooder(port, 50, CALM_S)
        started, cpu0 = time.monotonic(), sim.cpu_s()
        assert client.stdout is not None
        client.stdout.readline()
        ended, cpu1 = time.monotonic(), sim.cpu_s()
        client.wait(30)
        report = sim.stop()
    m = re.search(r"scan-to-command latency p50=([\d.]+) ms p99=([\d.]+) ms", "".join(sim.log))
    nan = float("nan")
    return {"p50": float(m.group(1)) if m else nan, "p99": float(m.group(2)) if m else nan,
            "cpu_pct": 100 * (cpu1 - cpu0) / (ended - started),
            "missed": report["control"]["missed_ticks"], "ticks": report["control"]["ticks"]}


def run(rounds: int = 2, old: str = "main") -> list[dict]:
    rows: list[dict] = []
    for rate in RATES:
        r = flood_case(rate)
        name = f"flood {r['rate']}/s" if rate == 0 else f"flood {rate}/s"
        if rate == 0:
            name = f"flood at max ({r['rate']}/s sent)"
        share = 100 * r["missed"] / max(1, r["ticks"] + r["missed"])
        calm = 100 * r["calm_missed"] / max(1, r["calm_ticks"] + r["calm_missed"])
        rows += [
            {"name": f"{name}: received by the daemon", "value": r["received"], "unit": "msgs"},
            {"name": f"{name}: handed to the loop", "value": r["handed_over"], "unit": "msgs"},
            {"name": f"{name}: missed ticks", "value": r["missed"], "unit": f"of {r['ticks'] + r['missed']}",
             "target": None},
            {"name": f"{name}: missed ticks share", "value": share, "unit": "%", "target": 1.0},
            {"name": f"{name}: same sim, 5 s before: missed", "value": calm, "unit": "%", "target": None},
            {"name": f"{name}: e-stop send to latch", "value": r["latch_ms"], "unit": "ms", "target": 100.0},
            {"name": f"{name}: e-stop send to brake", "value": r["brake_ms"], "unit": "ms", "target": 100.0},
            {"name": f"{name}: brake was the next motor command", "value": str(r["brake_first"]), "unit": "",
             "target": None},
            {"name": f"{name}: sim process CPU", "value": r["cpu_pct"], "unit": "% core", "target": None},
        ]
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "old"
        src.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", old], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive.stdout, check=True)
        results: dict[str, list[dict]] = {"inbox": [], "old": []}
        for k in range(rounds):
            order = [("inbox", None), ("old", src)] if k % 2 == 0 else [("old", src), ("inbox", None)]
            for label, tree in order:
                results[label].append(calm_case(tree))
    for label in ("old", "inbox"):
        rs = results[label]
        what = "this tree's inbox" if label == "inbox" else f"old path ({old})"
        rows += [
            {"name": f"50/s client, {what}: scan-to-command p50", "unit": "ms", "target": None,
             "value": statistics.median(r["p50"] for r in rs)},
            {"name": f"50/s client, {what}: scan-to-command p99", "unit": "ms", "target": None,
             "value": statistics.median(r["p99"] for r in rs)},
            {"name": f"50/s client, {what}: sim process CPU", "unit": "% core", "target": None,
             "value": statistics.median(r["cpu_pct"] for r in rs)},
        ]
    return rows


def main() -> None:
    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    old = sys.argv[2] if len(sys.argv) > 2 else "main"
    rows = run(rounds, old)
    print_rows(rows)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
