"""Inbound MAVLink as a sans-I/O decoder: one UDP datagram in, verified messages out.

A datagram is a unit: it is parsed alone and whatever is left of it is thrown away, so a stray
``FD 30`` cannot wait for the next datagram and swallow the command in it. Inside a datagram the
frames are found by their start marker (``FD`` MAVLink 2, ``FE`` MAVLink 1), length and CRC
(X.25 with the message's CRC_EXTRA); a candidate that fails advances one byte, so a valid frame
after garbage in the same datagram is still found. Unknown message ids are dropped (their CRC
cannot be checked) and never count as traffic. The link speaks MAVLink 2 only (our HEARTBEATs are
MAVLink 2, and ground stations answer in kind): a MAVLink 1 frame is refused and counted, since
its one-byte message id and lack of flags let random bytes pass as a frame some hundred times more
often than MAVLink 2's (about 3 in 10^6 fuzzed frames got through its CRC).

Signing (MAVLink 2, https://mavlink.io/en/guide/message_signing.html), with a secret key: every
frame must be signed. The signature (the first 6 bytes of SHA-256 over the key and the frame up to
the signature) is verified *first*; only then is the timestamp looked at and recorded. That order
is the MAVLink C library's; pymavlink (2.4.x) records a stream's timestamp before it checks the
signature, so forged or corrupted frames with a far-future timestamp lock the real ground station
out. Timestamps are kept per stream (link id, system id, component id): a known stream's timestamp
must increase; a new stream's may be at most one minute behind our own, which follows the largest
accepted timestamp. pymavlink decodes only the payload of a frame that passed all of this.

A hardening beyond the signing rules (which only ask each stream's timestamps to increase, and the
receiver to adopt the newest it accepts): with ``future_window`` set, a genuinely signed frame
stamped more than that far ahead of our clock (the ``now`` given to :meth:`MavlinkRx.decode`, the
wall clock) is refused and records nothing, so one frame from a laptop whose clock is an hour
ahead cannot make every later frame of that stream (or every new stream) look old.

Under a flood, :meth:`MavlinkRx.refuse_cheaply` turns away the common forgeries (a datagram that is
exactly one unsigned frame, or one signed frame whose signature fails) with one CRC and one
SHA-256, without the decoder's search, timestamp or payload work; anything else goes through
:meth:`MavlinkRx.decode`.

The decoder's work per datagram is bounded, so that no datagram costs more than a few frames do:
ground stations (QGroundControl, Mission Planner, MAVProxy, pymavlink) send one frame, or a few,
per datagram, and a MAVLink 2 frame is at most 280 bytes. A datagram longer than
:data:`MAX_DATAGRAM` is refused before any CRC (``oversized``); in a shorter one at most
:data:`MAX_CANDIDATES` frame starts are examined (each at most one CRC and one SHA-256) and at most
:data:`MAX_FRAMES` frames accepted, and the rest of it is dropped (``overfull``). Without these one
65,507-byte datagram of ``FD FF 00 00 00`` cost some 13,000 CRCs over 265 bytes (64 ms).

Counters (:attr:`MavlinkRx.counters`): ``frames`` (accepted), ``bad_data`` (datagrams with bytes
that were no valid frame), ``unknown_ids``, ``mavlink1_refused``, ``unsigned_refused``,
``bad_signature``, ``old_timestamp`` (a replay, or a stream too far behind), ``future_timestamp``
(a genuine signature on a timestamp too far ahead of our clock), ``oversized`` (datagrams longer
than :data:`MAX_DATAGRAM`), ``overfull`` (datagrams cut short at :data:`MAX_CANDIDATES` or
:data:`MAX_FRAMES`); and the work done, for tests and benchmarks: ``candidates`` (frame starts
examined), ``crcs`` (CRCs computed). Each refusal in
:meth:`MavlinkRx.decode` also appends its counter's name to :attr:`MavlinkRx.refused` (the refusals
in the last datagram decoded).
"""

from __future__ import annotations

import hashlib
import hmac
import os
from collections import OrderedDict
from typing import Any

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported anywhere: the MAVLink 2 dialects
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

MARKER_V2 = 0xFD
MARKER_V1 = 0xFE
HEADER_V2 = 10
HEADER_V1 = 6
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01
#: A new stream's timestamp may lag our own by one minute (units of 10 µs).
NEW_STREAM_LAG = 60 * 100_000
#: Streams remembered (the C library keeps 16); the least recently used is forgotten first. Only a
#: key holder can add one, so this bounds memory, not an attack.
MAX_STREAMS = 64
#: The longest datagram decoded (bytes): what one Ethernet frame carries over IPv4 (1500 - 20 - 8),
#: five MAVLink 2 frames of the largest size. Ground stations send one frame or a few per datagram;
#: a longer datagram is refused whole, before any CRC.
MAX_DATAGRAM = 1472
#: Frame starts (a marker byte, or the datagram's first byte) examined per datagram; each costs at
#: most one CRC (over at most 265 bytes) and one SHA-256. The rest of the datagram is dropped.
MAX_CANDIDATES = 16
#: Frames accepted (handed to the link to act on) per datagram; the rest of the datagram is dropped.
MAX_FRAMES = 4


