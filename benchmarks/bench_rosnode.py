"""The node surface (/rosout, the parameter services, ``zenoh.ros_distro``): what it adds to the scan
path and the CPU.

Runs of the nominal-load daemon of ``bench_daemon.py`` (UST-10LX at 40 Hz, VESC at 50 Hz, figure-8
source, safety, recorder) with the Zenoh bridge on and nobody subscribed, interleaved (:mod:`rounds`):

* ``rosout off``: ``rosout.enabled: false`` (no /rosout row, no log handler; the parameter services
  are declared whatever the setting, idle: a queryable costs nothing until queried);
* ``rosout on``: the shipped default (WARNING and above);
* ``rosout on, a ROS client``: a Zenoh session in another process subscribed to /rosout that calls
  the parameter services in rmw_zenoh's format twice a second, each call for another single
  parameter (an answer computed, not cached), and the whole list and every value once a second
  (``ros2 param dump``'s calls, answered from the cache the bridge warms at start);
* ``humble``: ``zenoh.ros_distro: humble``: only the key strings differ, expected to cost nothing.

Also, measured in this process: the log handler's cost per WARNING record (what a warning logged on
the scan path would add to it), and the parameter answers' cost, computed and cached.

``python benchmarks/bench_rosnode.py [SECONDS [ROUNDS]]``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import statistics
import sys
import time

import numpy as np
from bench_daemon import run as run_daemon
from rounds import interleaved, pooled_p99
from table import print_rows

ROS_CLIENT = '''
import itertools, sys, time, zenoh
from racecar_hw.base.parameter_messages import GetParametersRequest, ListParametersRequest
from racecar_hw.net import rmw
from racecar_hw.net.zenoh_config import session_config
from racecar_hw.rosmsg.typestore import ros2_types
port = sys.argv[1]
types = ros2_types()
session = zenoh.open(session_config("client", [], [f"tcp/127.0.0.1:{port}"]))
logs = [0]
session.declare_subscriber("0/rosout/**", lambda s: logs.__setitem__(0, logs[0] + 1))
def key(service, srv):
    return rmw.topic_key(0, f"/racecar_hw/{service}", srv, rmw.type_hash(srv))
get_key = key("get_parameters", "rcl_interfaces/srv/GetParameters")
list_key = key("list_parameters", "rcl_interfaces/srv/ListParameters")
def call(k, request, seq):
    attachment = rmw.Attachment(seq, time.time_ns(), bytes(16)).encode()
    return [r.ok.payload.to_bytes() for r in session.get(k, payload=types.serialize(request),
                                                         attachment=attachment, timeout=5) if r.ok]
from racecar_hw.base.parameter_messages import ListParametersResponse
names = []
while not names:
    got = call(list_key, ListParametersRequest(), 1)
    names = list(types.deserialize(got[0], ListParametersResponse).result.names) if got else []
    time.sleep(0.2)
for seq in itertools.count(2):
    call(get_key, GetParametersRequest([names[seq % len(names)]]), seq)
    if seq % 2 == 0:
        call(list_key, ListParametersRequest(), seq)
        call(get_key, GetParametersRequest(names), seq)
    time.sleep(0.5)
'''

P50, P99, CPU_P99, CPU = ("scan to VESC command p50 (in daemon)", "scan to VESC command p99 (in daemon)",
                          "  the daemon's CPU time in it, p99", "daemon CPU share of one core")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _daemon(seconds: float, **kwargs: object) -> list[dict]:
    """One bench_daemon run, tried again (twice at most) when a loaded host starts it too slowly."""
    for attempt in range(3):
        try:
            return run_daemon(seconds, **kwargs)
        except RuntimeError as err:
            if "did not start" not in str(err) or attempt == 2:
                raise
            print(f"the daemon did not start in time; again ({attempt + 1})", file=sys.stderr)
    raise AssertionError("unreachable")


def _pick(rows: list[dict], name: str) -> float:
    return next(r["value"] for r in rows if r["name"] == name)


def _handler_cost(n: int = 5000) -> list[dict]:
    """The log handler's own cost per WARNING record, in the logging thread: with it, minus without."""
    from racecar_hw.base.bus import Bus
    from racecar_hw.net.rosout import RosoutHandler, RosoutParams

    async def measure() -> tuple[float, float]:
        bus = Bus()
        bus.bind_loop(asyncio.get_running_loop())
        logger = logging.getLogger("bench_rosnode")
        logger.propagate = False
        logger.addHandler(logging.NullHandler())
        handler = RosoutHandler(bus, RosoutParams(max_rate_hz=1e6), "racecar_hw")
        costs = {}
        for installed in (False, True, False, True):
            if installed:
                handler.install(logger)
            samples = []
            for _ in range(n):
                start = time.perf_counter_ns()
                logger.warning("mux input %s timed out", "nav_0")
                samples.append(time.perf_counter_ns() - start)
                if len(samples) % 100 == 0:
                    await asyncio.sleep(0)  # let the loop run the queued publishes
            handler.uninstall(logger)
            costs.setdefault(installed, []).append(statistics.median(samples) / 1000)
        return min(costs[False]), min(costs[True])

    without, with_handler = asyncio.run(measure())
    return [{"name": "a WARNING record: the handler's added cost in the logging thread (median)",
             "value": with_handler - without, "unit": "us", "target": None}]


