"""The Zenoh bridge at nominal load: what it adds to the scan path and the CPU, and a remote round trip.

Four runs of the nominal-load daemon of ``bench_daemon.py`` (UST-10LX at 40 Hz, VESC at 50 Hz,
figure-8 source, safety, recorder), one after the other in this one invocation:

(a) the bridge off; on with no subscriber; on with three subscribers, each a Zenoh session in a
    separate process subscribed to every topic the car publishes (``<domain>/**``): the daemon's
    own scan-to-VESC-command p50/p99 and its CPU share, side by side (c);
(b) the external round trip: a ``racecar_hw.client`` in another process answers every scan with a
    drive command on nav_0 (steering alternating +-0.03 rad, so each answer changes the servo
    position); the time from the fake lidar handing a scan frame to its socket until the fake
    VESC reads the servo position that answers it. Scans whose answer came after the next scan
    was sent (the client skipped one) are not counted.

The settings of (a) run interleaved, ``ROUNDS`` times (default 3), each setting leading a round
in turn (:mod:`rounds`), and each row is the median over the rounds. The
p99 of the daemon's own CPU time in the scan path is shown too: unlike the wall-clock p99 it hardly
moves with the other tenants of the machine. So is the p99 of the round trip (fake lidar to fake
VESC) over every scan of every round of a setting taken together (:func:`rounds.pooled_p99`),
which rests on thousands of scans rather than on the eight slowest of one run.

``python benchmarks/bench_zenoh.py [SECONDS [ROUNDS]]``; ``run()`` returns the rows for run_all.py.

``--far-side`` runs :func:`far_side` instead (issue 25's "the far side must be cheap and fast"):
what one client answering every scan adds to the daemon's CPU, the client's own CPU and the round
trip, beside the four-process rclpy chain of ``bench_rclpy_chain.py`` (``--chain-python PY``) and
the same settings with older code (``--before TREE``), all interleaved::

    python benchmarks/bench_zenoh.py --far-side 15 3 --before /tmp/main --chain-python .venv-rclpy/bin/python

``BENCH_CLIENT_PROFILE=PATH`` runs the client under cProfile; ``BENCH_PYSPY=DIR`` (bench_daemon.py)
samples the daemon and the client with py-spy.
"""

from __future__ import annotations

import socket
import sys
import time
from collections.abc import Callable

import numpy as np
from bench_daemon import run as run_daemon
from rounds import code_from, interleaved, pooled_p99
from table import print_rows

from vesc.codec import SetServoPosition

SUBSCRIBERS = '''
import sys, time, zenoh
from racecar_hw.net.zenoh_config import session_config
port, n = sys.argv[1], int(sys.argv[2])
received = [0]
def take(sample):
    sample.payload.to_bytes()
    received[0] += 1
sessions = [zenoh.open(session_config("client", [], [f"tcp/127.0.0.1:{port}"])) for _ in range(n)]
subs = [s.declare_subscriber("0/**", take) for s in sessions]
while True:
    time.sleep(1)
'''

