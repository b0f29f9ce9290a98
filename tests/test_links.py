"""racecar_hw.runtime.links: link states for the panel, and reminders while a device stays away."""

from __future__ import annotations

import logging

import pytest

from racecar_hw.runtime.links import LinkWatch

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

S = 1_000_000_000


class Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def test_connecting_up_lost_and_reminders(caplog) -> None:
    caplog.set_level(logging.WARNING)
    clock = Clock()
    up = {"v": False}
    watch = LinkWatch("VESC", lambda: up["v"], detail=lambda: "no serial device at /dev/vesc",
                      remind_s=10.0, remind_max_s=40.0, clock=clock, wall=lambda: 0.0)
    assert watch.poll() == "connecting" and watch.text() == "connecting 0 s"
    reminders = []
    for t in range(1, 121):  # two minutes without the VESC: reminded at 10, 30, 70, 110 s
        clock.ns = t * S
        watch.poll()
        if watch.reminders > len(reminders):
            reminders.append(t)
    assert reminders == [10, 30, 70, 110]
    assert "VESC still not connected after 10 s (no serial device at /dev/vesc); retrying" in caplog.text
    assert watch.text() == "connecting 120 s"
    up["v"] = True
    assert watch.poll() == "up" and watch.text() == "up"
    assert "VESC link up after 120 s" in caplog.text
    clock.ns = 200 * S
    up["v"] = False
    assert watch.poll() == "lost"
    caplog.clear()
    clock.ns = 211 * S
    watch.poll()
    assert "VESC still lost after 11 s" in caplog.text
    clock.ns = 235 * S
    assert watch.text().startswith("lost since ") and watch.text().endswith("(35 s)")
