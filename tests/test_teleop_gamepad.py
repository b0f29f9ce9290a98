"""Gamepad teleop: the evdev decoder on recorded byte streams, the profiles, and the pad on a FIFO."""

from __future__ import annotations

import asyncio
import importlib.util
import os
import struct
import time
from pathlib import Path

import pytest
from conftest import async_wait_for
from hypothesis import given
from hypothesis import strategies as st

from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError, DeviceNotFound, RemoteProtocolError
from racecar_hw.base.messages import AckermannDriveStamped, Bool
from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.gamepad import (
    ABS_RX,
    ABS_Y,
    BTN_START,
    BTN_TL,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    F710_D,
    F710_X,
    LAYOUT_64LE,
    PROFILES,
    PS4,
    SYN_DROPPED,
    SYN_REPORT,
    AxisSpec,
    EventDecoder,
    GamepadParams,
    GamepadTeleop,
    InputEvent,
    PadState,
    TeleopMapping,
    find_gamepad,
    iter_events,
    pack_event,
)

DATA = Path(__file__).resolve().parent / "data"
SPEED, STEER = 2.0, 0.34


def recorded(profile: str) -> bytes:
    return (DATA / f"teleop_{profile}.events").read_bytes()


def ev(kind: int, code: int, value: int, sec: int = 1, usec: int = 0) -> InputEvent:
    return InputEvent(sec, usec, kind, code, value)


def stream(*events: InputEvent) -> bytes:
    return b"".join(pack_event(e, LAYOUT_64LE) for e in events)


def test_recorded_files_match_the_generator() -> None:
    spec = importlib.util.spec_from_file_location("make_events", DATA / "make_events.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for name in PROFILES:
        assert module.session(name) == recorded(name), name


def test_event_layout_is_24_bytes_on_64_bit() -> None:
    assert EventDecoder(LAYOUT_64LE).event_size == 24
    assert len(recorded("f710_x")) % 24 == 0


@given(st.sampled_from(sorted(PROFILES)), st.lists(st.integers(1, 60), min_size=1, max_size=80))
def test_decoder_is_independent_of_fragmentation(profile: str, cuts: list[int]) -> None:
    data = recorded(profile)
    whole = list(iter_events(data, LAYOUT_64LE))
    decoder = EventDecoder(LAYOUT_64LE)
    got = []
    pos = 0
    for n in cuts * (len(data) // sum(cuts) + 1):
        got += decoder.feed(data[pos:pos + n])
        pos += n
        if pos >= len(data):
            break
    assert got == whole
    assert decoder.pending == 0


@given(st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 999_999), st.integers(0, 0xFFFF),
                          st.integers(0, 0xFFFF), st.integers(-2**31, 2**31 - 1)), max_size=20),
       st.binary(max_size=23))
def test_decoder_round_trips_any_event(fields: list[tuple[int, int, int, int, int]], tail: bytes) -> None:
    events = [InputEvent(*f) for f in fields]
    decoder = EventDecoder(LAYOUT_64LE)
    assert decoder.feed(stream(*events) + tail) == events
    assert decoder.pending == len(tail)


def test_trailing_partial_event_is_an_error_for_whole_buffers() -> None:
    with pytest.raises(RemoteProtocolError):
        list(iter_events(recorded("ps4")[:-5], LAYOUT_64LE))


def replay(profile: str, chunk: int) -> list[tuple[bool, bool, float, float, frozenset[int]]]:
    """(deadman, autonomy, speed, steering, pressed) after every frame of the recorded session."""
    p = PROFILES[profile]
    mapping = TeleopMapping(p, SPEED, STEER, deadzone=0.01)
    decoder, state = EventDecoder(LAYOUT_64LE), PadState(p.centres())
    out = []
    data = recorded(profile)
    for i in range(0, len(data), chunk):
        for frame in state.feed(decoder.feed(data[i:i + chunk])):
            c = mapping.command(frame)
            out.append((c.deadman, c.autonomy, c.speed, c.steering, frame.pressed))
    return out


