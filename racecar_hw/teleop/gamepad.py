"""Gamepad teleop from the Linux evdev stream, without python-evdev.

Layers, bottom up:

* :class:`EventDecoder` - sans-I/O: bytes of ``struct input_event`` in (any fragmentation),
  :class:`InputEvent` out. On 64-bit Linux an event is 24 bytes: ``struct timeval`` (two longs:
  seconds, microseconds), ``__u16 type``, ``__u16 code``, ``__s32 value``.
* :class:`PadState` - groups events into frames at ``EV_SYN/SYN_REPORT`` (nothing takes effect
  before the report), and handles ``SYN_DROPPED``: everything up to and including the next
  SYN_REPORT is discarded and the pad falls back to "all buttons released, sticks centred" until
  the shell re-reads the device state (EVIOCGKEY / EVIOCGABS) or new events arrive.
* :class:`GamepadProfile` and :class:`TeleopMapping` - which codes are the deadman (LB), autonomy
  (RB), arm (START), disarm (BACK), e-stop (B; CIRCLE on the DualShock) buttons and the speed
  (left stick vertical) and steering (right stick horizontal) axes of the Logitech F710 in X and D
  mode and the Sony DualShock 4. B latches the mux e-stop; the release combination is B and START
  held together for ``estop_release_hold_s`` (2 s) with the speed stick centred.
* :class:`GamepadTeleop` - the asyncio shell: finds the pad under ``/dev/input``, reads it
  non-blocking, publishes AckermannDriveStamped on the mux's teleop input at a fixed rate while
  the deadman is held, and the autonomy lock (std_msgs/Bool). Unplug and replug are handled.

Axes follow REP-103 once mapped: speed positive forward (stick pushed up), steering positive to the
left (stick pushed left). See ``docs/teleop.md`` for the mappings and semantics.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import logging
import os
import stat
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mux.params import LockParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.errors import ConfigError, DeviceNotFound, RemoteProtocolError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Bool, stamp_now
from racecar_hw.base.params import param
from racecar_hw.base.topics import TELEOP_TOPIC
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.gamepad_estop import EstopButtons

log = logging.getLogger(__name__)

# --- linux/input-event-codes.h ------------------------------------------------------------------

EV_SYN, EV_KEY, EV_REL, EV_ABS, EV_MSC = 0x00, 0x01, 0x02, 0x03, 0x04
SYN_REPORT, SYN_CONFIG, SYN_MT_REPORT, SYN_DROPPED = 0, 1, 2, 3

ABS_X, ABS_Y, ABS_Z, ABS_RX, ABS_RY, ABS_RZ = 0x00, 0x01, 0x02, 0x03, 0x04, 0x05
ABS_HAT0X, ABS_HAT0Y = 0x10, 0x11
ABS_CNT = 0x40

BTN_TRIGGER, BTN_THUMB, BTN_THUMB2, BTN_TOP, BTN_TOP2, BTN_PINKIE = 0x120, 0x121, 0x122, 0x123, 0x124, 0x125
BTN_BASE, BTN_BASE2, BTN_BASE3, BTN_BASE4, BTN_BASE5, BTN_BASE6 = 0x126, 0x127, 0x128, 0x129, 0x12A, 0x12B
BTN_SOUTH, BTN_EAST, BTN_C, BTN_NORTH, BTN_WEST, BTN_Z = 0x130, 0x131, 0x132, 0x133, 0x134, 0x135
BTN_TL, BTN_TR, BTN_TL2, BTN_TR2 = 0x136, 0x137, 0x138, 0x139
BTN_SELECT, BTN_START, BTN_MODE, BTN_THUMBL, BTN_THUMBR = 0x13A, 0x13B, 0x13C, 0x13D, 0x13E
KEY_CNT = 0x300

#: ``struct input_event`` as the running kernel lays it out (native long and alignment).
NATIVE_LAYOUT = "@llHHi"
#: 64-bit little-endian layout (x86_64, aarch64): the recorded test streams use this.
LAYOUT_64LE = "<qqHHi"
#: 32-bit little-endian layout (armv7 with a 32-bit time_t).
LAYOUT_32LE = "<llHHi"


@dataclass(frozen=True)
class InputEvent:
    """One ``struct input_event``: kernel timestamp (s, µs), type, code and value."""

    sec: int
    usec: int
    type: int
    code: int
    value: int

    @property
    def time_ns(self) -> int:
        """The kernel timestamp in integer nanoseconds (CLOCK_REALTIME unless the reader changed it)."""
        return self.sec * NS_PER_S + self.usec * 1000


def pack_event(event: InputEvent, layout: str = NATIVE_LAYOUT) -> bytes:
    """``event`` as the kernel writes it (used by the fake-pad tests and the recording script)."""
    return struct.pack(layout, event.sec, event.usec, event.type, event.code, event.value)


class EventDecoder:
    """Sans-I/O: ``feed(bytes)`` returns the complete events; a partial event waits for more bytes."""

    def __init__(self, layout: str = NATIVE_LAYOUT) -> None:
        self._struct = struct.Struct(layout)
        self._buf = bytearray()
        #: events decoded so far
        self.events = 0

    @property
    def event_size(self) -> int:
        """Bytes per event (24 on 64-bit Linux)."""
        return self._struct.size

    @property
    def pending(self) -> int:
        """Bytes of an incomplete event held back."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[InputEvent]:
        """Add bytes read from the device; return every event now complete, in order."""
        self._buf += data
        size = self._struct.size
        whole = len(self._buf) - len(self._buf) % size
        out = [InputEvent(*fields) for fields in self._struct.iter_unpack(self._buf[:whole])]
        del self._buf[:whole]
        self.events += len(out)
        return out

    def reset(self) -> None:
        """Forget a held-back partial event (the device was closed)."""
        self._buf.clear()


