"""The daemon at nominal load: CPU share, peak memory, scan-to-command latency.

Load: a UST-10LX streaming 1081-beam scans at 40 Hz over TCP, the VESC polled at 50 Hz with a
command stream at 50 Hz, the safety controller on, the recorder writing every topic to MCAP, and
a navigation source (figure-8 driver) at 20 Hz. The fake devices run in this process; the daemon
runs alone in a ``racecar-hw run`` subprocess, so its CPU time (utime + stime) and peak RSS (VmHWM)
are its own; so is its PSS at the end of the measurement (smaps_rollup: its private memory plus its
share of the pages it shares with other processes, smem's measure).

Latency, two ways:

- in the daemon (the target): from the read that completed a scan frame returning to the resulting
  VESC command written, as the daemon measures it and logs in its shutdown summary. The daemon
  also splits each of these into its loop thread's CPU time and the rest, the time the thread was
  off the CPU: preempted by another thread, or its virtual CPU not running at all (steal);
- round trip (for information): from the fake lidar handing a frame to the socket until the fake
  VESC reads the next motor command. It adds both links and this process's own thread scheduling
  (the fakes share one interpreter here), and a 50 Hz control tick landing in the window by chance
  can make a sample shorter than the scan path alone.

The last row is the share of the machine's busy CPU time that the hypervisor gave to other
tenants during the run (``steal`` in /proc/stat): on a shared virtual machine it is what makes the
p99 vary from run to run.

The fake lidar sees the shipped room map (racecar_hw.sim's world) from where the fake VESC's
motor and servo have driven the car. The daemon runs twice, with the safety controller's obstacle
memory off and then on (the default), so that what the memory adds to the CPU share and to the
scan-to-command latency is measured in one run; ``--memory on|off`` runs only one. ``run()`` (for
run_all.py and the other daemon benchmarks) runs once with the shipped default unless asked.

Run ``python benchmarks/bench_daemon.py [SECONDS] [--no-recorder] [--memory on|off | --imu |
--all-interfaces]`` (``--imu``: four runs, the VESC's IMU off, on, on, off; ``--all-interfaces``:
one run with Zenoh and DDS on as well as the Foxglove live view and the status page, nobody
connected, as the car runs by default); ``run()``
returns the rows for run_all.py. ``BENCH_VERBOSE=1`` also prints round-trip percentiles, the CPU
share of each daemon thread and of the benchmark's own fakes; ``BENCH_PROFILE=PATH`` runs the
daemon under cProfile.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, ExitStack
from pathlib import Path

import numpy as np
import yaml
from fakes import room_fakes
from rounds import thread_cpu_s
from table import print_rows

from vesc.codec import SetCurrent, SetCurrentBrake, SetRpm

CPU_TARGET = 10.0   # percent of one core
RSS_TARGET = 150.0  # MB
PSS_TARGET = 90.0  # MB, with every interface on (issue 26)
LATENCY_P99_TARGET = 2.0  # ms


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _thread_wakeups(pid: int) -> dict[str, int]:
    """Voluntary context switches per thread of a process, by thread name: each is the thread
    blocking (on a lock, a queue, epoll, a timer) and being woken again, a wake-up."""
    out: dict[str, int] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            status = (task / "status").read_text()
        except OSError:
            continue
        for line in status.splitlines():
            if line.startswith("voluntary_ctxt_switches:"):
                out[f"{name}[{task.name}]"] = int(line.split()[1])
    return out


def _host_ticks() -> tuple[int, int]:
    """(busy, stolen) clock ticks of all CPUs so far, from /proc/stat (steal: time the hypervisor
    gave this virtual machine's CPUs to others while they had work)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle, iowait
    return sum(fields[:8]) - idle, fields[7]


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


#: With ``--all-interfaces``, besides Zenoh on a free port: DDS on a domain of its own, and the
#: Foxglove live view and the status page (on by default; here on free ports); nobody connected.
ALL_INTERFACES = {"dds": {"enabled": True, "domain_id": 177}}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pss_mb(pid: int) -> float:
    """The process's proportional set size (MB): its private pages plus its share of each page it
    shares with other processes (shared libraries), as smem reports it; /proc/PID/smaps_rollup."""
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
        if line.startswith("Pss:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def run(seconds: float = 20.0, recorder: bool = True, zenoh_port: int | None = None,
        helpers: list[list[str]] | None = None, on_results: object = None, *,
        config_extra: dict | None = None,
        attach: Callable[[Path], AbstractContextManager[object]] | None = None,
        memory: tuple[bool, ...] | None = None) -> list[dict]:
    """The rows for one run. ``zenoh_port``: the Zenoh bridge on, listening there (None: off).

    ``helpers``: commands started once the daemon runs and stopped after the measurement (Zenoh
    subscribers, a remote client); ``on_results(sent_ns, commands)``, if given, is called with the
    fake lidar's frame send times and the fake VESC's commands, and returns extra rows.
    ``config_extra`` sections are merged into the daemon's config, and ``attach(log_path)`` (once the
    daemon runs) returns a context kept open while measuring: clients of the live interfaces, for
    bench_live.py. ``memory``: one run per obstacle-memory setting, in that order, each row's name
    ending in the setting (None: one run with the shipped default, the memory on).
    """
    if memory is None:
        return _run_once(seconds, recorder, zenoh_port, helpers, on_results, config_extra, attach, None)
    rows = []
    for enabled in memory:
        label = "memory on" if enabled else "memory off"
        for row in _run_once(seconds, recorder, zenoh_port, helpers, on_results, config_extra, attach,
                             enabled):
            rows.append({**row, "name": f"{row['name']}, {label}"})
    return rows


def _run_once(seconds: float, recorder: bool, zenoh_port: int | None, helpers: list[list[str]] | None,
              on_results: object, config_extra: dict | None,
              attach: Callable[[Path], AbstractContextManager[object]] | None,
              memory: bool | None) -> list[dict]:
    # Each fake in its own thread, and a short GIL switch interval, so that the fake VESC reads a
    # command when it arrives rather than after the fake lidar has encoded its next frame.
    sys.setswitchinterval(0.0002)
    # the car drives its figure-8 in the shipped room, and the lidar sees the room from where the
    # car is (the obstacle memory's load depends on a world that stays put)
    with tempfile.TemporaryDirectory() as tmp, room_fakes(tmp) as (vesc, lidar):
        host, port = lidar.tcp_address
        config = {
            "vesc": {"port": f"{tmp}/vesc", "poll_rate_hz": 50.0},
            "lidar": {"model": "ust-10lx", "tcp": f"{host}:{port}"},
            "mux": {"rate_hz": 50.0},
            "safety": {"mode": "arc", **({} if memory is None else {"memory": {"enabled": memory}})},
            "recorder": {"enabled": recorder, "path": f"{tmp}/bags", "format": "mcap"},
            "figure8": {"enabled": True, "speed_mps": 0.5, "steering_angle_rad": 0.25, "figure8s": 0},
            "arming": {"start_armed": True},
            "gamepad": {"enabled": False},
            "status": {"enabled": False},
            # the shipped defaults (on, loopback) on free ports: no clients, so they send nothing
            "foxglove": {"port": 0},
            "web": {"port": 0},
            "zenoh": ({"enabled": True, "listen": [f"tcp/127.0.0.1:{zenoh_port}"]}
                      if zenoh_port else {"enabled": False}),
            # off unless a benchmark turns it on (bench_dds.py): the rows stay comparable
            "dds": {"enabled": False},
        }
        if helpers and any("--drives" in h for h in helpers):
            config["figure8"] = {"enabled": False}  # the remote client drives nav_0
        for section, values in (config_extra or {}).items():
            config.setdefault(section, {}).update(values)
        cfg = Path(tmp) / "bench.yaml"
        cfg.write_text(yaml.safe_dump(config))
        profile = os.environ.get("BENCH_PROFILE")  # a path: run the daemon under cProfile
        profile = os.path.abspath(profile) if profile else None  # the daemon runs in tmp
        prefix = ["-m", "cProfile", "-o", profile] if profile else []
        command = [sys.executable, *prefix, "-m", "racecar_hw.cli", "-v", "run", "--config", str(cfg)]
        log_path = Path(tmp) / "daemon.log"
        log_file = log_path.open("w")
        # started in the temporary directory: ``-m`` and ``-c`` put the working directory first on
        # sys.path, which would shadow the tree PYTHONPATH names (the --before settings)
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=log_file, text=True, cwd=tmp)
        clients = ExitStack()
        others: list[subprocess.Popen] = []
        try:
            deadline = time.monotonic() + 60  # a loaded machine (load 20 on 2 cores) took more than 20 s
            while lidar.clients == 0 or len(vesc.commands) < 50:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError(f"daemon did not start: {log_path.read_text()[-2000:]}")
                time.sleep(0.05)
            if attach is not None:
                clients.enter_context(attach(log_path))
            others = [subprocess.Popen(h, stdout=subprocess.DEVNULL, cwd=tmp) for h in helpers or []]
            time.sleep(4.0 if others else 2.0)  # warm up: caches, first bag chunk, helpers connected
            lidar.frames_sent_ns.clear()
            vesc.clear_commands()
            threads0 = thread_cpu_s(proc.pid)
            wakeups0 = _thread_wakeups(proc.pid)
            helper_threads0 = [(o, thread_cpu_s(o.pid)) for o in others]
            fakes0 = time.process_time()
            host0 = _host_ticks()
            spies = _spy(proc.pid, others, seconds)
            helpers0 = sum(_cpu_s(o.pid) for o in others)
            cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
            time.sleep(seconds)
            cpu1, t1 = _cpu_s(proc.pid), time.monotonic()
            helpers1 = sum(_cpu_s(o.pid) for o in others)
            for spy in spies:
                spy.wait(30)
            host1 = _host_ticks()
            fakes1 = time.process_time()
            threads1 = thread_cpu_s(proc.pid)
            wakeups1 = _thread_wakeups(proc.pid)
            helper_threads = [(o.args, t0_, thread_cpu_s(o.pid)) for o, t0_ in helper_threads0]
            rss = _peak_rss_mb(proc.pid)
            pss = _pss_mb(proc.pid)
            sent = np.array(lidar.frames_sent_ns, dtype=np.int64)
            commands = list(vesc.commands)
            motor = np.array([c.t_ns for c in commands
                              if isinstance(c.packet, (SetRpm, SetCurrentBrake, SetCurrent))], dtype=np.int64)
        finally:
            clients.close()
            for other in others:
                other.terminate()
                try:
                    other.wait(10)
                except subprocess.TimeoutExpired:
                    other.kill()
            proc.terminate()
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
            log_file.close()
        summary = _summary(log_path.read_text())
    idx = np.searchsorted(motor, sent, side="right")
    ok = idx < len(motor)
    latency_ms = (motor[idx[ok]] - sent[ok]) / 1e6
    if os.environ.get("BENCH_VERBOSE"):
        qs = (50, 75, 90, 95, 98, 99, 100)
        print("latency percentiles (ms):", {q: round(float(np.percentile(latency_ms, q)), 2) for q in qs},
              file=sys.stderr)
        print(f"the benchmark's fakes: {100.0 * (fakes1 - fakes0) / (t1 - t0):.2f} % of a core",
              file=sys.stderr)
        for name, cpu in sorted(threads1.items()):
            share = 100.0 * (cpu - threads0.get(name, 0.0)) / (t1 - t0)
            rate = (wakeups1.get(name, 0) - wakeups0.get(name, 0)) / (t1 - t0)
            print(f"thread {name}: {share:.2f} % of a core, {rate:.1f} wake-ups/s", file=sys.stderr)
        for args, before, after in helper_threads:
            print(f"helper {' '.join(map(str, args))[-60:]!r}:", file=sys.stderr)
            for name, cpu in sorted(after.items()):
                share = 100.0 * (cpu - before.get(name, 0.0)) / (t1 - t0)
                if share >= 0.05:
                    print(f"  thread {name}: {share:.2f} % of a core", file=sys.stderr)
    scans = len(sent)
    extra = on_results(sent, commands) if callable(on_results) else []
    rows = [
        {"name": "daemon CPU share of one core", "value": 100.0 * (cpu1 - cpu0) / (t1 - t0),
         "unit": "%", "target": CPU_TARGET},
        {"name": "daemon thread wake-ups per second", "unit": "/s", "target": None,
         "value": sum(n - wakeups0.get(name, 0) for name, n in wakeups1.items()) / (t1 - t0)},
        {"name": "helpers' CPU share of one core", "value": 100.0 * (helpers1 - helpers0) / (t1 - t0),
         "unit": "%", "target": None},
        {"name": "daemon peak RSS", "value": rss, "unit": "MB", "target": RSS_TARGET},
        {"name": "daemon PSS at the end of the measurement", "value": pss, "unit": "MB",
         "target": PSS_TARGET},
        {"name": "scans during measurement", "value": scans, "unit": "scans", "target": None},
        {"name": "scan rate", "value": scans / (t1 - t0), "unit": "Hz", "target": None},
        {"name": "scan to VESC command p50 (in daemon)", "value": summary["p50"], "unit": "ms",
         "target": None},
        {"name": "scan to VESC command p99 (in daemon)", "value": summary["p99"], "unit": "ms",
         "target": LATENCY_P99_TARGET},
        {"name": "  the daemon's CPU time in it, p50", "value": summary["cpu_p50"], "unit": "ms",
         "target": None},
        {"name": "  the daemon's CPU time in it, p99", "value": summary["cpu_p99"], "unit": "ms",
         "target": None},
        {"name": "  the time off the CPU in it, p99", "value": summary["off_cpu_p99"], "unit": "ms",
         "target": None},
        {"name": "round trip fake lidar to fake VESC p50", "value": float(np.percentile(latency_ms, 50)),
         "unit": "ms", "target": None},
        {"name": "round trip fake lidar to fake VESC p99", "value": float(np.percentile(latency_ms, 99)),
         "unit": "ms", "target": None, "samples": latency_ms},
        {"name": "host: CPU time stolen by the hypervisor", "unit": "% of busy",
         "value": 100.0 * (host1[1] - host0[1]) / max(1, host1[0] - host0[0]), "target": None},
    ]
    return rows + list(extra)


