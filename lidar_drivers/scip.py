"""Hokuyo SCIP 2.0 as a sans-I/O codec, for the host and for a (fake) device.

No sockets, clocks or sleeps here: bytes in, typed events out; typed commands in, bytes out.

Host side: :meth:`Command.encode` (and subclasses) turns a request into bytes;
:class:`ResponseDecoder` takes the device's bytes in arbitrary chunks (:meth:`~ResponseDecoder.
receive_data`) and hands back typed replies (:meth:`~ResponseDecoder.next_event`). Bad bytes from
the device never raise: a response with a wrong checksum becomes a :class:`ChecksumMismatch` event,
bytes that are not a response a :class:`MalformedResponse` event, and the decoder resynchronises on
the next empty line (every SCIP reply ends with ``LF LF``; CR LF and lone CR count as LF) and on
the next echo and status line: a reply cut short, or missing only its final line feed, costs
itself and never the reply after it.

Device side: :class:`CommandDecoder` turns the host's bytes into :class:`Command` objects (or
:class:`UnknownCommand` / :class:`InvalidCommand`), and the ``encode_*`` functions build replies.

Wire format (Hokuyo C-42-03320B): a reply is the echoed command line, a status line (two
characters and a checksum), data lines each with their own checksum, and an empty line. Numbers
are 6-bit groups, most significant first, each plus 0x30, in 2, 3 or 4 characters. Scan data is
cut into lines of 64 characters, so a value can straddle a line break. The checksum of a line is
``(sum(bytes) & 0x3F) + 0x30``; on ``KEY:VALUE;c`` lines the ``;`` is not summed.

Distances are integer millimetres; timestamps are the device's 24-bit millisecond counter.
"""

from __future__ import annotations

import functools
import math
import re
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from racecar_hw.base.errors import LocalProtocolError, RemoteProtocolError

LINE_CHARS = 64
"""Characters of encoded data per data line."""

TAG_MAX = 16
"""Longest ``;string`` tag a device echoes back."""

MAX_BUFFER = 1 << 18
"""Bytes buffered without a reply end before the decoder drops them as garbage."""

SCAN_KINDS = ("GD", "GE", "GS", "MD", "ME", "MS")
SIMPLE_COMMANDS = ("VV", "PP", "II", "BM", "QT", "RS", "RT", "%ST", "SCIP2.0")
INFO_COMMANDS = ("VV", "PP", "II")

#: Characters per value by scan kind: S = 2 (12 bits), D and E = 3 (18 bits).
_WIDTH = {"D": 3, "E": 3, "S": 2}

# --- status codes ------------------------------------------------------------------------------

_COMMON_STATUS = {
    "00": "ok",
    "99": "scan data follows (streaming)",
    "0E": "unknown command",
    "0F": "command not supported by this device",
    "0G": "tag string too long",
    "0H": "command too short",
    "0D": "command too long",
    "0L": "abnormal state",
    "0M": "unstable: scan skipped",
    "98": "resumed after the device confirmed normal operation",
}

_SCAN_STATUS = {
    "01": "start step is not a number",
    "02": "end step is not a number",
    "03": "cluster count is not a number",
    "04": "end step out of range",
    "05": "end step smaller than start step",
    "06": "scan interval is not a number",
    "07": "number of scans is not a number",
    "10": "laser is off",
}

_BY_COMMAND = {
    "BM": {"01": "laser not lit: unstable or abnormal condition", "02": "laser is already on"},
    "TM": {"01": "invalid time-sync control code",
           "02": "already in time-sync mode",
           "03": "already out of time-sync mode",
           "04": "TM1 outside time-sync mode"},
    "SS": {"01": "baud rate is not a number", "02": "invalid baud rate",
           "03": "already at that baud rate", "04": "baud rate not supported"},
}


def status_meaning(command: str, status: str) -> str:
    """What a status code means in reply to ``command`` (``"MD"``, ``"TM1"``, ``"BM"``, ...)."""
    name = command[:2] if command[:1] != "%" else command
    if status in _BY_COMMAND.get(name, {}):
        return _BY_COMMAND[name][status]
    if status in _COMMON_STATUS:
        return _COMMON_STATUS[status]
    if name in SCAN_KINDS and status in _SCAN_STATUS:
        return _SCAN_STATUS[status]
    if status.isdigit():
        code = int(status)
        if 1 <= code <= 9:
            return "invalid parameter"
        if 21 <= code <= 49:
            return f"processing stopped to verify an error (code {status})"
        if 50 <= code <= 97:
            return f"hardware fault (code {status})"
    return f"unknown status {status}"


def is_hardware_fault(status: str) -> bool:
    """Whether ``status`` is one of the hardware-fault codes 50..97."""
    return status.isdigit() and 50 <= int(status) <= 97


# --- character encoding and checksums -----------------------------------------------------------


