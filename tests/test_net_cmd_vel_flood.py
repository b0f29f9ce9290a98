"""Acceptance: a Zenoh client flooding ``/cmd_vel`` as fast as it can does not starve the control loop,
and an e-stop from a second session still latches at once and brakes first.

``racecar-hw sim`` runs in its own process with its Zenoh bridge on a free loopback port; the flood
comes from a third process (tests/zenoh_flood.py, one Python process sending as fast as it can);
this test's own Zenoh session reads ``/diagnostics`` (the daemon's control-loop ticks and missed
ticks, the inbox's counts) and ``/odom``, and sends the e-stop. The sim's log says when the fake
VESC read the brake, and whether it was the first motor command written after the e-stop latched.

One 5-second flood must leave at least 99 % of the control ticks. The sim runs ahead of the other
tenants of the test machine (tests/conftest.py, ``ahead_of_other_load``), and the test runs while no
other test does (``alone``): another tenant of a loaded 2-core machine can starve the loop by itself,
as a calm window shows (three pytest-xdist workers did: 33 of 233 ticks missed), and what is measured is the
flood's effect (a loop that does per-message work, as before the inbox, missed 147 of 900 ticks at
5,000 messages/s). The e-stop is sent into a flood of its own at the end.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time

import pytest
import zenoh
from conftest import ahead_of_other_load
from zenoh_util import ROOT, endpoint, free_port, start_sim

from racecar_hw.base.messages import Bool, DiagnosticArray, Odometry, String
from racecar_hw.net import rmw
from racecar_hw.net.zenoh_config import session_config
from racecar_hw.rosmsg.typestore import ros2_types

FLOOD = str(ROOT / "tests" / "zenoh_flood.py")
FLOOD_S = 5.0
#: The calm window before the flood: what the machine alone costs the control loop, printed beside
#: the flood's counts to read a failure by (not asserted on). 150 ticks at 50 Hz are enough, as in
#: tests/test_net_flood.py.
CALM_S = 3.0
#: The flooder's niceness: on the shared 2-core test machine a flooder at normal priority takes a
#: core from every process on it (a calm window already misses ticks there); at 19 it still sends
#: over 100,000 messages/s from the CPU others leave idle. benchmarks/bench_flood.py floods at
#: normal priority.
FLOOD_NICE = 19
SPEED = 0.25
ACTIVE = "/vesc/low_level/ackermann_cmd_mux/active"


def _key(topic: str, cls: type) -> str:
    return rmw.topic_key(0, topic, cls.ROS_TYPE, rmw.type_hash(cls.ROS_TYPE))


def _open(port: int, timeout_s: float = 90.0) -> zenoh.Session:
    """A client session to the sim's bridge, once it listens."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(session_config("client", [], [endpoint(port)]))
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


class _Watch:
    """The control-loop statuses and the inbox's counts from /diagnostics, and the odometry speeds."""

    def __init__(self) -> None:
        self.types = ros2_types()
        self.cond = threading.Condition()
        self.control: list[tuple[float, int, int]] = []  # (monotonic s, ticks, missed)
        self.inbox: dict[str, str] = {}
        self.speeds: list[tuple[float, float]] = []
        self.source = ""  # the mux's active source, as its active topic last said

    def on_diagnostics(self, sample: zenoh.Sample) -> None:
        array = self.types.deserialize(sample.payload.to_bytes(), DiagnosticArray)
        with self.cond:
            for status in array.status:
                values = {kv.key: kv.value for kv in status.values}
                if status.name == "racecar_hw: control loop":
                    self.control.append((time.monotonic(), int(values["ticks"]), int(values["missed ticks"])))
                elif status.name == "racecar_hw: network inbox":
                    self.inbox = values
            self.cond.notify_all()

    def on_active(self, sample: zenoh.Sample) -> None:
        source = self.types.deserialize(sample.payload.to_bytes(), String).data
        with self.cond:
            self.source = source
            self.cond.notify_all()

    def driving_on(self, source: str, not_before: float, deadline: float) -> bool:
        """Wait from monotonic time ``not_before`` until the mux's active source is ``source`` (by
        ``deadline``); whether it was."""
        with self.cond:
            return self.cond.wait_for(lambda: time.monotonic() >= not_before and self.source == source,
                                      max(0.0, deadline - time.monotonic()))

    def on_odom(self, sample: zenoh.Sample) -> None:
        odom = self.types.deserialize(sample.payload.to_bytes(), Odometry)
        self.speeds.append((time.monotonic(), float(odom.twist.twist.linear.x)))

    def after(self, t: float, timeout_s: float = 30.0) -> tuple[float, int, int]:
        """The first control status received after monotonic time ``t``."""
        with self.cond:
            ok = self.cond.wait_for(lambda: self.control and self.control[-1][0] > t, timeout_s)
            assert ok, "no /diagnostics from the daemon"
            return next(c for c in self.control if c[0] > t)

    def before(self, t: float) -> tuple[float, int, int]:
        with self.cond:
            return [c for c in self.control if c[0] <= t][-1]

    def window(self, start: float, end: float) -> tuple[int, int]:
        """(ticks, missed ticks) between the first status after ``start`` and the last before ``end``."""
        first, last = self.after(start), self.before(end)
        assert last[0] - first[0] > 0.6 * (end - start)
        return last[1] - first[1], last[2] - first[2]


