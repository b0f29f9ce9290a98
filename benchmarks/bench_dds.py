"""The DDS interface at nominal load: what it adds to the scan path and the CPU, and a round trip
through a stock rclpy node.

The nominal-load daemon of ``bench_daemon.py`` (UST-10LX at 40 Hz, VESC at 50 Hz, figure-8 source,
safety, recorder), one run per setting:

(a) DDS off; on with nobody; on with one rclpy node (the PyPI Kilted wheels, Fast DDS, from
    ``.ros-venv``) subscribed to every topic the car publishes whose type has a wheel (/scan with
    the sensor-data QoS, /odom, the servo position, the mux's active source): the daemon's own
    scan-to-VESC-command p50/p99 and its CPU share;
(b) the round trip: an rclpy node answers every /scan with a /cmd_vel Twist (the turn rate
    alternating, so each answer changes the servo position); the time from the fake lidar handing a
    scan frame to its socket until the fake VESC reads the servo position that answers it
    (``bench_zenoh._round_trip``), next to the same through the Zenoh client.

(a)'s settings run interleaved, ``ROUNDS`` times (default 3), each leading a round in turn
(:mod:`rounds`); each row is the median over the rounds, and the round trip's p99 is taken over
every scan of every round of a setting together (:func:`rounds.pooled_p99`), as in
``bench_zenoh.py``: one run's p99 rests on its eight slowest scans. Each run uses a DDS domain of
its own (``ROS_DOMAIN_ID`` for the rclpy node). ``python benchmarks/bench_dds.py [SECONDS
[ROUNDS]]``; ``run()`` returns the rows.

``--far-side`` runs :func:`far_side` instead (issue 25's "the far side must be cheap and fast", as
``bench_zenoh.py --far-side`` for Zenoh): an rclpy node subscribed to ``/scan`` and ``/odom``
answering every scan with ``/cmd_vel``, against the daemon with DDS on and nobody subscribed, both
with the figure-8 source off; with ``--before TREE`` the same two with the daemon importing an
older source tree; with ``--chain`` the four-process rclpy chain of ``bench_rclpy_chain.py`` in the
same rounds (the issue's yardstick for the round trip); all interleaved::

    python benchmarks/bench_dds.py --far-side 15 3 --before /tmp/main --chain
"""

from __future__ import annotations

import os
import random
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bench_daemon import run as run_daemon
from bench_zenoh import CLIENT, _free_port, _pick, _round_trip
from rounds import code_from, interleaved, pooled_p99
from table import print_rows

ROS_PYTHON = str(Path(os.environ.get("RACECAR_ROS_VENV", Path(__file__).resolve().parents[1] / ".ros-venv"))
                 / "bin" / "python")

SUBSCRIBER = '''
import importlib, rclpy
from rclpy.qos import qos_profile_sensor_data
rclpy.init()
node = rclpy.create_node("bench_subscriber")
topics = [("/scan", "sensor_msgs.msg", "LaserScan"), ("/odom", "nav_msgs.msg", "Odometry"),
          ("/vesc/sensors/servo_position_command", "std_msgs.msg", "Float64"),
          ("/vesc/low_level/ackermann_cmd_mux/active", "std_msgs.msg", "String")]
for topic, module, name in topics:
    cls = getattr(importlib.import_module(module), name)
    node.create_subscription(cls, topic, lambda m: None,
                             qos_profile_sensor_data if topic == "/scan" else 10)
rclpy.spin(node)
'''

ANSWER = '''
import rclpy
from geometry_msgs.msg import Twist
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import LaserScan
rclpy.init()
node = rclpy.create_node("bench_driver")
pub = node.create_publisher(Twist, "/cmd_vel", 10)
sign = [1.0]
def answer(scan):
    sign[0] = -sign[0]
    t = Twist()
    t.linear.x = 0.3
    t.angular.z = 0.2 * sign[0]
    pub.publish(t)
node.create_subscription(LaserScan, "/scan", answer, qos_profile_sensor_data)
rclpy.spin(node)
'''

#: ANSWER, also subscribed to /odom (a navigation node reads both)
FAR_ANSWER = ANSWER.replace("rclpy.spin(node)", """from nav_msgs.msg import Odometry
node.create_subscription(Odometry, "/odom", lambda m: None, 10)
rclpy.spin(node)""")