def checksum(data: bytes) -> int:
    """The SCIP checksum byte of ``data``: ``(sum & 0x3F) + 0x30``."""
    return (sum(data) & 0x3F) + 0x30


def encode_int(value: int, width: int) -> bytes:
    """``value`` in ``width`` characters of 6 bits each (2, 3 or 4 in SCIP)."""
    if not 0 <= value < 1 << (6 * width):
        raise LocalProtocolError(f"{value} does not fit in {width} SCIP characters")
    return bytes(((value >> (6 * (width - 1 - i))) & 0x3F) + 0x30 for i in range(width))


def decode_int(chars: bytes) -> int:
    """The number encoded in ``chars``; raises ValueError on a character outside 0x30..0x6F."""
    value = 0
    for c in chars:
        if not 0x30 <= c <= 0x6F:
            raise ValueError(f"{chars!r} is not SCIP-encoded")
        value = (value << 6) | (c - 0x30)
    return value


def encode_values(values: np.ndarray, width: int) -> bytes:
    """Many values, ``width`` characters each, concatenated (no line breaks)."""
    v = np.asarray(values, dtype=np.int64)
    if v.size and (v.min() < 0 or v.max() >= 1 << (6 * width)):
        raise LocalProtocolError(f"values out of range for {width} SCIP characters")
    # one column of characters at a time, written straight into bytes (a scan's 2,000 values:
    # a third of the time of shifting all in int64 and converting)
    chars = np.empty((v.size, width), dtype=np.uint8)
    for k in range(width):
        np.bitwise_and(v >> (6 * (width - 1 - k)), 0x3F, out=chars[:, k], casting="unsafe")
    chars += 0x30
    return chars.tobytes()


def decode_values(payload: np.ndarray | bytes, width: int) -> np.ndarray:
    """Values from concatenated characters (``uint32``); ValueError on a bad length or character."""
    p = np.frombuffer(payload, dtype=np.uint8) if isinstance(payload, bytes) else payload
    if p.size % width:
        raise ValueError(f"{p.size} characters is not a whole number of {width}-character values")
    c = p.reshape(-1, width) - np.uint8(0x30)  # wraps below 0x30, so one bound checks both
    if c.size and int(c.max()) > 0x3F:
        raise ValueError("character outside 0x30..0x6F in scan data")
    out = c[:, 0].astype(np.uint32)
    for i in range(1, width):
        out <<= 6
        out |= c[:, i]
    return out


_ONES = np.ones(LINE_CHARS, dtype=np.float32)


def data_lines(payload: bytes) -> bytes:
    """``payload`` cut into 64-character lines, each followed by its checksum and LF."""
    n = len(payload)
    if n == 0:
        return b""
    full = n // LINE_CHARS
    out = bytearray()
    if full:
        body = np.frombuffer(payload, dtype=np.uint8, count=full * LINE_CHARS).reshape(full, LINE_CHARS)
        framed = np.empty((full, LINE_CHARS + 2), dtype=np.uint8)
        framed[:, :LINE_CHARS] = body
        # float32 sums are exact here (at most 64 * 0x6F) and cheaper than an integer sum by row
        sums = (body.astype(np.float32) @ _ONES).astype(np.int32)
        framed[:, LINE_CHARS] = (sums & 0x3F) + 0x30
        framed[:, LINE_CHARS + 1] = 0x0A
        out += framed.tobytes()
    rest = payload[full * LINE_CHARS:]
    if rest:
        out += rest + bytes([checksum(rest), 0x0A])
    return bytes(out)


def join_data_lines(region: bytes) -> np.ndarray:
    """The characters of LF-separated data lines with their checksums removed.

    ``region`` holds the lines without the final LF. Raises :class:`ChecksumError` naming the
    first bad line, ValueError on an empty line.
    """
    arr = np.frombuffer(region + b"\n", dtype=np.uint8)
    stride = LINE_CHARS + 2
    full = arr.size // stride
    rem = arr.size - full * stride
    if (region.count(b"\n") + 1 == full + (1 if rem else 0)
            and (full == 0 or bool((arr[stride - 1:full * stride:stride] == 0x0A).all()))):
        body = arr[:full * stride].reshape(full, stride)
        # float32 sums are exact here (at most 64 * 255) and much faster than integer reduce
        sums = (body[:, :LINE_CHARS].astype(np.float32) @ _ONES).astype(np.int32)
        bad = np.flatnonzero(((sums & 0x3F) + 0x30) != body[:, LINE_CHARS])
        if bad.size:
            raise ChecksumError(bytes(body[bad[0], :LINE_CHARS + 1]))
        parts = [body[:, :LINE_CHARS].reshape(-1)]
        if rem:
            last = arr[full * stride:-1]
            if last.size < 2:
                raise ValueError("empty data line")
            if checksum(last[:-1].tobytes()) != int(last[-1]):
                raise ChecksumError(last.tobytes())
            parts.append(last[:-1])
        return np.concatenate(parts) if len(parts) > 1 else parts[0]
    # lines of another width: slower, line by line
    chunks = []
    for line in region.split(b"\n"):
        if len(line) < 2:
            raise ValueError("empty data line")
        if checksum(line[:-1]) != line[-1]:
            raise ChecksumError(line)
        chunks.append(line[:-1])
    return np.frombuffer(b"".join(chunks), dtype=np.uint8)


