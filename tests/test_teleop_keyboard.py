"""Keyboard teleop: escape-sequence decoding, the deadman, and the shell on a real pipe and pty."""

from __future__ import annotations

import asyncio
import os
import pty
import termios

import pytest
from conftest import async_wait_for
from hypothesis import given
from hypothesis import strategies as st

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.messages import AckermannDriveStamped
from racecar_hw.teleop.keyboard import Key, KeyboardParams, KeyboardState, KeyboardTeleop, KeyDecoder

UP, DOWN, RIGHT, LEFT = b"\x1b[A", b"\x1b[B", b"\x1b[C", b"\x1b[D"


def test_plain_keys_and_arrows() -> None:
    d = KeyDecoder()
    assert d.feed(b"wasd q") == [Key.FASTER, Key.LEFT, Key.SLOWER, Key.RIGHT, Key.STOP, Key.QUIT]
    assert d.feed(UP + DOWN + RIGHT + LEFT) == [Key.FASTER, Key.SLOWER, Key.RIGHT, Key.LEFT]
    assert d.feed(b"\x1bOA\x1bOD") == [Key.FASTER, Key.LEFT]  # application cursor mode
    assert d.feed(b"\x1b[1;5C") == [Key.RIGHT]  # Ctrl+Right
    assert d.feed(b"\x03") == [Key.QUIT]


def test_unknown_sequences_are_skipped() -> None:
    d = KeyDecoder()
    assert d.feed(b"x\x1b[15~w\x1bxz") == [Key.FASTER]  # F5, Alt+x
    assert d.ignored > 0


def test_split_escape_sequences_wait_for_their_end() -> None:
    d = KeyDecoder()
    assert d.feed(b"\x1b") == []
    assert d.feed(b"[") == []
    assert d.feed(b"1;5") == []
    assert d.feed(b"A") == [Key.FASTER]
    assert d.feed(b"\x1b") == []
    d.flush()
    assert d.feed(b"s") == [Key.SLOWER]


SEQUENCES = [UP, DOWN, RIGHT, LEFT, b"\x1bOB", b"\x1b[1;2D", b"w", b"a", b" ", b"q", b"\r", b"\x1b[15~", b"z"]


@given(st.lists(st.sampled_from(SEQUENCES), max_size=30), st.lists(st.integers(1, 7), min_size=1))
def test_decoding_is_independent_of_fragmentation(seqs: list[bytes], cuts: list[int]) -> None:
    data = b"".join(seqs)
    whole = KeyDecoder().feed(data)
    d = KeyDecoder()
    got: list[Key] = []
    pos, i = 0, 0
    while pos < len(data):
        n = cuts[i % len(cuts)]
        got += d.feed(data[pos:pos + n])
        pos, i = pos + n, i + 1
    assert got == whole


@given(st.binary(max_size=200))
def test_decoder_never_fails_on_garbage(data: bytes) -> None:
    keys = KeyDecoder().feed(data)
    assert all(isinstance(k, Key) for k in keys)


