"""The VESC serial protocol as a sans-I/O codec: bytes in, typed packets out, and back.

Framing (vedderb/bldc ``comm/packet.c``)::

    02 LEN            PAYLOAD CRC_HI CRC_LO 03     payload 1..255 bytes
    03 LEN_HI LEN_LO  PAYLOAD CRC_HI CRC_LO 03     payload 255..max bytes (sent only above 255)
    04 LEN (3 bytes)  PAYLOAD CRC_HI CRC_LO 03     decoded, never sent (compiled out in firmware)

The CRC is CRC-16/XMODEM over the payload (``binascii.crc_hqx(payload, 0)``), big-endian. Payload
byte 0 is the command id. All multi-byte fields are big-endian and signed unless noted.

:class:`VescCodec` is used from either side of the wire. The host (our driver) sends requests and
commands and decodes replies; the device (the fake VESC) decodes requests and commands and sends
replies. The decoder never raises on input: a bad start byte, length, CRC or end byte drops ONE
byte and retries (as the firmware does), counted in :class:`CodecStats`; so does a reply whose
payload is all zeros (its CRC is 0x0000, so zeros on the line pass it); an unknown or malformed
packet comes out as :class:`RawPacket`. Encoding refuses NaN, infinities and values the wire
cannot carry with :class:`~racecar_hw.base.errors.LocalProtocolError`.

GET_VALUES replies change layout with the firmware (see :func:`values_layout`); the codec picks
the layout from :attr:`VescCodec.firmware`. The codec never changes it on its own: a FW_VERSION
frame can be line noise (an all-zero payload has CRC 0x0000 and reads as version 0.0), so only the
driver's handshake decides which reply to believe (:func:`known_firmware`) and sets it.
"""

from __future__ import annotations

import binascii
import enum
import functools
import math
import operator
import struct
from dataclasses import dataclass, field
from typing import ClassVar

from racecar_hw.base.errors import LocalProtocolError

START_SHORT = 0x02
START_LONG = 0x03
START_HUGE = 0x04
END = 0x03
#: The firmware's PACKET_MAX_PL_LEN (comm/packet.h).
MAX_PAYLOAD = 512

_I16 = struct.Struct(">h")
_I32 = struct.Struct(">i")
_U16 = struct.Struct(">H")
_I16_MIN, _I16_MAX = -(2**15), 2**15 - 1
_I32_MIN, _I32_MAX = -(2**31), 2**31 - 1


class CommandId(enum.IntEnum):
    """VESC command ids (``COMM_PACKET_ID`` in datatypes.h) that racecar-hw speaks."""

    FW_VERSION = 0
    GET_VALUES = 4
    SET_DUTY = 5
    SET_CURRENT = 6
    SET_CURRENT_BRAKE = 7
    SET_RPM = 8
    SET_POS = 9
    SET_HANDBRAKE = 10
    SET_SERVO_POS = 12
    PRINT = 21
    ALIVE = 30
    GET_IMU_DATA = 65


class Role(enum.Enum):
    """Which end of the wire a codec sits on."""

    HOST = "host"  #: sends requests and commands, decodes replies (the driver)
    DEVICE = "device"  #: decodes requests and commands, sends replies (the fake VESC)


# --- packets ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class FwVersionRequest:
    """COMM_FW_VERSION request (host -> device)."""

    ID: ClassVar[int] = CommandId.FW_VERSION


@dataclass(frozen=True)
class FwVersion:
    """COMM_FW_VERSION reply (device -> host).

    ``hw_name`` and ``uuid`` (12-byte STM32 id) are None when the firmware did not send them;
    ``extra`` holds whatever follows the UUID (pairing byte, test version, HW type, ..., which
    depend on the version and are kept raw).
    """

    ID: ClassVar[int] = CommandId.FW_VERSION

    major: int
    minor: int
    hw_name: str | None = None
    uuid: bytes | None = None
    extra: bytes = b""

    @property
    def version(self) -> tuple[int, int]:
        """(major, minor)."""
        return (self.major, self.minor)


@dataclass(frozen=True)
class GetValuesRequest:
    """COMM_GET_VALUES request (host -> device). Does not reset the firmware command timeout."""

    ID: ClassVar[int] = CommandId.GET_VALUES