_STRIDE = LINE_CHARS + 2

_LINE_CHECK = np.ones(_STRIDE)
_LINE_CHECK[LINE_CHARS:] = (-1.0, 24.0)
"""Weights of a data line's bytes whose weighted sum is a multiple of 64 when its checksum holds.

A checksum ``c = (sum & 0x3F) + 0x30`` holds when ``sum - c + 16`` is a multiple of 64; the line's
LF (0x0A) weighted 24 adds 240, which is 16 modulo 64.
"""

_DATA_CHARS = bytes(range(0x30, 0x70))
"""The characters of data lines: encoded values and checksums."""


@functools.lru_cache(maxsize=16)
def _data_layout(region_len: int, width: int) -> tuple[int, bytes, np.ndarray] | None:
    """The layout of data lines filling ``region_len`` bytes, all of 64 characters but the last.

    (the lines before the last, the LF bytes expected after them, the characters of each value as
    an (n, width) array of positions). None when no such lines fill the region or their characters
    do not split into values.
    """
    full = (region_len - 2) // _STRIDE
    last = region_len - full * _STRIDE  # the last line's characters and checksum
    if full < 0 or not 2 <= last <= LINE_CHARS + 1:
        return None
    pos = np.arange(region_len, dtype=np.intp)
    data = np.flatnonzero((pos % _STRIDE < LINE_CHARS) & (pos < region_len - 1))
    if data.size % width:
        return None
    value_pos = data.reshape(-1, width)
    value_pos.flags.writeable = False
    return full, b"\n" * full, value_pos


_WEIGHTS = {w: np.array([float(1 << (6 * (w - 1 - i))) for i in range(w)]) for w in (2, 3, 4)}
_ZERO = {w: 0x30 * float(weights.sum()) for w, weights in _WEIGHTS.items()}


def decode_data_lines(region: bytes, width: int) -> np.ndarray | None:
    """The values (``float64``, whole numbers) of data lines of 64 characters, or None when
    ``region`` is anything else.

    The same values as ``decode_values(join_data_lines(region), width)`` when that succeeds; None
    where that would raise (a bad checksum, a short line, a character outside 0x30..0x6F), so the
    caller can take the slow path for its exact error.

    This runs between a scan's last byte and the motor command. After an idle gap the first call
    of each numpy function costs some 20 us on a shared machine (its code has left the CPU caches),
    so it uses few functions: one ``bytes.translate`` checks the characters, one matrix product
    and ``fmod`` the line checksums, and a gather and another matrix product give the values.
    """
    layout = _data_layout(len(region), width) if width in _WEIGHTS else None
    if layout is None:
        return None
    full, lfs, value_pos = layout
    # an LF ends every line, and every other byte is a character of 0x30..0x6F
    if region[LINE_CHARS + 1::_STRIDE] != lfs or region.translate(None, _DATA_CHARS) != lfs:
        return None
    if checksum(region[full * _STRIDE:-1]) != region[-1]:
        return None
    f = np.frombuffer(region, dtype=np.uint8).astype(np.float64)
    if full and np.count_nonzero(np.fmod(f[:full * _STRIDE].reshape(full, _STRIDE) @ _LINE_CHECK, 64.0)):
        return None
    return f[value_pos] @ _WEIGHTS[width] - _ZERO[width]


class ChecksumError(ValueError):
    """Internal: a line whose checksum does not match (becomes a ChecksumMismatch event)."""

    def __init__(self, line: bytes) -> None:
        super().__init__(f"checksum mismatch on {line[:70]!r}")
        self.line = line


def _checked(line: bytes) -> bytes:
    """``line`` without its checksum character, or ChecksumError."""
    if len(line) < 2 or checksum(line[:-1]) != line[-1]:
        raise ChecksumError(line)
    return line[:-1]


# --- sensor parameters (the PP reply) ----------------------------------------------------------

_PP_KEYS = ("DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN")