@dataclass(frozen=True)
class PadFrame:
    """The pad after one SYN_REPORT: buttons held, raw axis values, and the buttons that changed."""

    time_ns: int
    buttons: frozenset[int]
    axes: dict[int, int]
    pressed: frozenset[int] = frozenset()
    released: frozenset[int] = frozenset()


class PadState:
    """Sans-I/O: events in, one :class:`PadFrame` per SYN_REPORT out.

    ``centre`` gives each axis's resting raw value, used at start, after SYN_DROPPED and on
    :meth:`release_all` (a vanished pad). Axes never reported stay at their centre.
    """

    def __init__(self, centre: dict[int, int] | None = None) -> None:
        self._centre = dict(centre or {})
        self.buttons: set[int] = set()
        self.axes: dict[int, int] = dict(self._centre)
        self._pending_keys: dict[int, int] = {}
        self._pending_abs: dict[int, int] = {}
        self._dropping = False
        #: SYN_DROPPED events seen (the kernel's buffer overflowed)
        self.dropped = 0
        #: SYN_REPORTs turned into frames
        self.frames = 0

    @property
    def resyncing(self) -> bool:
        """True between a SYN_DROPPED and the SYN_REPORT that ends the discarded stretch."""
        return self._dropping

    def process(self, event: InputEvent) -> PadFrame | None:
        """Take one event; return a frame when it was a SYN_REPORT that completed one."""
        if event.type == EV_SYN:
            if event.code == SYN_DROPPED:
                self.dropped += 1
                self._dropping = True
                self._pending_keys.clear()
                self._pending_abs.clear()
                return None
            if event.code != SYN_REPORT:
                return None
            if self._dropping:
                # The state is unknown: fail safe until new events or an ioctl resync say otherwise.
                self._dropping = False
                return self._replace(set(), dict(self._centre), event.time_ns)
            return self._commit(event.time_ns)
        if self._dropping:
            return None
        if event.type == EV_KEY:
            self._pending_keys[event.code] = event.value
        elif event.type == EV_ABS:
            self._pending_abs[event.code] = event.value
        return None

    def feed(self, events: list[InputEvent]) -> list[PadFrame]:
        """:meth:`process` every event; return the frames completed."""
        frames = []
        for event in events:
            frame = self.process(event)
            if frame is not None:
                frames.append(frame)
        return frames

    def release_all(self, time_ns: int = 0) -> PadFrame:
        """Every button released, every axis centred (the pad vanished); returns that frame."""
        self._pending_keys.clear()
        self._pending_abs.clear()
        self._dropping = False
        return self._replace(set(), dict(self._centre), time_ns)

    def resync(self, buttons: set[int], axes: dict[int, int], time_ns: int = 0) -> PadFrame:
        """Replace the state with one read from the device (EVIOCGKEY / EVIOCGABS)."""
        self._pending_keys.clear()
        self._pending_abs.clear()
        return self._replace(set(buttons), {**self._centre, **axes}, time_ns)

    def _commit(self, time_ns: int) -> PadFrame:
        buttons = set(self.buttons)
        for code, value in self._pending_keys.items():
            if value:  # 1 press, 2 autorepeat
                buttons.add(code)
            else:
                buttons.discard(code)
        axes = {**self.axes, **self._pending_abs}
        self._pending_keys.clear()
        self._pending_abs.clear()
        return self._replace(buttons, axes, time_ns)

    def _replace(self, buttons: set[int], axes: dict[int, int], time_ns: int) -> PadFrame:
        pressed = frozenset(buttons - self.buttons)
        released = frozenset(self.buttons - buttons)
        self.buttons = buttons
        self.axes = axes
        self.frames += 1
        return PadFrame(time_ns, frozenset(buttons), dict(axes), pressed, released)


