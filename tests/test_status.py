"""The console status panel: rendering, the live terminal panel, and plain lines for pipes."""

from __future__ import annotations

import asyncio
import io
import math

import pytest
from conftest import async_wait_for
from rich.console import Console

from racecar_hw.runtime.panel import StatusPanel, render
from racecar_hw.runtime.status import StatusSnapshot, plain_line, status_fields
from racecar_hw.teleop.keyboard import KEY_HINTS

FULL = StatusSnapshot(speed_mps=1.25, steering_rad=-0.15, mux_source="nav_0", battery_v=11.8,
                      scan_rate_hz=39.9, safety_state="limiting", safety_allowed_mps=0.5,
                      vesc_crc_errors=3, vesc_reconnects=1, lidar_reconnects=2, armed=True,
                      sim_pose=(1.5, -2.0, math.pi / 2))


def console(**kwargs: object) -> tuple[Console, io.StringIO]:
    out = io.StringIO()
    return Console(file=out, **{"width": 100, **kwargs}), out  # type: ignore[arg-type]


def test_render_shows_every_field() -> None:
    con, out = console()
    con.print(render(FULL))
    text = out.getvalue()
    for expected in ("racecar-hw", "+1.25 m/s", "-0.150 rad", "nav_0", "11.8 V", "39.9 Hz",
                     "limiting (max 0.50 m/s)", "crc errors 3, reconnects 1", "reconnects 2", "ARMED",
                     "x 1.50 m", "y -2.00 m", "yaw 90 deg"):
        assert expected in text, expected
    assert all(len(line) <= 100 for line in text.splitlines())


def test_render_shows_link_states_and_the_simulation() -> None:
    snap = StatusSnapshot(vesc_link="lost since 14:02:31 (35 s)", lidar_link="up", sim_time_s=12.34,
                          sim_pose=(1.0, 2.0, 0.0), clearance_m=0.456)
    con, out = console()
    con.print(render(snap))
    text = out.getvalue()
    for expected in ("lost since 14:02:31 (35 s), crc er…", "up, reconnects 0", "sim time",
                     "12.3 s", "clearance", "0.46 m"):
        assert expected in text, expected
    assert "lost since 14:02:31 (35 s), crc errors 0, reconnects 0" in plain_line(snap)  # in full
    con2, out2 = console(width=120)
    con2.print(render(StatusSnapshot()))
    con2.print(render(StatusSnapshot(battery_v=12.0, scan_rate_hz=40.0, speed_mps=-1.0)))
    con2.print(render(snap))
    con2.print(render(StatusSnapshot(vesc_link="connecting 1234 s", vesc_crc_errors=123456,
                                     vesc_reconnects=99999, lidar_link="lost since 23:59:59 (86399 s)",
                                     lidar_reconnects=123456, sim_pose=(-12.34, -12.34, -3.1),
                                     safety_state="limiting", safety_allowed_mps=0.25)))
    lines = out2.getvalue().splitlines()
    assert {len(line) for line in lines} == {100}  # the box keeps its width as values come and go
    assert "x -12.34 m  y -12.34 m  yaw -178 deg" in out2.getvalue()  # a pose fits whole
    long_link = next(line for line in lines if "connecting 1234 s" in line)
    assert "vesc       connecting 1234 s, crc errors 1234…  lidar      lost since 23:59:59 (86399 s), " \
           "recon… │" in long_link  # each value cut at its column with an ellipsis, the state kept


def test_an_80_column_terminal_gets_one_field_per_row_every_value_whole() -> None:
    snap = StatusSnapshot(vesc_link="lost since 14:02:31 (35 s)", lidar_link="connecting 12 s",
                          sim_time_s=1.0, sim_pose=(-12.34, -12.34, -3.1), clearance_m=0.5,
                          vesc_crc_errors=123456, vesc_reconnects=99999,
                          live_view="ws://127.0.0.1:8765", page="http://127.0.0.1:8080/", keys=KEY_HINTS)
    con, out = console(width=80)
    con.print(render(snap))
    con.print(render(StatusSnapshot()))
    lines = out.getvalue().splitlines()
    assert {len(line) for line in lines} == {80}
    assert "…" not in out.getvalue()  # nothing cut
    for label, text in status_fields(snap):
        assert any(f"│ {label:9}  {text}" in line for line in lines), (label, text)
    assert "live view  ws://127.0.0.1:8765" in out.getvalue() and "page       http://127.0.0.1:8080/" \
        in out.getvalue()
    assert "keys       arrows/WASD, space stop, q quit" in out.getvalue()


