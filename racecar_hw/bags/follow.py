"""Replay recorded Ackermann commands from a bag into a command-mux input (the lab0 bag follower).

Three pieces, usable alone:

* :func:`load_commands` reads ``ackermann_msgs/AckermannDriveStamped`` (or ``AckermannDrive``), or
  ``geometry_msgs/Twist`` (or ``TwistStamped``, converted with the wheelbase by
  :func:`command_from_message`), on one topic of a ROS 1 ``.bag`` or a ROS 2 bag (sqlite3 or
  MCAP), with clear :class:`BagError`\\ s. Without a topic it picks the bag's only drive topic
  (:func:`choose_topic`). A damaged bag gives a BagError and nothing else, its declared sizes are
  checked before anything is allocated, and every command is checked (finite, within the car's
  limits) before it is used: see :mod:`racecar_hw.bags.validate`.
* :func:`schedule` and :class:`CommandSync` turn the commands into timed steps (python-can
  ``MessageSync`` style): a fixed rate or the bag's own timestamps, optionally time-scaled,
  forwards or backwards, once or looping.
* :class:`BagFollower` publishes the steps, re-stamped, into a mux input topic on absolute
  deadlines, reporting progress.

Backwards = reversed order + negated speed + unchanged steering: an Ackermann path's curvature is
tan(steering)/wheelbase whatever the direction of travel, so the same steering with the opposite
speed retraces the path. With timestamps, the gaps between commands are replayed reversed. When
the recorded speeds exceed what the car may do in reverse (the safety controller's reverse cap),
every speed is scaled down by the same factor and the timing stretched by its inverse, so the path
is still retraced, only slower (:func:`fit_speed`); each command is then repeated at its
unstretched spacing, so that no stretched gap outlasts the mux input's timeout where the recorded
one did not (:func:`keep_alive`).

Twist to Ackermann: ``speed = linear.x``, ``steering = atan(wheelbase * angular.z / linear.x)``
(the steering whose path has the recorded yaw rate at the recorded speed, as the racecar stacks'
``cmd_vel_to_ackermann_drive`` computes it). A Twist that turns in place (``angular.z`` with no
``linear.x``) cannot be driven by an Ackermann car: it becomes a stop, with a warning.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rosbags.interfaces import Connection

from racecar_hw.bags.validate import (
    DEFAULT_MAX_MESSAGE_BYTES,
    CommandLimits,
    check_commands,
    check_storage,
    describe,
    guarded,
)
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.errors import BagError, ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, stamp_now
from racecar_hw.base.params import param
from racecar_hw.base.topics import NAV0_TOPIC
from racecar_hw.rosmsg.typestore import ros2_types

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)

ACKERMANN_TYPES = ("ackermann_msgs/msg/AckermannDriveStamped", "ackermann_msgs/msg/AckermannDrive")
TWIST_TYPES = ("geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped")
ACCEPTED_TYPES = ACKERMANN_TYPES + TWIST_TYPES
#: A mux input topic contains this; a bag's inputs are preferred over the mux output (see choose_topic).
MUX_INPUT_PART = "/ackermann_cmd_mux/input/"
#: Wheelbase (m) for converting Twist when the caller gives none: the F1TENTH car's.
DEFAULT_WHEELBASE_M = 0.25
#: How long a replay waits for the car to be ready (:attr:`BagFollower.ready`) before it starts
#: anyway, s: a device that never comes up is then reported by the command's exit status.
READY_WAIT_S = 10.0


@dataclass(frozen=True)
class Command:
    """One recorded command: its bag time (ns since the epoch) and the drive it asked for."""

    t_ns: int
    drive: AckermannDrive


@dataclass(frozen=True)
class Step:
    """One command to publish ``offset_ns`` after the replay started."""

    offset_ns: int
    drive: AckermannDrive


@dataclass
class FollowerParams:
    """Parameters of the bag follower."""

    bag: str = param("", "ROS 1 .bag file or ROS 2 bag directory (sqlite3 or MCAP) to follow")
    topic: str = param("", "topic in the bag holding AckermannDriveStamped, AckermannDrive, Twist or "
                           "TwistStamped; empty: the bag's only such topic (a mux input preferred)")
    input_topic: str = param(NAV0_TOPIC, "mux input topic the commands are published on", topic=True)
    rate_hz: float = param(20.0, "fixed publish rate when not using the bag timestamps", unit="Hz",
                           min=0.1, max=1000.0)
    use_timestamps: bool = param(False, "replay with the bag's own timing instead of rate_hz")
    time_scale: float = param(1.0, "speed-up of the replay timing (2 = twice as fast); commands "
                                   "themselves are unchanged", min=0.01, max=100.0)
    reverse: bool = param(False, "follow the path backwards: reversed order, negated speed, same "
                                 "steering")
    loop: bool = param(False, "start again after the last command")
    frame_id: str = param("base_link", "frame_id of the re-stamped commands", nonempty=True)
    stop_at_end: bool = param(True, "publish one zero-speed, centred command when the replay ends")
    max_message_bytes: int = param(DEFAULT_MAX_MESSAGE_BYTES, "largest message, or chunk of messages, "
                                   "read from the bag; a bag declaring a larger one is refused before "
                                   "it is read", unit="B", min=1024, max=2**40)

    def __post_init__(self) -> None:
        if not self.input_topic.startswith("/"):
            raise ConfigError("input_topic", f"{self.input_topic!r} is not an absolute topic name")


# --- reading ----------------------------------------------------------------------------------


def _describe(conns: Sequence[Connection]) -> str:
    seen: dict[tuple[str, str], int] = {}
    for c in conns:
        seen[(c.topic, c.msgtype)] = seen.get((c.topic, c.msgtype), 0) + c.msgcount
    return ", ".join(f"{t} ({ty}, {n} msgs)" for (t, ty), n in sorted(seen.items())) or "none"


def _open_reader(path: Path, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> AnyReader:
    if not path.exists():
        raise BagError(f"bag not found: {path}")
    check_storage(path, max_bytes)  # first: it refuses a FIFO or device before anything reads it
    if path.is_file() and path.stat().st_size == 0:
        raise BagError(f"{path} is empty (0 bytes): not a bag (was the recording killed before "
                       "anything was written?)")
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix in (".mcap", ".db3")]
        if files and all(p.stat().st_size == 0 for p in files):
            raise BagError(f"{path}: its storage file is empty (0 bytes)")
    # imported here, where a bag is read: rosbags' readers and their storage plug-ins are a few MB
    # a daemon that does not follow a bag never needs (docs/install.md, "Memory")
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    reader = AnyReader([path], default_typestore=ros2_types().store)
    try:
        reader.open()
    except Exception as err:
        text = str(err)
        hint = ""
        if "not indexed" in text or "end magic" in text:
            hint = f" (an interrupted recording? try: racecar-hw bag recover {path})"
        raise BagError(f"cannot read bag {path}: {describe(err)}{hint}") from err
    return reader


def choose_topic(conns: Sequence[Connection], path: Path | str = "the bag") -> str:
    """The topic to follow when none was given: the only one carrying drive commands.

    With several, the only mux input among them wins (a recording of the whole bus holds the
    input that drove and the mux output, which already went through the safety controller);
    otherwise :class:`BagError` lists them.
    """
    counts: dict[str, int] = {}
    for c in conns:
        if c.msgtype in ACCEPTED_TYPES:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
    candidates = sorted(t for t, n in counts.items() if n) or sorted(counts)
    if len(candidates) == 1:
        return candidates[0]
    inputs = [t for t in candidates if MUX_INPUT_PART in t]
    if len(inputs) == 1:
        return inputs[0]
    if not candidates:
        raise BagError(f"{path} has no topic of type {', '.join(ACCEPTED_TYPES)} to follow; "
                       f"topics found: {_describe(conns)}")
    raise BagError(f"{path} has {len(candidates)} topics with drive commands: "
                   f"{', '.join(f'{t} ({counts[t]} msgs)' for t in candidates)}; choose one with --topic")


def command_from_message(msgtype: str, msg: Any, t_ns: int,
                         wheelbase_m: float = DEFAULT_WHEELBASE_M) -> Command:
    """The one conversion of a bag message (a rosbags object of ``msgtype``) into a :class:`Command`.

    Ackermann messages keep speed and steering; Twist gives speed ``linear.x`` and the steering
    ``atan(wheelbase * angular.z / linear.x)`` (0 when ``linear.x`` is 0: see the module doc).
    """
    if msgtype in TWIST_TYPES:
        twist = msg.twist if msgtype.endswith("Stamped") else msg
        speed = float(twist.linear.x)
        yaw_rate = float(twist.angular.z)
        steering = math.atan(wheelbase_m * yaw_rate / speed) if speed != 0.0 else 0.0
        return Command(t_ns, AckermannDrive(steering_angle=steering, speed=speed))
    types = ros2_types()
    drive = msg.drive if msgtype.endswith("Stamped") else msg
    return Command(t_ns, types.from_ros(drive, AckermannDrive))


#: The largest message (bytes, serialized) taken as a drive command: an AckermannDriveStamped or a
#: TwistStamped is under 100 bytes and its frame id; every command is held until all are read.
MAX_COMMAND_BYTES = 64 * 1024


@guarded
def load_commands(path: str | Path, topic: str | None = None,
                  wheelbase_m: float = DEFAULT_WHEELBASE_M, *, limits: CommandLimits | None = None,
                  max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> list[Command]:
    """The drive commands on ``topic`` (None or "": :func:`choose_topic`) of the bag at ``path``,
    in bag-time order; Twist is converted with ``wheelbase_m`` (m). Commands beyond ``limits``
    are clamped to them, as the VESC driver clamps any command, with one warning that counts them.

    Raises :class:`BagError` (and nothing else) for a missing or zero-byte file, an unreadable or
    damaged bag, one declaring a record over ``max_message_bytes``, an empty bag, a missing topic or
    one of another type (listing the topics and types found), a storage that yields nothing although
    its metadata counts messages, and a command that is not finite or physically absurd
    (:func:`~racecar_hw.bags.validate.check_commands`).
    """
    limits = limits or CommandLimits()
    bag = Path(path)
    reader = _open_reader(bag, max_message_bytes)
    try:
        conns = reader.connections
        if not conns or reader.message_count == 0:
            raise BagError(f"{bag} holds no messages (topics: {_describe(conns)})")
        if not topic:
            topic = choose_topic(conns, bag)
            log.info("%s: following topic %s", bag, topic)
        mine = [c for c in conns if c.topic == topic]
        if not mine:
            raise BagError(f"topic {topic} is not in {bag}; topics found: {_describe(conns)}")
        expected = sum(c.msgcount for c in mine)
        raw = []
        for c, t, data in reader.messages(connections=mine):
            if len(data) > MAX_COMMAND_BYTES:  # kept until all are read: a bag of such would fill memory
                raise BagError(f"{bag}: a message on {topic} ({c.msgtype}) holds {len(data)} bytes, where a "
                               f"drive command takes under {MAX_COMMAND_BYTES}: damaged, or not commands")
            raw.append((c, t, data))
        if expected and not raw:
            raise BagError(
                f"{bag}: the metadata says {expected} messages on {topic}, but reading yielded 0. "
                "In ROS 2 bags this happens when the QoS profiles in metadata.yaml do not match "
                "the storage's topics table; the bag must be repaired (e.g. re-record or convert "
                "it) before it can be followed")
        wrong = [c for c in mine if c.msgtype not in ACCEPTED_TYPES]
        if wrong:
            raise BagError(f"topic {topic} in {bag} carries {wrong[0].msgtype}, expected one of "
                           f"{', '.join(ACCEPTED_TYPES)}; topics found: {_describe(conns)}")
        if not raw:
            raise BagError(f"{bag} holds no messages on {topic} (topics: {_describe(conns)})")
        out = []
        turning_in_place = 0
        for conn, t_ns, data in raw:
            msg = reader.deserialize(data, conn.msgtype)
            if conn.msgtype in TWIST_TYPES and _turns_in_place(msg, conn.msgtype):
                turning_in_place += 1
            command = command_from_message(conn.msgtype, msg, t_ns, wheelbase_m)
            if conn.msgtype in TWIST_TYPES:  # a Twist names no steering angle: not the bag's ask
                command = _clamp_steering(command, limits.max_steering_rad)
            out.append(command)
    finally:
        reader.close()
    if turning_in_place:
        log.warning("%s: %d of %d Twist commands on %s turn in place (angular.z without linear.x), "
                    "which an Ackermann car cannot do: they are followed as stops", bag,
                    turning_in_place, len(out), topic)
    out.sort(key=lambda c: c.t_ns)
    check_commands(out, bag, topic)
    return clamp_commands(out, limits, bag, topic)


def clamp_commands(commands: list[Command], limits: CommandLimits, bag: str | Path,
                   topic: str) -> list[Command]:
    """``commands`` with speed and steering clamped to ``limits``; one warning counts the clamped
    ones and names the most the bag asked for (a bag from a car that steers further is normal)."""
    out: list[Command] = []
    clamped = 0
    top_speed = top_steering = 0.0
    for command in commands:
        drive = limits.clamp(command.drive)
        if drive is not command.drive:
            clamped += 1
            top_speed = max(top_speed, abs(command.drive.speed))
            top_steering = max(top_steering, abs(command.drive.steering_angle))
            command = dataclasses.replace(command, drive=drive)
        out.append(command)
    if clamped:
        asked = []
        if top_speed > limits.max_speed_mps:
            asked.append(f"speed up to {top_speed:g} m/s (limit {limits.max_speed_mps:g})")
        if top_steering > limits.max_steering_rad:
            asked.append(f"steering up to {top_steering:g} rad (limit {limits.max_steering_rad:g})")
        log.warning("%s: %d of %d commands on %s ask for more than this car's limits, %s: they are "
                    "clamped to the limits (vesc.speed_max_mps, vesc.steering_max_rad), as any "
                    "command is", bag, clamped, len(out), topic, " and ".join(asked))
    return out


def _turns_in_place(msg: Any, msgtype: str) -> bool:
    twist = msg.twist if msgtype.endswith("Stamped") else msg
    return float(twist.linear.x) == 0.0 and float(twist.angular.z) != 0.0


def _clamp_steering(command: Command, limit_rad: float) -> Command:
    steering = command.drive.steering_angle
    if not abs(steering) > limit_rad:  # within the limit, or NaN (left to check_commands)
        return command
    drive = dataclasses.replace(command.drive, steering_angle=math.copysign(limit_rad, steering))
    return dataclasses.replace(command, drive=drive)


@guarded
def summarize_bag(path: str | Path) -> dict[str, tuple[str, int]]:
    """Every topic of the bag with its type and the number of messages actually read.

    Each message is read and deserialized, so an unreadable one raises; a topic whose metadata
    counts messages that the storage does not yield raises :class:`BagError`.
    """
    bag = Path(path)
    reader = _open_reader(bag)
    try:
        found: dict[str, tuple[str, int]] = {}
        for conn in reader.connections:
            count = 0
            for c, _t, data in reader.messages(connections=[conn]):
                reader.deserialize(data, c.msgtype)
                count += 1
            if conn.msgcount and not count:
                raise BagError(f"{bag}: the metadata says {conn.msgcount} messages on {conn.topic}, "
                               "but reading yielded 0 (metadata.yaml QoS differs from the storage?)")
            old_type, old_count = found.get(conn.topic, (conn.msgtype, 0))
            found[conn.topic] = (old_type, old_count + count)
    finally:
        reader.close()
    return found


# --- timing -----------------------------------------------------------------------------------


def schedule(commands: Sequence[Command], *, rate_hz: float = 20.0, use_timestamps: bool = False,
             time_scale: float = 1.0, reverse: bool = False, speed_scale: float = 1.0) -> list[Step]:
    """Timed steps for ``commands``: offsets from the start of one pass, in ns.

    A fixed rate puts step ``i`` at ``i / (rate_hz * time_scale)``; timestamps put it at its
    bag-time distance from the first (or, reversed, from the last) command divided by
    ``time_scale``. Reversing also negates speed (steering unchanged). ``speed_scale`` (0..1]
    multiplies every speed and stretches the timing by its inverse: the same path, slower.
    """
    if rate_hz <= 0 or time_scale <= 0 or not 0 < speed_scale <= 1:
        raise ValueError("rate_hz and time_scale must be positive, speed_scale in (0, 1]")
    cmds = list(reversed(commands)) if reverse else list(commands)
    if not cmds:
        return []
    steps = []
    pace = time_scale * speed_scale
    period = NS_PER_S / (rate_hz * pace)
    t0 = cmds[0].t_ns
    sign = -1.0 if reverse else 1.0
    for i, cmd in enumerate(cmds):
        offset = abs(cmd.t_ns - t0) / pace if use_timestamps else i * period
        drive = cmd.drive
        if reverse or speed_scale != 1.0:
            drive = dataclasses.replace(drive, speed=sign * speed_scale * drive.speed)
        steps.append(Step(round(offset), drive))
    return steps


def keep_alive(steps: Sequence[Step], speed_scale: float) -> list[Step]:
    """``steps`` of a replay slowed by ``speed_scale`` (< 1: :func:`schedule`), each command
    repeated at its unstretched spacing until the next one.

    A stretched gap would otherwise let the mux input's timeout expire where the recording's did
    not (a 0.15 s hole of a held-up recorder becomes 0.3 s, over the default 0.2 s), and the car
    would stop there and fall short of the path. With the repeats the mux sees commands as often
    as it did in the recording: a gap its timeout bridged then is bridged now, and one it did not
    bridge drives the car as far as it did then (a timeout's worth at the slower speed per
    repeat, as many repeats as the stretch: exactly so when ``1 / speed_scale`` is a whole number,
    as :func:`fit_speed` makes it).
    """
    if speed_scale >= 1.0 or len(steps) < 2:
        return list(steps)
    repeats = math.ceil(1.0 / speed_scale - 1e-9) - 1  # exact for 1/2, 1/3 ... (fit_speed's)
    out: list[Step] = []
    for step, following in zip(steps, steps[1:], strict=False):
        out.append(step)
        gap = following.offset_ns - step.offset_ns
        for k in range(1, repeats + 1):
            at = step.offset_ns + round(gap * speed_scale * k)
            if at < following.offset_ns:
                out.append(Step(at, step.drive))
    out.append(steps[-1])
    return out


def fit_speed(commands: Sequence[Command], limit_mps: float | None, reverse: bool) -> float:
    """The ``speed_scale`` that keeps every speed of the replay within ``limit_mps`` (m/s): 1/2,
    1/3, 1/4 ..., the largest such that does, so that the replay is a whole number of times slower
    and :func:`keep_alive` repeats each command exactly as often as the stretch needs.

    ``limit_mps`` applies to reverse driving (the safety controller's reverse cap): forwards
    commands replayed backwards, and backwards ones replayed forwards. 1.0 when nothing exceeds it.
    """
    if limit_mps is None or limit_mps <= 0:
        return 1.0
    sign = -1.0 if reverse else 1.0
    fastest = max((-sign * c.drive.speed for c in commands), default=0.0)  # reverse speeds, > 0
    return 1.0 / math.ceil(fastest / limit_mps - 1e-9) if fastest > limit_mps else 1.0


@dataclass(frozen=True)
class Hole:
    """A stretch of the recording with no command: ``at_s`` after the first command, ``gap_s`` long."""

    at_s: float
    gap_s: float


def holes(commands: Sequence[Command], factor: float = 3.0) -> list[Hole]:
    """The gaps between consecutive commands longer than ``factor`` times the median gap.

    A source that skipped its ticks (a held-up laptop, a dropped wireless link) leaves such holes.
    A fixed-rate replay closes them up, so the path comes out shorter than the recorded one.
    """
    if len(commands) < 3:
        return []
    gaps = [b.t_ns - a.t_ns for a, b in zip(commands, commands[1:], strict=False)]
    usual = sorted(gaps)[len(gaps) // 2]
    if usual <= 0:
        return []
    t0 = commands[0].t_ns
    return [Hole((commands[i].t_ns - t0) / NS_PER_S, gap / NS_PER_S)
            for i, gap in enumerate(gaps) if gap > factor * usual]


class CommandSync:
    """Steps with absolute offsets over one pass or, with ``loop``, forever.

    A new pass starts one ``gap_ns`` after the last step of the previous pass (the fixed-rate
    period, by default). ``len()`` is the steps of one pass; :attr:`pass_ns` its duration.
    """

    def __init__(self, steps: Sequence[Step], *, loop: bool = False, gap_ns: int = NS_PER_S // 20) -> None:
        self.steps = list(steps)
        self.loop = loop
        self.gap_ns = gap_ns
        self.pass_ns = (self.steps[-1].offset_ns if self.steps else 0) + gap_ns

    def __len__(self) -> int:
        return len(self.steps)

    def __iter__(self) -> Iterator[tuple[int, int, Step]]:
        """Yields (absolute offset ns, index within the pass, step)."""
        base = 0
        while self.steps:
            for i, step in enumerate(self.steps):
                yield base + step.offset_ns, i, step
            if not self.loop:
                return
            base += self.pass_ns

    def play(self, sleep: Callable[[float], None] = time.sleep,
             now_ns: Callable[[], int] = monotonic_ns) -> Iterator[Step]:
        """Yield each step at its deadline, sleeping in between (for scripts without asyncio)."""
        start = now_ns()
        for offset, _i, step in self:
            delay = (start + offset - now_ns()) / NS_PER_S
            if delay > 0:
                sleep(delay)
            yield step


# --- the follower -----------------------------------------------------------------------------

Progress = Callable[[float, float], None]


class BagFollower:
    """Publishes a bag's Ackermann commands, re-stamped, into a mux input topic.

    ``progress(fraction, eta_s)`` is called after each command (fraction of the current pass,
    seconds left in it). ``done`` turns true when a non-looping replay has finished or ``stop()``
    was called. Commands enter the mux as a normal source, so deadman, timeouts and safety apply.
    """

    def __init__(self, bus: Bus, params: FollowerParams, progress: Progress | None = None, *,
                 wheelbase_m: float = DEFAULT_WHEELBASE_M,
                 reverse_speed_cap_mps: float | None = None,
                 limits: CommandLimits | None = None) -> None:
        self.bus = bus
        self.params = params
        self.progress = progress
        self.wheelbase_m = wheelbase_m
        self.reverse_speed_cap_mps = reverse_speed_cap_mps
        #: what a command may ask for (the car's configured limits); commands beyond them are clamped
        self.limits = limits or CommandLimits()
        self.done = False
        self.published = 0
        self.late_ns_max = 0
        self._stop = asyncio.Event()
        self.commands: list[Command] = []
        #: every speed of the replay is multiplied by this (and the timing stretched): see fit_speed
        self.speed_scale = 1.0
        self._steps: list[Step] | None = None
        #: whether the car can act on a command (its VESC answers and, with a lidar, the safety
        #: controller has a scan); the replay starts once it is true, or after READY_WAIT_S. None: at once
        self.ready: Callable[[], bool] | None = None
        #: why the car cannot get ready in this replay (a device whose port does not exist), or None
        #: while it may; asked while the replay waits for :attr:`ready`: with a reason the replay
        #: ends before its first command (``racecar-hw follow`` sets it; the daemon's own follower
        #: keeps waiting, since its devices may be plugged in later)
        self.hopeless: Callable[[], str | None] | None = None

    def load(self) -> list[Step]:
        """Read and check the bag and build the steps (raises BagError); done once, also by :meth:`run`,
        so a caller can load first and refuse a bad bag before the car is touched."""
        if self._steps is not None:
            return self._steps
        p = self.params
        self.commands = load_commands(p.bag, p.topic, self.wheelbase_m, limits=self.limits,
                                      max_message_bytes=p.max_message_bytes)
        if not p.use_timestamps and (found := holes(self.commands)):
            longest = max(found, key=lambda h: h.gap_s)
            log.warning("%s: the recording has %d gap(s) over three times its usual spacing "
                        "(longest %.0f ms, %.1f s in); a fixed-rate replay closes them up and "
                        "shortens the path: set use_timestamps to replay them", p.bag, len(found),
                        longest.gap_s * 1e3, longest.at_s)
        self.speed_scale = fit_speed(self.commands, self.reverse_speed_cap_mps, p.reverse)
        if self.speed_scale < 1.0:
            cap = self.reverse_speed_cap_mps
            log.warning("%s: the replay reverses at up to %.2f m/s, over the safety controller's "
                        "reverse cap of %.2f m/s: every speed is scaled by %.2f and the timing "
                        "stretched to match, so the path is retraced %.1f times slower", p.bag,
                        (cap or 0.0) / self.speed_scale, cap, self.speed_scale, 1 / self.speed_scale)
        self._steps = keep_alive(schedule(self.commands, rate_hz=p.rate_hz,
                                          use_timestamps=p.use_timestamps, time_scale=p.time_scale,
                                          reverse=p.reverse, speed_scale=self.speed_scale),
                                 self.speed_scale)
        return self._steps

    def stop(self) -> None:
        """End the replay at the next deadline."""
        self._stop.set()

    async def run(self) -> int:
        """Replay; returns the number of commands published."""
        p = self.params
        steps = await asyncio.to_thread(self.load)
        gap = round(NS_PER_S / (p.rate_hz * p.time_scale * self.speed_scale))
        sync = CommandSync(steps, loop=p.loop, gap_ns=gap)
        log.info("following %d commands from %s (%s, %s)", len(sync), p.bag,
                 "backwards" if p.reverse else "forwards",
                 "bag timing" if p.use_timestamps else f"{p.rate_hz:g} Hz")
        await self._wait_until_ready()
        start = monotonic_ns()
        last_offset = sync.steps[-1].offset_ns if sync.steps else 0
        try:
            for offset, index, step in sync:
                deadline = start + offset
                while not self._stop.is_set() and (delay := deadline - monotonic_ns()) > 0:
                    await asyncio.sleep(min(delay / NS_PER_S, 0.1))  # wake at least every 0.1 s
                if self._stop.is_set():
                    break
                self.late_ns_max = max(self.late_ns_max, monotonic_ns() - start - offset)
                self._publish(step.drive)
                if self.progress is not None:
                    fraction = (index + 1) / len(sync)
                    self.progress(fraction, max(0.0, (last_offset - step.offset_ns) / NS_PER_S))
        finally:
            if p.stop_at_end:
                self._publish(AckermannDrive())
            self.done = True
        return self.published

    async def _wait_until_ready(self) -> None:
        """Hold the replay's start until :attr:`ready` (at most READY_WAIT_S): commands played
        while the VESC or the lidar is still connecting would be lost, the start of the bag with them."""
        if self.ready is None or self.ready():
            return
        log.info("waiting for the car (VESC and lidar) before replaying")
        deadline = monotonic_ns() + round(READY_WAIT_S * NS_PER_S)
        while not self._stop.is_set() and not self.ready():
            if self.hopeless is not None and (why := self.hopeless()):
                log.error("not replaying %s: %s", self.params.bag, why)
                self._stop.set()
                return
            if monotonic_ns() >= deadline:
                log.warning("the car is not ready after %.0f s; replaying anyway", READY_WAIT_S)
                return
            await asyncio.sleep(0.02)

    def _publish(self, drive: AckermannDrive) -> None:
        self.bus.publish(self.params.input_topic,
                         AckermannDriveStamped(stamp_now(self.params.frame_id, wall_ns()), drive))
        self.published += 1


def follow(bus: Bus, params: FollowerParams, progress: Progress | None = None) -> BagFollower:
    """A follower for ``params``; ``await follower.run()`` replays (for the CLI's ``follow``)."""
    return BagFollower(bus, params, progress)