# --- profiles ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisSpec:
    """An absolute axis: its code and raw range; ``invert`` flips it so that the mapped sign is right."""

    code: int
    minimum: int
    maximum: int
    invert: bool = False

    @property
    def centre(self) -> int:
        """The raw resting value (rounded down for even ranges such as 0..255)."""
        return (self.minimum + self.maximum) // 2

    def normalise(self, raw: int, deadzone: float = 0.0) -> float:
        """``raw`` scaled to -1..1 (clamped), with a rescaled ``deadzone`` (0..1) around the centre."""
        half = (self.maximum - self.minimum) / 2.0
        if half <= 0:
            return 0.0
        value = (raw - (self.minimum + self.maximum) / 2.0) / half
        value = max(-1.0, min(1.0, value))
        if self.invert:
            value = -value
        if abs(value) <= deadzone:
            return 0.0
        scaled = (abs(value) - deadzone) / (1.0 - deadzone)
        return scaled if value > 0 else -scaled


@dataclass(frozen=True)
class GamepadProfile:
    """How one pad reports itself and which codes drive the car.

    ``speed`` is the left stick's vertical axis, inverted so pushing up is +1; ``steering`` the
    right stick's horizontal axis, inverted so pushing left is +1 (REP-103: left is positive).
    ``buttons`` names every button code for logs and docs.
    """

    name: str
    description: str
    vendor: int
    products: tuple[int, ...]
    speed: AxisSpec
    steering: AxisSpec
    deadman: int
    autonomy: int
    arm: int
    disarm: int
    name_hints: tuple[str, ...] = ()
    buttons: dict[int, str] = field(default_factory=dict)
    #: latches the mux e-stop; held with ``arm`` for the release time, releases it (-1: none)
    estop: int = -1

    def centres(self) -> dict[int, int]:
        """Resting raw values of the mapped axes."""
        return {self.speed.code: self.speed.centre, self.steering.code: self.steering.centre}

    def with_ranges(self, ranges: dict[int, tuple[int, int]]) -> GamepadProfile:
        """This profile with axis ranges read from the device (EVIOCGABS) where known."""
        def adjust(axis: AxisSpec) -> AxisSpec:
            lo, hi = ranges.get(axis.code, (axis.minimum, axis.maximum))
            return AxisSpec(axis.code, lo, hi, axis.invert) if hi > lo else axis
        return GamepadProfile(self.name, self.description, self.vendor, self.products,
                              adjust(self.speed), adjust(self.steering), self.deadman, self.autonomy,
                              self.arm, self.disarm, self.name_hints, self.buttons, self.estop)


F710_X = GamepadProfile(
    name="f710_x",
    description="Logitech F710, switch on X (XInput, xpad driver), 046d:c21f",
    vendor=0x046D, products=(0xC21F,),
    speed=AxisSpec(ABS_Y, -32768, 32767, invert=True),
    steering=AxisSpec(ABS_RX, -32768, 32767, invert=True),
    deadman=BTN_TL, autonomy=BTN_TR, arm=BTN_START, disarm=BTN_SELECT,
    name_hints=("f710",),
    buttons={BTN_SOUTH: "A", BTN_EAST: "B", BTN_NORTH: "X", BTN_WEST: "Y", BTN_TL: "LB",
             BTN_TR: "RB", BTN_SELECT: "BACK", BTN_START: "START", BTN_MODE: "LOGITECH",
             BTN_THUMBL: "L3", BTN_THUMBR: "R3"},
    estop=BTN_EAST,
)

