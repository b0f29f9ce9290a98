"""Stop is for anyone, release is for an operator: the mux's e-stop latch on the real bus.

Who engaged the latch decides who may release it (:mod:`mux.estop`): an operator surface releases
any latch, the plain release topic (from a network session, or from code on the bus) only a latch
the e-stop topic alone engaged, and only where ``mux.estop_release_sources`` names it. The live
acceptance runs (real sim, Zenoh sessions, the status page) are in tests/test_estop_live.py.
"""

from __future__ import annotations

import logging

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mux.arbiter import MuxState
from mux.estop import (
    DAEMON,
    OPERATORS,
    REFUSED_ASSERTED,
    REFUSED_NOT_ALLOWED,
    REFUSED_OPERATOR_LATCH,
    RELEASE_SOURCES,
    SURFACES,
    EstopRecord,
    Origin,
    release_refusal,
)
from mux.node import CommandMux
from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDriveStamped, Bool, DiagnosticArray
from racecar_hw.base.params import build
from racecar_hw.runtime.refusals import Refusals

WALL_NS = 1_700_000_000_123_456_789
WEB = Origin("web", "web page (127.0.0.1)")
FOX = Origin("foxglove", "foxglove client 3")
NET = Origin("network", "zenoh")


def _mux(refusals: Refusals | None = None, **overrides) -> tuple[Bus, CommandMux]:
    bus = Bus()
    return bus, CommandMux(bus, MuxParams(**overrides), clock=lambda: 5_000_000_000,
                           wall_clock=lambda: WALL_NS, refusals=refusals)


def _values(mux: CommandMux) -> dict[str, str]:
    return {kv.key: kv.value for kv in mux.diagnostics().status[0].values}


def test_an_operator_latch_is_not_released_by_the_topic_from_the_network_or_the_bus():
    bus, mux = _mux()
    mux.engage_estop("e-stop from web page", WEB)
    for _ in range(5):  # what the attacker sent: false, then release
        mux.publish_from(NET, "/estop", Bool(False))
        mux.publish_from(NET, "/estop_release", Bool(True))
        bus.publish("/estop_release", Bool(True))  # code on the bus: not an operator either
    assert mux.state is MuxState.ESTOP
    assert mux.release_refusals == 10
    assert mux.last_refusal == f"local topic (/estop_release): {REFUSED_OPERATOR_LATCH}"
    values = _values(mux)
    assert values["estop"].startswith("latched by web page (127.0.0.1) at ")
    assert values["estop_release_refusals"] == "10"
    # Foxglove is an operator: it may release what the page latched
    assert mux.release_estop(FOX)
    assert mux.state is MuxState.RUNNING
    assert _values(mux)["estop"].startswith("released by foxglove client 3 at ")


def test_a_topic_latch_is_released_by_the_topic_where_the_config_allows_it():
    bus, mux = _mux()
    mux.publish_from(NET, "/estop", Bool(True))
    assert mux.state is MuxState.ESTOP
    assert mux.estop is not None and mux.estop.by == NET
    mux.publish_from(NET, "/estop_release", Bool(True))
    assert mux.state is MuxState.ESTOP  # the topic still says true
    assert mux.last_refusal.endswith(REFUSED_ASSERTED)
    mux.publish_from(NET, "/estop", Bool(False))
    mux.publish_from(NET, "/estop_release", Bool(True))
    assert mux.state is MuxState.RUNNING
    assert mux.estop.released_by == NET


def test_a_topic_latch_is_not_released_by_the_topic_where_the_config_leaves_network_out():
    _bus, mux = _mux(estop_release_sources=list(OPERATORS))
    mux.publish_from(NET, "/estop", Bool(True))
    mux.publish_from(NET, "/estop", Bool(False))
    mux.publish_from(NET, "/estop_release", Bool(True))
    assert mux.state is MuxState.ESTOP
    assert mux.last_refusal == f"network topic (zenoh): {REFUSED_NOT_ALLOWED}"
    assert mux.release_estop(WEB)


def test_an_operator_who_engages_a_topic_latch_again_makes_it_an_operator_latch():
    _bus, mux = _mux()
    mux.publish_from(NET, "/estop", Bool(True))
    mux.engage_estop("e-stop from web page", WEB)
    mux.publish_from(NET, "/estop", Bool(False))
    mux.publish_from(NET, "/estop_release", Bool(True))
    assert mux.state is MuxState.ESTOP
    assert "(also by web page (127.0.0.1))" in mux.estop_text()


def test_start_estopped_and_a_fault_reset_are_released_only_by_an_operator():
    bus, mux = _mux(start_estopped=True)
    bus.publish("/estop_release", Bool(True))
    mux.publish_from(NET, "/estop_release", Bool(True))
    assert mux.state is MuxState.ESTOP
    assert mux.estop_text().startswith("latched by mux.start_estopped at ")
    assert mux.release_estop(WEB)
    bus.publish("/vesc/low_level/ackermann_cmd_mux/input/teleop",
                AckermannDriveStamped(drive=None))  # type: ignore[arg-type]
    assert mux.state is MuxState.FAULT
    assert mux.reset() is MuxState.ESTOP
    mux.publish_from(NET, "/estop_release", Bool(True))
    assert mux.state is MuxState.ESTOP
    assert mux.release_estop(FOX)


