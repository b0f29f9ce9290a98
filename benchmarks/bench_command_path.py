"""A remote command's CPU cost in the daemon: the event loop's hand-over and the input thread's offer.

The far side of issue 25 (a client answering every scan) costs the daemon's event loop one
hand-over per command: the inbox's ``drain``, the control path's ``take_input`` (the bus, the mux's
early step with the safety controller's limit, the VESC write, the output's publication to the
bus's subscribers). This measures that work alone, as CPU time of the thread that does it, not
wall time, so that a busy shared host moves it little.

The real :class:`~racecar_hw.daemon.Daemon` runs in this process, in its own asyncio loop, at
nominal load (the fake UST-10LX at 40 Hz over TCP and the fake VESC on a pty, in a child process
so that they do not contend for this one's GIL; the safety controller, the recorder writing MCAP,
the Zenoh bridge on a free port with nobody connected, the Foxglove live view and the status page
on free ports; the figure-8 source off, as the far-side benchmark has it). A thread of this
benchmark plays the Zenoh input thread: every 25 ms (40 commands a second, one per scan) it offers
a CDR-encoded
``AckermannDriveStamped`` for nav_0 with :meth:`Inbox.offer_cdr`, the call the Zenoh and DDS input
threads make. Measured:

- **the loop's hand-over**: ``time.thread_time_ns`` around every ``Inbox.drain`` the loop runs
  (its own wake-up's callback), per drain that handed over one command;
- **the offer**: the same around each ``offer_cdr`` in the sending thread (decode, finiteness
  check, the inbox's lock, the loop's wake-up);
- with ``--profile``, cProfile switched on inside each drain only: the Python calls per command
  and the functions that take the time.

Environment: ``BENCH_PROFILE=PATH`` (with ``--profile``) keeps the whole profile for pstats;
``BENCH_LOOP_PROFILE=1`` profiles the whole loop thread with and without commands and prints what
the commands add, per command; ``BENCH_WARM=1`` repeats each hand-over at once (caches warm) and
times its parts; ``BENCH_LISTENER=1`` measures the loop's and the process's share with a client in
another process reading every scan and odometry (no answers) before the commands, which then come
on top; ``BENCH_SUBSCRIBERS=1`` prints who the command's publications reach.

Run ``python benchmarks/bench_command_path.py [COMMANDS] [--rounds N] [--before TREE] [--profile]``;
``--before TREE`` alternates rounds with another source tree (``git archive main | tar -x``), each
round in a fresh process with ``PYTHONPATH`` naming the tree. ``run()`` returns the rows for
run_all.py.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import io
import json
import math
import multiprocessing
import os
import pstats
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from fakes import room_fakes
from rounds import thread_cpu_s
from table import print_rows

from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.config import load_config
from racecar_hw.daemon import Daemon
from racecar_hw.rosmsg.typestore import ros2_types

INPUT = "nav_0"
PERIOD_S = 0.025  # one command per scan at 40 Hz


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _overrides(tmp: str, vesc_port: str, lidar: tuple[str, int]) -> list[str]:
    host, port = lidar
    return [f"vesc.port={vesc_port}", "vesc.poll_rate_hz=50", "lidar.model=ust-10lx",
            f"lidar.tcp={host}:{port}", "mux.rate_hz=50", "safety.mode=arc",
            "recorder.enabled=true", f"recorder.path={tmp}/bags", "recorder.format=mcap",
            "figure8.enabled=false", "arming.start_armed=true", "gamepad.enabled=false",
            "status.enabled=false", "foxglove.port=0", "web.port=0", "zenoh.enabled=true",
            f"zenoh.listen=[tcp/127.0.0.1:{_free_port()}]", "dds.enabled=false"]


def _fakes(tmp: str, ready: Any, stop: Any) -> None:
    """The fake VESC and the fake lidar in a process of their own (not contending for our GIL)."""
    with room_fakes(tmp) as (_, lidar):
        ready.put(lidar.tcp_address)
        stop.wait()


def measure(commands: int, profile: bool = False) -> dict:
    """One round in this process: ``commands`` commands at 40/s; CPU times in ns, per command."""
    ctx = multiprocessing.get_context("fork")  # before this process starts any thread
    with tempfile.TemporaryDirectory() as tmp:
        ready, stop = ctx.Queue(), ctx.Event()
        fakes = ctx.Process(target=_fakes, args=(tmp, ready, stop), daemon=True)
        fakes.start()
        try:
            address = ready.get(timeout=30)
            config = load_config(None, _overrides(tmp, f"{tmp}/vesc", address))
            return asyncio.run(_measure(Daemon(config), commands, profile))
        finally:
            stop.set()
            fakes.join(10)


async def _measure(daemon: Daemon, commands: int, profile: bool) -> dict:
    inbox = daemon.inbox
    assert inbox is not None, "the Zenoh bridge is on: the daemon has an inbox"
    topic = next(i.topic for i in daemon.config.mux.inputs if i.name == INPUT)
    drains: list[tuple[int, int]] = []  # (CPU ns, commands handed over)
    measuring = False
    # CPU time, not wall time: a GIL wait or a preemption is not the code's cost
    profiler = cProfile.Profile(time.thread_time_ns, 1e-9) if profile else None
    drain = inbox.drain
    warm_repeat = bool(os.environ.get("BENCH_WARM"))  # also time a second, warm hand-over
    warm_cpu: list[int] = []
    warm_parts: dict[str, list[int]] = {}

    counts = inbox._slots[topic].counts  # read in place: counts() copies every input's

    def handed() -> int:
        return counts.handed_over

    def timed_drain() -> None:  # the inbox wakes the loop with self.drain: this instead
        if not measuring:
            drain()
            return
        before = handed()
        if profiler is not None:
            profiler.enable()
        t0 = time.thread_time_ns()
        drain()
        t1 = time.thread_time_ns()
        if profiler is not None:
            profiler.disable()
        drains.append((t1 - t0, handed() - before))
        if warm_repeat and drains[-1][1] == 1:  # the same work again at once, its caches warm
            slot = inbox._slots[topic]
            msg = inbox.deliver.__self__.bus.latest(topic)  # the command just handed over
            inbox.offer("zenoh", topic, msg)
            slot.next_ns = 0
            t2 = time.thread_time_ns()
            drain()
            warm_cpu.append(time.thread_time_ns() - t2)
            # and its parts, warm, one by one (the mux's early step and the write repeated)
            control = inbox.deliver.__self__
            mux, now = control.mux, time.monotonic_ns()
            name = control.remote_inputs[topic]
            parts = [("bus.publish(input)", lambda: control.bus.publish(topic, msg)),
                     ("mux.decide_early", lambda: mux.decide_early(name, now, control.filters)),
                     ("arbitrate", lambda: mux._arbitrate(now)),
                     ("safety.limit", lambda: control.safety.limit(msg.drive, name, now)),
                     ("vesc.command", lambda: control._write(msg.drive)),
                     ("publish_output", lambda: mux.publish_output(mux.last_output)),
                     ("publish_state_if_due", lambda: control.safety.publish_state_if_due(now)),
                     ("empty call", lambda: None)]
            for label, fn in parts:
                t3 = time.thread_time_ns()
                fn()
                warm_parts.setdefault(label, []).append(time.thread_time_ns() - t3)

    inbox.drain = timed_drain  # type: ignore[method-assign]
    stop = asyncio.Event()
    task = asyncio.create_task(daemon.run(stop))
    deadline = time.monotonic() + 60
    while (daemon.vesc is None or daemon.vesc.stats.drive_commands < 50
           or not daemon.control.alive(time.monotonic_ns())):
        if time.monotonic() > deadline or task.done():
            stop.set()
            await task
            raise RuntimeError("the daemon did not start driving")
        await asyncio.sleep(0.05)
    if os.environ.get("BENCH_SUBSCRIBERS"):  # who the command's publications reach
        bus = daemon.bus
        for name in (topic, daemon.config.mux.output_topic, "/vesc/sensors/servo_position_command"):
            print(name, [s.callback for s in bus._subs.get(name, [])])
        print("every topic", [s.callback for s in bus._all])
    types = ros2_types()
    offers: list[int] = []
    done = threading.Event()

    def sender(n: int, record: bool) -> None:
        # the Zenoh input thread's call, at the client's pace
        next_t = time.monotonic()
        for i in range(n):
            msg = AckermannDriveStamped(stamp_now("base_link", time.time_ns()),
                                        AckermannDrive(0.4 + 0.001 * (i % 100), 0.1, 1.0))
            payload = types.serialize(msg)
            t0 = time.thread_time_ns()
            inbox.offer_cdr("zenoh", topic, AckermannDriveStamped, payload)
            t1 = time.thread_time_ns()
            if record:
                offers.append(t1 - t0)
            next_t += PERIOD_S
            time.sleep(max(0.0, next_t - time.monotonic()))

    warm = threading.Thread(target=sender, args=(80, False), name="bench-warm")
    warm.start()
    while warm.is_alive():
        await asyncio.sleep(0.05)
    # the loop's CPU share with no command for as long as the commanded phase lasts
    whole = bool(os.environ.get("BENCH_LOOP_PROFILE")) and profiler is None
    idle_prof = cProfile.Profile(time.thread_time_ns, 1e-9) if whole else None
    busy_prof = cProfile.Profile(time.thread_time_ns, 1e-9) if whole else None
    if idle_prof is not None:
        idle_prof.enable()
    idle0, t0 = time.thread_time_ns(), time.monotonic()
    await asyncio.sleep(commands * PERIOD_S)
    idle_pct = 100.0 * (time.thread_time_ns() - idle0) / 1e9 / (time.monotonic() - t0)
    listener = None
    listen_pct = listen_process_pct = idle_process_pct = math.nan
    if os.environ.get("BENCH_LISTENER"):
        # a client in another process reading every scan (and odometry), answering nothing: what
        # serving a subscriber costs the loop, apart from the commands (which then come on top)
        threads0 = thread_cpu_s(os.getpid())
        idle_process_pct = await asyncio.to_thread(_process_share, commands * PERIOD_S)
        threads1 = thread_cpu_s(os.getpid())
        port = daemon.config.zenoh.listen[0].rsplit(":", 1)[1]
        listener = subprocess.Popen([sys.executable, "-c", LISTENER, port], cwd=tempfile.gettempdir())
        await asyncio.sleep(4.0)  # connected, its first scans through
        threads1b = thread_cpu_s(os.getpid())
        listen0, t0 = time.thread_time_ns(), time.monotonic()
        listen_process_pct = await asyncio.to_thread(_process_share, commands * PERIOD_S)
        threads2 = thread_cpu_s(os.getpid())
        span = commands * PERIOD_S
        added = {name: 100.0 * ((threads2.get(name, 0.0) - threads1b.get(name, 0.0))
                                - (threads1.get(name, 0.0) - threads0.get(name, 0.0))) / span
                 for name in threads2}
        print("threads' CPU share added by the listener (points):",
              ", ".join(f"{n} {v:+.2f}" for n, v in sorted(added.items(), key=lambda kv: -kv[1])
                        if abs(v) >= 0.05), file=sys.stderr)
        listen_pct = 100.0 * (time.thread_time_ns() - listen0) / 1e9 / (time.monotonic() - t0)
    if idle_prof is not None:
        idle_prof.disable()
        busy_prof.enable()  # type: ignore[union-attr]
    measuring = True
    loop_cpu0 = time.thread_time_ns()
    t0 = time.monotonic()
    finished = asyncio.Event()
    loop = asyncio.get_running_loop()
    # one wake-up of the loop at the end, as the idle phase's one timer: no polling meanwhile
    main = threading.Thread(target=lambda: (sender(commands, True), done.set(),
                                            loop.call_soon_threadsafe(finished.set)),
                            name="bench-sender")
    main.start()
    await finished.wait()
    await asyncio.sleep(0.1)  # the last hand-over
    measuring = False
    loop_cpu = time.thread_time_ns() - loop_cpu0
    if busy_prof is not None:
        busy_prof.disable()
    if listener is not None:
        listener.terminate()
        listener.wait(10)
    wall = time.monotonic() - t0
    stop.set()
    await task
    single = np.array([cpu for cpu, n in drains if n == 1], dtype=np.int64)
    handed_over = sum(n for _, n in drains)
    result = {
        "commands": commands,
        "handed_over": handed_over,
        "drains": len(drains),
        "drain_cpu_us_p50": float(np.percentile(single, 50)) / 1e3,
        "drain_cpu_us_p90": float(np.percentile(single, 90)) / 1e3,
        "drain_cpu_us_mean": float(single.mean()) / 1e3,
        "offer_cpu_us_p50": float(np.percentile(offers, 50)) / 1e3,
        "offer_cpu_us_mean": float(np.mean(offers)) / 1e3,
        "loop_cpu_pct": 100.0 * loop_cpu / 1e9 / wall,
        "loop_idle_cpu_pct": idle_pct,
        "loop_listener_cpu_pct": listen_pct,
        "process_idle_cpu_pct": idle_process_pct,
        "process_listener_cpu_pct": listen_process_pct,
        # the loop's share difference per command: includes its wake-up, but the phase without
        # commands has work of its own (the mux idle, the car standing): no clean measure
        "loop_added_us": (100.0 * loop_cpu / 1e9 / wall - idle_pct) / 100.0 / (handed_over / wall) * 1e6,
    }
    if idle_prof is not None and busy_prof is not None:
        result["loop_profile"] = _difference(idle_prof, busy_prof, handed_over)
    if warm_cpu:
        result["warm_drain_cpu_us_p50"] = float(np.percentile(warm_cpu, 50)) / 1e3
        result["warm_parts_us_p50"] = {k: float(np.percentile(v, 50)) / 1e3 for k, v in warm_parts.items()}
    if profiler is not None:
        out = io.StringIO()
        stats = pstats.Stats(profiler, stream=out)
        result["calls_per_command"] = stats.total_calls / max(1, handed_over)  # type: ignore[attr-defined]
        stats.sort_stats("tottime").print_stats(25)
        if os.environ.get("BENCH_PROFILE"):  # a path: the whole profile, for pstats
            stats.dump_stats(os.environ["BENCH_PROFILE"])
        result["profile"] = out.getvalue()
    return result


def _difference(idle: cProfile.Profile, busy: cProfile.Profile, commands: int) -> str:
    """What the commands added to the whole loop thread's profile (the same time without them
    subtracted), per command: calls and CPU time of each function, the largest first."""
    def table(prof: cProfile.Profile) -> dict[tuple, tuple[int, float]]:
        stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
        return {func: (nc, tt) for func, (_cc, nc, tt, _ct, _callers) in stats.items()}

    before, after = table(idle), table(busy)
    rows = []
    for func in set(before) | set(after):
        nc0, tt0 = before.get(func, (0, 0.0))
        nc1, tt1 = after.get(func, (0, 0.0))
        rows.append(((tt1 - tt0) / commands * 1e6, (nc1 - nc0) / commands, func))
    rows.sort(reverse=True)
    total_tt = sum(r[0] for r in rows)
    total_nc = sum(r[1] for r in rows)
    lines = [f"whole loop thread, added per command: {total_nc:.0f} calls, {total_tt:.0f} us "
             "(profiled: slower than without)", "  us/cmd  calls/cmd  function"]
    for tt, nc, (path, line, name) in rows[:30]:
        where = f"{'/'.join(Path(path).parts[-2:])}:{line}" if line else path
        lines.append(f"{tt:8.1f} {nc:10.2f}  {where}({name})")
    return "\n".join(lines)


LISTENER = '''
import sys
from racecar_hw.client import Car
car = Car(f"tcp/127.0.0.1:{sys.argv[1]}")
for scan in car.scans(timeout=30):
    car.odom  # read, as a navigation node would
'''


def _process_share(seconds: float) -> float:
    """This process's CPU share of one core over the next ``seconds`` (blocks the caller)."""
    cpu0, t0 = time.process_time(), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (time.process_time() - cpu0) / (time.monotonic() - t0)