def test_state_steps_clamps_and_deadman() -> None:
    p = KeyboardParams(speed_step_mps=0.5, steering_step_rad=0.1, max_speed_mps=1.0,
                       max_steering_rad=0.34, hold_s=0.5)
    s = KeyboardState(p)
    assert s.command(0) is None  # nothing before the first key
    for _ in range(3):
        s.on_key(Key.FASTER, 0)
    for _ in range(5):
        s.on_key(Key.LEFT, 0)
    cmd = s.command(NS_PER_S // 4)
    assert cmd is not None and cmd.speed == 1.0 and cmd.steering_angle == pytest.approx(0.34)
    s.on_key(Key.RIGHT, NS_PER_S // 4)
    assert s.steering == pytest.approx(0.24)
    assert s.command(NS_PER_S) is None  # 0.75 s after the last key: stale
    s.on_key(Key.LEFT, 2 * NS_PER_S)  # a key after a stale stretch starts from zero
    assert (s.speed, s.steering) == (0.0, pytest.approx(0.1))
    s.on_key(Key.STOP, 2 * NS_PER_S)
    assert (s.speed, s.steering) == (0.0, 0.0)
    s.on_key(Key.SLOWER, 2 * NS_PER_S)
    assert s.speed == -0.5  # reverse


def test_latched_mode_keeps_the_set_point() -> None:
    s = KeyboardState(KeyboardParams(latched=True))
    s.on_key(Key.FASTER, 0)
    cmd = s.command(100 * NS_PER_S)
    assert cmd is not None and cmd.speed == 0.25
    s.on_key(Key.QUIT, 100 * NS_PER_S)
    assert s.command(100 * NS_PER_S) is None


class Clock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def test_tick_publishes_while_fresh_then_one_zero() -> None:
    bus = Bus()
    got: list[tuple[float, float]] = []
    p = KeyboardParams(hold_s=0.5)
    bus.subscribe(p.topic, lambda m: got.append((m.drive.speed, m.drive.steering_angle)))
    clock = Clock()
    kb = KeyboardTeleop(bus, p, fd=0, clock=clock)
    kb.feed(UP + LEFT)
    assert got == [(0.25, 0.05)]  # published at once
    clock.now = NS_PER_S // 5
    kb.tick()
    assert got[-1] == (0.25, 0.05)
    clock.now = NS_PER_S
    kb.tick()
    assert got[-1] == (0.0, 0.0)
    n = len(got)
    clock.now = 2 * NS_PER_S
    kb.tick()
    assert len(got) == n  # stale: silent


def test_shell_on_a_pipe_drives_then_quits() -> None:
    async def main() -> None:
        bus = Bus()
        p = KeyboardParams(rate_hz=50.0, hold_s=5.0)
        got: list[AckermannDriveStamped] = []
        bus.subscribe(p.topic, got.append)
        r, w = os.pipe()
        kb = KeyboardTeleop(bus, p, fd=r)
        task = asyncio.create_task(kb.run())
        os.write(w, b"ww" + LEFT[:1])
        await async_wait_for(lambda: len(got) >= 5)
        assert got[-1].drive.speed == 0.5 and got[-1].drive.steering_angle == 0.0
        os.write(w, LEFT[1:])
        await async_wait_for(lambda: got[-1].drive.steering_angle == 0.05)
        os.write(w, b"q")
        await asyncio.wait_for(task, 10)
        assert got[-1].drive.speed == 0.0 and got[-1].drive.steering_angle == 0.0
        os.close(r)
        os.close(w)

    asyncio.run(main())


@pytest.mark.parametrize("keys", [b"ww", b""])
def test_input_from_a_file_or_dev_null_is_read_to_its_end_then_stops(tmp_path, keys) -> None:
    """``--keyboard < keys.txt`` or ``< /dev/null``: no selector can watch a file (it raised
    PermissionError, a failed component); its keys are taken, then its end stops the car."""
    path = tmp_path / "keys.txt"
    path.write_bytes(keys)

    async def main() -> list[AckermannDriveStamped]:
        bus = Bus()
        p = KeyboardParams(rate_hz=50.0, hold_s=5.0)
        got: list[AckermannDriveStamped] = []
        bus.subscribe(p.topic, got.append)
        fd = os.open(path if keys else os.devnull, os.O_RDONLY)
        try:
            kb = KeyboardTeleop(bus, p, fd=fd)
            await asyncio.wait_for(kb.run(), 10)
            assert kb.state.speed == (0.5 if keys else 0.0)  # the file's keys were taken
            return got
        finally:
            os.close(fd)

    got = asyncio.run(main())
    assert got and got[-1].drive.speed == 0.0


def test_shell_on_a_pty_uses_cbreak_and_restores_the_terminal() -> None:
    async def main() -> None:
        bus = Bus()
        master, slave = pty.openpty()
        before = termios.tcgetattr(slave)
        got: list[AckermannDriveStamped] = []
        p = KeyboardParams(rate_hz=50.0)
        bus.subscribe(p.topic, got.append)
        kb = KeyboardTeleop(bus, p, fd=slave)
        task = asyncio.create_task(kb.run())
        await async_wait_for(lambda: not termios.tcgetattr(slave)[3] & termios.ICANON)
        os.write(master, b"s")  # no newline needed in cbreak mode
        await async_wait_for(lambda: bool(got) and got[-1].drive.speed == -0.25)
        os.write(master, b"q")  # Ctrl-C stays a signal in cbreak mode (the CLI's KeyboardInterrupt)
        await asyncio.wait_for(task, 10)
        assert termios.tcgetattr(slave) == before
        os.close(master)
        os.close(slave)

    asyncio.run(main())


def test_e_latches_the_mux_estop_and_shift_r_releases_it_as_an_operator() -> None:
    from mux.arbiter import MuxState
    from mux.estop import Origin
    from mux.node import CommandMux
    from racecar_hw.base.messages import Bool

    async def main() -> None:
        bus = Bus()
        mux = CommandMux(bus)
        keyboard = Origin("keyboard", "keyboard")
        p = KeyboardParams(rate_hz=50.0, hold_s=5.0)
        got: list[AckermannDriveStamped] = []
        bus.subscribe(p.topic, got.append)
        r, w = os.pipe()
        kb = KeyboardTeleop(bus, p, fd=r, on_estop=lambda: mux.engage_estop("e key", keyboard),
                            on_release=lambda: mux.release_estop(keyboard))
        task = asyncio.create_task(kb.run())
        # a topic's e-stop: the release topic could undo it, the keyboard can too
        bus.publish("/estop", Bool(True))
        bus.publish("/estop", Bool(False))
        os.write(w, b"R")
        await async_wait_for(lambda: mux.state is MuxState.RUNNING)
        os.write(w, b"ww")
        await async_wait_for(lambda: got and got[-1].drive.speed == 0.5)
        os.write(w, b"e")  # e-stop: latched, and the keyboard's own set-point drops to zero
        await async_wait_for(lambda: mux.state is MuxState.ESTOP)
        assert mux.estop_text().startswith("latched by keyboard at ")
        await async_wait_for(lambda: got[-1].drive.speed == 0.0)
        os.write(w, b"r")  # lower-case r is no key: nothing happens
        bus.publish("/estop_release", Bool(True))  # the topic cannot undo the keyboard's e-stop
        assert mux.state is MuxState.ESTOP
        os.write(w, b"R")
        await async_wait_for(lambda: mux.state is MuxState.RUNNING)
        os.write(w, b"q")
        await asyncio.wait_for(task, 10)
        os.close(r)
        os.close(w)

    asyncio.run(main())