def _spy(daemon: int, helpers: list[subprocess.Popen], seconds: float) -> list[subprocess.Popen]:
    """With ``BENCH_PYSPY=DIR``: py-spy samples the daemon and each helper while measuring (collapsed
    stacks per thread, DIR/daemon-N.txt and DIR/helper-N-K.txt; N counts the runs)."""
    out = os.environ.get("BENCH_PYSPY")
    if not out:
        return []
    spy = Path(sys.executable).with_name("py-spy")
    n = len(list(Path(out).glob("daemon-*.txt")))
    targets = [(daemon, f"daemon-{n}")] + [(h.pid, f"helper-{n}-{k}") for k, h in enumerate(helpers)]
    return [subprocess.Popen([str(spy), "record", "--nonblocking", "--threads", "--format", "raw",
                              "-r", "250", "-d", str(int(seconds)), "-o", f"{out}/{name}.txt",
                              "--pid", str(pid)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for pid, name in targets]


def _summary(log: str) -> dict[str, float]:
    """The scan-to-command latencies from the daemon's shutdown summary line."""
    match = re.search(r"scan-to-command latency p50=([\d.]+) ms p99=([\d.]+) ms .*; "
                      r"on the CPU p50=([\d.]+) ms p99=([\d.]+) ms; off it p99=([\d.]+) ms", log)
    if match is None:
        raise RuntimeError("the daemon logged no control summary:\n" + log[-2000:])
    return dict(zip(("p50", "p99", "cpu_p50", "cpu_p99", "off_cpu_p99"),
                    map(float, match.groups()), strict=True))


def _against(seconds: float, before: str, rounds: int) -> list[dict]:
    """The nominal-load daemon with Zenoh and DDS on and nobody listening, this code against the
    source tree ``before`` (the daemon importing it), interleaved for ``rounds`` rounds; medians."""
    from rounds import code_from, interleaved, pooled_p99  # noqa: PLC0415

    def nominal() -> list[dict]:
        return run(seconds, zenoh_port=_free_port(), config_extra=ALL_INTERFACES)

    results = interleaved({"this code": nominal, "before": code_from(before, nominal)}, rounds)
    names = ("daemon CPU share of one core", "scan to VESC command p50 (in daemon)",
             "scan to VESC command p99 (in daemon)", "  the daemon's CPU time in it, p99",
             "daemon thread wake-ups per second", "host: CPU time stolen by the hypervisor")
    rows = []
    for label, runs in results.items():
        for name in names:
            values = [next(r["value"] for r in rows_ if r["name"] == name) for rows_ in runs]
            rows.append({"name": f"{label}: {name.strip()} (median of {len(values)}; "
                                 f"{min(values):.2f}-{max(values):.2f})",
                         "value": float(np.median(values)), "unit": "", "target": None})
        rows.append({"name": f"{label}: round trip lidar to VESC, p99 of all rounds' scans",
                     "value": pooled_p99(runs), "unit": "ms", "target": None})
    return rows


def main() -> None:
    args = sys.argv[1:]
    seconds = float(args[0]) if args and not args[0].startswith("-") else 20.0
    memory: tuple[bool, ...] = (False, True)
    if "--memory" in args:
        memory = (args[args.index("--memory") + 1] == "on",)
    if "--imu" in args:  # the VESC's IMU polled or not, alternating off, on, on, off (issue 28)
        rows = []
        for on in (False, True, True, False):
            for row in run(seconds, recorder="--no-recorder" not in args, config_extra={"vesc": {"imu": on}}):
                rows.append({**row, "name": f"{row['name']}, imu {'on' if on else 'off'}"})
        print_rows(rows)
        return
    if "--before" in args:  # this code against another tree, every interface on, nobody listening
        print_rows(_against(seconds, args[args.index("--before") + 1],
                            int(args[args.index("--rounds") + 1]) if "--rounds" in args else 4))
        return
    if "--all-interfaces" in args:  # issue 26: the memory with every network interface on
        print_rows(run(seconds, recorder="--no-recorder" not in args, zenoh_port=_free_port(),
                       config_extra=ALL_INTERFACES))
        return
    rows = run(seconds, recorder="--no-recorder" not in args, memory=memory)
    print_rows(rows)


if __name__ == "__main__":
    main()