@dataclass(frozen=True)
class SensorParams:
    """The ``PP`` reply: distances in mm, angles in steps, ``scan_rpm`` the motor speed.

    Step ``AFRT`` points straight ahead; angles are radians, counter-clockwise (REP-103).
    """

    model: str
    dmin: int
    dmax: int
    ares: int
    amin: int
    amax: int
    afrt: int
    scan_rpm: int

    @classmethod
    def from_fields(cls, fields: Mapping[str, str]) -> SensorParams:
        """From PP's KEY:VALUE fields; RemoteProtocolError if one is missing or not a number, or
        the values describe no sensor (no steps per revolution, a motor standing, an empty or
        inverted step or distance range, the front outside the steps)."""
        try:
            params = cls(fields.get("MODL", ""), *(int(fields[k]) for k in _PP_KEYS))
        except (KeyError, ValueError) as err:
            raise RemoteProtocolError(f"PP reply lacks a numeric field: {err}") from err
        problem = params._implausible()
        if problem:
            raise RemoteProtocolError(f"PP reply describes no sensor: {problem}")
        return params

    def _implausible(self) -> str:
        """What makes these values impossible for a sensor, or empty."""
        if self.ares <= 0 or self.scan_rpm <= 0:
            return f"ARES {self.ares} steps a revolution, SCAN {self.scan_rpm} rpm (both must be positive)"
        if not 0 <= self.amin <= self.amax < self.ares * 2:
            return f"steps AMIN {self.amin} to AMAX {self.amax} (ARES {self.ares})"
        if not self.amin <= self.afrt <= self.amax:
            return f"front step AFRT {self.afrt} outside AMIN {self.amin} to AMAX {self.amax}"
        if not 0 <= self.dmin <= self.dmax:
            return f"distances DMIN {self.dmin} to DMAX {self.dmax} mm"
        return ""

    def fields(self) -> dict[str, str | int]:
        """The ``PP`` reply's fields in device order."""
        values = (self.dmin, self.dmax, self.ares, self.amin, self.amax, self.afrt, self.scan_rpm)
        return {"MODL": self.model, **dict(zip(_PP_KEYS, values, strict=True))}

    @property
    def steps(self) -> int:
        """Steps from AMIN to AMAX inclusive."""
        return self.amax - self.amin + 1

    @property
    def scan_period_s(self) -> float:
        """Seconds per revolution."""
        return 60.0 / self.scan_rpm

    @property
    def step_time_s(self) -> float:
        """Seconds between adjacent steps."""
        return 60.0 / (self.scan_rpm * self.ares)

    def step_of(self, angle: float) -> float:
        """The (fractional) step at ``angle`` radians."""
        return self.afrt + angle * self.ares / (2.0 * math.pi)

    def angle_of(self, step: float) -> float:
        """The angle of ``step`` in radians."""
        return (step - self.afrt) * 2.0 * math.pi / self.ares


# --- commands (host -> device) ------------------------------------------------------------------

_TAG_RE = re.compile(r"[\x20-\x7e]{0,16}")


def _check_tag(tag: str) -> None:
    if not _TAG_RE.fullmatch(tag) or ";" in tag:
        raise LocalProtocolError(f"tag {tag!r}: at most {TAG_MAX} printable characters, no ';'")


@dataclass(frozen=True)
class Command:
    """A command without parameters: VV, PP, II, BM, QT, RS, RT, %ST, SCIP2.0."""

    name: str
    tag: str = ""

    @property
    def body(self) -> str:
        """The command and its parameters, without the tag."""
        return self.name

    @property
    def line(self) -> str:
        """The command line as sent and echoed (no line end)."""
        return self.body + (f";{self.tag}" if self.tag else "")

    def encode(self) -> bytes:
        """The bytes the host sends."""
        _check_tag(self.tag)
        return (self.line + "\n").encode("ascii")


@dataclass(frozen=True)
class TimeCommand(Command):
    """TM0 (enter time-sync mode), TM1 (read the device time), TM2 (leave)."""

    name: str = "TM"
    code: int = 0

    @property
    def body(self) -> str:
        return f"TM{self.code}"

    def encode(self) -> bytes:
        if self.code not in (0, 1, 2):
            raise LocalProtocolError(f"TM control code {self.code} is not 0, 1 or 2")
        return super().encode()