@pytest.mark.parametrize("profile", sorted(PROFILES))
@pytest.mark.parametrize("chunk", [1, 7, 24, 1000])
def test_recorded_session_maps_to_commands(profile: str, chunk: int) -> None:
    p = PROFILES[profile]
    frames = replay(profile, chunk)
    assert len(frames) == 12
    centred, arm_down, arm_up, lb, full, half, rb, rb_up, centre2, lb_up, back, back_up = frames
    assert centred[:4] == (False, False, 0.0, 0.0)
    assert p.arm in arm_down[4]
    assert lb[0] and lb[2:4] == (0.0, 0.0)
    assert full[0] and full[2] == pytest.approx(SPEED) and full[3] == pytest.approx(STEER)
    assert half[0] and half[2] == pytest.approx(-SPEED / 2, abs=0.03)
    assert half[3] == pytest.approx(-STEER, abs=1e-9)
    assert rb[1] and not rb_up[1] and rb[0]
    assert centre2[0] and centre2[2:4] == (0.0, 0.0)
    assert not lb_up[0]
    assert p.disarm in back[4]
    assert not any(f[0] for f in (centred, arm_down, arm_up, back, back_up))


def test_events_take_effect_only_at_syn_report() -> None:
    state = PadState(F710_X.centres())
    assert state.process(ev(EV_KEY, BTN_TL, 1)) is None
    assert BTN_TL not in state.buttons
    frame = state.process(ev(EV_SYN, SYN_REPORT, 0))
    assert frame is not None and BTN_TL in frame.buttons and frame.pressed == {BTN_TL}
    # autorepeat (value 2) keeps a key held and is no new press
    state.process(ev(EV_KEY, BTN_TL, 2))
    frame = state.process(ev(EV_SYN, SYN_REPORT, 0))
    assert frame is not None and BTN_TL in frame.buttons and not frame.pressed


def test_syn_dropped_discards_to_the_next_report_and_releases_everything() -> None:
    state = PadState(F710_X.centres())
    state.feed([ev(EV_KEY, BTN_TL, 1), ev(EV_ABS, ABS_Y, -32768), ev(EV_SYN, SYN_REPORT, 0)])
    assert BTN_TL in state.buttons
    frames = state.feed([ev(EV_SYN, SYN_DROPPED, 0), ev(EV_KEY, BTN_START, 1), ev(EV_ABS, ABS_Y, 0)])
    assert frames == [] and state.resyncing and state.dropped == 1
    frame = state.process(ev(EV_SYN, SYN_REPORT, 0))
    assert frame is not None
    assert frame.buttons == frozenset() and frame.released == {BTN_TL}
    assert BTN_START not in frame.pressed  # discarded, never acted on
    assert frame.axes[ABS_Y] == F710_X.speed.centre
    mapping = TeleopMapping(F710_X, SPEED, STEER, 0.05)
    assert not mapping.command(frame).deadman
    # the next events apply normally again
    frame = state.feed([ev(EV_KEY, BTN_TL, 1), ev(EV_SYN, SYN_REPORT, 0)])[0]
    assert BTN_TL in frame.buttons


@given(st.integers(-40000, 40000), st.floats(0.0, 0.9))
def test_axis_normalise_is_bounded_and_signed(raw: int, deadzone: float) -> None:
    axis = AxisSpec(ABS_RX, -32768, 32767, invert=True)
    value = axis.normalise(raw, deadzone)
    assert -1.0 <= value <= 1.0
    if value:
        assert (value > 0) == (raw < 0)  # inverted: stick left (raw minimum) is positive


def test_deadzone_zeroes_small_deflections_and_keeps_full_scale() -> None:
    axis = AxisSpec(ABS_Y, 0, 255, invert=True)
    assert axis.normalise(130, 0.05) == 0.0
    assert axis.normalise(0, 0.05) == 1.0
    assert axis.normalise(255, 0.05) == -1.0


def test_profiles_match_the_ros_joystick_layouts() -> None:
    # joy_node numbers buttons in code order: LB is button 4 on all three pads
    assert F710_X.buttons[F710_X.deadman] == "LB" and F710_D.buttons[F710_D.deadman] == "LB"
    assert PS4.buttons[PS4.deadman] == "L1"
    assert sorted(F710_D.buttons).index(F710_D.deadman) == 4
    assert sorted(F710_X.buttons).index(F710_X.deadman) == 4
    assert sorted(PS4.buttons).index(PS4.deadman) == 4
    assert (F710_X.products, F710_D.products, PS4.products) == ((0xC21F,), (0xC219,), (0x05C4, 0x09CC))