F710_D = GamepadProfile(
    name="f710_d",
    description="Logitech F710, switch on D (DirectInput, hid-generic), 046d:c219",
    vendor=0x046D, products=(0xC219,),
    speed=AxisSpec(ABS_Y, 0, 255, invert=True),
    steering=AxisSpec(ABS_Z, 0, 255, invert=True),
    deadman=BTN_TOP2, autonomy=BTN_PINKIE, arm=BTN_BASE4, disarm=BTN_BASE3,
    name_hints=("cordless rumblepad 2",),
    buttons={BTN_TRIGGER: "X", BTN_THUMB: "A", BTN_THUMB2: "B", BTN_TOP: "Y", BTN_TOP2: "LB",
             BTN_PINKIE: "RB", BTN_BASE: "LT", BTN_BASE2: "RT", BTN_BASE3: "BACK",
             BTN_BASE4: "START", BTN_BASE5: "L3", BTN_BASE6: "R3"},
    estop=BTN_THUMB2,
)

PS4 = GamepadProfile(
    name="ps4",
    description="Sony DualShock 4 (hid-sony / hid-playstation), 054c:05c4 and 054c:09cc",
    vendor=0x054C, products=(0x05C4, 0x09CC),
    speed=AxisSpec(ABS_Y, 0, 255, invert=True),
    steering=AxisSpec(ABS_RX, 0, 255, invert=True),
    deadman=BTN_TL, autonomy=BTN_TR, arm=BTN_START, disarm=BTN_SELECT,
    name_hints=("wireless controller",),
    buttons={BTN_SOUTH: "CROSS", BTN_EAST: "CIRCLE", BTN_NORTH: "TRIANGLE", BTN_WEST: "SQUARE",
             BTN_TL: "L1", BTN_TR: "R1", BTN_TL2: "L2", BTN_TR2: "R2", BTN_SELECT: "SHARE",
             BTN_START: "OPTIONS", BTN_MODE: "PS", BTN_THUMBL: "L3", BTN_THUMBR: "R3"},
    estop=BTN_EAST,
)

#: Every known profile by name.
PROFILES: dict[str, GamepadProfile] = {p.name: p for p in (F710_X, F710_D, PS4)}


def profile_for_id(vendor: int, product: int) -> GamepadProfile | None:
    """The profile of a USB vendor/product id, or None."""
    for profile in PROFILES.values():
        if profile.vendor == vendor and product in profile.products:
            return profile
    return None


def profile_for_name(name: str) -> GamepadProfile | None:
    """The profile whose name hints match a device name (case-insensitive), or None."""
    lowered = name.lower()
    for profile in PROFILES.values():
        if any(hint in lowered for hint in profile.name_hints):
            return profile
    return None


# --- mapping -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TeleopCommand:
    """What the pad asks for: deadman and autonomy buttons held, speed (m/s) and steering (rad)."""

    deadman: bool
    autonomy: bool
    speed: float
    steering: float


class TeleopMapping:
    """Frames to commands for one profile, with the speed and steering scales and a deadzone."""

    def __init__(self, profile: GamepadProfile, max_speed_mps: float, max_steering_rad: float,
                 deadzone: float) -> None:
        self.profile = profile
        self.max_speed_mps = max_speed_mps
        self.max_steering_rad = max_steering_rad
        self.deadzone = deadzone

    def command(self, frame: PadFrame) -> TeleopCommand:
        """The command a frame asks for."""
        p = self.profile
        speed = p.speed.normalise(frame.axes.get(p.speed.code, p.speed.centre), self.deadzone)
        steer = p.steering.normalise(frame.axes.get(p.steering.code, p.steering.centre), self.deadzone)
        return TeleopCommand(p.deadman in frame.buttons, p.autonomy in frame.buttons,
                             speed * self.max_speed_mps, steer * self.max_steering_rad)


# --- device discovery and ioctls ---------------------------------------------------------------


def _ioc(direction: int, kind: str, number: int, size: int) -> int:
    return (direction << 30) | (size << 16) | (ord(kind) << 8) | number


_IOC_READ = 2
EVIOCGID = _ioc(_IOC_READ, "E", 0x02, 8)


def EVIOCGNAME(length: int) -> int:  # noqa: N802 - the kernel's macro name
    """ioctl request: the device name into a buffer of ``length`` bytes."""
    return _ioc(_IOC_READ, "E", 0x06, length)


def EVIOCGKEY(length: int) -> int:  # noqa: N802
    """ioctl request: the bitmap of keys held now."""
    return _ioc(_IOC_READ, "E", 0x18, length)