def _round_in(tree: str | None, commands: int, profile: bool) -> dict:
    """One round in a fresh process, importing ``tree`` first (None: this tree)."""
    env = dict(os.environ)
    if tree:
        env["PYTHONPATH"] = tree
    here = Path(__file__).resolve().parent
    code = (f"import sys, json; sys.path.insert(0, {str(here)!r}); import bench_command_path as b; "
            f"print('RESULT', json.dumps(b.measure({commands}, {profile!r})))")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          cwd=tempfile.gettempdir(), timeout=600, check=False)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"round failed: {proc.stderr[-3000:]}")


def run(commands: int = 400, rounds: int = 1, before: str | None = None,
        profile: bool = False) -> list[dict]:
    """Rows: the loop's CPU per command (median of each round's p50), the offer's; with ``before``,
    both settings interleaved, the order alternating round by round."""
    settings = {"after": None, **({"before": before} if before else {})}
    results: dict[str, list[dict]] = {name: [] for name in settings}
    for r in range(rounds):
        order = list(settings) if r % 2 == 0 else list(reversed(settings))
        for name in order:
            res = _round_in(settings[name], commands, profile)
            results[name].append(res)
            if "loop_profile" in res:
                print(f"--- {name}, round {r + 1}\n{res['loop_profile']}")
            if profile:
                print(f"--- {name}, round {r + 1}: {res['calls_per_command']:.0f} Python calls per "
                      f"command\n{res['profile']}")
    rows = []
    for name, runs in results.items():
        label = f" ({name})" if before else ""
        shown = list(_ROWS)
        if not math.isnan(runs[0]["loop_listener_cpu_pct"]):  # BENCH_LISTENER
            shown += _LISTENER_ROWS
        if profile:
            shown.append(("Python calls per command", "calls_per_command", ""))
        rows += [{"name": title + label, "value": float(np.median([x[key] for x in runs])),
                  "unit": unit, "target": None} for title, key, unit in shown]
    return rows