@dataclass(frozen=True)
class Values:
    """COMM_GET_VALUES reply (device -> host), in SI units.

    Temperatures °C, currents A, ``duty`` -1..1, ``erpm`` electrical RPM, voltages V, charge Ah,
    energy Wh, tachometer in counts (6 per electrical revolution), ``pid_pos`` degrees.
    ``status`` bit 0: firmware command timeout active, bit 1: kill switch active (>= 5.03).
    Fields the firmware's layout does not carry stay 0. In the pre-3.07 layout ``temp_fet`` is
    the hottest of the six MOSFET sensors and ``temp_mos1..3`` the first three.
    """

    ID: ClassVar[int] = CommandId.GET_VALUES

    temp_fet: float = 0.0
    temp_motor: float = 0.0
    current_motor: float = 0.0
    current_input: float = 0.0
    avg_id: float = 0.0
    avg_iq: float = 0.0
    duty: float = 0.0
    erpm: int = 0
    v_in: float = 0.0
    amp_hours: float = 0.0
    amp_hours_charged: float = 0.0
    watt_hours: float = 0.0
    watt_hours_charged: float = 0.0
    tachometer: int = 0
    tachometer_abs: int = 0
    fault: int = 0
    pid_pos: float = 0.0
    controller_id: int = 0
    temp_mos1: float = 0.0
    temp_mos2: float = 0.0
    temp_mos3: float = 0.0
    avg_vd: float = 0.0
    avg_vq: float = 0.0
    status: int = 0
    temp_pcb: float = 0.0


@dataclass(frozen=True)
class SetDuty:
    """COMM_SET_DUTY: duty cycle -1..1, wire i32 duty x 1e5."""

    ID: ClassVar[int] = CommandId.SET_DUTY
    duty: float


@dataclass(frozen=True)
class SetCurrent:
    """COMM_SET_CURRENT: motor current in A (negative brakes/reverses), wire i32 A x 1e3."""

    ID: ClassVar[int] = CommandId.SET_CURRENT
    current: float


@dataclass(frozen=True)
class SetCurrentBrake:
    """COMM_SET_CURRENT_BRAKE: braking current in A, wire i32 A x 1e3."""

    ID: ClassVar[int] = CommandId.SET_CURRENT_BRAKE
    current: float


@dataclass(frozen=True)
class SetRpm:
    """COMM_SET_RPM: electrical RPM, wire i32 (rounded)."""

    ID: ClassVar[int] = CommandId.SET_RPM
    erpm: float


@dataclass(frozen=True)
class SetPosition:
    """COMM_SET_POS: rotor position in degrees, wire i32 deg x 1e6."""

    ID: ClassVar[int] = CommandId.SET_POS
    degrees: float


@dataclass(frozen=True)
class SetServoPosition:
    """COMM_SET_SERVO_POS: servo position 0..1 (1000..2000 µs), wire i16 x 1000.

    Does not reset the firmware command timeout.
    """

    ID: ClassVar[int] = CommandId.SET_SERVO_POS
    position: float


@dataclass(frozen=True)
class Alive:
    """COMM_ALIVE: resets the firmware command timeout, nothing else."""

    ID: ClassVar[int] = CommandId.ALIVE


#: COMM_GET_IMU_DATA's fields in mask-bit order (comm/commands.c): angles (rad), acceleration (g),
#: angular rate (deg/s), magnetic field (µT; 0 on BMI160/LSM6DS3 boards), orientation quaternion.
IMU_FIELDS: tuple[str, ...] = ("roll", "pitch", "yaw", "acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y",
                               "gyro_z", "mag_x", "mag_y", "mag_z", "q0", "q1", "q2", "q3")
#: Fields whose non-finite value (NaN, inf) is read as absent, as if the mask had left it out,
#: instead of refusing the reply: nothing in racecar-hw publishes them (the firmware's roll, pitch
#: and yaw, the magnetometer), so a NaN there must not throw away good gyro and accelerometer
#: readings. A non-finite acceleration, rate or quaternion component refuses the whole reply.
IMU_LENIENT_FIELDS = frozenset({"roll", "pitch", "yaw", "mag_x", "mag_y", "mag_z"})
#: Every field: what the F1TENTH driver asks for.
IMU_MASK_ALL = 0xFFFF
#: The firmware that added COMM_GET_IMU_DATA (CHANGELOG: 3.52).
IMU_SINCE = (3, 52)
#: The firmware that appends the controller id byte to the IMU reply (bldc commit e0bc1154).
IMU_ID_SINCE = (6, 5)


@dataclass(frozen=True)
class GetImuDataRequest:
    """COMM_GET_IMU_DATA request (host -> device): ``mask`` bit i asks for :data:`IMU_FIELDS` [i]."""

    ID: ClassVar[int] = CommandId.GET_IMU_DATA

    mask: int = IMU_MASK_ALL