class MavlinkRx:
    """Decodes datagrams; checks signatures with ``secret_key`` (None: unsigned link).

    :attr:`timestamp` is our signing time (10 µs units since 2015); the owner raises it to the
    wall clock and reads it back for outgoing signatures. It only ever increases.
    """

    def __init__(self, secret_key: bytes | None = None, timestamp: int = 0, future_window: int = 0) -> None:
        self.secret_key = secret_key
        self.timestamp = timestamp
        #: how far (10 µs units) a signed frame may be stamped ahead of ``now``; 0 = no limit
        self.future_window = future_window
        self.streams: OrderedDict[tuple[int, int, int], int] = OrderedDict()
        self.counters: dict[str, int] = dict.fromkeys(
            ("frames", "bad_data", "unknown_ids", "mavlink1_refused", "unsigned_refused", "bad_signature",
             "old_timestamp", "future_timestamp", "oversized", "overfull", "candidates", "crcs"), 0)
        #: the counter names of the refusals in the last datagram decoded
        self.refused: list[str] = []
        self._now: int | None = None
        self._mav = mavlink.MAVLink(None)  # payload decoding only: no buffer, no signing state

    def restart(self, timestamp: int) -> int:
        """Forget every stream's timestamp and set our signing time to ``timestamp`` (the wall
        clock), as a fresh start does; returns how many streams were forgotten."""
        forgotten = len(self.streams)
        self.streams.clear()
        self.timestamp = timestamp
        return forgotten

    def _refuse(self, counter: str) -> None:
        self.counters[counter] += 1
        self.refused.append(counter)

    def refuse_cheaply(self, data: bytes) -> str | None:
        """With signing on: the refusal (its counter's name, counted) when ``data`` is exactly one
        MAVLink 2 frame with a good CRC that is unsigned (``"unsigned_refused"``), or signed with a
        signature that fails (``"bad_signature"``); None when the datagram needs :meth:`decode`
        (a genuine frame, several frames, garbage). One CRC and one SHA-256 at most, no timestamp
        and no payload. The CRC is checked so that a damaged header whose length happens to span
        the datagram cannot hide a good frame behind it from the decoder."""
        key = self.secret_key
        n = len(data)
        if key is None or n < HEADER_V2 + 2 or data[0] != MARKER_V2:
            return None
        plen, incompat = data[1], data[2]
        if incompat & ~IFLAG_SIGNED:
            return None
        if HEADER_V2 + plen + 2 + (SIGNATURE_LEN if incompat else 0) != n:
            return None
        cls = mavlink.mavlink_map.get(data[7] | (data[8] << 8) | (data[9] << 16))
        end = HEADER_V2 + plen
        if cls is None:
            return None
        self.counters["crcs"] += 1
        if _crc(data[1:end] + bytes((cls.crc_extra,))) != data[end] | (data[end + 1] << 8):
            return None
        if not incompat:
            refusal = "unsigned_refused"
        elif hmac.compare_digest(hashlib.sha256(key + data[:-6]).digest()[:6], data[-6:]):
            return None  # genuine: timestamp and payload in decode()
        else:
            refusal = "bad_signature"
        self.counters[refusal] += 1
        return refusal

    def decode(self, data: bytes, now: int | None = None) -> list[Any]:
        """Every verified message in one datagram (pymavlink message objects), in order.

        ``now``: our clock in signing units (10 µs since 2015), for the future-timestamp window;
        None skips that check. A datagram longer than :data:`MAX_DATAGRAM` bytes is refused whole
        (``oversized``); past :data:`MAX_CANDIDATES` frame starts or :data:`MAX_FRAMES` frames the
        rest of a datagram is dropped (``overfull``)."""
        self._now = now
        self.refused.clear()
        out: list[Any] = []
        n = len(data)
        if n > MAX_DATAGRAM:
            self._refuse("oversized")
            return out
        i = 0
        bad = False
        candidates = 0
        while i < n:
            if candidates == MAX_CANDIDATES or len(out) == MAX_FRAMES:
                self._refuse("overfull")
                break
            candidates += 1
            frame = self._frame_at(data, i)
            if frame is None:
                bad = True
                i += 1
                nxt = _next_marker(data, i)
                i = n if nxt < 0 else nxt
                continue
            kind, total = frame
            if kind == "ok":
                msg, used = self._accept(data[i:i + total])
                if msg is not None:
                    out.append(msg)
                i += used
            else:  # unknown id: its CRC cannot be checked, so it may be garbage posing as a frame
                i += 1
                nxt = _next_marker(data, i)
                i = n if nxt < 0 else nxt
        self.counters["candidates"] += candidates
        if bad:
            self._refuse("bad_data")
        return out

    def _frame_at(self, data: bytes, i: int) -> tuple[str, int] | None:
        """("ok", length) for a whole frame with a good CRC at ``i``, ("unknown", length) for one
        whose message id is unknown, None for no frame."""
        marker = data[i]
        avail = len(data) - i
        if marker == MARKER_V2:
            if avail < HEADER_V2 + 2:
                return None
            plen, incompat = data[i + 1], data[i + 2]
            if incompat & ~IFLAG_SIGNED:
                return None
            msgid = data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16)
            header = HEADER_V2
            total = HEADER_V2 + plen + 2 + (SIGNATURE_LEN if incompat & IFLAG_SIGNED else 0)
        elif marker == MARKER_V1:
            if avail < HEADER_V1 + 2:
                return None
            plen, msgid, header = data[i + 1], data[i + 5], HEADER_V1
            total = HEADER_V1 + plen + 2
        else:
            return None
        if total > avail:
            return None
        cls = mavlink.mavlink_map.get(msgid)
        if cls is None:
            self._refuse("unknown_ids")
            return ("unknown", total)
        end = i + header + plen
        self.counters["crcs"] += 1
        if _crc(data[i + 1:end] + bytes((cls.crc_extra,))) != data[end] | (data[end + 1] << 8):
            return None
        return ("ok", total)

    def _accept(self, frame: bytes) -> tuple[Any | None, int]:
        """(the message or None, bytes consumed). The CRC proves the frame up to its signature
        block; only a good signature proves the block too. A frame whose signature fails is
        consumed up to its CRC, since its "signature" may be the start of the next frame."""
        if frame[0] != MARKER_V2:
            self._refuse("mavlink1_refused")
            return None, len(frame)
        signed = bool(frame[2] & IFLAG_SIGNED)
        if self.secret_key is not None:  # signing on: every frame signed, every signature checked
            if not signed:
                self._refuse("unsigned_refused")
                return None, len(frame)
            verdict = self._signature(frame)
            if verdict != "ok":
                return None, len(frame) - (SIGNATURE_LEN if verdict == "forged" else 0)
        try:
            msg = self._mav.decode(bytearray(frame))
        except mavlink.MAVError:
            self._refuse("bad_data")
            return None, len(frame)
        msg._signed = signed and self.secret_key is not None
        self.counters["frames"] += 1
        if signed and self.secret_key is None:  # a signature we cannot check proves nothing
            return msg, len(frame) - SIGNATURE_LEN
        return msg, len(frame)

    def _signature(self, frame: bytes) -> str:
        """"ok", "forged" (the signature fails), "future" (a good signature on a timestamp too far
        ahead of our clock) or "old" (a good signature, a stale timestamp): the signature first,
        then the timestamp, and only then is it recorded."""
        assert self.secret_key is not None
        expected = hashlib.sha256(self.secret_key + frame[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, frame[-6:]):
            self._refuse("bad_signature")
            return "forged"
        link_id = frame[-SIGNATURE_LEN]
        stamp = int.from_bytes(frame[-12:-6], "little")
        if self.future_window and self._now is not None and stamp > self._now + self.future_window:
            self._refuse("future_timestamp")
            return "future"
        stream = (link_id, frame[5], frame[6])
        last = self.streams.get(stream)
        if (stamp <= last) if last is not None else (stamp + NEW_STREAM_LAG < self.timestamp):
            self._refuse("old_timestamp")
            return "old"
        self.streams[stream] = stamp
        self.streams.move_to_end(stream)
        if len(self.streams) > MAX_STREAMS:
            self.streams.popitem(last=False)
        self.timestamp = max(self.timestamp, stamp)
        return "ok"


#: fastcrc's CRC-16/MCRF4XX (C code) when pymavlink found it (a pymavlink dependency), else None.
_FAST_CRC = getattr(mavlink, "mcrf4xx", None)


def _crc(data: bytes) -> int:
    """MAVLink's CRC-16/MCRF4XX of ``data`` (fastcrc's, else pymavlink's own)."""
    return int(_FAST_CRC(data, 0xFFFF)) if _FAST_CRC is not None else int(mavlink.x25crc(data).crc)


def _next_marker(data: bytes, start: int) -> int:
    """The index of the next ``FD`` or ``FE`` at or after ``start``, or -1."""
    v2, v1 = data.find(MARKER_V2, start), data.find(MARKER_V1, start)
    if v2 < 0:
        return v1
    return v2 if v1 < 0 else min(v2, v1)


__all__ = ["MAX_CANDIDATES", "MAX_DATAGRAM", "MAX_FRAMES", "MavlinkRx"]