def _flood(port: int, seconds: float) -> tuple[subprocess.Popen, float]:
    command = [sys.executable, FLOOD, str(port), "--seconds", str(seconds), "--speed", str(SPEED),
               "--nice", str(FLOOD_NICE)]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    assert line == "flooding", (line, proc.stderr.read() if proc.poll() is not None else "")
    return proc, time.monotonic()


def _result(proc: subprocess.Popen) -> dict:
    assert proc.stdout is not None
    result = json.loads(proc.stdout.readline())
    proc.wait(30)
    return result


@pytest.mark.slow
@pytest.mark.alone  # it measures the pace of the machine (docs/tests.md, "Alone")
def test_a_cmd_vel_flood_neither_starves_the_loop_nor_delays_an_estop(tmp_path):
    port = free_port()
    # what is measured is the flood's effect on the daemon, not other tenants' of the test machine
    sim = start_sim(tmp_path, port, scenario="wall", duration=300.0, preexec_fn=ahead_of_other_load)
    procs: list[subprocess.Popen] = []
    session = None
    rounds: list[dict] = []
    try:
        session = _open(port)
        watch = _Watch()
        subs = [session.declare_subscriber(_key("/diagnostics", DiagnosticArray), watch.on_diagnostics),
                session.declare_subscriber(_key("/odom", Odometry), watch.on_odom),
                session.declare_subscriber(_key(ACTIVE, String), watch.on_active)]
        estop = session.declare_publisher(_key("/estop", Bool))
        calm = time.monotonic()
        watch.after(calm)  # the daemon ticks
        time.sleep(CALM_S)
        calm_ticks, calm_missed = watch.window(calm, time.monotonic())
        proc, started = _flood(port, FLOOD_S)
        procs.append(proc)
        result = _result(proc)
        ticks, missed = watch.window(started, time.monotonic())
        rounds.append({**result, "ticks": ticks, "missed": missed})
        # the e-stop, from this second session, into a flood of its own while the car drives
        proc, started = _flood(port, 3.0)
        procs.append(proc)
        # 2 s into it, once the flood drives the car: the flooder (niceness 19) can be starved by
        # other load for longer than the input's timeout, and an e-stop sent in such a gap found
        # the mux idle, which is not what this checks
        driving = watch.driving_on("cmd_vel", started + 2.0, started + 2.9)
        payload = ros2_types().serialize(Bool(True))
        sent_at = time.monotonic()
        sent_wall = time.time()
        estop.put(payload, attachment=rmw.encode_attachment(1, time.time_ns(), bytes(16)))
        last_flood = _result(proc)
        time.sleep(0.6)  # the last /diagnostics after the flood
        inbox = dict(watch.inbox)
        speeds = [v for t, v in watch.speeds if sent_at - 1.5 <= t <= sent_at]
        for sub in subs:
            sub.undeclare()
        report = sim.interrupt()
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if session is not None:
            session.close()
        sim.kill()
    summary = f"calm: {calm_ticks} ticks, {calm_missed} missed; floods: {rounds}; inbox: {inbox}"
    assert driving, f"the flood did not drive the car 2-2.9 s into it (mux: {watch.source}); {summary}"
    # they were floods, far faster than the car takes commands, and the inbox coalesced them
    assert all(r["rate"] > 2000 for r in [*rounds, last_flood]), summary
    received = int(re.match(r"received (\d+)", inbox["/cmd_vel"]).group(1))
    superseded = int(re.search(r"superseded (\d+)", inbox["/cmd_vel"]).group(1))
    assert received > 10_000 and superseded > 0.9 * received, summary
    # at most 1 % of the control ticks during a 5-second flood were missed
    flood, = rounds
    assert flood["missed"] <= 0.01 * (flood["ticks"] + flood["missed"]), summary
    # the car drove under the flood, and the e-stop latched within 0.1 s of being sent, its brake
    # the next motor command the fake VESC read
    order = [source for _, source in report["mux_switches"]]
    assert "estop" in order and order[order.index("estop") - 1] == "cmd_vel", report["mux_switches"]
    assert report["max_speed_mps"] > 0.15
    if speeds:  # odometry may not reach this session through the flood's congestion: the report says it
        assert max(speeds) > 0.15, speeds
    line = re.search(r"sim: e-stop from network topic /estop \(zenoh\) at wall ([\d.]+); fake VESC: brake "
                     r"[^\n]* at wall ([\d.]+) \(\+[\d.]+ ms\), ([^\n]*)", sim.log)
    assert line, sim.log[-3000:]
    latched, braked = float(line.group(1)), float(line.group(2))
    assert latched - sent_wall <= 0.1 and braked - sent_wall <= 0.1, (latched - sent_wall, braked - sent_wall)
    assert line.group(3) == "the first motor command written after the request"
    assert report["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
    print(summary, f"e-stop latched {1e3 * (latched - sent_wall):.1f} ms and braked "
                   f"{1e3 * (braked - sent_wall):.1f} ms after it was sent")