def EVIOCGABS(axis: int) -> int:  # noqa: N802
    """ioctl request: ``struct input_absinfo`` (value, minimum, maximum, fuzz, flat, resolution)."""
    return _ioc(_IOC_READ, "E", 0x40 + axis, 24)


@dataclass(frozen=True)
class InputDevice:
    """An event node found under /dev/input: its path, name and USB id (0 when unknown)."""

    path: str
    name: str = ""
    vendor: int = 0
    product: int = 0


def _read_text(path: Path) -> str:
    try:
        return path.read_text(errors="replace").strip()
    except OSError:
        return ""


def _hex(text: str) -> int:
    try:
        return int(text, 16)
    except ValueError:
        return 0


def describe_event_node(node: str, sys_class: str = "/sys/class/input") -> InputDevice:
    """Name and USB id of ``/dev/input/eventN`` (or a symlink to it) from sysfs."""
    real = os.path.realpath(node)
    base = Path(sys_class) / os.path.basename(real) / "device"
    return InputDevice(node, _read_text(base / "name"), _hex(_read_text(base / "id" / "vendor")),
                       _hex(_read_text(base / "id" / "product")))


def list_event_devices(input_dir: str = "/dev/input",
                       sys_class: str = "/sys/class/input") -> list[InputDevice]:
    """Every ``eventN`` node in ``input_dir`` with its sysfs name and id, in number order."""
    nodes = []
    with contextlib.suppress(OSError):
        for entry in os.listdir(input_dir):
            if entry.startswith("event") and entry[5:].isdigit():
                nodes.append((int(entry[5:]), os.path.join(input_dir, entry)))
    return [describe_event_node(path, sys_class) for _, path in sorted(nodes)]


_SIDE_NODES = ("motion sensors", "touchpad")


def find_gamepad(device: str, profile: str, input_dir: str = "/dev/input",
                 sys_class: str = "/sys/class/input") -> tuple[str, GamepadProfile]:
    """The event node to open and its profile.

    ``device`` is a path (a /dev/input/by-id symlink, an event node, or any readable file or
    FIFO), a case-insensitive substring of the device name, or ``auto`` (the first node whose USB
    id or name a profile knows). ``profile`` is a profile name or ``auto``. Raises DeviceNotFound.
    """
    fixed = PROFILES.get(profile)
    if device.startswith("/"):
        if not os.path.exists(device):
            raise DeviceNotFound(f"gamepad {device} does not exist")
        if fixed is not None:
            return device, fixed
        info = describe_event_node(device, sys_class)
        found = profile_for_id(info.vendor, info.product) or profile_for_name(info.name)
        if found is None:
            raise DeviceNotFound(f"gamepad {device} ({info.name or 'unknown name'}, "
                                 f"{info.vendor:04x}:{info.product:04x}) matches no profile; "
                                 f"set teleop profile to one of {', '.join(PROFILES)}")
        return device, found
    wanted = device.lower()
    for info in list_event_devices(input_dir, sys_class):
        if device != "auto" and wanted not in info.name.lower():
            continue
        if info.name.lower().endswith(_SIDE_NODES):
            continue  # the DualShock's motion-sensor and touchpad nodes share its USB id
        found = fixed or profile_for_id(info.vendor, info.product) or profile_for_name(info.name)
        if found is not None:
            return info.path, found
    raise DeviceNotFound(f"no gamepad matching {device!r} under {input_dir}")


def read_abs_ranges(fd: int, codes: list[int]) -> dict[int, tuple[int, int]]:
    """Axis (minimum, maximum) by EVIOCGABS; empty where the fd is no evdev node."""
    ranges = {}
    for code in codes:
        buf = bytearray(24)
        try:
            fcntl.ioctl(fd, EVIOCGABS(code), buf)
        except OSError:
            continue
        _value, lo, hi, _fuzz, _flat, _res = struct.unpack("6i", buf)
        ranges[code] = (lo, hi)
    return ranges


