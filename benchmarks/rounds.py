"""Settings of one benchmark run interleaved, so that a noisy spell on a shared host hits each alike.

Each setting leads a round in turn, so no setting always runs right after the same other one (a
fixed order showed up as a steady +0.07-0.09 ms in a p99 on this host; see docs/benchmarks.md).
Use a multiple of the number of settings as the number of rounds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

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