#: The rows of the table: (title, key of a round's result, unit), each the median over the rounds.
_ROWS = [
    ("loop CPU per command, drain + take_input, p50", "drain_cpu_us_p50", "us"),
    ("loop CPU per command, mean", "drain_cpu_us_mean", "us"),
    ("input thread CPU per offer_cdr, p50", "offer_cpu_us_p50", "us"),
    ("loop share difference per command (commanded - none)", "loop_added_us", "us"),
    ("event loop CPU share, no command", "loop_idle_cpu_pct", "%"),
    ("event loop CPU share while commanded", "loop_cpu_pct", "%"),
]
#: With BENCH_LISTENER: the shares with and without a listener of the scans and odometry.
_LISTENER_ROWS = [
    ("event loop CPU share, a listener (BENCH_LISTENER)", "loop_listener_cpu_pct", "%"),
    ("daemon process CPU share, no listener", "process_idle_cpu_pct", "%"),
    ("daemon process CPU share, a listener", "process_listener_cpu_pct", "%"),
]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("commands", nargs="?", type=int, default=400)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--before", help="another source tree, rounds alternating with this one")
    parser.add_argument("--profile", action="store_true", help="cProfile inside each hand-over")
    args = parser.parse_args()
    print(f"load average: {os.getloadavg()}", flush=True)
    print_rows(run(args.commands, args.rounds, args.before, args.profile))
    print(f"load average: {os.getloadavg()}")