def fake_sysfs(tmp_path: Path, devices: dict[int, tuple[str, str, str]]) -> tuple[Path, Path]:
    dev, sys_class = tmp_path / "dev", tmp_path / "sys"
    dev.mkdir()
    for n, (name, vendor, product) in devices.items():
        (dev / f"event{n}").write_bytes(b"")
        base = sys_class / f"event{n}" / "device"
        (base / "id").mkdir(parents=True)
        (base / "name").write_text(name + "\n")
        (base / "id" / "vendor").write_text(vendor + "\n")
        (base / "id" / "product").write_text(product + "\n")
    return dev, sys_class


def test_find_gamepad_by_id_name_and_path(tmp_path: Path) -> None:
    dev, sys_class = fake_sysfs(tmp_path, {
        0: ("AT Translated Set 2 keyboard", "0001", "0001"),
        3: ("Sony Interactive Entertainment Wireless Controller Motion Sensors", "054c", "09cc"),
        4: ("Sony Interactive Entertainment Wireless Controller", "054c", "09cc"),
        11: ("Logitech Logitech Cordless RumblePad 2", "046d", "c219"),
    })
    path, profile = find_gamepad("auto", "auto", str(dev), str(sys_class))
    assert (path, profile) == (str(dev / "event4"), PS4)
    path, profile = find_gamepad("rumblepad", "auto", str(dev), str(sys_class))
    assert (path, profile) == (str(dev / "event11"), F710_D)
    link = tmp_path / "usb-Logitech_Wireless_Gamepad-event-joystick"
    link.symlink_to(dev / "event11")
    assert find_gamepad(str(link), "auto", str(dev), str(sys_class)) == (str(link), F710_D)
    assert find_gamepad(str(link), "f710_x", str(dev), str(sys_class)) == (str(link), F710_X)
    with pytest.raises(DeviceNotFound):
        find_gamepad("xbox", "auto", str(dev), str(sys_class))
    with pytest.raises(DeviceNotFound, match="matches no profile"):
        find_gamepad(str(dev / "event0"), "auto", str(dev), str(sys_class))
    with pytest.raises(DeviceNotFound):
        find_gamepad(str(tmp_path / "missing"), "ps4", str(dev), str(sys_class))


def test_params_refuse_bad_values() -> None:
    with pytest.raises(ConfigError, match="rescan_max_s"):
        GamepadParams(rescan_min_s=2.0, rescan_max_s=1.0)
    lock = GamepadParams().lock_params()
    assert lock.topic == "/vesc/autonomy_lock" and lock.timeout_s > 0
    assert 20 < lock.priority < 90  # above every nav input, below teleop


class Recorder:
    def __init__(self, bus: Bus, params: GamepadParams) -> None:
        self.drives: list[tuple[float, float]] = []
        self.locks: list[bool] = []
        bus.subscribe(params.topic, self._drive)
        bus.subscribe(params.autonomy_lock_topic, lambda m: self.locks.append(m.data))

    def _drive(self, msg: AckermannDriveStamped) -> None:
        self.drives.append((msg.drive.speed, msg.drive.steering_angle))


