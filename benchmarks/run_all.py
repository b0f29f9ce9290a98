"""Run every benchmark and print one table: ``python benchmarks/run_all.py [NAME ...]``.

Each ``bench_<area>.py`` exposes ``run() -> list[dict]`` with rows {name, value, unit, target}.
Targets are what this machine (2 cores) should reach; :mod:`table` marks a row that misses its.
Nothing here asserts: benchmarks measure, tests check behaviour.
"""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

from table import print_rows

HERE = Path(__file__).resolve().parent
ALL = ("vesc", "lidar_scip", "lidar_rplidar", "mux", "command_path", "safety", "scan_path", "sim",
       "sim_env", "bags", "status", "daemon", "live", "zenoh", "mavlink", "rosnode", "safety_scenarios",
       "lockstep", "fuzz")
#: Benchmarks whose module is not bench_<name>.py.
MODULES = {"fuzz": "fuzz"}


def main(argv: list[str]) -> int:
    sys.path.insert(0, str(HERE))
    names = argv or list(ALL)
    unknown = [name for name in names if name not in ALL]
    if unknown:
        print(f"unknown benchmark {', '.join(unknown)}; choose from {', '.join(ALL)}", file=sys.stderr)
        return 2
    rows: list[tuple[str, dict]] = []
    for name in names:
        module = importlib.import_module(MODULES.get(name, f"bench_{name}"))
        started = time.perf_counter()
        for row in module.run():
            rows.append((name, row))
        print(f"  {name}: {time.perf_counter() - started:.1f} s", file=sys.stderr)
    print_rows([r for _, r in rows], areas=[area for area, _ in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
