"""The refusal counts as a ``/diagnostics`` status, a panel line and status-page rows; and on the bus
of a running daemon, published with the mux's diagnostics."""

from __future__ import annotations

import asyncio
import logging

from conftest import async_wait_for

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.messages import DiagnosticArray, DiagnosticStatus
from racecar_hw.config import load_config
from racecar_hw.daemon import Daemon
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.security_status import STATUS_NAME, SecurityStatus
from racecar_hw.runtime.status import StatusSnapshot, plain_line


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000 * NS_PER_S

    def __call__(self) -> int:
        return self.ns


def _values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_nothing_refused_is_ok_and_says_so():
    clock = Clock()
    status = SecurityStatus(Refusals(logger=logging.getLogger("quiet"), clock=clock), clock=clock).status()
    assert (status.level, status.name) == (DiagnosticStatus.OK, STATUS_NAME)
    assert status.message == "nothing refused"
    assert _values(status) == {"refused in all": "0"}


def test_counts_per_surface_and_reason_warn_while_recent_then_ok():
    clock = Clock()
    refusals = Refusals(logger=logging.getLogger("quiet"), clock=clock)
    security = SecurityStatus(refusals, recent_s=10.0, clock=clock)
    for _ in range(100):
        refusals.note("zenoh", "10.0.0.9", "user/password: invalid password")
    refusals.note("mavlink", "10.0.0.8:14550", "bad signature", 3)
    refusals.note("web", "127.0.0.1", "no token")
    status = security.status()
    values = _values(status)
    assert status.level == DiagnosticStatus.WARN and status.message == "104 refused, the last 0 s ago"
    assert values["refused in all"] == "104"
    assert values["zenoh: user/password: invalid password"] == "100"
    assert values["mavlink: bad signature"] == "3" and values["web: no token"] == "1"
    # the sources with the most refusals are named, the worst first
    sources = [k for k in values if k.startswith("source ")]
    assert sources[0] == "source 10.0.0.9 (zenoh: user/password: invalid password)"
    assert security.rows() == [("mavlink", "bad signature", 3), ("web", "no token", 1),
                               ("zenoh", "user/password: invalid password", 100)]
    line = security.line()
    assert line == ("104 (recent): mavlink bad signature 3, web no token 1, "
                    "zenoh user/password: invalid password 100")
    clock.ns += 11 * NS_PER_S
    status = security.status()
    assert status.level == DiagnosticStatus.OK and status.message == "104 refused, none in the last 11 s"
    assert not security.recent() and "(recent)" not in (security.line() or "")
    refusals.note("web", "127.0.0.1", "no token")
    assert security.status().level == DiagnosticStatus.WARN


def test_the_panel_shows_a_refused_line_only_once_something_was_refused():
    assert "refused" not in plain_line(StatusSnapshot())
    line = plain_line(StatusSnapshot(refused="3 (recent): web no token 3"))
    assert "refused 3 (recent): web no token 3" in line


def test_the_daemon_publishes_the_security_status_with_the_mux_diagnostics():
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "zenoh.enabled=false",
                                "web.enabled=false", "foxglove.enabled=false", "gamepad.enabled=false",
                                "mavlink.enabled=false", "safety.mode=off"])
    bus = Bus()
    daemon = Daemon(config, bus=bus)
    got: list[DiagnosticArray] = []
    bus.subscribe(config.mux.diagnostics_topic, got.append)

    def security() -> list[DiagnosticStatus]:
        return [s for a in got for s in a.status if s.name == STATUS_NAME]

    async def main() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(daemon.run(stop))
        try:
            await async_wait_for(lambda: security(), timeout=30)
            daemon.refusals.note("web", "192.0.2.7", "too many connections", 5)
            await async_wait_for(lambda: security()[-1].level == DiagnosticStatus.WARN, timeout=30)
        finally:
            stop.set()
            await task

    asyncio.run(main())
    names = [s.name for a in got for s in a.status]  # one of each per diagnostics tick
    assert abs(names.count(STATUS_NAME) - names.count("racecar_hw: command mux")) <= 1
    assert _values(security()[-1])["web: too many connections"] == "5"
    assert daemon.live_state().refused == (("web", "too many connections", 5),)
    assert daemon.snapshot().refused is not None and "web too many connections 5" in daemon.snapshot().refused