def _answer_cost() -> list[dict]:
    """The parameter answers: computed (the first call of its kind) and cached, for the shipped config."""
    from racecar_hw.base.parameter_messages import GetParametersRequest
    from racecar_hw.base.params import describe, to_dict
    from racecar_hw.config import Config, load_config
    from racecar_hw.net.parameters import CdrAnswers, ParameterService
    from racecar_hw.rosmsg.typestore import ros2_types

    types = ros2_types()
    service = ParameterService(to_dict(load_config(None)), {n: d for n, _, d in describe(Config)})
    names = list(service.values)
    rows = []
    for label, request in (("one parameter", GetParametersRequest(names[:1])),
                           (f"all {len(names)} parameters", GetParametersRequest(names))):
        raw = types.serialize(request)
        computed, cached = [], []
        for _ in range(5):
            answers = CdrAnswers(service)
            start = time.perf_counter()
            answers.answer("get_parameters", raw)
            computed.append(time.perf_counter() - start)
            start = time.perf_counter()
            answers.answer("get_parameters", raw)
            cached.append(time.perf_counter() - start)
        rows.append({"name": f"get_parameters of {label}: computed (median)", "unit": "ms", "target": None,
                     "value": statistics.median(computed) * 1000})
        rows.append({"name": f"get_parameters of {label}: cached (median)", "unit": "ms", "target": None,
                     "value": statistics.median(cached) * 1000})
    start = time.perf_counter()
    CdrAnswers(service).warm()
    rows.append({"name": "warming the answers at start (once, off the loop)", "unit": "ms", "target": None,
                 "value": (time.perf_counter() - start) * 1000})
    return rows


def run(seconds: float = 20.0, rounds: int = 4) -> list[dict]:
    off = {"rosout": {"enabled": False}}

    def client(seconds: float) -> list[dict]:
        port = _free_port()
        return _daemon(seconds, zenoh_port=port, helpers=[[sys.executable, "-c", ROS_CLIENT, str(port)]])

    configs = {"rosout off": lambda: _daemon(seconds, zenoh_port=_free_port(), config_extra=off),
               "rosout on": lambda: _daemon(seconds, zenoh_port=_free_port()),
               "rosout on, a ROS client": lambda: client(seconds),
               "humble": lambda: _daemon(seconds, zenoh_port=_free_port(),
                                         config_extra={"zenoh": {"ros_distro": "humble"}})}
    results = interleaved(configs, rounds)
    rows, medians = [], {}
    for label, runs in results.items():
        for name, short, unit in ((P50, "scan to VESC command p50", "ms"),
                                  (P99, "scan to VESC command p99", "ms"),
                                  (CPU_P99, "the daemon's CPU time in it, p99", "ms"),
                                  (CPU, "daemon CPU share", "%")):
            value = float(np.median([_pick(r, name) for r in runs]))
            medians[label, name] = value
            rows.append({"name": f"{label}: {short}", "value": value, "unit": unit, "target": None})
    for label in ("rosout on", "rosout on, a ROS client", "humble"):
        rows.append({"name": f"p99 added, {label} (vs rosout off)", "unit": "ms", "target": 0.05,
                     "value": medians[label, P99] - medians["rosout off", P99]})
        rows.append({"name": f"CPU-time p99 added, {label}", "unit": "ms", "target": 0.05,
                     "value": medians[label, CPU_P99] - medians["rosout off", CPU_P99]})
        rows.append({"name": f"round-trip p99 of all rounds added, {label}", "unit": "ms", "target": 0.05,
                     "value": pooled_p99(results[label]) - pooled_p99(results["rosout off"])})
        rows.append({"name": f"CPU added, {label}", "unit": "% of a core", "target": None,
                     "value": medians[label, CPU] - medians["rosout off", CPU]})
    rows.extend(_handler_cost())
    rows.extend(_answer_cost())
    steal = "host: CPU time stolen by the hypervisor"
    rows.append({"name": "host steal, all runs (max)", "unit": "% of busy", "target": None,
                 "value": max(_pick(r, steal) for runs in results.values() for r in runs)})
    return rows


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 20.0
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 4
    print_rows(run(seconds, rounds))


if __name__ == "__main__":
    main()