P99 = "scan to VESC command p99 (in daemon)"
P50 = "scan to VESC command p50 (in daemon)"
CPU_P99 = "  the daemon's CPU time in it, p99"
CPU = "daemon CPU share of one core"


def _dds(domain: int) -> dict:
    return {"dds": {"enabled": True, "domain_id": domain}}


def run(seconds: float = 20.0, rounds: int = 3) -> list[dict]:
    """(a)'s three settings interleaved for ``rounds`` rounds (:mod:`rounds`): medians over the
    rounds, and the round trip's p99 over every scan of every round (:func:`rounds.pooled_p99`);
    then (b) once per far side."""
    if not Path(ROS_PYTHON).exists():
        raise SystemExit(f"no ROS 2 environment at {ROS_PYTHON} (.ci/run makes it)")
    env_domain = random.randrange(100, 200)
    os.environ["ROS_DOMAIN_ID"] = str(env_domain)  # the rclpy helpers inherit it
    every = "on, one rclpy subscriber of every topic"
    results = interleaved({
        "off": lambda: run_daemon(seconds),
        "on, nobody": lambda: run_daemon(seconds, config_extra=_dds(env_domain)),
        every: lambda: run_daemon(seconds, config_extra=_dds(env_domain),
                                  helpers=[[ROS_PYTHON, "-c", SUBSCRIBER]]),
    }, rounds)
    trip = run_daemon(seconds, config_extra=_dds(env_domain),
                      helpers=[[ROS_PYTHON, "-c", ANSWER, "--drives"]], on_results=_round_trip)
    port = _free_port()
    ztrip = run_daemon(seconds, zenoh_port=port,
                       helpers=[[sys.executable, "-c", CLIENT, str(port), "--drives"]],
                       on_results=_round_trip)

    def median(label: str, name: str) -> float:
        return float(np.median([_pick(r, name) for r in results[label]]))

    rows = []
    for label in results:
        for name, short, unit, target in ((P50, "scan to VESC command p50", "ms", None),
                                          (P99, "scan to VESC command p99", "ms", 2.0),
                                          (CPU_P99, "the daemon's CPU time in it, p99", "ms", None),
                                          (CPU, "daemon CPU share", "%", None)):
            rows.append({"name": f"DDS {label}: {short}", "value": median(label, name), "unit": unit,
                         "target": target})
        rows.append({"name": f"DDS {label}: round trip lidar to VESC, p99 of all rounds' scans",
                     "value": pooled_p99(results[label]), "unit": "ms", "target": None})
    for label in ("on, nobody", every):
        rows.append({"name": f"(a) p99 added, DDS {label}", "value": median(label, P99) - median("off", P99),
                     "unit": "ms", "target": 0.05})
        rows.append({"name": f"(a) CPU-time p99 added, DDS {label}", "unit": "ms", "target": 0.05,
                     "value": median(label, CPU_P99) - median("off", CPU_P99)})
        rows.append({"name": f"(a) round-trip p99 of all rounds added, DDS {label}", "unit": "ms",
                     "target": 0.05, "value": pooled_p99(results[label]) - pooled_p99(results["off"])})
        rows.append({"name": f"(a) CPU added, DDS {label}", "value": median(label, CPU) - median("off", CPU),
                     "unit": "% of a core", "target": None})
    for label, result in (("rclpy over DDS", trip), ("racecar_hw.client over Zenoh", ztrip)):
        for row in result:
            if row["name"].startswith("(b)"):
                rows.append({**row, "name": row["name"].replace("(b)", f"(b) {label}:")})
        rows.append({"name": f"(b) {label}: daemon CPU share", "value": _pick(result, CPU), "unit": "%",
                     "target": None})
    steal = "host: CPU time stolen by the hypervisor"
    runs = [r for each in results.values() for r in each] + [trip, ztrip]
    rows.append({"name": "host steal, all runs (max)", "unit": "% of busy",
                 "value": max(_pick(r, steal) for r in runs), "target": None})
    return rows