def read_device_state(fd: int, codes: list[int]) -> tuple[set[int], dict[int, int]] | None:
    """Keys held now and current axis values (EVIOCGKEY, EVIOCGABS), or None on a non-evdev fd."""
    keys = bytearray(KEY_CNT // 8)
    try:
        fcntl.ioctl(fd, EVIOCGKEY(len(keys)), keys)
    except OSError:
        return None
    held = {i for i in range(KEY_CNT) if keys[i // 8] >> (i % 8) & 1}
    axes = {}
    for code in codes:
        buf = bytearray(24)
        with contextlib.suppress(OSError):
            fcntl.ioctl(fd, EVIOCGABS(code), buf)
            axes[code] = struct.unpack("6i", buf)[0]
    return held, axes


# --- the asyncio shell -------------------------------------------------------------------------


@dataclass
class GamepadParams:
    """The gamepad teleop: which pad, its mapping, and what it publishes."""

    enabled: bool = param(False, "run the gamepad teleop")
    device: str = param("auto", "a path (/dev/input/by-id/..., /dev/input/eventN, or a FIFO), a "
                                "substring of the device name, or auto (first known pad)", nonempty=True)
    profile: str = param("auto", "button/axis mapping; auto picks it from the USB id or name",
                         choices=("auto", *PROFILES))
    topic: str = param(TELEOP_TOPIC, "mux input for AckermannDriveStamped teleop commands", topic=True)
    rate_hz: float = param(20.0, "command rate while the deadman is held", unit="Hz",
                           min=1.0, max=200.0)
    max_speed_mps: float = param(2.0, "speed at full stick", unit="m/s", min=0.0, max=20.0)
    max_steering_rad: float = param(0.34, "steering at full stick (+ left)", unit="rad",
                                    min=0.0, max=1.0)
    deadzone: float = param(0.05, "stick deadzone around the centre, fraction of full travel",
                            min=0.0, max=0.9)
    autonomy_lock: bool = param(True, "publish the autonomy lock (RB); switch off in the simulation "
                                      "so navigation runs without a pad")
    autonomy_lock_topic: str = param("/vesc/autonomy_lock",
                                     "std_msgs/Bool; true (engaged) while RB is released", topic=True)
    autonomy_lock_priority: int = param(50, "mux lock priority: above every nav input, below "
                                            "teleop and safety", min=0, max=255)
    autonomy_lock_timeout_s: float = param(0.5, "mux lock deadman timeout: a silent pad engages it",
                                           unit="s", min=0.05, max=10.0)
    require_centred_to_arm: bool = param(True, "START arms only with the speed stick centred")
    estop_release_hold_s: float = param(
        2.0, "B (CIRCLE) latches the mux e-stop; B and START held together this long, with the speed "
             "stick centred, release it", unit="s", min=0.5, max=10.0)
    rescan_min_s: float = param(0.5, "first retry delay after the pad is not found or vanished",
                                unit="s", min=0.01, max=60.0)
    rescan_max_s: float = param(5.0, "longest retry delay (the delay doubles up to this)",
                                unit="s", min=0.01, max=600.0)
    input_dir: str = param("/dev/input", "where event nodes live", nonempty=True)
    sys_class_dir: str = param("/sys/class/input", "where device names and ids are read", nonempty=True)
    layout: str = param("native", "struct input_event layout; native on a real device",
                        choices=("native", "64le", "32le"))

    def __post_init__(self) -> None:
        if not self.topic.startswith("/"):
            raise ConfigError("topic", f"{self.topic!r} is not an absolute topic name")
        if not self.autonomy_lock_topic.startswith("/"):
            raise ConfigError("autonomy_lock_topic",
                              f"{self.autonomy_lock_topic!r} is not an absolute topic name")
        if self.rescan_max_s < self.rescan_min_s:
            raise ConfigError("rescan_max_s", "must not be below rescan_min_s")

    def lock_params(self) -> LockParams:
        """The mux lock entry that makes the autonomy lock work (add it to ``mux.locks``)."""
        return LockParams("autonomy", self.autonomy_lock_topic, self.autonomy_lock_priority,
                          self.autonomy_lock_timeout_s)


_LAYOUTS = {"native": NATIVE_LAYOUT, "64le": LAYOUT_64LE, "32le": LAYOUT_32LE}


class GamepadTeleop:
    """The pad on the bus. ``async run()`` until cancelled; see the module docstring.

    While the deadman (LB) is held, AckermannDriveStamped commands go to ``params.topic`` at
    ``rate_hz``; when it is released (or the pad vanishes) one zero command goes out at once and
    then nothing, so the mux times the input out. With ``autonomy_lock`` on, the lock topic gets
    ``True`` (engaged: navigation masked) while RB is released and ``False`` while RB is held, at
    ``rate_hz`` while the pad is connected; a vanished pad sends one ``True`` and then goes silent
    (the mux's lock timeout keeps it engaged).
    """

    def __init__(self, bus: Bus, params: GamepadParams, arming: Arming, *,
                 clock: Callable[[], int] = monotonic_ns,
                 on_estop: Callable[[], object] | None = None,
                 on_release: Callable[[], object] | None = None) -> None:
        self.bus = bus
        self.params = params
        self.arming = arming
        self._clock = clock
        #: B latches the e-stop (``on_estop``: the daemon latches the mux e-stop as the gamepad
        #: operator); B and START held for ``estop_release_hold_s`` release it (``on_release``)
        self.estop_buttons = EstopButtons(params.estop_release_hold_s, clock, on_estop, on_release)
        self._layout = _LAYOUTS[params.layout]
        self.profile: GamepadProfile | None = PROFILES.get(params.profile)
        self.mapping: TeleopMapping | None = None
        self.state = PadState()
        self.decoder = EventDecoder(self._layout)
        self.command = TeleopCommand(False, False, 0.0, 0.0)
        self.device_path: str | None = None
        self._fd: int | None = None
        self._gone: asyncio.Future[str] | None = None
        #: times a pad was opened / vanished
        self.connects = 0
        self.disconnects = 0
        #: drive commands and lock messages published
        self.published = 0
        self.lock_published = 0
        #: START presses refused because the speed stick was not centred
        self.arm_refused = 0
        #: deadman presses so far
        self.deadman_presses = 0
        bus.declare(params.topic, AckermannDriveStamped)
        if params.autonomy_lock:
            bus.declare(params.autonomy_lock_topic, Bool)

    @property
    def connected(self) -> bool:
        """True while a pad is open."""
        return self._fd is not None

    @property
    def deadman_held(self) -> bool:
        """True while LB is held on a connected pad."""
        return self.command.deadman

    # --- frames ----------------------------------------------------------------------------

    def handle_frame(self, frame: PadFrame) -> None:
        """Apply one frame: arming buttons, deadman edges (a release publishes one stop)."""
        if self.mapping is None:
            return
        profile = self.mapping.profile
        before = self.command
        self.command = self.mapping.command(frame)
        if profile.disarm in frame.pressed:
            self.arming.disarm("gamepad", "BACK on the gamepad")
        elif profile.arm in frame.pressed:
            if self.params.require_centred_to_arm and self.command.speed != 0.0:
                self.arm_refused += 1
                log.warning("gamepad START ignored: centre the speed stick before arming")
            else:
                self.arming.arm("gamepad", "START on the gamepad")
        self.estop_buttons.frame(profile.estop, profile.arm, frame)
        if before.deadman and not self.command.deadman:
            self._publish_drive(AckermannDrive())
        elif self.command.deadman and not before.deadman:
            self.deadman_presses += 1
            self._publish_current()
        if before.autonomy != self.command.autonomy:
            self._publish_lock()

    def _publish_current(self) -> None:
        self._publish_drive(AckermannDrive(steering_angle=self.command.steering, speed=self.command.speed))

    def _publish_drive(self, drive: AckermannDrive) -> None:
        self.bus.publish(self.params.topic, AckermannDriveStamped(stamp_now("base_link", wall_ns()), drive))
        self.published += 1

    def _publish_lock(self) -> None:
        if not self.params.autonomy_lock:
            return
        engaged = not (self.connected and self.command.autonomy)
        self.bus.publish(self.params.autonomy_lock_topic, Bool(engaged))
        self.lock_published += 1

    def tick(self) -> None:
        """One fixed-rate step: the current command while the deadman is held, and the lock."""
        if not self.connected:
            return
        self.estop_buttons.check_release(self.command.speed == 0.0)
        if self.command.deadman:
            self._publish_current()
        self._publish_lock()

    # --- device ----------------------------------------------------------------------------

    def _open(self) -> None:
        path, profile = find_gamepad(self.params.device, self.params.profile, self.params.input_dir,
                                     self.params.sys_class_dir)
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError as err:
            raise DeviceNotFound(f"cannot open gamepad {path}: {err.strerror}") from err
        axes = [profile.speed.code, profile.steering.code]
        profile = profile.with_ranges(read_abs_ranges(fd, axes))
        self.profile = profile
        self.mapping = TeleopMapping(profile, self.params.max_speed_mps, self.params.max_steering_rad,
                                     self.params.deadzone)
        self.state = PadState(profile.centres())
        self.decoder = EventDecoder(self._layout)
        self.device_path = path
        self._fd = fd
        self.connects += 1
        current = read_device_state(fd, axes)
        if current is not None:
            self.handle_frame(self.state.resync(*current, time_ns=wall_ns()))
        log.info("gamepad %s opened as %s", path, profile.description)

    def _close(self, why: str) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(fd)
        os.close(fd)
        self.disconnects += 1
        log.warning("gamepad %s gone: %s; deadman released", self.device_path, why)
        self.handle_frame(self.state.release_all(wall_ns()))
        if self.params.autonomy_lock:
            self.bus.publish(self.params.autonomy_lock_topic, Bool(True))
            self.lock_published += 1

    def _on_readable(self) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            data = os.read(fd, self.decoder.event_size * 64)
        except BlockingIOError:
            return
        except OSError as err:  # ENODEV: unplugged
            self._vanish(f"read failed: {errno.errorcode.get(err.errno or 0, err)}")
            return
        if not data:
            self._vanish("end of stream")
            return
        self._consume(data)

    def _consume(self, data: bytes) -> None:
        dropped = self.state.dropped
        for frame in self.state.feed(self.decoder.feed(data)):
            self.handle_frame(frame)
        if self.state.dropped != dropped and not self.state.resyncing and self._fd is not None:
            # The kernel dropped events: re-read the real state where the fd is an evdev node
            # (otherwise the pad stays "all released" until new events arrive).
            assert self.profile is not None
            current = read_device_state(self._fd, [self.profile.speed.code, self.profile.steering.code])
            if current is not None:
                self.handle_frame(self.state.resync(*current, time_ns=wall_ns()))

    def _vanish(self, why: str) -> None:
        if self._gone is not None and not self._gone.done():
            self._gone.set_result(why)

    async def _read_until_gone(self) -> str:
        assert self._fd is not None
        loop = asyncio.get_running_loop()
        self._gone = loop.create_future()
        mode = os.fstat(self._fd).st_mode
        if stat.S_ISREG(mode):
            await self._replay_file(self._fd)
        else:
            loop.add_reader(self._fd, self._on_readable)
        return await self._gone

    async def _replay_file(self, fd: int) -> None:
        """A recorded stream in a regular file (epoll refuses those), paced by its timestamps."""
        assert self._gone is not None
        start: tuple[int, int] | None = None
        while not self._gone.done():
            data = os.read(fd, self.decoder.event_size * 64)
            if not data:
                self._vanish("end of recorded stream")
                return
            for event in self.decoder.feed(data):
                if start is None:
                    start = (event.time_ns, self._clock())
                wait_ns = start[1] + (event.time_ns - start[0]) - self._clock()
                if wait_ns > 0:
                    await asyncio.sleep(wait_ns / NS_PER_S)
                frame = self.state.process(event)
                if frame is not None:
                    self.handle_frame(frame)

    async def run(self) -> None:
        """Find, read and publish until cancelled; rescans with backoff after unplug or not found."""
        publisher = asyncio.create_task(self._publish_loop())
        delay = self.params.rescan_min_s
        missing_logged = False
        try:
            while True:
                try:
                    self._open()
                except DeviceNotFound as err:
                    if not missing_logged:
                        log.warning("%s; retrying", err)
                        missing_logged = True
                    await asyncio.sleep(delay)
                    delay = min(delay * 2, self.params.rescan_max_s)
                    continue
                missing_logged = False
                delay = self.params.rescan_min_s
                why = "teleop stopped"
                try:
                    why = await self._read_until_gone()
                finally:
                    self._close(why)
                await asyncio.sleep(delay)
        finally:
            publisher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await publisher

    async def _publish_loop(self) -> None:
        ticker = Ticker(self.params.rate_hz, self._clock)
        while True:
            await ticker.tick()
            self.tick()


def iter_events(data: bytes, layout: str = NATIVE_LAYOUT) -> Iterator[InputEvent]:
    """Every complete event in ``data``; raises RemoteProtocolError on a trailing partial event."""
    decoder = EventDecoder(layout)
    yield from decoder.feed(data)
    if decoder.pending:
        raise RemoteProtocolError(f"{decoder.pending} trailing bytes do not make a whole input_event")


__all__ = [
    "F710_D", "F710_X", "PS4", "PROFILES", "AxisSpec", "EventDecoder",
    "GamepadParams", "GamepadProfile", "GamepadTeleop", "InputEvent", "PadFrame", "PadState",
    "TeleopCommand", "TeleopMapping", "find_gamepad", "pack_event",
]