def test_the_live_view_page_and_keys_fit_the_wide_panel_whole() -> None:
    snap = StatusSnapshot(live_view="ws://127.0.0.1:8765", page="http://127.0.0.1:8080/", keys=KEY_HINTS)
    con, out = console()
    con.print(render(snap))
    text = out.getvalue()
    assert "ws://127.0.0.1:8765" in text and "http://127.0.0.1:8080/" in text and KEY_HINTS in text
    assert "live view ws://127.0.0.1:8765 | page http://127.0.0.1:8080/ | keys " in plain_line(snap)


def test_log_records_go_above_the_live_panel_not_behind_it() -> None:
    """A log line written straight to the terminal would scroll the panel and leave fragments."""
    import logging

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    terminal = Tty()
    handler = logging.StreamHandler(terminal)
    root = logging.getLogger()
    root.addHandler(handler)
    con, out = console(force_terminal=True, color_system=None)
    panel = StatusPanel(con, refresh_hz=50.0)
    try:
        async def scenario() -> None:
            panel.start()
            logging.getLogger("racecar_hw.test").warning("VESC still not connected")
            panel.update(FULL)
            await async_wait_for(lambda: panel.redraws >= 2)
            await panel.stop()

        asyncio.run(scenario())
        logging.getLogger("racecar_hw.test").warning("after the panel")
    finally:
        root.removeHandler(handler)
    assert "VESC still not connected" in out.getvalue()  # through the panel's console
    assert terminal.getvalue() == "after the panel\n"  # the terminal handler is back afterwards


def test_render_unknown_values() -> None:
    con, out = console()
    con.print(render(StatusSnapshot()))
    text = out.getvalue()
    assert "idle" in text and "n/a" in text and "sim pose" not in text
    assert "speed" in text and "battery" in text


def test_plain_line() -> None:
    line = plain_line(FULL)
    assert "\n" not in line
    assert line.startswith("speed +1.25 m/s | steer -0.150 rad | mux nav_0 | battery 11.8 V")
    assert "armed ARMED" in line and "sim pose x 1.50 m" in line
    assert "armed disarmed" in plain_line(StatusSnapshot(armed=False))
    invalid = plain_line(StatusSnapshot(speed_mps=math.nan, battery_v=math.inf, sim_pose=(math.nan, 0, 0)))
    assert "nan" not in invalid and "inf" not in invalid  # a summary never says nan
    assert "speed invalid" in invalid and "battery invalid" in invalid and "sim pose invalid" in invalid


def test_plain_lines_when_not_a_terminal() -> None:
    con, out = console()
    panel = StatusPanel(con, plain_interval_s=0.05)
    assert not panel.interactive

    async def scenario() -> None:
        panel.start()
        panel.start()  # idempotent
        panel.update(StatusSnapshot(speed_mps=0.5, mux_source="teleop"))
        await async_wait_for(lambda: "mux teleop" in out.getvalue())
        panel.update(StatusSnapshot(speed_mps=-0.5, mux_source="safety"))
        await async_wait_for(lambda: "mux safety" in out.getvalue())
        await panel.stop()
        await panel.stop()

    asyncio.run(scenario())
    lines = out.getvalue().splitlines()
    assert len(lines) == panel.redraws >= 2
    assert all(line.startswith("speed ") for line in lines)
    assert "speed -0.50 m/s" in lines[-1]


def test_live_panel_on_a_terminal() -> None:
    con, out = console(force_terminal=True, color_system=None)
    panel = StatusPanel(con, refresh_hz=50.0)
    assert panel.interactive

    async def scenario() -> None:
        panel.start()
        panel.update(FULL)
        await async_wait_for(lambda: "nav_0" in out.getvalue() and panel.redraws >= 3)
        await panel.stop()

    asyncio.run(scenario())
    text = out.getvalue()
    assert "11.8 V" in text and "ARMED" in text
    assert "speed +1.25" not in text  # the panel, not the plain line


def test_source_is_polled_and_errors_never_escape() -> None:
    con, out = console()
    calls = {"n": 0}

    def source() -> StatusSnapshot:
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("snapshot failed")
        return StatusSnapshot(battery_v=12.0 + calls["n"])

    panel = StatusPanel(con, plain_interval_s=0.02, source=source)

    async def scenario() -> None:
        panel.start()
        await async_wait_for(lambda: calls["n"] >= 4)
        await panel.stop()

    asyncio.run(scenario())
    assert panel.render_errors == 1
    assert "battery 13.0 V" in out.getvalue() and "battery 15.0 V" in out.getvalue()


def test_bad_rates_are_refused() -> None:
    with pytest.raises(ValueError):
        StatusPanel(refresh_hz=0)