CLIENT = '''
import os, sys
if os.environ.get("BENCH_CLIENT_PROFILE"):  # a path: the client under cProfile, written at SIGTERM
    import cProfile, signal
    _profile = cProfile.Profile()
    def _dump(*_):
        _profile.disable()
        _profile.dump_stats(os.environ["BENCH_CLIENT_PROFILE"])
        os._exit(0)
    signal.signal(signal.SIGTERM, _dump)
    _profile.enable()
from racecar_hw.client import Car
# --drives: answer every scan with a command, the steering alternating so each answer shows
car = Car(f"tcp/127.0.0.1:{sys.argv[1]}")
sign = 1.0
for scan in car.scans(timeout=30):
    sign = -sign
    car.drive(0.3, 0.03 * sign)
'''


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _percentiles(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    return float(np.percentile(values, 50)), float(np.percentile(values, 99))


def _latencies(sent: np.ndarray, commands: list) -> list[float]:
    """Frame sent -> first later servo command whose position differs from the one before it (ms)."""
    servo = [(c.t_ns, c.packet.position) for c in commands if isinstance(c.packet, SetServoPosition)]
    times = np.array([t for t, _ in servo], dtype=np.int64)
    latencies = []
    for i, t_sent in enumerate(sent[:-1]):
        j = int(np.searchsorted(times, t_sent, side="right"))
        if j == 0:
            continue
        before = servo[j - 1][1]
        for t, position in servo[j:]:
            if t >= sent[i + 1]:
                break
            if abs(position - before) > 0.01:
                latencies.append((t - t_sent) / 1e6)
                break
    return latencies


def _round_trip(sent: np.ndarray, commands: list) -> list[dict]:
    latencies = _latencies(sent, commands)
    p50, p99 = _percentiles(latencies)
    return [
        {"name": "(b) remote round trip: scan frame out -> client's command at the VESC, p50",
         "value": p50, "unit": "ms", "target": None},
        {"name": "(b) remote round trip, p99", "value": p99, "unit": "ms", "target": 2.0},
        {"name": "(b) scans answered and matched", "value": len(latencies), "unit": "scans", "target": None},
    ]


def _callback_cost(n: int = 20000) -> list[dict]:
    """The bridge's own work on the scan path, per scan: its bus callback (after the motor write)."""
    from mux.params import MuxParams
    from racecar_hw.base.bus import Bus
    from racecar_hw.base.messages import LaserScan
    from racecar_hw.net.rmw import SampleStamps
    from racecar_hw.net.topics import topic_table
    from racecar_hw.net.zenoh_bridge import ZenohBridge, _Out
    from racecar_hw.net.zenoh_config import ZenohParams
    from safety.params import SafetyParams

    rows = topic_table(MuxParams(), SafetyParams())
    bridge = ZenohBridge(Bus(), ZenohParams(), rows)
    out = _Out(rows[0], None, SampleStamps(bytes(16)), latched=False)
    enqueue = bridge._enqueuer(out)
    scan = LaserScan()
    result = []
    for matching in (False, True):
        out.matching = matching
        start = time.perf_counter()
        for _ in range(n):
            enqueue(scan)
        cost = (time.perf_counter() - start) / n * 1e6
        who = "a subscriber listens" if matching else "nobody listens"
        result.append({"name": f"(a) the bridge's callback per scan, {who}", "value": cost, "unit": "us",
                       "target": None})
    return result


def _pick(rows: list[dict], name: str) -> float:
    return next(r["value"] for r in rows if r["name"] == name)


def run(seconds: float = 20.0, rounds: int = 3) -> list[dict]:
    py = sys.executable
    configs = {"off": lambda: run_daemon(seconds),
               "on, no subscriber": lambda: run_daemon(seconds, zenoh_port=_free_port()),
               "on, 3 subscribers": lambda: _three(seconds)}
    results = interleaved(configs, rounds)
    port = _free_port()
    trip = run_daemon(seconds, zenoh_port=port, helpers=[[py, "-c", CLIENT, str(port), "--drives"]],
                      on_results=_round_trip)
    p50, p99, cpu_p99, cpu = ("scan to VESC command p50 (in daemon)", "scan to VESC command p99 (in daemon)",
                              "  the daemon's CPU time in it, p99", "daemon CPU share of one core")
    rows = []
    medians: dict[tuple[str, str], float] = {}
    for label, runs in results.items():
        for name, short, unit, target in ((p50, "scan to VESC command p50", "ms", None),
                                          (p99, "scan to VESC command p99", "ms", 2.0),
                                          (cpu_p99, "the daemon's CPU time in it, p99", "ms", None),
                                          (cpu, "daemon CPU share", "%", 10.0)):
            value = float(np.median([_pick(r, name) for r in runs]))
            medians[label, name] = value
            rows.append({"name": f"bridge {label}: {short}", "value": value, "unit": unit, "target": target})
    for label in ("on, no subscriber", "on, 3 subscribers"):
        rows.append({"name": f"(a) p99 added, bridge {label}", "unit": "ms", "target": 0.05,
                     "value": medians[label, p99] - medians["off", p99]})
        rows.append({"name": f"(a) CPU-time p99 added, bridge {label}", "unit": "ms", "target": 0.05,
                     "value": medians[label, cpu_p99] - medians["off", cpu_p99]})
        rows.append({"name": f"(c) CPU added, bridge {label}", "unit": "% of a core", "target": None,
                     "value": medians[label, cpu] - medians["off", cpu]})
    for label in ("off", "on, no subscriber", "on, 3 subscribers"):
        rows.append({"name": f"bridge {label}: round trip lidar to VESC, p99 of all rounds' scans",
                     "value": pooled_p99(results[label]), "unit": "ms", "target": None})
    for label in ("on, no subscriber", "on, 3 subscribers"):
        rows.append({"name": f"(a) round-trip p99 of all rounds added, bridge {label}", "unit": "ms",
                     "target": 0.05, "value": pooled_p99(results[label]) - pooled_p99(results["off"])})
    rows.extend(_callback_cost())
    rows.extend(r for r in trip if r["name"].startswith("(b)"))
    rows.append({"name": "(b) daemon CPU share with the remote client driving", "value": _pick(trip, cpu),
                 "unit": "%", "target": None})
    steal = "host: CPU time stolen by the hypervisor"
    every = [r for runs in results.values() for r in runs] + [trip]
    rows.append({"name": "host steal, all runs (max)", "unit": "% of busy",
                 "value": max(_pick(r, steal) for r in every), "target": None})
    return rows


def far_side(seconds: float = 20.0, rounds: int = 4, chain_python: str | None = None,
             before: str | None = None) -> list[dict]:
    """What one remote ``racecar_hw.client`` answering every scan costs, and its round trip.

    Settings interleaved for ``rounds`` rounds (:mod:`rounds`): the bridge on with nobody
    subscribed; the same with the client answering every scan (both with the figure-8 source off,
    as the client drives nav_0); and, with ``chain_python`` (a Python with rclpy, see
    ``bench_rclpy_chain.py``), the four-process rclpy chain doing the same job against the same
    fakes. Rows: the daemon's CPU share in both (median over rounds) and what the client adds, the
    client's own CPU share, the round trip (scan frame out of the fake lidar to the answer at the
    fake VESC) p50 / p99 over every answered scan of every round, and the chain's. With ``before``
    (a source tree of racecar-hw, e.g. ``git archive main``), the two Zenoh settings also run with
    the daemon and the client importing that code, interleaved with the rest ("before" rows).
    """
    py = sys.executable
    quiet = {"figure8": {"enabled": False}}
    trips: dict[str, list[float]] = {"client": [], "client, before": [], "rclpy chain": []}

    def collect(label: str) -> Callable[[np.ndarray, list], list[dict]]:
        def on_results(sent: np.ndarray, commands: list) -> list[dict]:
            trips[label].extend(_latencies(sent, commands))
            return []
        return on_results

    def client(label: str) -> list[dict]:
        port = _free_port()
        return run_daemon(seconds, zenoh_port=port, helpers=[[py, "-c", CLIENT, str(port), "--drives"]],
                          on_results=collect(label))

    settings: dict[str, Callable[[], list[dict]]] = {
        "no subscriber": lambda: run_daemon(seconds, zenoh_port=_free_port(), config_extra=quiet),
        "client": lambda: client("client"),
    }
    if before:
        settings["no subscriber, before"] = code_from(before, settings["no subscriber"])
        settings["client, before"] = code_from(before, lambda: client("client, before"))
    if chain_python:
        from bench_rclpy_chain import run as run_chain  # noqa: PLC0415

        settings["rclpy chain"] = lambda: run_chain(seconds, chain_python, on_results=collect("rclpy chain"))
    results = interleaved(settings, rounds)
    cpu, helpers = "daemon CPU share of one core", "helpers' CPU share of one core"
    wakeups = "daemon thread wake-ups per second"
    p99, cpu_p99 = "scan to VESC command p99 (in daemon)", "  the daemon's CPU time in it, p99"
    med = {label: float(np.median([_pick(r, cpu) for r in runs])) for label, runs in results.items()
           if label != "rclpy chain"}
    rows = []
    for suffix in ("", ", before") if before else ("",):
        quiet_label, client_label = "no subscriber" + suffix, "client" + suffix
        rows += [
            {"name": f"daemon CPU, bridge on, nobody subscribed{suffix}", "value": med[quiet_label],
             "unit": "%", "target": None},
            {"name": f"daemon CPU, one client answering every scan{suffix}", "value": med[client_label],
             "unit": "%", "target": None},
            {"name": f"CPU added to the daemon by the client{suffix}", "unit": "points", "target": 2.0,
             "value": med[client_label] - med[quiet_label]},
            {"name": f"daemon thread wake-ups/s added by the client{suffix}", "unit": "/s", "target": None,
             "value": float(np.median([_pick(r, wakeups) for r in results[client_label]])
                            - np.median([_pick(r, wakeups) for r in results[quiet_label]]))},
            {"name": f"nobody subscribed{suffix}: scan to VESC command p99 (in daemon), median", "unit": "ms",
             "target": None, "value": float(np.median([_pick(r, p99) for r in results[quiet_label]]))},
            {"name": f"nobody subscribed{suffix}: the daemon's CPU time in it, p99, median", "unit": "ms",
             "target": None, "value": float(np.median([_pick(r, cpu_p99) for r in results[quiet_label]]))},
            {"name": f"nobody subscribed{suffix}: daemon thread wake-ups/s", "unit": "/s", "target": None,
             "value": float(np.median([_pick(r, wakeups) for r in results[quiet_label]]))},
            {"name": f"the client's own CPU share{suffix}", "unit": "%", "target": None,
             "value": float(np.median([_pick(r, helpers) for r in results[client_label]]))},
            {"name": f"daemon + client CPU{suffix}", "unit": "%", "target": None,
             "value": float(np.median([_pick(r, cpu) + _pick(r, helpers) for r in results[client_label]]))},
        ]
    for label in trips:
        if label not in results:
            continue
        p50, p99 = _percentiles(trips[label])
        rows += [{"name": f"{label}: round trip scan frame out -> answer at the VESC, p50", "value": p50,
                  "unit": "ms", "target": None},
                 {"name": f"{label}: round trip, p99", "value": p99, "unit": "ms", "target": 2.0},
                 {"name": f"{label}: scans answered and matched", "value": len(trips[label]),
                  "unit": "scans", "target": None}]
    if "rclpy chain" in results:
        rows.append({"name": "rclpy chain: CPU of its four processes", "unit": "%", "target": None,
                     "value": float(np.median([_pick(r, helpers) for r in results["rclpy chain"]]))})
    steal = "host: CPU time stolen by the hypervisor"
    every = [r for runs in results.values() for r in runs]
    rows.append({"name": "host steal, all runs (max)", "unit": "% of busy",
                 "value": max(_pick(r, steal) for r in every), "target": None})
    return rows


def _three(seconds: float) -> list[dict]:
    port = _free_port()
    return run_daemon(seconds, zenoh_port=port, helpers=[[sys.executable, "-c", SUBSCRIBERS, str(port), "3"]])


def main() -> None:
    args = sys.argv[1:]
    far = "--far-side" in args
    chain = args[args.index("--chain-python") + 1] if "--chain-python" in args else None
    before = args[args.index("--before") + 1] if "--before" in args else None
    numbers = [a for a in args if not a.startswith("-") and a not in (chain, before)]
    seconds = float(numbers[0]) if numbers else 20.0
    rounds = int(numbers[1]) if len(numbers) > 1 else (4 if far else 3)
    print_rows(far_side(seconds, rounds, chain, before) if far else run(seconds, rounds))


if __name__ == "__main__":
    main()
