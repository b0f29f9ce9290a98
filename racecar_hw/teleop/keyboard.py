"""Keyboard teleop in a terminal, for the simulation.

Keys: UP / ``w`` speed + one step, DOWN / ``s`` speed - one step, LEFT / ``a`` steering one step to
the left, RIGHT / ``d`` one step to the right, SPACE stop (speed 0, steering centred), ENTER keep
going (refreshes the deadman without changing anything), ``q`` quit (Ctrl-C too when stdin is not
a terminal; on a terminal Ctrl-C stays a signal, SIGINT, for the caller), ``e`` latch the mux
e-stop, ``R`` (shift: a deliberate key) release it. The keyboard is an operator surface: its release
may undo an e-stop latched anywhere (:mod:`mux.estop`); the daemon wires both to the mux.

Deadman: by default commands flow only while keys keep arriving - each key keeps the car going
for ``hold_s`` (0.6 s; terminal autorepeat refreshes it while a key is held down). When that time
passes without a key, one zero command is published, the set-point resets to zero and nothing more
is published until the next key (the mux times the teleop input out). With ``latched: true`` the
set-point is kept and published until SPACE or ``q`` instead (for a simulation only).

:class:`KeyDecoder` (sans-I/O: bytes in, :class:`Key` out, escape sequences split anywhere) and
:class:`KeyboardState` (keys and times in, commands out) carry the logic; :class:`KeyboardTeleop`
is the asyncio shell that puts the terminal in cbreak mode when stdin is a TTY.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import os
import sys
import termios
import tty
from collections.abc import Callable
from dataclasses import dataclass

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns, nanoseconds, wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.base.params import param
from racecar_hw.base.topics import TELEOP_TOPIC
from racecar_hw.runtime.ticker import Ticker

log = logging.getLogger(__name__)


class Key(enum.Enum):
    """A decoded key."""

    FASTER = "faster"
    SLOWER = "slower"
    LEFT = "left"
    RIGHT = "right"
    STOP = "stop"
    KEEP = "keep"
    QUIT = "quit"
    ESTOP = "estop"
    RELEASE = "release"


_PLAIN = {
    b"w": Key.FASTER, b"W": Key.FASTER, b"s": Key.SLOWER, b"S": Key.SLOWER,
    b"a": Key.LEFT, b"A": Key.LEFT, b"d": Key.RIGHT, b"D": Key.RIGHT,
    b" ": Key.STOP, b"\r": Key.KEEP, b"\n": Key.KEEP,
    b"q": Key.QUIT, b"Q": Key.QUIT, b"\x03": Key.QUIT, b"\x04": Key.QUIT,
    b"e": Key.ESTOP, b"E": Key.ESTOP, b"R": Key.RELEASE,
}
_ARROWS = {ord("A"): Key.FASTER, ord("B"): Key.SLOWER, ord("C"): Key.RIGHT, ord("D"): Key.LEFT}
_ESC = 0x1B


class KeyDecoder:
    """Sans-I/O: terminal bytes in, keys out.

    Arrows arrive as ``ESC [ A`` (normal mode) or ``ESC O A`` (application mode), possibly with
    parameters (``ESC [ 1 ; 5 A`` with Ctrl); other escape sequences and unknown bytes are skipped.
    An escape sequence split across reads waits for its end.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        #: bytes skipped as unknown
        self.ignored = 0

    def feed(self, data: bytes) -> list[Key]:
        """Add bytes from the terminal; return the keys now complete."""
        self._buf += data
        keys: list[Key] = []
        buf = self._buf
        i = 0
        while i < len(buf):
            byte = buf[i]
            if byte != _ESC:
                key = _PLAIN.get(bytes([byte]))
                if key is None:
                    self.ignored += 1
                else:
                    keys.append(key)
                i += 1
                continue
            if i + 1 >= len(buf):
                break  # a lone ESC so far: wait for more
            intro = buf[i + 1]
            if intro == ord("O"):
                if i + 2 >= len(buf):
                    break
                key = _ARROWS.get(buf[i + 2])
                if key is not None:
                    keys.append(key)
                else:
                    self.ignored += 3
                i += 3
            elif intro == ord("["):
                j = i + 2
                while j < len(buf) and not 0x40 <= buf[j] <= 0x7E:
                    j += 1
                if j >= len(buf):
                    break  # the final byte has not arrived yet
                key = _ARROWS.get(buf[j])
                if key is not None:
                    keys.append(key)
                else:
                    self.ignored += j + 1 - i
                i = j + 1
            else:
                self.ignored += 1  # ESC then something else (Alt+key): drop the ESC
                i += 1
        del buf[:i]
        return keys

    def flush(self) -> None:
        """Drop a dangling partial escape sequence (a lone ESC press)."""
        self.ignored += len(self._buf)
        self._buf.clear()


@dataclass
class KeyboardParams:
    """The terminal keyboard teleop."""

    topic: str = param(TELEOP_TOPIC, "mux input for AckermannDriveStamped teleop commands", topic=True)
    rate_hz: float = param(20.0, "command rate while keys are fresh", unit="Hz", min=1.0, max=200.0)
    speed_step_mps: float = param(0.25, "speed change per key", unit="m/s", min=0.01, max=5.0)
    steering_step_rad: float = param(0.05, "steering change per key", unit="rad", min=0.005, max=1.0)
    max_speed_mps: float = param(1.5, "largest |speed|", unit="m/s", min=0.0, max=20.0)
    max_steering_rad: float = param(0.34, "largest |steering|", unit="rad", min=0.0, max=1.0)
    hold_s: float = param(0.6, "deadman: commands flow this long after the last key", unit="s",
                          min=0.05, max=10.0)
    latched: bool = param(False, "keep publishing the set-point without keys (simulation only)")

    def __post_init__(self) -> None:
        if not self.topic.startswith("/"):
            raise ConfigError("topic", f"{self.topic!r} is not an absolute topic name")


class KeyboardState:
    """Sans-I/O: the set-point and the deadman. Times are monotonic ns."""

    def __init__(self, params: KeyboardParams) -> None:
        self.params = params
        self.speed = 0.0
        self.steering = 0.0
        self.last_key_ns: int | None = None
        self.quit = False

    def on_key(self, key: Key, now_ns: int) -> None:
        """Apply one key pressed at ``now_ns``."""
        p = self.params
        if not self.fresh(now_ns):
            self.speed = self.steering = 0.0
        if key is Key.QUIT:
            self.quit = True
            self.speed = self.steering = 0.0
        elif key is Key.STOP:
            self.speed = self.steering = 0.0
        elif key is Key.FASTER:
            self.speed = _clamp(self.speed + p.speed_step_mps, p.max_speed_mps)
        elif key is Key.SLOWER:
            self.speed = _clamp(self.speed - p.speed_step_mps, p.max_speed_mps)
        elif key is Key.LEFT:
            self.steering = _clamp(self.steering + p.steering_step_rad, p.max_steering_rad)
        elif key is Key.RIGHT:
            self.steering = _clamp(self.steering - p.steering_step_rad, p.max_steering_rad)
        self.last_key_ns = now_ns

    def fresh(self, now_ns: int) -> bool:
        """True while commands should flow (a recent key, or latched with a key ever pressed)."""
        if self.quit or self.last_key_ns is None:
            return False
        if self.params.latched:
            return True
        return now_ns - self.last_key_ns <= nanoseconds(self.params.hold_s)

    def command(self, now_ns: int) -> AckermannDrive | None:
        """The command to publish now, or None to publish nothing."""
        if not self.fresh(now_ns):
            return None
        return AckermannDrive(steering_angle=self.steering, speed=self.speed)


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, round(value, 9)))


