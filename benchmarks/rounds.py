"""Settings of one benchmark run interleaved, so that a noisy spell on a shared host hits each alike.

Each setting leads a round in turn, so no setting always runs right after the same other one (a
fixed order showed up as a steady +0.07-0.09 ms in a p99 on this host; see docs/benchmarks.md).
Use a multiple of the number of settings as the number of rounds.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

T = TypeVar("T")


def interleaved(settings: dict[str, Callable[[], T]], rounds: int) -> dict[str, list[T]]:
    """Run every setting once per round, the order rotated by one each round; results per setting."""
    labels = list(settings)
    results: dict[str, list[T]] = {label: [] for label in labels}
    for n in range(rounds):
        k = n % len(labels)
        for label in labels[k:] + labels[:k]:
            results[label].append(settings[label]())
    return results


def code_from(tree: str | None, fn: Callable[[], T]) -> Callable[[], T]:
    """``fn`` with the daemon and its helpers importing racecar-hw from ``tree`` (None: this one):
    ``PYTHONPATH`` set for the processes it starts (they start outside the repo, so it decides)."""
    if tree is None:
        return fn

    def run_there() -> T:
        before = os.environ.get("PYTHONPATH")
        os.environ["PYTHONPATH"] = tree
        try:
            return fn()
        finally:
            if before is None:
                del os.environ["PYTHONPATH"]
            else:
                os.environ["PYTHONPATH"] = before

    return run_there


ROUND_TRIP_P99 = "round trip fake lidar to fake VESC p99"


def pooled_p99(runs: list[list[dict]]) -> float:
    """The p99 (ms) of every round-trip sample of ``runs`` (bench_daemon rows) taken together.

    A p99 of one 20 s run rests on its 8 slowest scans, and the median of a few such p99s moves by
    0.1 ms between runs of the same code on this host; thousands of samples from every round
    pinned down together move far less.
    """
    samples = [row["samples"] for rows in runs for row in rows if row["name"] == ROUND_TRIP_P99]
    return float(np.percentile(np.concatenate(samples), 99))


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds of each thread of process ``pid`` so far, by thread name and id (/proc, Linux)."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        out[f"{name}[{task.name}]"] = cpu
    return out
