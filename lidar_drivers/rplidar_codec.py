"""Slamtec RPLIDAR serial protocol as a sans-I/O codec, for both ends of the wire.

Host side: :class:`RplidarClient` turns requests into bytes (:meth:`RplidarClient.send`) and bytes
from the device into typed events (:meth:`RplidarClient.receive_data`, :meth:`next_event`).
Device side (the fake lidar): :class:`RequestParser` turns host bytes into :class:`Request` events
and the ``encode_*`` functions build responses, scan nodes and express capsules.

Wire format (reference ``lidars.md`` section 2):

* request ``A5 cmd``; when ``cmd & 0x80`` a payload follows: ``A5 cmd len payload cs`` with ``cs``
  the XOR of every byte before it;
* response descriptor ``A5 5A`` + u32 little-endian (low 30 bits: payload size, bits 30-31: mode,
  1 = loop: payloads repeat with no new descriptor) + a type byte;
* standard scan node (5 bytes): ``quality<<2 | !S<<1 | S``, u16 ``angle_q6<<1 | 1``, u16 distance
  in mm x 4 (0 = invalid);
* express capsule (84 bytes): ``0xA0|cs_lo``, ``0x50|cs_hi`` (cs = XOR of bytes 2..83), u16 start
  angle q6 (bit 15: first capsule after the scan request), 16 cabins of two samples each;
* ultra (0x84) and dense (0x85) capsules: see :mod:`lidar_drivers.rplidar_capsules`;
* GET_LIDAR_CONF (firmware 1.24+, and every C/S-series unit): request payload u32 key [+ u16 scan
  mode id], answer u32 key + value (:class:`ConfKey`); the scan modes a device lists are
  :class:`ScanMode` records.

Angles are the device's own: degrees, clockwise seen from above, [0, 360). Distances are mm.
Measurements come out in batches of numpy arrays (:class:`Measurements`), in time order.

Nothing from the device raises: garbage is skipped up to the next plausible frame and counted in
:class:`CodecStats`; an express capsule pair whose start-angle step is implausible (a duplicated
or reordered capsule) is dropped, as its samples would land at wrong angles. Only a caller asking
for something the protocol cannot say raises :class:`~racecar_hw.base.errors.LocalProtocolError`.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from lidar_drivers import rplidar_capsules as caps
from racecar_hw.base.errors import LocalProtocolError

SYNC = 0xA5
SYNC2 = 0x5A
DESCRIPTOR = b"\xa5\x5a"
DESCRIPTOR_LEN = 7
NODE_LEN = 5
CAPSULE_LEN = 84
SAMPLES_PER_CAPSULE = 32
MODE_SINGLE = 0
MODE_LOOP = 1
#: Consecutive plausible nodes needed to lock onto the node stream again after a bad node.
NODE_RESYNC_RUN = 4
#: Largest angle step (device degrees) between neighbouring nodes while re-locking.
NODE_RESYNC_MAX_STEP_DEG = 20.0
FULL_TURN_Q6 = 360 * 64
#: Start-angle step between consecutive express capsules (degrees) any model can produce: 32
#: samples of 100-500 µs at 2-25 revolutions per second. A GET_SAMPLERATE answer narrows it.
CAPSULE_STEP_DEG = (2.0, 150.0)
#: Scan rates (Hz) the narrowed range allows around the device's express sample period.
CAPSULE_SCAN_HZ = (2.0, 25.0)
#: A capsule step may differ from the last accepted one by this fraction (the motor speed drifts
#: slowly; a duplicated or skipped capsule changes the step by 100 %).
CAPSULE_STEP_TOLERANCE = 0.25
#: After this many in-range steps in a row that all disagree with the last accepted one, the
#: motor speed really changed: the next in-range step is taken as the new reference.
CAPSULE_RELOCK = 8
#: An express capsule as a packed numpy record (little-endian, 84 bytes).
CAPSULE_DTYPE = np.dtype([
    ("sync_cs_lo", "u1"), ("sync_cs_hi", "u1"), ("start", "<u2"),
    ("cabins", np.dtype([("d1", "<u2"), ("d2", "<u2"), ("dtheta", "u1")]), (16,)),
])


class Command(IntEnum):
    """Request command bytes."""

    STOP = 0x25
    RESET = 0x40
    SCAN = 0x20
    FORCE_SCAN = 0x21
    GET_INFO = 0x50
    GET_HEALTH = 0x52
    GET_SAMPLERATE = 0x59
    EXPRESS_SCAN = 0x82
    GET_LIDAR_CONF = 0x84
    SET_MOTOR_RPM = 0xA8
    SET_MOTOR_PWM = 0xF0
    GET_ACC_BOARD_FLAG = 0xFF


class AnswerType(IntEnum):
    """Response descriptor type bytes."""

    INFO = 0x04
    HEALTH = 0x06
    SAMPLERATE = 0x15
    LIDAR_CONF = 0x20
    SCAN = 0x81
    EXPRESS = 0x82
    HQ = 0x83
    ULTRA_CAPSULED = 0x84
    DENSE_CAPSULED = 0x85
    ULTRA_DENSE_CAPSULED = 0x86
    ACC_BOARD_FLAG = 0xFF


#: What each measurement answer type carries, for logs and errors.
ANSWER_NAMES = {
    AnswerType.SCAN: "standard nodes", AnswerType.EXPRESS: "express capsules",
    AnswerType.HQ: "HQ nodes", AnswerType.ULTRA_CAPSULED: "ultra capsules",
    AnswerType.DENSE_CAPSULED: "dense capsules",
    AnswerType.ULTRA_DENSE_CAPSULED: "ultra-dense capsules",
}
#: Measurement answer types this codec decodes, with their samples per packet.
DECODED_ANSWERS = {AnswerType.SCAN: 1, AnswerType.EXPRESS: 32,
                   AnswerType.ULTRA_CAPSULED: caps.ULTRA_SAMPLES,
                   AnswerType.DENSE_CAPSULED: caps.DENSE_SAMPLES}


class ConfKey(IntEnum):
    """GET_LIDAR_CONF keys (``sl_lidar_cmd.h``). Per-mode keys take the mode id as payload."""

    DESIRED_ROT_FREQ = 0x01  # u16 rpm, u16 PWM reference
    MIN_ROT_FREQ = 0x04
    MAX_ROT_FREQ = 0x05
    SCAN_MODE_COUNT = 0x70  # u16
    SCAN_MODE_US_PER_SAMPLE = 0x71  # u32, 1/256 µs
    SCAN_MODE_MAX_DISTANCE = 0x74  # u32, 1/256 m
    SCAN_MODE_ANS_TYPE = 0x75  # u8
    SCAN_MODE_TYPICAL = 0x7C  # u16
    SCAN_MODE_NAME = 0x7F  # NUL-terminated text


#: Keys whose request carries a scan mode id.
PER_MODE_KEYS = frozenset({ConfKey.SCAN_MODE_US_PER_SAMPLE, ConfKey.SCAN_MODE_MAX_DISTANCE,
                           ConfKey.SCAN_MODE_ANS_TYPE, ConfKey.SCAN_MODE_NAME})


#: (payload size, mode) every answer type must announce; LIDAR_CONF varies in size.
_ANSWER_SHAPE: dict[int, tuple[int, int]] = {
    AnswerType.INFO: (20, MODE_SINGLE),
    AnswerType.HEALTH: (3, MODE_SINGLE),
    AnswerType.SAMPLERATE: (4, MODE_SINGLE),
    AnswerType.SCAN: (NODE_LEN, MODE_LOOP),
    AnswerType.EXPRESS: (CAPSULE_LEN, MODE_LOOP),
    AnswerType.ULTRA_CAPSULED: (caps.ULTRA_LEN, MODE_LOOP),
    AnswerType.DENSE_CAPSULED: (caps.DENSE_LEN, MODE_LOOP),
    AnswerType.ACC_BOARD_FLAG: (4, MODE_SINGLE),
}
#: Packet size of every measurement answer type the codec decodes.
PACKET_LEN = {kind: _ANSWER_SHAPE[kind][0] for kind in DECODED_ANSWERS}
_LIDAR_CONF_MAX = 64

#: The answer type each request gets back; requests missing here get no answer.
ANSWER_TO: dict[int, int] = {
    Command.SCAN: AnswerType.SCAN,
    Command.FORCE_SCAN: AnswerType.SCAN,
    Command.GET_INFO: AnswerType.INFO,
    Command.GET_HEALTH: AnswerType.HEALTH,
    Command.GET_SAMPLERATE: AnswerType.SAMPLERATE,
    Command.EXPRESS_SCAN: AnswerType.EXPRESS,
    Command.GET_LIDAR_CONF: AnswerType.LIDAR_CONF,
    Command.GET_ACC_BOARD_FLAG: AnswerType.ACC_BOARD_FLAG,
}

HEALTH_STATUS = {0: "good", 1: "warning", 2: "error"}
HEALTH_MEANING = {
    0: "the device works normally",
    1: "the device sees a potential risk of hardware failure but still measures",
    2: "the device is in protection stop (hardware fault): it will not measure until reset",
}


# --- requests (host -> device) -----------------------------------------------------------------


@dataclass(frozen=True)
class Request:
    """One request: a command byte and, for commands >= 0x80, a payload of at most 255 bytes."""

    command: int
    payload: bytes = b""

    def encode(self) -> bytes:
        """The bytes on the wire; raises LocalProtocolError for a request the protocol cannot say."""
        if not 0 <= self.command <= 0xFF:
            raise LocalProtocolError(f"command 0x{self.command:x} is not a byte")
        has_payload = bool(self.command & 0x80)
        if not has_payload:
            if self.payload:
                raise LocalProtocolError(f"command 0x{self.command:02x} (< 0x80) carries no payload")
            return bytes((SYNC, self.command))
        if len(self.payload) > 255:
            raise LocalProtocolError(f"payload of {len(self.payload)} bytes exceeds 255")
        frame = bytes((SYNC, self.command, len(self.payload))) + self.payload
        return frame + bytes((xor_checksum(frame),))

    @classmethod
    def simple(cls, command: Command) -> Request:
        """A request with no payload (STOP, RESET, SCAN, GET_INFO ...)."""
        return cls(int(command))

    @classmethod
    def express_scan(cls, mode: int = 0, flags: int = 0) -> Request:
        """EXPRESS_SCAN in working ``mode``: a scan mode id from GET_LIDAR_CONF, or 0 for the
        legacy express capsules of a device without the configuration commands."""
        if not 0 <= mode <= 0xFF or not 0 <= flags <= 0xFFFF:
            raise LocalProtocolError(f"express scan mode {mode} / flags {flags} out of range")
        return cls(Command.EXPRESS_SCAN, struct.pack("<BHH", mode, flags, 0))

    @classmethod
    def get_lidar_conf(cls, key: int, mode: int | None = None) -> Request:
        """GET_LIDAR_CONF for ``key``; per-mode keys (:data:`PER_MODE_KEYS`) need the ``mode`` id."""
        if not 0 <= key <= 0xFFFFFFFF or (mode is not None and not 0 <= mode <= 0xFFFF):
            raise LocalProtocolError(f"configuration key 0x{key:x} / mode {mode} out of range")
        if (key in PER_MODE_KEYS) != (mode is not None):
            raise LocalProtocolError(f"configuration key 0x{key:x} "
                                     f"{'needs' if key in PER_MODE_KEYS else 'takes no'} scan mode")
        payload = struct.pack("<I", key) + (b"" if mode is None else struct.pack("<H", mode))
        return cls(Command.GET_LIDAR_CONF, payload)

    @classmethod
    def set_motor_rpm(cls, rpm: int) -> Request:
        """The motor speed command of the S series (and newer), in revolutions per minute."""
        if not 0 <= rpm <= 0xFFFF:
            raise LocalProtocolError(f"motor rpm {rpm} outside 0..65535")
        return cls(Command.SET_MOTOR_RPM, struct.pack("<H", rpm))

    @classmethod
    def set_motor_pwm(cls, pwm: int) -> Request:
        """SET_MOTOR_PWM, duty 0..1023 (A2/A3 accessory board)."""
        if not 0 <= pwm <= 1023:
            raise LocalProtocolError(f"motor PWM {pwm} outside 0..1023")
        return cls(Command.SET_MOTOR_PWM, struct.pack("<H", pwm))

    @classmethod
    def get_acc_board_flag(cls) -> Request:
        """GET_ACC_BOARD_FLAG (u32 payload, 0)."""
        return cls(Command.GET_ACC_BOARD_FLAG, struct.pack("<I", 0))


def xor_checksum(data: bytes | bytearray | memoryview) -> int:
    """XOR of every byte."""
    cs = 0
    for b in bytes(data):
        cs ^= b
    return cs


# --- events (device -> host) -------------------------------------------------------------------


@dataclass(frozen=True)
class DeviceInfo:
    """GET_INFO: model id (major<<4 | minor), firmware, hardware revision, 16-byte serial number."""

    model_id: int
    firmware_major: int
    firmware_minor: int
    hardware: int
    serial: bytes

    @property
    def major(self) -> int:
        """Series: 1-3 = A1-A3, 4 = C1, 6-8 = S1-S3."""
        return self.model_id >> 4

    @property
    def model_name(self) -> str:
        """``A1M8`` style name from the two nibbles, as the SDK prints it."""
        series = {4: "C", 6: "S", 7: "S", 8: "S"}.get(self.major, "A")
        number = self.major - 5 if series == "S" else (1 if series == "C" else self.major)
        return f"{series}{number}M{self.model_id & 0xF}"

    @property
    def firmware(self) -> str:
        """``major.minor`` with two minor digits, e.g. ``1.29``."""
        return f"{self.firmware_major}.{self.firmware_minor:02d}"

    @property
    def serial_hex(self) -> str:
        """The serial number as upper-case hex."""
        return self.serial.hex().upper()


@dataclass(frozen=True)
class Health:
    """GET_HEALTH: status 0 good / 1 warning / 2 error, and a 16-bit error code (little-endian)."""

    status: int
    error_code: int

    @property
    def status_name(self) -> str:
        return HEALTH_STATUS.get(self.status, f"unknown status {self.status}")

    @property
    def meaning(self) -> str:
        return HEALTH_MEANING.get(self.status, "undocumented health status")


@dataclass(frozen=True)
class SampleRate:
    """GET_SAMPLERATE: time per sample in microseconds for standard and express scans."""

    standard_us: int
    express_us: int


@dataclass(frozen=True)
class AccBoardFlag:
    """GET_ACC_BOARD_FLAG: bit 0 set means the motor speed is set with SET_MOTOR_PWM."""

    flags: int

    @property
    def pwm_supported(self) -> bool:
        return bool(self.flags & 1)


@dataclass(frozen=True)
class LidarConf:
    """GET_LIDAR_CONF answer: the key asked for and its raw value bytes."""

    key: int
    value: bytes

    def number(self, size: int) -> int | None:
        """The value as a little-endian unsigned integer of ``size`` bytes; None if too short."""
        if len(self.value) < size:
            return None
        return int.from_bytes(self.value[:size], "little")

    @property
    def text(self) -> str:
        """The value as text (up to the first NUL; undecodable bytes replaced)."""
        return self.value.split(b"\0", 1)[0].decode("ascii", "replace")


@dataclass(frozen=True)
class ScanMode:
    """One scan mode a device lists: its id, name, µs per sample, range (m) and answer type."""

    id: int
    name: str
    us_per_sample: float
    max_distance_m: float
    answer_type: int

    @property
    def samples_per_s(self) -> float:
        return 1e6 / self.us_per_sample if self.us_per_sample > 0 else 0.0

    @property
    def answer_name(self) -> str:
        return ANSWER_NAMES.get(self.answer_type, f"answer type 0x{self.answer_type:02x}")

    def describe(self) -> str:
        """``Sensitivity (id 3): 15.9 k samples/s, 25 m, ultra capsules (0x84)``."""
        return (f"{self.name} (id {self.id}): {self.samples_per_s / 1000:.1f} k samples/s, "
                f"{self.max_distance_m:g} m, {self.answer_name} (0x{self.answer_type:02x})")


def supports_conf_commands(info: DeviceInfo) -> bool:
    """Whether a device answers GET_LIDAR_CONF, decided as Slamtec's SDK decides it: every
    C/S-series (and newer) unit, and A-series firmware 1.24 or later."""
    return info.major >= 4 or (info.firmware_major, info.firmware_minor) >= (1, 24)


@dataclass(frozen=True)
class ScanStarted:
    """The descriptor of a scan stream: samples follow until the host sends STOP.

    ``express`` is True for every capsule format; ``answer_type`` says which (0 when the event
    was built by hand without one).
    """

    express: bool
    answer_type: int = 0


@dataclass(frozen=True, eq=False)
class Measurements:
    """Consecutive samples in time order (device convention: degrees clockwise, mm).

    ``start`` marks the first sample of a new revolution; ``distance_mm`` 0 means no valid return.
    ``held_back`` is how many samples the decoder has received after the last one here but not
    emitted yet (an express capsule waits for the next one), for time-stamping.
    """

    start: np.ndarray
    quality: np.ndarray
    angle_deg: np.ndarray
    distance_mm: np.ndarray
    express: bool
    held_back: int = 0

    def __len__(self) -> int:
        return len(self.angle_deg)


Event = DeviceInfo | Health | SampleRate | AccBoardFlag | LidarConf | ScanStarted | Measurements


@dataclass
class CodecStats:
    """What the decoder had to throw away."""

    bytes_in: int = 0
    garbage_bytes: int = 0
    resyncs: int = 0
    bad_descriptors: int = 0
    bad_nodes: int = 0
    checksum_errors: int = 0
    bad_capsule_steps: int = 0
    samples: int = 0


# --- host-side decoder -------------------------------------------------------------------------


class _State(IntEnum):
    HUNT = 0  # looking for A5 5A
    PAYLOAD = 1  # a single response's payload
    NODES = 2  # standard scan stream
    CAPSULES = 3  # express scan stream
    FRAMES = 4  # ultra or dense capsule stream


class RplidarClient:
    """The host end of an RPLIDAR link, without I/O.

    ``send(request)`` returns the bytes to write and tells the decoder which answer to expect:
    once a request that has an answer was sent, everything before a descriptor of that answer's
    type is garbage (stale scan nodes, the text banner after RESET). STOP and RESET end a scan
    stream. ``receive_data`` accepts arbitrary chunks; ``next_event`` returns the next event or
    None when more bytes are needed.
    """

    def __init__(self, capsule_step_deg: tuple[float, float] = CAPSULE_STEP_DEG) -> None:
        self.stats = CodecStats()
        #: Express capsule start-angle steps (degrees) accepted; set from a GET_SAMPLERATE answer.
        self.capsule_step_deg = capsule_step_deg
        self._step_ref_q6: int | None = None
        self._step_misses = 0
        self._buf = bytearray()
        self._state = _State.HUNT
        self._expect: int | None = None
        self._size = 0
        self._type = 0
        self._node_locked = True
        self._prev_capsule: np.ndarray | None = None
        self._events: deque[Event] = deque()
        self._prev_frame: np.ndarray | None = None  # the last ultra/dense capsule, not decoded yet

    @property
    def streaming(self) -> bool:
        """Whether a scan stream (standard or express) is being decoded."""
        return self._state in (_State.NODES, _State.CAPSULES, _State.FRAMES)

    @property
    def buffered(self) -> int:
        """Bytes received but not decoded yet (a partial frame)."""
        return len(self._buf)

    def send(self, request: Request, answer: int | None = None) -> bytes:
        """Bytes for ``request``; updates what the decoder expects next.

        ``answer`` overrides the answer type expected: an EXPRESS_SCAN in a scan mode is answered
        with that mode's type (ultra or dense capsules).
        """
        data = request.encode()
        if answer is None:
            answer = ANSWER_TO.get(request.command)
        if answer is not None:
            self._expect = answer
            self._enter_hunt()
        elif request.command in (Command.STOP, Command.RESET):
            self._expect = None
            self._enter_hunt()
        return data

    def _enter_hunt(self) -> None:
        self._state = _State.HUNT
        self._forget_capsules()

    def _forget_capsules(self) -> None:
        self._prev_capsule = None
        self._prev_frame = None
        self._step_ref_q6 = None
        self._step_misses = 0

    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Feed bytes from the device; decode as far as possible."""
        self.stats.bytes_in += len(data)
        self._buf += data
        self._decode()

    def next_event(self) -> Event | None:
        """The next decoded event, or None when more data is needed."""
        return self._events.popleft() if self._events else None

    def events(self) -> list[Event]:
        """Every event decoded so far."""
        out = list(self._events)
        self._events.clear()
        return out

    def _decode(self) -> None:
        while True:
            if self._state == _State.HUNT:
                if not self._hunt():
                    return
            elif self._state == _State.PAYLOAD:
                if len(self._buf) < self._size:
                    return
                payload = bytes(self._buf[: self._size])
                del self._buf[: self._size]
                self._state = _State.HUNT
                self._expect = None
                event = _single_event(self._type, payload)
                if isinstance(event, SampleRate) and event.express_us > 0:
                    turn = SAMPLES_PER_CAPSULE * event.express_us * 1e-6 * 360.0
                    self.capsule_step_deg = (turn * CAPSULE_SCAN_HZ[0], turn * CAPSULE_SCAN_HZ[1])
                self._events.append(event)
            elif self._state == _State.NODES:
                self._decode_nodes()
                return
            elif self._state == _State.FRAMES:
                self._decode_frames()
                return
            else:
                self._decode_capsules()
                return

    def _hunt(self) -> bool:
        buf = self._buf
        while True:
            at = buf.find(DESCRIPTOR)
            if at < 0:
                keep = 1 if buf.endswith(b"\xa5") else 0
                self._discard(len(buf) - keep)
                return False
            self._discard(at)
            if len(buf) < DESCRIPTOR_LEN:
                return False
            word, kind = struct.unpack_from("<IB", buf, 2)
            size, mode = word & 0x3FFFFFFF, word >> 30
            if self._plausible(kind, size, mode):
                del buf[:DESCRIPTOR_LEN]
                self._type, self._size = kind, size
                if kind == AnswerType.SCAN:
                    self._state, self._node_locked = _State.NODES, True
                    self._events.append(ScanStarted(express=False, answer_type=kind))
                elif kind == AnswerType.EXPRESS:
                    self._state = _State.CAPSULES
                    self._forget_capsules()
                    self._events.append(ScanStarted(express=True, answer_type=kind))
                elif kind in _FRAME_DECODERS:
                    self._state = _State.FRAMES
                    self._forget_capsules()
                    self._events.append(ScanStarted(express=True, answer_type=kind))
                else:
                    self._state = _State.PAYLOAD
                return True
            self.stats.bad_descriptors += 1
            self.stats.resyncs += 1
            self._discard(1)

    def _plausible(self, kind: int, size: int, mode: int) -> bool:
        if self._expect is not None and kind != self._expect:
            return False
        if kind == AnswerType.LIDAR_CONF:
            return mode == MODE_SINGLE and 4 <= size <= _LIDAR_CONF_MAX
        return _ANSWER_SHAPE.get(kind) == (size, mode)

    def _discard(self, n: int) -> None:
        if n > 0:
            self.stats.garbage_bytes += n
            del self._buf[:n]

    # standard nodes

    def _decode_nodes(self) -> None:
        buf = self._buf
        while len(buf) >= NODE_LEN:
            if not self._node_locked:
                if not self._relock_nodes():
                    return
                continue
            n = len(buf) // NODE_LEN
            arr = np.frombuffer(buf, dtype=np.uint8, count=n * NODE_LEN).reshape(n, NODE_LEN)
            ok = _nodes_valid(arr)
            bad = n if bool(ok.all()) else int(np.argmin(ok))
            if bad:
                self._emit_nodes(arr[:bad])
            del arr
            del buf[: bad * NODE_LEN]
            if bad < n:
                self.stats.bad_nodes += 1
                self.stats.resyncs += 1
                self._node_locked = False
                self._discard(1)

    def _relock_nodes(self) -> bool:
        """Skip bytes until NODE_RESYNC_RUN plausible nodes follow; False when more data is needed.

        Every start offset in the buffer is tried at once (a byte-by-byte search cost about 80 us a
        noise byte on the event loop: 2 KB of line noise stalled it for over 100 ms)."""
        buf = self._buf
        need = NODE_RESYNC_RUN * NODE_LEN
        starts = len(buf) - need + 1  # offsets with a whole run of nodes after them
        if starts <= 0:
            return False
        raw = np.frombuffer(buf, dtype=np.uint8)
        width = len(raw) - NODE_LEN + 1  # a node could start at any of these
        b0, b1, b2 = raw[:width], raw[1:width + 1], raw[2:width + 2]
        angle_q6 = (b1.astype(np.int32) | (b2.astype(np.int32) << 8)) >> 1
        node_ok = ((((b0 >> 1) ^ b0) & 1) == 1) & ((b1 & 1) == 1) & (angle_q6 < FULL_TURN_Q6)
        angles = angle_q6 / 64.0
        run_ok = node_ok[:starts].copy()
        for k in range(1, NODE_RESYNC_RUN):
            here, before = slice(k * NODE_LEN, k * NODE_LEN + starts), slice((k - 1) * NODE_LEN,
                                                                             (k - 1) * NODE_LEN + starts)
            run_ok &= node_ok[here]
            run_ok &= np.mod(angles[here] - angles[before], 360.0) < NODE_RESYNC_MAX_STEP_DEG
        del raw, b0, b1, b2
        found = np.flatnonzero(run_ok)
        if len(found):
            self._discard(int(found[0]))
            self._node_locked = True
            return True
        self._discard(starts)
        return False

    def _emit_nodes(self, arr: np.ndarray) -> None:
        b0 = arr[:, 0]
        angle_q6 = (arr[:, 1].astype(np.int32) | (arr[:, 2].astype(np.int32) << 8)) >> 1
        dist_q2 = arr[:, 3].astype(np.int32) | (arr[:, 4].astype(np.int32) << 8)
        self.stats.samples += len(arr)
        self._events.append(Measurements(
            start=(b0 & 1).astype(bool), quality=(b0 >> 2).astype(np.uint8),
            angle_deg=angle_q6 / 64.0, distance_mm=dist_q2 / 4.0, express=False))

    # express capsules

    def _decode_capsules(self) -> None:
        buf = self._buf
        batches: list[np.ndarray] = []
        while len(buf) >= CAPSULE_LEN:
            n = len(buf) // CAPSULE_LEN
            arr = np.frombuffer(buf, dtype=np.uint8, count=n * CAPSULE_LEN).reshape(n, CAPSULE_LEN)
            ok = caps.capsules_valid(arr)
            good = n if bool(ok.all()) else int(np.argmin(ok))
            if good:
                batches.append(arr[:good].copy())
            del arr
            del buf[: good * CAPSULE_LEN]
            if good < n:
                self._flush_capsules(batches)
                batches = []
                self._forget_capsules()
                self.stats.checksum_errors += 1
                self.stats.resyncs += 1
                self._resync_capsules()
        self._flush_capsules(batches)

    def _resync_capsules(self) -> None:
        """Drop bytes up to the next position that starts with the two sync nibbles."""
        buf = self._buf
        self._discard(1)
        raw = np.frombuffer(buf, dtype=np.uint8)
        if len(raw) < 2:
            return
        hits = np.flatnonzero(((raw[:-1] & 0xF0) == 0xA0) & ((raw[1:] & 0xF0) == 0x50))
        del raw
        self._discard(int(hits[0]) if len(hits) else len(buf) - 1)

    def _flush_capsules(self, batches: list[np.ndarray]) -> None:
        if not batches:
            return
        caps = np.concatenate(batches) if len(batches) > 1 else batches[0]
        first = (caps[:, 3] & 0x80) != 0
        # A capsule flagged as the first of a stream has no valid predecessor.
        if first.any():
            last_first = int(np.flatnonzero(first)[-1])
            self._prev_capsule = None
            caps = caps[last_first:]
        if self._prev_capsule is not None:
            caps = np.concatenate([self._prev_capsule[None, :], caps])
        self._prev_capsule = caps[-1].copy()
        if len(caps) < 2:
            return
        m = decode_capsules(caps)
        dropped = self._capsule_pairs_dropped(caps)
        if dropped is not None:
            self.stats.bad_capsule_steps += len(dropped)
            if len(dropped) == len(caps) - 1:
                return
            keep = np.ones(len(caps) - 1, dtype=bool)
            keep[dropped] = False
            mask = np.repeat(keep, SAMPLES_PER_CAPSULE)
            m = Measurements(start=m.start[mask], quality=m.quality[mask], angle_deg=m.angle_deg[mask],
                             distance_mm=m.distance_mm[mask], express=True, held_back=m.held_back)
        self.stats.samples += len(m)
        self._events.append(m)

    def _capsule_pairs_dropped(self, caps: np.ndarray,
                               step_deg: tuple[float, float] | None = None) -> list[int] | None:
        """The consecutive pairs of ``caps`` whose start-angle step is implausible (None: none).

        Capsule n's samples are spread from its start angle to capsule n+1's, so a duplicated or
        reordered capsule puts them at wrong angles. A pair is kept when its step lies in
        ``step_deg`` (default :attr:`capsule_step_deg`) and within :data:`CAPSULE_STEP_TOLERANCE` of
        the last kept step. Every capsule format has its start angle in bytes 2-3.
        (Plain Python: for the 25-30 capsules of a revolution it is faster than numpy's calls.)
        """
        starts = ((caps[:, 2].astype(np.int32) | (caps[:, 3].astype(np.int32) << 8)) & 0x7FFF).tolist()
        lo, hi = (round(d * 64) for d in (step_deg or self.capsule_step_deg))
        ref, misses = self._step_ref_q6, self._step_misses
        dropped: list[int] | None = None
        prev = starts[0]
        for i, start in enumerate(starts[1:]):
            step = (start - prev) % FULL_TURN_Q6
            prev = start
            in_range = lo <= step <= hi
            if in_range and (ref is None or abs(step - ref) <= CAPSULE_STEP_TOLERANCE * ref):
                ref, misses = step, 0
                continue
            if dropped is None:
                dropped = []
            dropped.append(i)
            if in_range:
                misses += 1
                if misses >= CAPSULE_RELOCK:
                    ref, misses = None, 0
        self._step_ref_q6, self._step_misses = ref, misses
        return dropped


    # ultra and dense capsules

    def _decode_frames(self) -> None:
        """Cut whole capsules of the current type; a bad one is dropped and the stream re-locks
        on the next sync nibbles. A capsule is decoded when its successor arrives."""
        size = _ANSWER_SHAPE[self._type][0]
        buf = self._buf
        run: list[np.ndarray] = []
        while len(buf) >= size:
            n = len(buf) // size
            arr = np.frombuffer(buf, dtype=np.uint8, count=n * size).reshape(n, size)
            ok = caps.capsules_valid(arr)
            good = n if bool(ok.all()) else int(np.argmin(ok))
            if good:
                run.append(arr[:good].copy())
            del arr
            del buf[: good * size]
            if good < n:
                self._emit_frames(run)
                run, self._prev_frame = [], None
                self.stats.checksum_errors += 1
                self.stats.resyncs += 1
                self._resync_capsules()
        self._emit_frames(run)

    def _emit_frames(self, run: list[np.ndarray]) -> None:
        if not run:
            return
        frames = np.concatenate(run)
        first = np.flatnonzero(frames[:, 3] & 0x80)
        if len(first):  # a capsule flagged as the first of a stream has no valid predecessor
            self._prev_frame, frames = None, frames[int(first[-1]):]
        if self._prev_frame is not None:
            frames = np.concatenate([self._prev_frame[None, :], frames])
        self._prev_frame = frames[-1].copy()
        if len(frames) < 2:
            return
        angle, dist, start = _FRAME_DECODERS[self._type](frames)
        # the express range: an ultra or dense capsule holds more samples, but at the scan rates
        # the listed models run its step stays well inside it
        dropped = self._capsule_pairs_dropped(frames, CAPSULE_STEP_DEG)
        if dropped is not None:
            self.stats.bad_capsule_steps += len(dropped)
            if len(dropped) == len(frames) - 1:
                return
            keep = np.ones(len(frames) - 1, dtype=bool)
            keep[dropped] = False
            mask = np.repeat(keep, len(angle) // (len(frames) - 1))
            angle, dist, start = angle[mask], dist[mask], start[mask]
        self.stats.samples += len(angle)
        self._events.append(Measurements(
            start=start, quality=(dist > 0).astype(np.uint8) * np.uint8(0x2F), angle_deg=angle,
            distance_mm=dist, express=True, held_back=DECODED_ANSWERS[self._type]))


_FRAME_DECODERS = {AnswerType.ULTRA_CAPSULED: caps.decode_ultra,
                   AnswerType.DENSE_CAPSULED: caps.decode_dense}


def _nodes_valid(arr: np.ndarray) -> np.ndarray:
    b0 = arr[:, 0]
    angle_q6 = (arr[:, 1].astype(np.int32) | (arr[:, 2].astype(np.int32) << 8)) >> 1
    return ((((b0 >> 1) ^ b0) & 1) == 1) & ((arr[:, 1] & 1) == 1) & (angle_q6 < FULL_TURN_Q6)


def decode_capsules(caps: np.ndarray) -> Measurements:
    """Samples of every capsule but the last in ``caps`` (K consecutive valid capsules, K x 84).

    As in the SDK, capsule n's 32 samples are spread evenly from its start angle to capsule n+1's,
    minus each sample's compensation angle dθ (6 bits, 1/8 degree); a sample is the start of a
    revolution when the angle wraps past 360 degrees before the next sample.
    """
    rec = np.ascontiguousarray(caps, dtype=np.uint8).view(CAPSULE_DTYPE).reshape(-1)
    k = len(rec) - 1
    start_q8 = (rec["start"].astype(np.int32) & 0x7FFF) << 2
    cur = start_q8[:-1]
    diff_q8 = start_q8[1:] - cur
    diff_q8 += (diff_q8 < 0) * (360 << 8)
    inc_q16 = (diff_q8 << 3)[:, None]  # per sample: diff / 32, in q16
    cabins = rec["cabins"][:-1]
    word = np.empty((k, 16, 2), dtype=np.int32)  # dist_q2 | dθ bits 5:4, two samples per cabin
    word[:, :, 0] = cabins["d1"]
    word[:, :, 1] = cabins["d2"]
    nibbles = cabins["dtheta"]
    offset_q3 = np.empty((k, 16, 2), dtype=np.int32)
    offset_q3[:, :, 0] = nibbles & 0xF
    offset_q3[:, :, 1] = nibbles >> 4
    offset_q3 |= (word & 3) << 4
    raw_q16 = (cur << 8)[:, None] + inc_q16 * _CAPSULE_K[None, :]
    angle_q6 = ((raw_q16 - (offset_q3.reshape(k, SAMPLES_PER_CAPSULE) << 13)) >> 10) % FULL_TURN_Q6
    start = ((raw_q16 + inc_q16) % (360 << 16)) < inc_q16
    dist = (word >> 2).ravel().astype(np.float64)
    return Measurements(
        start=start.ravel(), quality=(dist > 0).astype(np.uint8) * np.uint8(0x2F),
        angle_deg=angle_q6.ravel() * (1 / 64), distance_mm=dist, express=True,
        held_back=SAMPLES_PER_CAPSULE)


_CAPSULE_K = np.arange(SAMPLES_PER_CAPSULE, dtype=np.int32)


def _single_event(kind: int, payload: bytes) -> Event:
    if kind == AnswerType.INFO:
        model, minor, major, hw = payload[:4]
        return DeviceInfo(model, major, minor, hw, payload[4:20])
    if kind == AnswerType.HEALTH:
        status, code = struct.unpack("<BH", payload)
        return Health(status, code)
    if kind == AnswerType.SAMPLERATE:
        std, exp = struct.unpack("<HH", payload)
        return SampleRate(std, exp)
    if kind == AnswerType.ACC_BOARD_FLAG:
        return AccBoardFlag(struct.unpack("<I", payload)[0])
    (key,) = struct.unpack_from("<I", payload)
    return LidarConf(key, payload[4:])


# --- device side: request parser and response encoders ----------------------------------------


@dataclass
class RequestParser:
    """The device end: host bytes in, :class:`Request` events out. Garbage is skipped and counted."""

    bad_checksums: int = 0
    garbage_bytes: int = 0
    _buf: bytearray = field(default_factory=bytearray)

    def receive_data(self, data: bytes | bytearray | memoryview) -> list[Request]:
        """Feed host bytes; returns every complete request."""
        self._buf += data
        out: list[Request] = []
        buf = self._buf
        while buf:
            at = buf.find(SYNC)
            if at < 0:
                self.garbage_bytes += len(buf)
                buf.clear()
                break
            if at:
                self.garbage_bytes += at
                del buf[:at]
            if len(buf) < 2:
                break
            cmd = buf[1]
            if not cmd & 0x80:
                out.append(Request(cmd))
                del buf[:2]
                continue
            if len(buf) < 3 or len(buf) < 4 + buf[2]:
                break
            n = buf[2]
            frame = bytes(buf[: 4 + n])
            if xor_checksum(frame[:-1]) != frame[-1]:
                self.bad_checksums += 1
                self.garbage_bytes += 1
                del buf[:1]
                continue
            out.append(Request(cmd, frame[3:-1]))
            del buf[: 4 + n]
        return out


def encode_descriptor(size: int, mode: int, kind: int) -> bytes:
    """A response descriptor: ``A5 5A`` + size (30 bits) | mode << 30 + type."""
    if not 0 <= size < (1 << 30) or mode not in (0, 1, 2, 3) or not 0 <= kind <= 0xFF:
        raise LocalProtocolError(f"descriptor size={size} mode={mode} type={kind} cannot be encoded")
    return DESCRIPTOR + struct.pack("<IB", size | (mode << 30), kind)


def _answer(kind: AnswerType, payload: bytes) -> bytes:
    size, mode = _ANSWER_SHAPE[kind]
    return encode_descriptor(size, mode, kind) + payload


def encode_info(info: DeviceInfo) -> bytes:
    """Descriptor and GET_INFO payload."""
    if len(info.serial) != 16:
        raise LocalProtocolError("the serial number is 16 bytes")
    return _answer(AnswerType.INFO, bytes((info.model_id, info.firmware_minor, info.firmware_major,
                                           info.hardware)) + info.serial)


def encode_health(health: Health) -> bytes:
    """Descriptor and GET_HEALTH payload (error code little-endian, as the SDK reads it)."""
    return _answer(AnswerType.HEALTH, struct.pack("<BH", health.status, health.error_code))


def encode_samplerate(rate: SampleRate) -> bytes:
    """Descriptor and GET_SAMPLERATE payload."""
    return _answer(AnswerType.SAMPLERATE, struct.pack("<HH", rate.standard_us, rate.express_us))


def encode_acc_board_flag(flag: AccBoardFlag) -> bytes:
    """Descriptor and GET_ACC_BOARD_FLAG payload."""
    return _answer(AnswerType.ACC_BOARD_FLAG, struct.pack("<I", flag.flags))


def encode_scan_descriptor(express: bool, answer_type: int | None = None) -> bytes:
    """The loop-mode descriptor that opens a scan stream: standard nodes, express capsules, or the
    measurement ``answer_type`` given (ultra or dense capsules)."""
    if answer_type is None:
        answer_type = AnswerType.EXPRESS if express else AnswerType.SCAN
    return _answer(AnswerType(answer_type), b"")


def encode_lidar_conf(key: int, value: bytes) -> bytes:
    """Descriptor and GET_LIDAR_CONF answer: the key asked for, then its value."""
    if len(value) + 4 > _LIDAR_CONF_MAX:
        raise LocalProtocolError(f"configuration value of {len(value)} bytes is too long")
    return encode_descriptor(4 + len(value), MODE_SINGLE, AnswerType.LIDAR_CONF) + \
        struct.pack("<I", key) + value


def parse_conf_request(req: Request) -> tuple[int, int | None] | None:
    """(key, scan mode id or None) of a GET_LIDAR_CONF request; None if the payload is malformed."""
    if len(req.payload) < 4:
        return None
    (key,) = struct.unpack_from("<I", req.payload)
    mode = struct.unpack_from("<H", req.payload, 4)[0] if len(req.payload) >= 6 else None
    return key, mode


def encode_nodes(start: np.ndarray, quality: np.ndarray, angle_deg: np.ndarray,
                 distance_mm: np.ndarray) -> bytes:
    """Standard 5-byte nodes (device angles in degrees clockwise, distances mm, quality 0..63)."""
    s = np.asarray(start, dtype=np.uint8) & 1
    q = np.clip(np.asarray(quality, dtype=np.int64), 0, 63).astype(np.uint8)
    angle_q6 = np.round(np.mod(np.asarray(angle_deg, dtype=np.float64), 360.0) * 64).astype(np.int64)
    angle_q6 %= FULL_TURN_Q6
    dist_q2 = np.clip(np.round(np.asarray(distance_mm, dtype=np.float64) * 4), 0, 0xFFFF).astype(np.int64)
    out = np.empty((len(s), NODE_LEN), dtype=np.uint8)
    out[:, 0] = (q << 2) | ((s ^ 1) << 1) | s
    a = (angle_q6 << 1) | 1
    out[:, 1], out[:, 2] = a & 0xFF, a >> 8
    out[:, 3], out[:, 4] = dist_q2 & 0xFF, dist_q2 >> 8
    return out.tobytes()


def encode_capsules(start_angle_deg: np.ndarray, distance_mm: np.ndarray,
                    first: bool = False) -> bytes:
    """Express capsules: one start angle (degrees clockwise) and 32 distances (mm) per capsule.

    Compensation angles dθ are 0, so every decoder agrees on the sample angles. ``first`` sets the
    new-scan bit on the first capsule (the first capsule after the EXPRESS_SCAN request).
    """
    starts = np.round(np.mod(np.asarray(start_angle_deg, dtype=np.float64), 360.0) * 64).astype(np.int64)
    starts %= FULL_TURN_Q6
    dist = np.clip(np.round(np.asarray(distance_mm, dtype=np.float64)), 0, 0x3FFF).astype(np.int64)
    dist = dist.reshape(len(starts), SAMPLES_PER_CAPSULE)
    k = len(starts)
    out = np.zeros((k, CAPSULE_LEN), dtype=np.uint8)
    sa = starts.copy()
    if first and k:
        sa[0] |= 0x8000
    out[:, 2], out[:, 3] = sa & 0xFF, sa >> 8
    cab = np.zeros((k, 16, 5), dtype=np.uint8)
    d = (dist << 2).reshape(k, 16, 2)
    cab[:, :, 0], cab[:, :, 1] = d[:, :, 0] & 0xFF, d[:, :, 0] >> 8
    cab[:, :, 2], cab[:, :, 3] = d[:, :, 1] & 0xFF, d[:, :, 1] >> 8
    out[:, 4:] = cab.reshape(k, 80)
    cs = np.bitwise_xor.reduce(out[:, 2:], axis=1)
    out[:, 0] = 0xA0 | (cs & 0x0F)
    out[:, 1] = 0x50 | (cs >> 4)
    return out.tobytes()