#: The keys, in a few words, for the status panel.
KEY_HINTS = "arrows/WASD, space stop, q quit"


class KeyboardTeleop:
    """Reads keys from ``fd`` (stdin by default) and drives the mux's teleop input.

    ``async run()`` returns after ``q`` / Ctrl-C or end of input; it restores the terminal and
    publishes one zero command on the way out. ``e`` calls ``on_estop()`` and ``R``
    ``on_release()`` (the daemon latches and releases the mux e-stop as the keyboard operator).
    """

    def __init__(self, bus: Bus, params: KeyboardParams | None = None, fd: int | None = None, *,
                 clock: Callable[[], int] = monotonic_ns,
                 on_estop: Callable[[], object] | None = None,
                 on_release: Callable[[], object] | None = None) -> None:
        self.bus = bus
        self.on_estop = on_estop
        self.on_release = on_release
        self.params = params or KeyboardParams()
        self.fd = sys.stdin.fileno() if fd is None else fd
        self._clock = clock
        self.decoder = KeyDecoder()
        self.state = KeyboardState(self.params)
        self.published = 0
        self._was_fresh = False
        self._done: asyncio.Future[None] | None = None
        bus.declare(self.params.topic, AckermannDriveStamped)

    def _publish(self, drive: AckermannDrive) -> None:
        self.bus.publish(self.params.topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()), drive))
        self.published += 1

    def feed(self, data: bytes) -> None:
        """Bytes from the terminal: keys are applied and the set-point published at once."""
        now = self._clock()
        keys = self.decoder.feed(data)
        for key in keys:
            if key is Key.ESTOP:
                self.state.on_key(Key.STOP, now)
                if self.on_estop is not None:
                    self.on_estop()
            elif key is Key.RELEASE:
                if self.on_release is not None:
                    self.on_release()
            else:
                self.state.on_key(key, now)
        if keys:
            self.tick(now)

    def tick(self, now_ns: int | None = None) -> None:
        """One fixed-rate step: publish while fresh; one zero command when it goes stale."""
        now = self._clock() if now_ns is None else now_ns
        drive = self.state.command(now)
        if drive is not None:
            self._publish(drive)
        elif self._was_fresh:
            self._publish(AckermannDrive())
            self.state.speed = self.state.steering = 0.0
        self._was_fresh = drive is not None

    def _on_readable(self) -> None:
        try:
            data = os.read(self.fd, 64)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if data:
            self.feed(data)
        if (not data or self.state.quit) and self._done is not None and not self._done.done():
            self._done.set_result(None)

    def _read_to_end(self) -> None:
        """Take input that is a file (``< keys.txt``, ``< /dev/null``) as a pipe's: its keys (at most
        :data:`MAX_FILE_INPUT` bytes), then its end."""
        taken = 0
        while not (self._done is not None and self._done.done()) and taken < MAX_FILE_INPUT:
            taken += 64
            self._on_readable()
        if self._done is not None and not self._done.done():
            self._done.set_result(None)

    async def run(self) -> None:
        """Drive until ``q`` or end of input (or cancellation)."""
        loop = asyncio.get_running_loop()
        self._done = loop.create_future()
        saved = None
        if os.isatty(self.fd):
            saved = termios.tcgetattr(self.fd)
            tty.setcbreak(self.fd)
        blocking = os.get_blocking(self.fd)
        os.set_blocking(self.fd, False)
        try:
            loop.add_reader(self.fd, self._on_readable)
        except PermissionError:  # a regular file or /dev/null: no selector watches it, it is all there
            self._read_to_end()
        ticker = Ticker(self.params.rate_hz, self._clock)
        try:
            while not self._done.done():
                tick = asyncio.ensure_future(ticker.tick())
                await asyncio.wait({tick, self._done}, return_when=asyncio.FIRST_COMPLETED)
                if tick.done():
                    self.tick()
                else:
                    tick.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await tick
        finally:
            loop.remove_reader(self.fd)
            os.set_blocking(self.fd, blocking)
            if saved is not None:
                termios.tcsetattr(self.fd, termios.TCSADRAIN, saved)
            self._publish(AckermannDrive())


#: Bytes of keys read from input that is a file, not a terminal or a pipe.
MAX_FILE_INPUT = 1 << 16

HELP = ("keyboard teleop: UP/w faster, DOWN/s slower, LEFT/a RIGHT/d steer, SPACE stop, "
        "ENTER keep going, e e-stop, R (shift) release it, q quit")

__all__ = ["HELP", "Key", "KeyDecoder", "KeyboardParams", "KeyboardState", "KeyboardTeleop"]