def test_the_daemon_itself_may_always_release_unless_the_topic_holds_it():
    _bus, mux = _mux(estop_release_sources=[])
    mux.engage_estop("web", WEB)
    assert mux.release_estop()  # a call in Python: the daemon's origin
    mux.publish_from(NET, "/estop", Bool(True))
    assert not mux.release_estop()
    assert mux.last_refusal.endswith(REFUSED_ASSERTED)


def test_engagements_and_releases_are_logged_with_their_source_and_refusals_rate_limited(caplog):
    refusals = Refusals(interval_s=3600.0)
    _bus, mux = _mux(refusals)
    with caplog.at_level(logging.INFO):
        mux.engage_estop("e-stop from web page", WEB)
        for _ in range(500):  # a 50 Hz flood for 10 s
            mux.publish_from(NET, "/estop", Bool(False))
            mux.publish_from(NET, "/estop_release", Bool(True))
        mux.publish_from(NET, "/estop", Bool(True))
        mux.publish_from(NET, "/estop", Bool(True))  # the same source again: no new line
        mux.publish_from(NET, "/estop", Bool(False))  # (while the topic says true nobody releases)
        assert mux.release_estop(WEB)
    lines = [r.getMessage() for r in caplog.records]
    assert "mux e-stop engaged by web page (127.0.0.1): e-stop from web page" in lines
    assert sum("refused" in line for line in lines) == 1  # the first; the rest are summarised
    assert refusals.by_source() == {("estop", "network topic (zenoh)",
                                     f"release refused: {REFUSED_OPERATOR_LATCH}"): 500}
    assert sum("engaged again by network topic (zenoh)" in line for line in lines) == 1
    assert any(line.startswith("mux e-stop released by web page (127.0.0.1) (it was latched by web page")
               for line in lines)
    assert len(lines) < 10


def test_diagnostics_say_who_latched_and_when():
    bus, mux = _mux()
    got: list[DiagnosticArray] = []
    bus.subscribe("/diagnostics", got.append)
    assert _values(mux)["estop"] == "never engaged"
    mux.engage_estop("e-stop from web page", WEB)
    mux.publish_diagnostics()
    values = {kv.key: kv.value for kv in got[-1].status[0].values}
    assert values["estop"] == f"latched by web page (127.0.0.1) at {_clock(WALL_NS)}"
    assert values["estop_release_refusals"] == "0" and "estop_last_refusal" not in values


def _clock(ns: int) -> str:
    import time

    return time.strftime("%H:%M:%S", time.localtime(ns // 1_000_000_000)) + ".123"


def test_release_sources_are_validated_naming_the_key():
    assert build(MuxParams, {}, "mux").estop_release_sources == list(RELEASE_SOURCES)
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"estop_release_sources": ["web", "zenoh"]}, "mux")
    assert err.value.key == "mux.estop_release_sources[1]" and "network" in str(err.value)
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"estop_release_sources": ["web", "web"]}, "mux")
    assert err.value.key == "mux.estop_release_sources[1]"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"estop_release_sources": [DAEMON]}, "mux")
    assert err.value.key == "mux.estop_release_sources[0]"
    with pytest.raises(ValueError, match="unknown e-stop surface"):
        Origin("zenoh")


@settings(max_examples=300, deadline=None)
@given(engagers=st.lists(st.sampled_from(SURFACES), min_size=1, max_size=5),
       releaser=st.sampled_from(SURFACES),
       allowed=st.lists(st.sampled_from(RELEASE_SOURCES), unique=True))
def test_the_rule_a_topic_never_releases_what_anything_else_engaged(engagers, releaser, allowed):
    record = EstopRecord(Origin(engagers[0], "a"), 0, "test")
    for surface in engagers[1:]:
        record.engaged_again(Origin(surface, "b"))
    why = release_refusal(Origin(releaser, "c"), record, allowed)
    if releaser == DAEMON:
        assert why is None
    elif releaser not in allowed:
        assert why == REFUSED_NOT_ALLOWED
    elif Origin(releaser).is_topic and any(not Origin(s).is_topic for s in engagers):
        assert why == REFUSED_OPERATOR_LATCH
    else:
        assert why is None


def test_the_panel_says_who_latched_the_estop_on_a_line_of_its_own():
    import io

    from rich.console import Console

    from racecar_hw.runtime.panel import render
    from racecar_hw.runtime.status import StatusSnapshot, plain_line

    _bus, mux = _mux()
    mux.engage_estop("e-stop from web page", WEB)
    snap = StatusSnapshot(speed_mps=0.0, mux_source="estop", estop=mux.estop_text())
    out = io.StringIO()
    Console(file=out, width=100, color_system=None).print(render(snap))
    row = next(line for line in out.getvalue().splitlines() if "e-stop" in line)
    assert f"latched by web page (127.0.0.1) at {_clock(WALL_NS)}" in row  # in full, not cut
    assert f"e-stop latched by web page (127.0.0.1) at {_clock(WALL_NS)}" in plain_line(snap)
    assert "e-stop" not in plain_line(StatusSnapshot())  # never engaged: no line