def frames_of(profile: str) -> list[bytes]:
    """The recorded session split at each SYN_REPORT (one write per report)."""
    data = recorded(profile)
    out, start = [], 0
    for i in range(0, len(data), 24):
        _s, _u, kind, code, _v = struct.unpack(LAYOUT_64LE, data[i:i + 24])
        if kind == EV_SYN and code == SYN_REPORT:
            out.append(data[start:i + 24])
            start = i + 24
    return out


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_pad_on_a_fifo_drives_arms_and_stops(tmp_path: Path, profile: str) -> None:
    fifo = tmp_path / "event-joystick"
    os.mkfifo(fifo)
    params = GamepadParams(enabled=True, device=str(fifo), profile=profile, rate_hz=50.0,
                           layout="64le", deadzone=0.01, rescan_min_s=0.05, rescan_max_s=0.2)

    async def main() -> None:
        bus = Bus()
        arming = Arming(start_armed=False)
        rec = Recorder(bus, params)
        pad = GamepadTeleop(bus, params, arming)
        task = asyncio.create_task(pad.run())
        await async_wait_for(lambda: pad.connected)
        writer = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        frames = frames_of(profile)
        # half an event first: nothing may happen until the rest arrives
        os.write(writer, frames[0][:10])
        os.write(writer, frames[0][10:] + frames[1] + frames[2])
        await async_wait_for(lambda: arming.armed)
        await async_wait_for(lambda: len(rec.locks) >= 3)
        assert rec.drives == [] and all(rec.locks)  # no deadman: silent; RB released: lock engaged
        os.write(writer, frames[3] + frames[4])  # LB, then full up / full left
        await async_wait_for(lambda: len([d for d in rec.drives if d[0] > 1.9]) >= 5)
        assert rec.drives[-1] == pytest.approx((SPEED, STEER))
        os.write(writer, frames[5])  # half reverse, full right
        await async_wait_for(lambda: rec.drives[-1][0] < 0)
        assert rec.drives[-1] == pytest.approx((-SPEED / 2, -STEER), abs=0.03)
        os.write(writer, frames[6])  # RB held: lock released
        await async_wait_for(lambda: rec.locks[-1] is False)
        os.write(writer, frames[7] + frames[8] + frames[9])  # RB up, centre, LB released
        await async_wait_for(lambda: not pad.deadman_held)
        assert rec.drives[-1] == (0.0, 0.0) and rec.locks[-1] is True
        count = len(rec.drives)
        locks = len(rec.locks)
        await async_wait_for(lambda: len(rec.locks) >= locks + 5)
        assert len(rec.drives) == count  # deadman released: nothing more is published
        os.write(writer, frames[10] + frames[11])  # BACK
        await async_wait_for(lambda: not arming.armed)
        assert arming.source == "gamepad" and arming.changes == 2
        os.close(writer)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())


def test_unplug_releases_the_deadman_at_once_and_replug_resumes(tmp_path: Path) -> None:
    fifo = tmp_path / "event-joystick"
    os.mkfifo(fifo)
    params = GamepadParams(enabled=True, device=str(fifo), profile="f710_x", rate_hz=50.0,
                           layout="64le", rescan_min_s=0.05, rescan_max_s=0.2)
    frames = frames_of("f710_x")

    async def main() -> None:
        bus = Bus()
        rec = Recorder(bus, params)
        pad = GamepadTeleop(bus, params, Arming(start_armed=True))
        task = asyncio.create_task(pad.run())
        await async_wait_for(lambda: pad.connected)
        writer = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.write(writer, frames[3] + frames[4])  # LB held, full speed
        await async_wait_for(lambda: len(rec.drives) >= 3 and rec.drives[-1][0] > 1.9)
        os.close(writer)  # unplugged
        await async_wait_for(lambda: pad.disconnects == 1)
        assert not pad.deadman_held
        assert rec.drives[-1] == (0.0, 0.0) and rec.locks[-1] is True
        count = len(rec.drives)
        await async_wait_for(lambda: pad.connected and pad.connects == 2)  # replugged (the FIFO is back)
        assert len(rec.drives) == count
        writer = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.write(writer, frames[3] + frames[4])
        await async_wait_for(lambda: len(rec.drives) > count and rec.drives[-1][0] > 1.9)
        os.close(writer)
        await async_wait_for(lambda: pad.disconnects == 2)
        os.unlink(fifo)  # gone for good: the pad keeps rescanning without publishing
        count = len(rec.drives)
        await asyncio.sleep(0)
        assert not pad.connected and len(rec.drives) == count
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())


def test_start_is_ignored_with_the_speed_stick_off_centre(tmp_path: Path) -> None:
    fifo = tmp_path / "pad"
    os.mkfifo(fifo)
    params = GamepadParams(enabled=True, device=str(fifo), profile="ps4", layout="64le",
                           autonomy_lock=False, rescan_min_s=0.05, rescan_max_s=0.2)

    async def main() -> None:
        bus = Bus()
        arming = Arming()
        pad = GamepadTeleop(bus, params, arming)
        task = asyncio.create_task(pad.run())
        await async_wait_for(lambda: pad.connected)
        writer = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.write(writer, stream(ev(EV_ABS, ABS_Y, 0), ev(EV_KEY, BTN_START, 1), ev(EV_SYN, SYN_REPORT, 0)))
        await async_wait_for(lambda: pad.arm_refused == 1)
        assert not arming.armed
        os.write(writer, stream(ev(EV_ABS, ABS_Y, 128), ev(EV_KEY, BTN_START, 0), ev(EV_SYN, SYN_REPORT, 0),
                                ev(EV_KEY, BTN_START, 1), ev(EV_SYN, SYN_REPORT, 0)))
        await async_wait_for(lambda: arming.armed)
        assert bus.latest(params.autonomy_lock_topic) is None  # lock switched off (simulation)
        os.close(writer)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())