def far_side(seconds: float = 15.0, rounds: int = 3, before: str | None = None,
             chain: bool = False) -> list[dict]:
    """What one rclpy node answering every scan over DDS adds to the daemon's CPU, and its round
    trip (scan frame out of the fake lidar to the answer at the fake VESC), interleaved with the
    daemon with nobody subscribed; with ``before`` (a source tree), both again on that code; with
    ``chain``, the four-process rclpy chain of ``bench_rclpy_chain.py`` in the same rounds."""
    from bench_zenoh import _latencies, _percentiles  # noqa: PLC0415

    if not Path(ROS_PYTHON).exists():
        raise SystemExit(f"no ROS 2 environment at {ROS_PYTHON} (.ci/run makes it)")
    domain = random.randrange(100, 200)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    quiet = {**_dds(domain), "figure8": {"enabled": False}}
    trips: dict[str, list[float]] = {"rclpy": [], "rclpy, before": [], "rclpy chain": []}

    def collect(label: str) -> Callable[[np.ndarray, list], list[dict]]:
        def on_results(sent: np.ndarray, commands: list) -> list[dict]:
            trips[label].extend(_latencies(sent, commands))
            return []
        return on_results

    def answered(label: str) -> list[dict]:
        return run_daemon(seconds, config_extra=_dds(domain), on_results=collect(label),
                          helpers=[[ROS_PYTHON, "-c", FAR_ANSWER, "--drives"]])

    settings = {"nobody": lambda: run_daemon(seconds, config_extra=quiet), "rclpy": lambda: answered("rclpy")}
    if before:
        settings["nobody, before"] = code_from(before, settings["nobody"])
        settings["rclpy, before"] = code_from(before, lambda: answered("rclpy, before"))
    if chain:
        from bench_rclpy_chain import run as run_chain  # noqa: PLC0415

        settings["rclpy chain"] = lambda: run_chain(seconds, ROS_PYTHON, on_results=collect("rclpy chain"))
    results = interleaved(settings, rounds)
    wakeups = "daemon thread wake-ups per second"

    def median(label: str, name: str) -> float:
        return float(np.median([_pick(r, name) for r in results[label]]))

    rows = []
    for suffix in ("", ", before") if before else ("",):
        nobody, answer = "nobody" + suffix, "rclpy" + suffix
        p50, p99 = _percentiles(trips[answer])
        rows += [
            {"name": f"daemon CPU, DDS on, nobody subscribed{suffix}", "value": median(nobody, CPU),
             "unit": "%", "target": None},
            {"name": f"daemon CPU, one rclpy node answering every scan{suffix}", "value": median(answer, CPU),
             "unit": "%", "target": None},
            {"name": f"CPU added to the daemon by the rclpy node{suffix}", "unit": "points", "target": 2.0,
             "value": median(answer, CPU) - median(nobody, CPU)},
            {"name": f"daemon thread wake-ups/s added by the rclpy node{suffix}", "unit": "/s",
             "target": None, "value": median(answer, wakeups) - median(nobody, wakeups)},
            {"name": f"nobody subscribed{suffix}: daemon thread wake-ups/s", "unit": "/s", "target": None,
             "value": median(nobody, wakeups)},
            {"name": f"rclpy{suffix}: round trip scan frame out -> answer at the VESC, p50", "value": p50,
             "unit": "ms", "target": None},
            {"name": f"rclpy{suffix}: round trip, p99", "value": p99, "unit": "ms", "target": 2.0},
            {"name": f"rclpy{suffix}: scans answered and matched", "value": len(trips[answer]),
             "unit": "scans", "target": None},
        ]
    if chain:
        p50, p99 = _percentiles(trips["rclpy chain"])
        rows += [{"name": "rclpy chain: round trip scan frame out -> answer at the VESC, p50", "value": p50,
                  "unit": "ms", "target": None},
                 {"name": "rclpy chain: round trip, p99", "value": p99, "unit": "ms", "target": 2.0},
                 {"name": "rclpy chain: scans answered and matched", "value": len(trips["rclpy chain"]),
                  "unit": "scans", "target": None}]
    steal = "host: CPU time stolen by the hypervisor"
    rows.append({"name": "host steal, all runs (max)", "unit": "% of busy", "target": None,
                 "value": max(_pick(r, steal) for each in results.values() for r in each)})
    return rows


def main() -> None:
    args = sys.argv[1:]
    before = args[args.index("--before") + 1] if "--before" in args else None
    numbers = [a for a in args if not a.startswith("-") and a != before]
    seconds = float(numbers[0]) if numbers else (15.0 if "--far-side" in args else 20.0)
    rounds = int(numbers[1]) if len(numbers) > 1 else 3
    print_rows(far_side(seconds, rounds, before, "--chain" in args) if "--far-side" in args
               else run(seconds, rounds))


if __name__ == "__main__":
    main()