@dataclass(frozen=True)
class ImuData:
    """COMM_GET_IMU_DATA reply (device -> host), in the firmware's units and axes.

    ``roll``, ``pitch``, ``yaw`` rad (the firmware negates roll and yaw relative to the quaternion:
    use ``q0..q3`` or ``gyro_z`` for heading); ``acc_*`` g; ``gyro_*`` deg/s; ``mag_*`` µT;
    ``q0`` (w), ``q1..q3`` (x, y, z). A field the reply's mask left out is None, and so is one of
    :data:`IMU_LENIENT_FIELDS` that came as NaN or inf: every value present is finite. ``controller_id``
    is the CAN id byte firmware 6.05 and later appends (None before).
    """

    ID: ClassVar[int] = CommandId.GET_IMU_DATA

    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    acc_x: float | None = None
    acc_y: float | None = None
    acc_z: float | None = None
    gyro_x: float | None = None
    gyro_y: float | None = None
    gyro_z: float | None = None
    mag_x: float | None = None
    mag_y: float | None = None
    mag_z: float | None = None
    q0: float | None = None
    q1: float | None = None
    q2: float | None = None
    q3: float | None = None
    controller_id: int | None = None

    @property
    def mask(self) -> int:
        """The mask of the fields present."""
        return sum(1 << i for i, name in enumerate(IMU_FIELDS) if getattr(self, name) is not None)


@dataclass(frozen=True)
class RawPacket:
    """A packet the codec does not decode in its role: an unknown id, or a malformed payload.

    ``reason`` is "unknown" for ids this codec does not know in its role, otherwise why the payload
    was refused. Encoding a RawPacket sends ``payload`` as is (id included).
    """

    payload: bytes
    reason: str = "unknown"

    @property
    def command_id(self) -> int:
        """Payload byte 0, or -1 for an empty payload."""
        return self.payload[0] if self.payload else -1


#: Commands that drive the motor; each resets the firmware's command timeout.
MotorCommand = SetDuty | SetCurrent | SetCurrentBrake | SetRpm | SetPosition
Request = (FwVersionRequest | GetValuesRequest | GetImuDataRequest | SetDuty | SetCurrent | SetCurrentBrake
           | SetRpm | SetPosition | SetServoPosition | Alive)
Reply = FwVersion | Values | ImuData
Packet = Request | Reply | RawPacket

#: Packets whose arrival resets the firmware's command timeout (comm/commands.c, timeout_reset()).
TIMEOUT_RESETTING: tuple[type, ...] = (SetDuty, SetCurrent, SetCurrentBrake, SetRpm, SetPosition, Alive)

_REQUEST_TYPES: tuple[type, ...] = (FwVersionRequest, GetValuesRequest, GetImuDataRequest, SetDuty,
                                    SetCurrent, SetCurrentBrake, SetRpm, SetPosition, SetServoPosition,
                                    Alive)
_REPLY_TYPES: tuple[type, ...] = (FwVersion, Values, ImuData)


# --- scalar helpers ----------------------------------------------------------------------------


#: COMM_SET_SERVO_POS carries the position in thousandths.
SERVO_SCALE = 1000.0


def servo_on_wire(position: float) -> float:
    """The servo position a VESC receives when ``position`` (0..1) is sent: thousandths, rounded."""
    return round(position * SERVO_SCALE) / SERVO_SCALE