def test_a_recorded_regular_file_replays_then_counts_as_unplugged(tmp_path: Path) -> None:
    params = GamepadParams(enabled=True, device=str(DATA / "teleop_f710_d.events"), profile="f710_d",
                           layout="64le", rescan_min_s=5.0, rescan_max_s=5.0)

    async def main() -> None:
        bus = Bus()
        arming = Arming()
        rec = Recorder(bus, params)
        pad = GamepadTeleop(bus, params, arming)
        started = time.monotonic()
        task = asyncio.create_task(pad.run())
        await async_wait_for(lambda: pad.disconnects == 1)
        assert time.monotonic() - started >= 0.11  # paced by the recorded stamps (12 reports, 10 ms apart)
        assert arming.changes == 2 and not arming.armed  # START then BACK
        assert pad.deadman_presses == 1
        assert rec.drives[-1] == (0.0, 0.0)
        assert isinstance(bus.latest(params.autonomy_lock_topic), Bool)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_b_latches_the_estop_and_b_with_start_held_releases_it_as_an_operator(tmp_path: Path,
                                                                             profile: str) -> None:
    from mux.arbiter import MuxState
    from mux.estop import Origin
    from mux.node import CommandMux

    fifo = tmp_path / "event-joystick"
    os.mkfifo(fifo)
    params = GamepadParams(enabled=True, device=str(fifo), profile=profile, rate_hz=50.0,
                           layout="64le", estop_release_hold_s=0.5, rescan_min_s=0.05, rescan_max_s=0.2)
    pad_profile = PROFILES[profile]
    b, start, speed = pad_profile.estop, pad_profile.arm, pad_profile.speed

    def buttons(*pressed: tuple[int, int]) -> bytes:
        return stream(*(ev(EV_KEY, code, value) for code, value in pressed), ev(EV_SYN, SYN_REPORT, 0))

    async def main() -> None:
        bus = Bus()
        mux = CommandMux(bus)
        origin = Origin("gamepad", "gamepad")
        releases: list[bool] = []
        pad = GamepadTeleop(bus, params, Arming(start_armed=True),
                            on_estop=lambda: mux.engage_estop("B on the gamepad", origin),
                            on_release=lambda: releases.append(mux.release_estop(origin)))
        task = asyncio.create_task(pad.run())
        await async_wait_for(lambda: pad.connected)
        writer = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.write(writer, buttons((b, 1)) + buttons((b, 0)))  # a press of B: latched
        await async_wait_for(lambda: mux.state is MuxState.ESTOP)
        assert mux.estop_text().startswith("latched by gamepad at ")
        # START alone, or B and START let go before the hold time, release nothing
        os.write(writer, buttons((start, 1)) + buttons((start, 0)))
        os.write(writer, buttons((b, 1), (start, 1)) + buttons((b, 0), (start, 0)))  # one read
        await asyncio.sleep(0.8)
        assert releases == [] and mux.state is MuxState.ESTOP
        # held with the speed stick pushed: refused (the car would leap off)
        os.write(writer, stream(ev(EV_ABS, speed.code, speed.maximum),
                                ev(EV_SYN, SYN_REPORT, 0)) + buttons((b, 1), (start, 1)))
        await asyncio.sleep(0.8)
        assert releases == [] and mux.state is MuxState.ESTOP
        os.write(writer, buttons((b, 0), (start, 0)))
        os.write(writer, stream(ev(EV_ABS, speed.code, speed.centre), ev(EV_SYN, SYN_REPORT, 0)))
        # held for the hold time with the stick centred: released, once
        os.write(writer, buttons((b, 1), (start, 1)))
        await async_wait_for(lambda: releases == [True])
        assert mux.state is MuxState.RUNNING
        await asyncio.sleep(0.3)
        assert releases == [True]
        os.close(writer)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())
