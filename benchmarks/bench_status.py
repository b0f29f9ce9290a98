"""Cost of what the operator sees: the link watches and one status-panel frame.

The daemon polls a :class:`~racecar_hw.runtime.links.LinkWatch` per device (VESC, lidar) every
0.5 s on its event loop; the panel renders a snapshot 4 times a second on a terminal (and not at
all under systemd). Both run next to the scan path, so their cost per call is what a scan can wait
behind, and their cost per second what they add to the daemon's CPU at nominal load.

Run ``python benchmarks/bench_status.py``; ``run()`` returns the rows for run_all.py.
"""

from __future__ import annotations

import io

from bench_mux import _best_us
from rich.console import Console
from table import print_rows

from racecar_hw.daemon import LINK_POLL_S
from racecar_hw.runtime.links import LinkWatch
from racecar_hw.runtime.panel import render
from racecar_hw.runtime.status import StatusSnapshot

SNAPSHOT = StatusSnapshot(speed_mps=1.25, steering_rad=-0.15, mux_source="nav_0", battery_v=11.8,
                          scan_rate_hz=39.9, safety_state="clear", vesc_crc_errors=0, armed=True,
                          vesc_link="up", lidar_link="lost since 14:02:31 (35 s)", sim_time_s=12.3,
                          sim_pose=(1.5, -2.0, 1.2), clearance_m=0.6)


def run() -> list[dict]:
    """Rows: one link poll (up, and down with its state text), CPU share of two watches, one frame."""
    up = LinkWatch("VESC", lambda: True)
    down = LinkWatch("lidar", lambda: False, remind_s=1e9)
    poll_up = _best_us(up.poll, 20000)
    poll_down = _best_us(lambda: (down.poll(), down.text()), 20000)
    share = 2 * max(poll_up, poll_down) / LINK_POLL_S / 1e6 * 100  # VESC and lidar, % of one core
    console = Console(file=io.StringIO(), width=100, force_terminal=True)
    frame = _best_us(lambda: console.print(render(SNAPSHOT)), 200) / 1000
    return [
        {"name": "link_watch_poll_up", "value": poll_up, "unit": "us", "target": None},
        {"name": "link_watch_poll_down_with_text", "value": poll_down, "unit": "us", "target": None},
        {"name": "link_watches_cpu_share", "value": share, "unit": "% of a core", "target": None},
        {"name": "status_panel_frame", "value": frame, "unit": "ms", "target": None},
    ]


if __name__ == "__main__":
    print_rows(run())