def _scaled(value: float, scale: float, lo: int, hi: int, what: str) -> int:
    """``round(value * scale)`` as an integer within [lo, hi], refusing NaN and infinities."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LocalProtocolError(f"{what}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise LocalProtocolError(f"{what}: {value} cannot be sent")
    wire = round(value * scale)
    if not lo <= wire <= hi:
        raise LocalProtocolError(f"{what}: {value} is out of range ({lo / scale:g} to {hi / scale:g})")
    return wire


def _i32(value: float, scale: float, what: str) -> bytes:
    return _I32.pack(_scaled(value, scale, _I32_MIN, _I32_MAX, what))


def _i16(value: float, scale: float, what: str) -> bytes:
    return _I16.pack(_scaled(value, scale, _I16_MIN, _I16_MAX, what))


def _u8(value: int, what: str) -> bytes:
    return bytes([_scaled(value, 1, 0, 255, what)])


# --- GET_VALUES layouts ------------------------------------------------------------------------


class Layout(enum.Enum):
    """The GET_VALUES reply layouts; the value is the payload length (id byte included)."""

    PRE_3_07 = 56  #: firmware <= 3.00: seven temperatures first, rpm at offset 25
    V3_07 = 54  #: 3.07 - 3.33: up to fault
    V3_34 = 58  #: 3.34 - 3.39: + pid_pos_now
    V3_40 = 59  #: 3.40 - 3.47: + controller_id
    V3_48 = 65  #: 3.48 - 3.59: + three MOSFET temperatures
    V3_60 = 73  #: 3.60 - 5.02: + avg_vd, avg_vq
    V5_03 = 74  #: 5.03 and later: + status byte


#: Firmware major versions with a known GET_VALUES layout: 2.x (the pre-3.07 layout) up to 7.x (the
#: master branch when this was written; reference vesc.md section 4).
KNOWN_MAJORS = range(2, 8)


def firmware_text(version: tuple[int, int]) -> str:
    """``version`` as the VESC (and VESC Tool, and vesc-info) writes it: the minor in two digits,
    6.02 for (6, 2) and 3.40 for (3, 40)."""
    major, minor = version
    return f"{major}.{minor:02d}"


def known_firmware(version: tuple[int, int]) -> bool:
    """Whether ``version`` is one whose telemetry layout this codec knows (2.0 to 7.99)."""
    major, minor = version
    return major in KNOWN_MAJORS and 0 <= minor <= 99


def values_layout(firmware: tuple[int, int] | None) -> Layout:
    """The GET_VALUES layout a firmware version sends; None (not known yet) means the newest."""
    if firmware is None:
        return Layout.V5_03
    if firmware < (3, 7):
        return Layout.PRE_3_07
    for since, layout in (((5, 3), Layout.V5_03), ((3, 60), Layout.V3_60), ((3, 48), Layout.V3_48),
                          ((3, 40), Layout.V3_40), ((3, 34), Layout.V3_34)):
        if firmware >= since:
            return layout
    return Layout.V3_07


# Fields of the >= 3.07 layout in wire order: (attribute, struct, scale). Scale 0 marks an integer.
_NEW_FIELDS: tuple[tuple[str, struct.Struct, float], ...] = (
    ("temp_fet", _I16, 10.0),
    ("temp_motor", _I16, 10.0),
    ("current_motor", _I32, 100.0),
    ("current_input", _I32, 100.0),
    ("avg_id", _I32, 100.0),
    ("avg_iq", _I32, 100.0),
    ("duty", _I16, 1000.0),
    ("erpm", _I32, 0),
    ("v_in", _I16, 10.0),
    ("amp_hours", _I32, 1e4),
    ("amp_hours_charged", _I32, 1e4),
    ("watt_hours", _I32, 1e4),
    ("watt_hours_charged", _I32, 1e4),
    ("tachometer", _I32, 0),
    ("tachometer_abs", _I32, 0),
    ("fault", struct.Struct(">B"), 0),
    ("pid_pos", _I32, 1e6),
    ("controller_id", struct.Struct(">B"), 0),
    ("temp_mos1", _I16, 10.0),
    ("temp_mos2", _I16, 10.0),
    ("temp_mos3", _I16, 10.0),
    ("avg_vd", _I32, 1000.0),
    ("avg_vq", _I32, 1000.0),
    ("status", struct.Struct(">B"), 0),
)

_OLD_FIELDS: tuple[tuple[str, struct.Struct, float], ...] = (
    ("current_motor", _I32, 100.0),
    ("current_input", _I32, 100.0),
    ("duty", _I16, 1000.0),
    ("erpm", _I32, 0),
    ("v_in", _I16, 10.0),
    ("amp_hours", _I32, 1e4),
    ("amp_hours_charged", _I32, 1e4),
    ("watt_hours", _I32, 1e4),
    ("watt_hours_charged", _I32, 1e4),
    ("tachometer", _I32, 0),
    ("tachometer_abs", _I32, 0),
    ("fault", struct.Struct(">B"), 0),
)


def _pack_field(value: float, fmt: struct.Struct, scale: float, name: str) -> bytes:
    lo, hi = {1: (0, 255), 2: (_I16_MIN, _I16_MAX), 4: (_I32_MIN, _I32_MAX)}[fmt.size]
    return fmt.pack(_scaled(value, scale or 1, lo, hi, name))


def _unpack_field(fmt: struct.Struct, scale: float, data: bytes, offset: int) -> float | int:
    raw = fmt.unpack_from(data, offset)[0]
    return raw / scale if scale else raw


class _ValuesPrefix:
    """The leading fields of :data:`_NEW_FIELDS` that fit a payload of ``end`` bytes (id byte
    included), packed and unpacked with one :class:`struct.Struct`: what the field-by-field loops of
    :func:`encode_values` and :func:`decode_values` do, in one call (the VESC is polled at 50 Hz)."""

    def __init__(self, end: int) -> None:
        fields, offset = [], 1
        for name, fmt, scale in _NEW_FIELDS:
            if offset >= end:  # (encode_values: fields start before the layout's end)
                break
            fields.append((name, fmt, scale))
            offset += fmt.size
        #: the fields read from ``end`` bytes: those that end within them
        read, offset = [], 1
        for name, fmt, scale in _NEW_FIELDS:
            if offset + fmt.size > end:
                break
            read.append((name, scale))
            offset += fmt.size
        self._names = tuple(name for name, _, _ in fields)
        self._get = operator.attrgetter(*self._names) if len(self._names) > 1 else None
        self._pack_scales = tuple(scale or 1 for _, _, scale in fields)
        self._pack = struct.Struct(">B" + "".join(fmt.format.lstrip(">") for _, fmt, _ in fields))
        self._read_names = tuple(name for name, _ in read)
        self._read_scales = tuple(scale for _, scale in read)
        self._unpack = struct.Struct(">" + "".join(fmt.format.lstrip(">") for _, fmt, _ in
                                                   _NEW_FIELDS[:len(read)]))

    def pack(self, values: Values) -> bytes | None:
        """The payload, or None when a value needs the field-by-field checks (anything but a
        plain finite int or float in range: the slow path then refuses it, naming the field)."""
        if self._get is None:
            return None
        raw = self._get(values)
        if not _PLAIN_NUMBERS.issuperset(map(type, raw)):
            return None
        try:
            wire = [round(v * s) for v, s in zip(raw, self._pack_scales, strict=True)]
            return self._pack.pack(CommandId.GET_VALUES, *wire)
        except (ValueError, OverflowError, struct.error):
            return None

    def unpack(self, payload: bytes) -> Values:
        raw = self._unpack.unpack_from(payload, 1)
        fields = zip(self._read_names, raw, self._read_scales, strict=True)
        return Values(**{name: value / scale if scale else value for name, value, scale in fields})


#: The exact types :meth:`_ValuesPrefix.pack` packs without the per-field checks (bool is refused
#: by them: it is neither).
_PLAIN_NUMBERS = frozenset((int, float))


@functools.cache
def _values_prefix(end: int) -> _ValuesPrefix:
    return _ValuesPrefix(end)


def encode_values(values: Values, layout: Layout) -> bytes:
    """The GET_VALUES reply payload (id byte included) for ``values`` in ``layout``."""
    out = bytearray([CommandId.GET_VALUES])
    if layout is Layout.PRE_3_07:
        temps = (values.temp_mos1, values.temp_mos2, values.temp_mos3, values.temp_fet,
                 values.temp_fet, values.temp_fet, values.temp_pcb)
        for i, t in enumerate(temps):
            out += _i16(t, 10.0, f"temperature {i}")
        for name, fmt, scale in _OLD_FIELDS:
            out += _pack_field(getattr(values, name), fmt, scale, name)
        return bytes(out)
    fast = _values_prefix(layout.value).pack(values)
    if fast is not None:
        return fast
    for name, fmt, scale in _NEW_FIELDS:
        if len(out) >= layout.value:
            break
        out += _pack_field(getattr(values, name), fmt, scale, name)
    return bytes(out)


def decode_values(payload: bytes, firmware: tuple[int, int] | None) -> Values | RawPacket:
    """A GET_VALUES reply payload (id included) in the layout of ``firmware``.

    Bytes after the fields that firmware defines are ignored; a payload too short for the
    layout's first 54 bytes (56 before 3.07) comes back as a :class:`RawPacket`.
    """
    layout = values_layout(firmware)
    fields: dict[str, float | int] = {}
    if layout is Layout.PRE_3_07:
        if len(payload) < Layout.PRE_3_07.value:
            return RawPacket(payload, f"GET_VALUES reply of {len(payload)} bytes, pre-3.07 needs 56")
        temps = [_I16.unpack_from(payload, 1 + 2 * i)[0] / 10.0 for i in range(7)]
        fields.update(temp_mos1=temps[0], temp_mos2=temps[1], temp_mos3=temps[2],
                      temp_fet=max(temps[:6]), temp_pcb=temps[6])
        offset = 15
        for name, fmt, scale in _OLD_FIELDS:
            fields[name] = _unpack_field(fmt, scale, payload, offset)
            offset += fmt.size
        return Values(**fields)  # type: ignore[arg-type]
    if len(payload) < Layout.V3_07.value:
        return RawPacket(payload, f"GET_VALUES reply of {len(payload)} bytes, needs at least 54")
    return _values_prefix(min(len(payload), layout.value)).unpack(payload)


# --- FW_VERSION --------------------------------------------------------------------------------


def encode_fw_version(reply: FwVersion) -> bytes:
    """The FW_VERSION reply payload (id included)."""
    out = bytearray([CommandId.FW_VERSION])
    out += _u8(reply.major, "major") + _u8(reply.minor, "minor")
    if reply.hw_name is not None:
        name = reply.hw_name.encode()
        if b"\0" in name:
            raise LocalProtocolError("hw_name must not contain NUL")
        out += name + b"\0"
    if reply.uuid is not None:
        if reply.hw_name is None or len(reply.uuid) != 12:
            raise LocalProtocolError("uuid needs a hw_name and must be 12 bytes")
        out += reply.uuid
    return bytes(out + reply.extra)


def decode_fw_version(payload: bytes) -> FwVersion | RawPacket:
    """A FW_VERSION reply payload (id included)."""
    if len(payload) < 3:
        return RawPacket(payload, "FW_VERSION reply shorter than 3 bytes")
    major, minor = payload[1], payload[2]
    rest = payload[3:]
    if not rest:
        return FwVersion(major, minor)
    nul = rest.find(b"\0")
    if nul < 0:
        return FwVersion(major, minor, rest.decode("latin-1"))
    name = rest[:nul].decode("latin-1")
    rest = rest[nul + 1:]
    if len(rest) < 12:
        return FwVersion(major, minor, name, None, bytes(rest))
    return FwVersion(major, minor, name, bytes(rest[:12]), bytes(rest[12:]))


# --- GET_IMU_DATA ------------------------------------------------------------------------------

_F32 = struct.Struct(">f")


#: Every IMU field of a reply, in wire order (None where absent).
_IMU_VALUES = operator.attrgetter(*IMU_FIELDS)


@functools.cache
def _imu_names(mask: int) -> tuple[str, ...]:
    """The IMU fields ``mask`` selects, in wire order."""
    return tuple(name for i, name in enumerate(IMU_FIELDS) if mask >> i & 1)


@functools.cache
def _f32s(count: int) -> struct.Struct:
    """``count`` big-endian float32s (the IMU reply's fields, read or written in one call)."""
    return struct.Struct(">" + "f" * count)


def encode_imu_data(reply: ImuData, firmware: tuple[int, int] | None = None) -> bytes:
    """The IMU reply payload (id included): the mask, each present field as float32, and from
    firmware 6.05 on the controller id (0 when ``reply`` has none)."""
    out = bytearray([CommandId.GET_IMU_DATA]) + _U16.pack(reply.mask)
    present = [value for value in _IMU_VALUES(reply) if value is not None]
    try:  # the fast path: every value a finite float32 (else the loop below, for its error)
        if all(map(math.isfinite, present)):
            out += _f32s(len(present)).pack(*present)
            if firmware is not None and firmware >= IMU_ID_SINCE:
                out.append(reply.controller_id or 0)
            return bytes(out)
    except (TypeError, OverflowError, struct.error):
        pass
    for name in IMU_FIELDS:
        value = getattr(reply, name)
        if value is not None:
            if not math.isfinite(value):
                raise LocalProtocolError(f"IMU {name}: {value} is not finite")
            try:
                out += _F32.pack(value)
            except (OverflowError, struct.error) as err:
                raise LocalProtocolError(f"IMU {name}: {value} does not fit a float32") from err
    if firmware is not None and firmware >= IMU_ID_SINCE:
        out.append(reply.controller_id or 0)
    return bytes(out)


def decode_imu_data(payload: bytes, firmware: tuple[int, int] | None = None) -> ImuData | RawPacket:
    """An IMU reply payload (id included), read by its echoed mask. From firmware 6.05 on
    (:data:`IMU_ID_SINCE`; None, not known yet, means the newest) the byte after the fields is the
    controller id; before 6.05 nothing follows the fields, and anything that does is ignored, as
    is anything after the id."""
    if len(payload) < 3:
        return RawPacket(payload, "GET_IMU_DATA reply without its mask")
    mask = _U16.unpack_from(payload, 1)[0]
    names = _imu_names(mask)
    end = 3 + 4 * len(names)
    if len(payload) < end:
        return RawPacket(payload, f"GET_IMU_DATA reply of {len(payload)} bytes, its mask {mask:#06x} "
                                  f"needs {end}")
    values = _f32s(len(names)).unpack_from(payload, 3)
    fields: dict[str, float | int] = dict(zip(names, values, strict=True))
    if not all(map(math.isfinite, values)):
        for name, value in zip(names, values, strict=True):
            if math.isfinite(value):
                continue
            if name not in IMU_LENIENT_FIELDS:
                return RawPacket(payload, f"GET_IMU_DATA {name} is not finite")
            del fields[name]  # unused: read as absent (IMU_LENIENT_FIELDS)
    if len(payload) > end and (firmware is None or firmware >= IMU_ID_SINCE):
        fields["controller_id"] = payload[end]
    return ImuData(**fields)  # type: ignore[arg-type]


# --- packets <-> payloads ----------------------------------------------------------------------


def encode_payload(packet: Packet, firmware: tuple[int, int] | None = None) -> bytes:
    """The payload (command id first) of ``packet``; replies to GET_VALUES use ``firmware``'s layout."""
    if isinstance(packet, (FwVersionRequest, GetValuesRequest, Alive)):
        return bytes([packet.ID])
    if isinstance(packet, SetDuty):
        _check_range(packet.duty, -1.0, 1.0, "duty")
        return bytes([packet.ID]) + _i32(packet.duty, 1e5, "duty")
    if isinstance(packet, SetCurrent):
        return bytes([packet.ID]) + _i32(packet.current, 1e3, "current")
    if isinstance(packet, SetCurrentBrake):
        return bytes([packet.ID]) + _i32(packet.current, 1e3, "brake current")
    if isinstance(packet, SetRpm):
        return bytes([packet.ID]) + _i32(packet.erpm, 1, "erpm")
    if isinstance(packet, SetPosition):
        return bytes([packet.ID]) + _i32(packet.degrees, 1e6, "position")
    if isinstance(packet, SetServoPosition):
        _check_range(packet.position, 0.0, 1.0, "servo position")
        return bytes([packet.ID]) + _i16(packet.position, SERVO_SCALE, "servo position")
    if isinstance(packet, GetImuDataRequest):
        if not 0 <= packet.mask <= 0xFFFF:
            raise LocalProtocolError(f"IMU mask {packet.mask} is not 16 bits")
        return bytes([packet.ID]) + _U16.pack(packet.mask)
    if isinstance(packet, ImuData):
        return encode_imu_data(packet, firmware)
    if isinstance(packet, FwVersion):
        return encode_fw_version(packet)
    if isinstance(packet, Values):
        return encode_values(packet, values_layout(firmware))
    if isinstance(packet, RawPacket):
        return packet.payload
    raise LocalProtocolError(f"not a VESC packet: {packet!r}")


def _check_range(value: float, lo: float, hi: float, what: str) -> None:
    _scaled(value, 1.0, _I32_MIN, _I32_MAX, what)  # refuses non-numbers, NaN and infinities
    if not lo <= value <= hi:
        raise LocalProtocolError(f"{what}: {value} is outside {lo:g}..{hi:g}")


_SCALED_COMMANDS: dict[int, tuple[type, float]] = {
    CommandId.SET_DUTY: (SetDuty, 1e5), CommandId.SET_CURRENT: (SetCurrent, 1e3),
    CommandId.SET_CURRENT_BRAKE: (SetCurrentBrake, 1e3), CommandId.SET_RPM: (SetRpm, 1),
    CommandId.SET_POS: (SetPosition, 1e6),
}


def _arg_i32(payload: bytes) -> int | None:
    return _I32.unpack_from(payload, 1)[0] if len(payload) >= 5 else None


def decode_request(payload: bytes) -> Request | RawPacket:
    """A host -> device payload as a typed request or command."""
    cid = payload[0]
    if cid == CommandId.FW_VERSION:
        return FwVersionRequest()
    if cid == CommandId.GET_VALUES:
        return GetValuesRequest()
    if cid == CommandId.ALIVE:
        return Alive()
    if cid == CommandId.GET_IMU_DATA:
        if len(payload) < 3:
            return RawPacket(payload, "GET_IMU_DATA without its mask")
        return GetImuDataRequest(_U16.unpack_from(payload, 1)[0])
    if cid == CommandId.SET_SERVO_POS:
        if len(payload) < 3:
            return RawPacket(payload, "SET_SERVO_POS without its i16 argument")
        return SetServoPosition(_I16.unpack_from(payload, 1)[0] / 1000.0)
    scaled = _SCALED_COMMANDS.get(cid)
    if scaled is None:
        return RawPacket(payload)
    raw = _arg_i32(payload)
    if raw is None:
        return RawPacket(payload, f"{CommandId(cid).name} without its i32 argument")
    cls, scale = scaled
    return cls(raw if scale == 1 else raw / scale)


def decode_reply(payload: bytes, firmware: tuple[int, int] | None) -> Reply | RawPacket:
    """A device -> host payload as a typed reply."""
    cid = payload[0]
    if cid == CommandId.FW_VERSION:
        return decode_fw_version(payload)
    if cid == CommandId.GET_VALUES:
        return decode_values(payload, firmware)
    if cid == CommandId.GET_IMU_DATA:
        return decode_imu_data(payload, firmware)
    return RawPacket(payload)


# --- framing -----------------------------------------------------------------------------------


def frame(payload: bytes) -> bytes:
    """``payload`` wrapped in start byte, length, CRC-16/XMODEM and end byte."""
    n = len(payload)
    if n == 0:
        raise LocalProtocolError("a VESC payload cannot be empty")
    if n <= 255:
        head = bytes((START_SHORT, n))
    elif n <= 0xFFFF:
        head = bytes((START_LONG,)) + _U16.pack(n)
    else:
        raise LocalProtocolError(f"payload of {n} bytes is too long")
    return head + payload + _U16.pack(binascii.crc_hqx(payload, 0)) + bytes((END,))


@dataclass
class CodecStats:
    """Decoder counters.

    ``frames``: good frames; ``crc_errors``: frames whose CRC did not match; ``resyncs``: times
    the decoder lost sync (a run of dropped bytes counts once); ``dropped_bytes``: bytes skipped;
    ``raw_packets``: frames decoded as :class:`RawPacket` (unknown id or malformed);
    ``zero_payloads``: frames from the device whose payload is all zeros (noise that passes the
    CRC, dropped); ``bytes_in``: bytes fed in.
    """

    frames: int = 0
    crc_errors: int = 0
    resyncs: int = 0
    dropped_bytes: int = 0
    raw_packets: int = 0
    zero_payloads: int = 0
    bytes_in: int = 0


@dataclass
class VescCodec:
    """One end of a VESC link: :meth:`receive_data` then :meth:`next_event`; :meth:`send` encodes.

    ``firmware`` selects the GET_VALUES layout; the caller sets it (the driver, from the FW_VERSION
    reply to its handshake request). ``max_payload`` bounds accepted lengths (the firmware's 512 by
    default).
    """

    role: Role
    firmware: tuple[int, int] | None = None
    max_payload: int = MAX_PAYLOAD
    stats: CodecStats = field(default_factory=CodecStats)
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _pos: int = field(default=0, repr=False)
    _in_sync: bool = field(default=True, repr=False)

    def receive_data(self, data: bytes) -> None:
        """Feed bytes read from the wire, in any chunking."""
        self.stats.bytes_in += len(data)
        if self._pos and self._pos >= len(self._buf) // 2:
            del self._buf[:self._pos]
            self._pos = 0
        self._buf += data

    def next_event(self) -> Packet | None:
        """The next decoded packet, or None when more bytes are needed."""
        buf = self._buf
        while True:
            pos = self._pos
            avail = len(buf) - pos
            if avail <= 0:
                return None
            start = buf[pos]
            if start == START_SHORT:
                head = 2
                if avail < head:
                    return None
                length = buf[pos + 1]
                ok = length >= 1
            elif start == START_LONG:
                head = 3
                if avail < head:
                    return None
                length = (buf[pos + 1] << 8) | buf[pos + 2]
                ok = 255 <= length <= self.max_payload
            elif start == START_HUGE:
                head = 4
                if avail < head:
                    return None
                length = (buf[pos + 1] << 16) | (buf[pos + 2] << 8) | buf[pos + 3]
                ok = 1 <= length <= self.max_payload
            else:
                self._drop()
                continue
            if not ok:
                self._drop()
                continue
            total = head + length + 3
            if avail < total:
                return None
            body = pos + head
            payload = bytes(buf[body:body + length])
            if buf[body + length + 2] != END:
                self._drop()
                continue
            crc = (buf[body + length] << 8) | buf[body + length + 1]
            if crc != binascii.crc_hqx(payload, 0):
                self.stats.crc_errors += 1
                self._drop()
                continue
            if self.role is Role.HOST and not any(payload):
                # CRC 0x0000 over zeros: line noise, and no VESC reply is all zeros (it would be
                # FW_VERSION 0.0). A host's FW_VERSION request is one zero byte, hence HOST only.
                self.stats.zero_payloads += 1
                self._drop()
                continue
            self._pos = pos + total
            self._in_sync = True
            self.stats.frames += 1
            event = self._decode(payload)
            if isinstance(event, RawPacket):
                self.stats.raw_packets += 1
            return event

    def events(self) -> list[Packet]:
        """Every packet decodable from the bytes received so far."""
        out: list[Packet] = []
        while (event := self.next_event()) is not None:
            out.append(event)
        return out

    def send(self, packet: Packet) -> bytes:
        """The framed bytes of ``packet``; refuses packets the other side would send."""
        wrong = _REPLY_TYPES if self.role is Role.HOST else _REQUEST_TYPES
        if isinstance(packet, wrong):
            raise LocalProtocolError(f"a {self.role.value} does not send {type(packet).__name__}")
        return frame(encode_payload(packet, self.firmware))

    def reset(self) -> None:
        """Forget buffered bytes (after a reconnect); statistics and firmware are kept."""
        self._buf.clear()
        self._pos = 0
        self._in_sync = True

    @property
    def buffered(self) -> int:
        """Bytes received and not yet consumed."""
        return len(self._buf) - self._pos

    def _drop(self) -> None:
        self._pos += 1
        self.stats.dropped_bytes += 1
        if self._in_sync:
            self._in_sync = False
            self.stats.resyncs += 1

    def _decode(self, payload: bytes) -> Packet:
        if self.role is Role.DEVICE:
            return decode_request(payload)
        return decode_reply(payload, self.firmware)
