"""Run every benchmark and print one table: ``python benchmarks/run_all.py [NAME ...]``.

Each ``bench_<area>.py`` exposes ``run() -> list[dict]`` with rows {name, value, unit, target}.
Targets are what this machine (2 cores) should reach; a row that misses its target is marked
(rates, in units per second, must reach the target; everything else must stay under it).
Nothing here asserts: benchmarks measure, tests check behaviour.
"""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ALL = ("vesc", "lidar_scip", "lidar_rplidar", "mux", "safety", "scan_path", "sim", "bags", "daemon")


def main(argv: list[str]) -> int:
    sys.path.insert(0, str(HERE))
    names = argv or list(ALL)
    rows: list[tuple[str, dict]] = []
    for name in names:
        module = importlib.import_module(f"bench_{name}")
        started = time.perf_counter()
        for row in module.run():
            rows.append((name, row))
        print(f"  {name}: {time.perf_counter() - started:.1f} s", file=sys.stderr)
    width = max(len(r["name"]) for _, r in rows)
    print(f"{'area':14} {'benchmark':{width}} {'value':>12} {'unit':10} {'target':>10}")
    for area, r in rows:
        target = r.get("target")
        value = r["value"]
        shown = f"{value:12.4g}" if isinstance(value, (int, float)) else f"{value!s:>12}"
        flag = ""
        if isinstance(target, (int, float)) and isinstance(value, (int, float)):
            higher_is_better = r.get("higher_is_better", str(r.get("unit", "")).endswith("/s"))
            met = value >= target if higher_is_better else value <= target
            flag = "" if met else "  MISSED"
        t = "" if target is None else f"{target:g}"
        print(f"{area:14} {r['name']:{width}} {shown} {r.get('unit', ''):10} {t:>10}{flag}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
