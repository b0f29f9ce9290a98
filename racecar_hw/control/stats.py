"""Counters of the control path: ticks, missed ticks, scan cuts, the scan rate and the
scan-to-command latencies (monotonic ns; reported in milliseconds)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from racecar_hw.base.clock import NS_PER_S

#: The scan rate counts the arrivals of this last stretch of time (ns; 1 s, the age past which the
#: MAVLink telemetry calls the lidar unhealthy): with none for that long the rate is 0 Hz, not the
#: rate from before the lidar went quiet. A lidar silent for ``lidar.stale_timeout_s`` (0.5 s) is
#: reconnected, so a working one has at least two arrivals in it.
SCAN_RATE_WINDOW_NS = NS_PER_S


@dataclass
class ControlStats:
    """Counters of the control loop."""

    ticks: int = 0
    missed_ticks: int = 0
    scan_cuts: int = 0
    last_tick_ns: int = 0
    #: recent scan-to-command latencies (ns): from the read that completed a scan returning to the
    #: scan path's VESC command written
    scan_to_command_ns: deque[int] = field(default_factory=lambda: deque(maxlen=100_000))
    #: the loop thread's CPU time (ns) in each of those: the rest of a latency is time the thread
    #: was off the CPU (preempted, or its virtual CPU not running)
    scan_to_command_cpu_ns: deque[int] = field(default_factory=lambda: deque(maxlen=100_000))
    #: arrival times (monotonic ns) of the last scans, for :meth:`scan_rate_hz`
    scan_times: deque[int] = field(default_factory=lambda: deque(maxlen=20))

    def note_scan(self, now_ns: int) -> None:
        """A scan arrived at ``now_ns`` (monotonic ns)."""
        self.scan_times.append(now_ns)

    def scan_rate_hz(self, now_ns: int) -> float:
        """Scans per second (Hz) over the last :data:`SCAN_RATE_WINDOW_NS` before ``now_ns``
        (monotonic ns): 0 with fewer than two arrivals in it (none yet, or the lidar went quiet)."""
        recent = [t for t in self.scan_times if now_ns - t <= SCAN_RATE_WINDOW_NS]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) * NS_PER_S / max(1, recent[-1] - recent[0])

    def latency_ms(self) -> dict[str, float]:
        """Percentiles of the recent scan-to-command latencies, milliseconds.

        ``p50``, ``p99``, ``max`` and ``count`` of the latencies; ``cpu_p50`` and ``cpu_p99`` of the
        CPU time in them, ``off_cpu_p99`` of the time off the CPU.
        """
        if not self.scan_to_command_ns:
            return {}
        wall = list(self.scan_to_command_ns)
        cpu = list(self.scan_to_command_cpu_ns)
        off = [w - c for w, c in zip(wall, cpu, strict=True)]
        return {"p50": _percentile(wall, 50) / 1e6, "p99": _percentile(wall, 99) / 1e6,
                "max": max(wall) / 1e6, "count": float(len(wall)),
                "cpu_p50": _percentile(cpu, 50) / 1e6, "cpu_p99": _percentile(cpu, 99) / 1e6,
                "off_cpu_p99": _percentile(off, 99) / 1e6}

    def summary(self) -> str:
        """One line for the log at exit; says so when no scan's command was timed (never ``nan``)."""
        head = f"{self.ticks} ticks, {self.missed_ticks} missed, {self.scan_cuts} scan cuts"
        lat = self.latency_ms()
        if not lat:
            return f"{head}; no scan-to-command latency measured (no scan led to a motor command)"
        return (f"{head}; scan-to-command latency p50={lat['p50']:.3f} ms p99={lat['p99']:.3f} ms "
                f"max={lat['max']:.3f} ms over {int(lat['count'])} scans; on the CPU "
                f"p50={lat['cpu_p50']:.3f} ms p99={lat['cpu_p99']:.3f} ms; off it "
                f"p99={lat['off_cpu_p99']:.3f} ms")


def _percentile(values: list[int], q: int) -> int:
    """The ``q``-th percentile of ``values`` (not empty): the nearest rank, no interpolation."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, (q * len(ordered)) // 100)]