@dataclass(frozen=True)
class ScanCommand(Command):
    """GD/GE/GS (one scan) or MD/ME/MS (``count`` scans, 0 = forever, every ``interval+1``-th).

    Steps ``start``..``end`` inclusive; ``cluster`` adjacent steps merge into one value (the
    device returns their minimum). For MD/ME/MS frames the echo carries the scans still to come
    in place of ``count``.
    """

    name: str = "MD"
    start: int = 0
    end: int = 0
    cluster: int = 1
    interval: int = 0
    count: int = 0

    @property
    def streaming(self) -> bool:
        """MD/ME/MS (a stream of frames) rather than GD/GE/GS (one reply)."""
        return self.name[0] == "M"

    @property
    def intensities(self) -> bool:
        """GE/ME: every step carries distance and intensity."""
        return self.name[1] == "E"

    @property
    def width(self) -> int:
        """Characters per value."""
        return _WIDTH[self.name[1]]

    @property
    def values(self) -> int:
        """Readings in one scan: ceil((end - start + 1) / cluster)."""
        cluster = max(self.cluster, 1)
        return -(-(self.end - self.start + 1) // cluster)

    @property
    def body(self) -> str:
        text = f"{self.name}{self.start:04d}{self.end:04d}{self.cluster:02d}"
        return text + (f"{self.interval:01d}{self.count:02d}" if self.streaming else "")

    def echo(self, remaining: int) -> str:
        """The echo line of a streamed frame with ``remaining`` scans still to come."""
        text = f"{self.name}{self.start:04d}{self.end:04d}{self.cluster:02d}{self.interval:01d}"
        return f"{text}{remaining:02d}" + (f";{self.tag}" if self.tag else "")

    def encode(self) -> bytes:
        if self.name not in SCAN_KINDS:
            raise LocalProtocolError(f"{self.name} is not a scan command")
        if not (0 <= self.start <= 9999 and 0 <= self.end <= 9999 and 0 <= self.cluster <= 99):
            raise LocalProtocolError(f"{self.name}: start/end 0..9999, cluster 0..99")
        if self.streaming and not (0 <= self.interval <= 9 and 0 <= self.count <= 99):
            raise LocalProtocolError(f"{self.name}: interval 0..9, count 0..99")
        return super().encode()


@dataclass(frozen=True)
class UnknownCommand:
    """Device side: a line that is no command this codec knows (the device answers 0E)."""

    line: str

    @property
    def name(self) -> str:
        return self.line.split(";", 1)[0]


@dataclass(frozen=True)
class InvalidCommand:
    """Device side: a known command with bad parameters; ``status`` is the error to answer."""

    line: str
    name: str
    status: str


# --- replies (device -> host) -------------------------------------------------------------------


@dataclass(frozen=True)
class Reply:
    """A reply: ``echo`` is the echoed command line, ``command`` its name (``TM1``, ``MD``, ...)."""

    echo: str
    command: str
    status: str
    tag: str

    @property
    def ok(self) -> bool:
        """Status 00 (done) or 99 (a streamed frame)."""
        return self.status in ("00", "99")

    @property
    def meaning(self) -> str:
        """The status in words."""
        return status_meaning(self.command, self.status)


@dataclass(frozen=True)
class StatusReply(Reply):
    """A reply without data: QT, RS, BM, TM0/2, an MD/ME acknowledgement, any error."""


@dataclass(frozen=True)
class InfoReply(Reply):
    """VV, PP or II: ``KEY`` -> ``VALUE`` text."""

    fields: Mapping[str, str]


@dataclass(frozen=True)
class TimeReply(Reply):
    """TM1: the device clock in ms (24 bits, wraps every 2**24 ms)."""

    time_ms: int


@dataclass(frozen=True)
class StateReply(Reply):
    """%ST (UST): three-digit state, e.g. ``000`` standby, ``004`` multi-scan."""

    state: str


@dataclass(frozen=True, eq=False)
class ScanReply(Reply):
    """One scan: GD/GE/GS reply or an MD/ME/MS frame.

    ``request`` is the echoed command (for streamed frames ``count`` holds the scans still to
    come); ``distances`` in mm (``float64`` holding whole numbers; values below DMIN are error
    codes); ``intensities`` for GE/ME (``float64``), else None; ``timestamp_ms`` the device clock
    at step 0; ``nbytes`` the reply's length on the wire (for transfer-time corrections).
    """

    request: ScanCommand
    timestamp_ms: int
    distances: np.ndarray = field(repr=False)
    intensities: np.ndarray | None = field(repr=False)
    nbytes: int = 0


@dataclass(frozen=True)
class DecodeError:
    """Bytes from the device that the decoder dropped, and why."""

    raw: bytes
    reason: str


@dataclass(frozen=True)
class ChecksumMismatch(DecodeError):
    """A response with a wrong checksum on one of its lines; the whole response is dropped."""


@dataclass(frozen=True)
class MalformedResponse(DecodeError):
    """Bytes that are not a SCIP response (noise, a truncated reply, another protocol)."""


Event = StatusReply | InfoReply | TimeReply | StateReply | ScanReply | ChecksumMismatch | MalformedResponse

_ECHO_RE = re.compile(
    rb"(?P<cmd>VV|PP|II|BM|QT|RS|RT|%ST|SCIP2\.0|TM[0-9]|(?P<scan>[GM][DSE])(?P<digits>[0-9]{10,13}))"
    rb"(?:;(?P<tag>[\x20-\x7e]{0,16}))?")


_ECHO_FIRST = frozenset(b"VPIBQRST%GM")
_STATUS_RE = re.compile(rb"[0-9A-Z]{2}[\x30-\x6f]")
#: The status line of a reply to a command this codec does not know: two printable characters.
_GENERIC_STATUS_RE = re.compile(rb"[\x21-\x7e]{2}[\x30-\x6f]")
#: Where a reply starts: an echo line, then a status line ending the block or followed by a line.
_HEAD_RE = re.compile(_ECHO_RE.pattern + rb"\n[0-9A-Z]{2}[\x30-\x6f](?=\n|\Z)")


#: A reply's end, the first empty line. A compiled search finds it in a scan's 6.7 kB in a third of
#: the time of ``bytearray.find`` (CPython's two-byte ``find`` steps through the data; ``re`` skips
#: to each LF).
_REPLY_END = re.compile(rb"\n\n")

#: How many of the following heads a damaged block's reply may span (bounds the work per block).
HEAD_TRIES = 3


def _reply_heads(block: bytes) -> list[int]:
    """Where replies may start in ``block``: an echo this codec knows, then a status line whose
    checksum holds. Heads may overlap (``MD...;TM1`` and ``TM1``)."""
    heads = []
    pos = 0
    while (m := _HEAD_RE.search(block, pos)) is not None:
        head = m.group(0)
        if checksum(head[-3:-1]) == head[-1] and _parse_echo(head[:-4]) is not None:
            heads.append(m.start())
        pos = m.start() + 1
    return heads


def _without_final_lf(sub: bytes, cut: bool) -> bytes:
    """``sub`` without the line feed that ended its last line, when another reply followed it."""
    return sub[:-1] if cut and sub.endswith(b"\n") else sub


@functools.lru_cache(maxsize=256)
def _parse_echo(line: bytes) -> tuple[str, ScanCommand | None, str] | None:
    """(command name, scan request or None, tag) when ``line`` is a whole echo line."""
    m = _ECHO_RE.fullmatch(line)
    if m is None:
        return None
    tag = (m["tag"] or b"").decode("ascii")
    if m["scan"] is None:
        return m["cmd"].decode("ascii"), None, tag
    name = m["scan"].decode("ascii")
    d = m["digits"].decode("ascii")
    streaming = name[0] == "M"
    if len(d) != (13 if streaming else 10):
        return None
    req = ScanCommand(name=name, tag=tag, start=int(d[0:4]), end=int(d[4:8]),
                      cluster=int(d[8:10]),
                      interval=int(d[10:11]) if streaming else 0,
                      count=int(d[11:13]) if streaming else 0)
    return name, req, tag


class ResponseDecoder:
    """Host side: device bytes in, replies out. Never raises on what the device sends.

    Counters: ``checksum_errors`` (responses dropped for a bad checksum), ``resyncs`` (runs of
    bytes dropped as garbage), ``bytes_in``.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._cr = False
        self._events: deque[Event] = deque()
        #: why :meth:`_reply` last found a reply's body unreadable ("540 readings, expected 1081"),
        #: for the MalformedResponse of a reply that no other cut makes whole
        self._unreadable: str | None = None
        self.checksum_errors = 0
        self.resyncs = 0
        self.bytes_in = 0

    def receive_data(self, data: bytes) -> None:
        """Add bytes as they arrived, in any chunking."""
        self.bytes_in += len(data)
        if self._cr and data[:1] == b"\n":
            data = data[1:]
        if b"\r" in data:
            data = data.replace(b"\r\n", b"\n")
            self._cr = data.endswith(b"\r")
            data = data.replace(b"\r", b"\n")
        else:
            self._cr = False
        self._buf += data

    def next_event(self) -> Event | None:
        """The next complete event, or None until more bytes arrive."""
        while not self._events:
            found = _REPLY_END.search(self._buf)
            if found is None:
                if len(self._buf) > MAX_BUFFER:
                    self._drop(bytes(self._buf), "no reply end in a long run of bytes")
                    self._buf.clear()
                    continue
                return None
            end = found.start()
            block = bytes(self._buf[:end])
            del self._buf[:end + 2]
            self._parse_block(block)
        return self._events.popleft()

    def __iter__(self):  # noqa: ANN204 - an iterator of events
        while (event := self.next_event()) is not None:
            yield event

    def _drop(self, raw: bytes, reason: str) -> None:
        self.resyncs += 1
        self._events.append(MalformedResponse(raw, reason))

    def _parse_block(self, block: bytes) -> None:
        if not block.lstrip(b"\n"):
            return  # stray empty lines between replies
        if block[0] in _ECHO_FIRST:  # the usual case: one whole reply
            event = self._reply(block)
            if event is not None and not isinstance(event, ChecksumMismatch):
                self._events.append(event)
                return
        # Garbage, or a damaged reply: cut short, or without its final line feed, so that it ran
        # into the next reply. Every reply starts with an echo line and a status line whose
        # checksum holds; cut the block at each such head, so one damaged reply costs one reply.
        heads = _reply_heads(block)
        if not heads:
            generic = self._generic(block)
            if generic is not None:
                self._events.append(generic)
            else:
                self._drop(block, "not a SCIP reply")
            return
        if heads[0]:
            self._drop(block[:heads[0]], "garbage before a reply")
        ends = [*heads[1:], len(block)]
        i = 0
        while i < len(heads):
            # a head may sit inside a reply (a tag can hold "QT\n00P"-like text, and garbage
            # glued to an echo can read as its tag): try the next few heads as this reply's end
            why = None
            for j in range(i, min(i + HEAD_TRIES, len(heads))):
                self._unreadable = None
                event = self._reply(_without_final_lf(block[heads[i]:ends[j]], ends[j] < len(block)))
                why = self._unreadable if j == i else why
                if event is not None and (j == i or not isinstance(event, ChecksumMismatch)):
                    if isinstance(event, ChecksumMismatch):
                        self.checksum_errors += 1
                    self._events.append(event)
                    i = j + 1
                    break
            else:
                self._drop(block[heads[i]:ends[i]],
                           why or "a damaged reply (cut short, or run into the next one)")
                i += 1

    @staticmethod
    def _generic(block: bytes) -> StatusReply | None:
        """A status-only reply to a command this codec does not know (e.g. ``XX`` -> 0E)."""
        lines = block.split(b"\n")
        if len(lines) != 2 or not re.fullmatch(rb"[\x21-\x7e][\x20-\x7e]*", lines[0]):
            return None
        if not _GENERIC_STATUS_RE.fullmatch(lines[1]) or checksum(lines[1][:2]) != lines[1][2]:
            return None
        echo = lines[0].decode("ascii")
        name, _, tag = echo.partition(";")
        return StatusReply(echo, name, lines[1][:2].decode("ascii"), tag)

    def _reply(self, sub: bytes) -> Event | None:
        """The event for the reply ``sub`` (no final empty line), a ChecksumMismatch, or None if
        ``sub`` does not start with a reply."""
        parts = sub.split(b"\n", 2)
        if len(parts) < 2:
            return None
        echo_line, status_line = parts[0], parts[1]
        echo = _parse_echo(echo_line)
        if echo is None or not _STATUS_RE.fullmatch(status_line):
            return None
        cmd, req, tag = echo
        echo_text = echo_line.decode("ascii")
        status = status_line[:2].decode("ascii")
        if checksum(status_line[:2]) != status_line[2]:
            return ChecksumMismatch(sub, "status line checksum")
        if len(parts) == 2:
            return StatusReply(echo_text, cmd, status, tag)
        rest = parts[2]
        try:
            if cmd in INFO_COMMANDS:
                return InfoReply(echo_text, cmd, status, tag, self._fields(rest.split(b"\n")))
            if cmd == "TM1" and len(rest) == 5:
                return TimeReply(echo_text, cmd, status, tag, decode_int(_checked(rest)))
            if cmd == "%ST" and len(rest) == 4:
                return StateReply(echo_text, cmd, status, tag, _checked(rest).decode("ascii"))
            if req is not None and rest[5:6] == b"\n":
                stamp = decode_int(_checked(rest[:5]))
                return self._scan(echo_text, req, status, stamp, rest[6:], len(sub) + 2)
        except ChecksumError as err:
            return ChecksumMismatch(sub, f"data line: {err}")
        except ValueError as err:
            self._unreadable = str(err)
            return None
        return None

    @staticmethod
    def _fields(data: list[bytes]) -> dict[str, str]:
        fields: dict[str, str] = {}
        for line in data:
            # KEY:VALUE;c  -- the sum excludes the ';'
            if len(line) < 4 or line[-2:-1] != b";" or b":" not in line:
                raise ValueError("not a KEY:VALUE;c line")
            if checksum(line[:-2]) != line[-1]:
                raise ChecksumError(line)
            key, _, value = line[:-2].decode("ascii", "replace").partition(":")
            fields[key] = value
        return fields

    @staticmethod
    def _scan(echo: str, req: ScanCommand, status: str, stamp: int, region: bytes,
              nbytes: int) -> ScanReply:
        values = decode_data_lines(region, req.width)
        if values is None:
            values = decode_values(join_data_lines(region), req.width).astype(np.float64)
        n = req.values
        if req.intensities:
            if values.size != 2 * n:
                raise ValueError(f"{values.size // 2} readings, expected {n}")
            pairs = values.reshape(-1, 2)
            return ScanReply(echo, req.name, status, req.tag, req, stamp, pairs[:, 0], pairs[:, 1],
                             nbytes)
        if values.size != n:
            raise ValueError(f"{values.size} readings, expected {n}")
        return ScanReply(echo, req.name, status, req.tag, req, stamp, values, None, nbytes)


# --- device side: decoding commands, encoding replies --------------------------------------------

_SCAN_CMD_RE = re.compile(r"([GM][DSE])(.*)")
_SCAN_FIELDS = (("01", 0, 4), ("02", 4, 8), ("03", 8, 10), ("06", 10, 11), ("07", 11, 13))


def parse_command(line: str) -> Command | UnknownCommand | InvalidCommand:
    """One command line from the host (no line end) as a command."""
    body, _, tag = line.partition(";")
    if len(tag) > TAG_MAX:
        return InvalidCommand(line, body[:2], "0G")
    if body in SIMPLE_COMMANDS:
        return Command(body, tag)
    if body.startswith("TM") and len(body) == 3:
        if body[2] not in "012":
            return InvalidCommand(line, "TM", "01")
        return TimeCommand(tag=tag, code=int(body[2]))
    m = _SCAN_CMD_RE.fullmatch(body)
    if m is None:
        return UnknownCommand(line)
    name, params = m.groups()
    want = 13 if name[0] == "M" else 10
    if len(params) < want:
        return InvalidCommand(line, name, "0H")
    if len(params) > want:
        return InvalidCommand(line, name, "0D")
    for status, a, b in _SCAN_FIELDS[: 5 if want == 13 else 3]:
        if not params[a:b].isdigit():
            return InvalidCommand(line, name, status)
    start, end = int(params[0:4]), int(params[4:8])
    if end < start:
        return InvalidCommand(line, name, "05")
    return ScanCommand(name=name, tag=tag, start=start, end=end, cluster=int(params[8:10]),
                       interval=int(params[10:11]) if want == 13 else 0,
                       count=int(params[11:13]) if want == 13 else 0)


class CommandDecoder:
    """Device side: host bytes in, commands out. A command ends at LF, CR or CR LF."""

    def __init__(self, max_line: int = 256) -> None:
        self._buf = bytearray()
        self.max_line = max_line
        self.dropped = 0

    def receive_data(self, data: bytes) -> None:
        """Add bytes from the host."""
        self._buf += data

    def next_event(self) -> Command | UnknownCommand | InvalidCommand | None:
        """The next command, or None until a whole line arrives. Empty lines are skipped."""
        while True:
            ends = [i for i in (self._buf.find(b"\n"), self._buf.find(b"\r")) if i >= 0]
            if not ends:
                if len(self._buf) > self.max_line:
                    self.dropped += len(self._buf)
                    self._buf.clear()
                return None
            end = min(ends)
            raw = bytes(self._buf[:end])
            del self._buf[:end + 1]
            if not raw:
                continue
            try:
                line = raw.decode("ascii")
            except UnicodeDecodeError:
                return UnknownCommand(raw.decode("ascii", "replace"))
            return parse_command(line)

    def __iter__(self):  # noqa: ANN204 - an iterator of commands
        while (event := self.next_event()) is not None:
            yield event


def encode_reply(echo: str, status: str, lines: Sequence[bytes] = ()) -> bytes:
    """A whole reply: echo, status with checksum, ready-made data lines (each ending LF), LF."""
    st = status.encode("ascii")
    return b"".join([echo.encode("ascii"), b"\n", st, bytes([checksum(st)]), b"\n", *lines, b"\n"])


def encode_info(echo: str, fields: Mapping[str, str | int], status: str = "00") -> bytes:
    """A VV/PP/II reply: ``KEY:VALUE;c`` lines (the checksum excludes the ';')."""
    lines = []
    for key, value in fields.items():
        kv = f"{key}:{value}".encode("ascii")
        lines.append(kv + b";" + bytes([checksum(kv)]) + b"\n")
    return encode_reply(echo, status, lines)


def _value_line(value: int, width: int) -> bytes:
    chars = encode_int(value, width)
    return chars + bytes([checksum(chars)]) + b"\n"


def encode_time(echo: str, time_ms: int) -> bytes:
    """A TM1 reply with the device clock (ms, wrapped to 24 bits)."""
    return encode_reply(echo, "00", [_value_line(time_ms & 0xFFFFFF, 4)])


def encode_state(echo: str, state: str) -> bytes:
    """A %ST reply with a three-digit state."""
    st = state.encode("ascii")
    return encode_reply(echo, "00", [st + bytes([checksum(st)]) + b"\n"])


def encode_scan(echo: str, status: str, timestamp_ms: int, distances: np.ndarray,
                intensities: np.ndarray | None = None, width: int = 3) -> bytes:
    """A GD/GE/GS reply or MD/ME/MS frame: timestamp line, then data in 64-character lines."""
    if intensities is not None:
        # distance, intensity, distance, ...: written into place (a scan: half the time of a stack)
        d, i = np.asarray(distances), np.asarray(intensities)
        if d.ndim != 1 or d.shape != i.shape:
            raise ValueError(f"{d.shape} distances and {i.shape} intensities do not pair up")
        values = np.empty(2 * d.size, dtype=np.result_type(d, i))
        values[0::2] = d
        values[1::2] = i
    else:
        values = np.asarray(distances)
    payload = encode_values(values, width)
    return encode_reply(echo, status, [_value_line(timestamp_ms & 0xFFFFFF, 4), data_lines(payload)])
