"""One fuzz harness for every parser, used by tests/test_fuzz.py (a few seconds each) and by
benchmarks/fuzz.py (10^6 frames each).

A target makes batches of valid frames (the bytes, and the keys of what decoding them must give);
the harness damages them with the mutations below, feeds the result to a fresh decoder, and counts:

* ``escaped``: exceptions out of the decoder other than its documented error (there is none for
  the wire codecs, :class:`~racecar_hw.base.errors.BagError` for bags);
* ``recovered`` / ``recoverable``: valid frames after damage or garbage whose keys all came out,
  out of those the protocol could deliver (a datagram cut inside a frame loses it by design, an
  express capsule is only decoded with its successor);
* ``invented``: decoded keys that no frame of the batch had: damage that passed the decoder's
  checks.

Mutations (:data:`MUTATIONS`): random bytes in place of a frame, bit flips, truncation,
duplication, garbage between valid frames, and random split points (chunks for a stream,
datagram boundaries for MAVLink).
"""

from __future__ import annotations

import math
import os
import random
import time
import traceback
from collections import Counter
from collections.abc import Callable, Hashable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from lidar_drivers import rplidar_codec as rp  # noqa: E402
from lidar_drivers import scip  # noqa: E402
from racecar_hw.base.errors import BagError  # noqa: E402
from racecar_hw.teleop.mavlink_rx import MavlinkRx  # noqa: E402
from vesc import codec as vc  # noqa: E402

MUTATIONS = ("random_bytes", "bit_flips", "truncation", "duplication", "garbage_between", "split_points")
#: Per frame: the chance of each damage (the rest stay intact) and of garbage before it.
DAMAGE = {"intact": 0.5, "random_bytes": 0.1, "bit_flips": 0.15, "truncation": 0.15, "duplication": 0.1}
GARBAGE = 0.3


@dataclass(frozen=True)
class Frame:
    """A valid frame's bytes and the keys decoding it must give (every one of them)."""

    data: bytes
    keys: tuple[Hashable, ...]


@dataclass
class Batch:
    """Frames to damage, and bytes that follow them undamaged (so the last frames can come out)."""

    frames: list[Frame]
    trailer: bytes = b""
    #: keys the trailer may give (not counted as recovered, not invented either)
    trailer_keys: tuple[Hashable, ...] = ()


@dataclass
class Target:
    """A parser under fuzz: ``batch(rng)`` makes frames, ``decode(chunks)`` runs a fresh decoder
    over the chunks (datagrams when ``datagrams``) and returns the keys of what came out."""

    name: str
    batch: Callable[[random.Random], Batch]
    decode: Callable[[list[bytes]], list[Hashable]]
    allowed: tuple[type[BaseException], ...] = ()
    datagrams: bool = False
    #: a frame is decoded together with the frame after it (express capsules)
    needs_successor: bool = False
    #: frames are lines: garbage glued to the front of a line makes the line another one
    lines: bool = False


@dataclass
class FuzzResult:
    """What one target did with ``frames`` frames."""

    parser: str
    frames: int = 0
    escaped: Counter[str] = field(default_factory=Counter)
    recovered: int = 0
    recoverable: int = 0
    invented: int = 0
    seconds: float = 0.0
    examples: list[str] = field(default_factory=list)
    #: what the invented keys were: their first element when a tuple with a name, else their type
    invented_kinds: Counter[str] = field(default_factory=Counter)

    @property
    def recovery_rate(self) -> float:
        """Recovered valid frames after damage, out of those the protocol could deliver."""
        return self.recovered / self.recoverable if self.recoverable else math.nan

    @property
    def throughput(self) -> float:
        """Frames per second through mutation and decoding."""
        return self.frames / self.seconds if self.seconds else math.nan

    def row(self) -> dict[str, Any]:
        return {"parser": self.parser, "frames": self.frames, "escaped": sum(self.escaped.values()),
                "recovery": self.recovery_rate, "invented": self.invented, "frames/s": self.throughput}


# --- the harness ------------------------------------------------------------------------------


@dataclass
class _Piece:
    data: bytes
    frame: int | None  # index in the batch of an intact copy, else None
    start: int = 0


def _damage(rng: random.Random, data: bytes, kind: str) -> bytes:
    if kind == "random_bytes":
        return rng.randbytes(max(1, len(data) + rng.randint(-3, 3)))
    if kind == "bit_flips":
        out = bytearray(data)
        for _ in range(rng.randint(1, 3)):
            out[rng.randrange(len(out))] ^= 1 << rng.randrange(8)
        return bytes(out)
    return data[:rng.randrange(len(data))]  # truncation


def _garbage(rng: random.Random) -> bytes:
    return rng.randbytes(rng.randint(1, 48))


def mutate(rng: random.Random, batch: Batch) -> tuple[list[_Piece], set[int]]:
    """The damaged stream as pieces, and the frames after damage that must come out."""
    pieces: list[_Piece] = []
    must: set[int] = set()
    damaged = False
    kinds, weights = list(DAMAGE), list(DAMAGE.values())
    for i, frame in enumerate(batch.frames):
        if rng.random() < GARBAGE:
            pieces.append(_Piece(_garbage(rng), None))
            damaged = True
        kind = rng.choices(kinds, weights)[0]
        if kind in ("intact", "duplication"):
            pieces.append(_Piece(frame.data, i))
            if kind == "duplication":
                pieces.append(_Piece(frame.data, i))
            if damaged:
                must.add(i)
            damaged = False
        else:
            pieces.append(_Piece(_damage(rng, frame.data, kind), None))
            damaged = True
    pos = 0
    for p in pieces:
        p.start = pos
        pos += len(p.data)
    return pieces, must


def _split(rng: random.Random, total: int, datagrams: bool, pieces: list[_Piece]) -> list[int]:
    """Chunk boundaries: random split points; for datagrams also the piece boundaries, mostly."""
    cuts = {rng.randrange(1, total) for _ in range(rng.randint(0, 4))} if total > 1 else set()
    if datagrams:
        cuts |= {p.start for p in pieces[1:] if rng.random() < 0.8}
    return sorted(c for c in cuts if 0 < c < total)


def run(target: Target, frames: int, seed: int = 0) -> FuzzResult:
    """Fuzz ``target`` with about ``frames`` frames (whole batches) from ``seed``."""
    rng = random.Random(seed)
    result = FuzzResult(target.name)
    started = time.perf_counter()
    while result.frames < frames:
        batch = target.batch(rng)
        pieces, must = mutate(rng, batch)
        data = b"".join(p.data for p in pieces)
        cuts = _split(rng, len(data), target.datagrams, pieces)
        bounds = [0, *cuts, len(data)]
        chunks = [data[a:b] for a, b in zip(bounds, bounds[1:], strict=False)]
        if batch.trailer:
            chunks.append(batch.trailer)
        result.frames += len(batch.frames)
        try:
            out = target.decode(chunks)
        except target.allowed:
            continue
        except Exception as err:  # noqa: BLE001 - counting what escapes is the point
            result.escaped[type(err).__name__] += 1
            if len(result.examples) < 3:
                result.examples.append("".join(traceback.format_exception(err)))
            continue
        got = set(out)
        known = {k for f in batch.frames for k in f.keys} | set(batch.trailer_keys)
        invented = got - known
        result.invented += len(invented)
        result.invented_kinds.update(_kind(k) for k in invented)
        deliverable = _deliverable(target, batch, pieces, must, set(cuts))
        result.recoverable += len(deliverable)
        result.recovered += sum(all(k in got for k in batch.frames[i].keys) for i in deliverable)
    result.seconds = time.perf_counter() - started
    return result


def _kind(key: Hashable) -> str:
    if isinstance(key, tuple) and key and isinstance(key[0], str):
        return key[0]
    return type(key).__name__


def _deliverable(target: Target, batch: Batch, pieces: list[_Piece], must: set[int],
                 cuts: set[int]) -> set[int]:
    """The frames of ``must`` the protocol can deliver from this stream."""
    out = set()
    for j, p in enumerate(pieces):
        if p.frame is None or p.frame not in must:
            continue
        if target.datagrams and any(p.start < c < p.start + len(p.data) for c in cuts):
            continue  # cut in two datagrams: lost by design
        if target.lines and j and not pieces[j - 1].data.endswith((b"\n", b"\r")):
            continue  # the damage before it did not end its line: the line is another one
        if target.needs_successor:
            nxt = pieces[j + 1] if j + 1 < len(pieces) else None
            if nxt is None:
                if not batch.trailer or p.frame != len(batch.frames) - 1:
                    continue
            elif nxt.frame != p.frame + 1:
                continue  # its successor was damaged (a copy of itself makes no successor either)
        out.add(p.frame)
    return out  # a duplicate counts once: with replay protection its second copy is refused


# --- VESC -------------------------------------------------------------------------------------

#: After the last frame: enough bytes to complete any false frame a damaged length started, none
#: of them a start byte. (Zeros would not do: an all-zero payload has CRC 0x0000, so a false frame
#: filled with zeros can pass, as line noise can on a real link: the driver refuses FW 0.0.)
FLUSH = b"\xff" * 600


def _vesc_values(rng: random.Random) -> vc.Values:
    return vc.Values(temp_fet=rng.randint(0, 900) / 10, temp_motor=rng.randint(0, 900) / 10,
                     current_motor=rng.randint(-5000, 5000) / 100, duty=rng.randint(-950, 950) / 1000,
                     erpm=rng.randint(-30000, 30000), v_in=rng.randint(60, 600) / 10,
                     tachometer=rng.randint(-10**6, 10**6), status=rng.randint(0, 3))


def _vesc_imu(rng: random.Random) -> vc.ImuData:
    """An IMU reply with a random mask, every value exact in float32 (as the wire carries it)."""
    mask = rng.randint(1, vc.IMU_MASK_ALL)
    return vc.ImuData(**{name: rng.randint(-2**20, 2**20) / 1024 for i, name in enumerate(vc.IMU_FIELDS)
                         if mask >> i & 1})


def vesc_replies() -> Target:
    """Device -> host: GET_VALUES (6.2 layout), IMU and FW_VERSION replies into the driver's codec."""
    device = vc.VescCodec(vc.Role.DEVICE, (6, 2))

    def batch(rng: random.Random) -> Batch:
        frames = []
        for _ in range(16):
            roll = rng.random()
            packet = (_vesc_values(rng) if roll < 0.7 else _vesc_imu(rng) if roll < 0.9
                      else vc.FwVersion(rng.randint(2, 7), rng.randint(0, 99), "60", rng.randbytes(12)))
            frames.append(Frame(device.send(packet), (_vesc_key(packet),)))
        return Batch(frames, FLUSH)

    def decode(chunks: list[bytes]) -> list[Hashable]:
        host = vc.VescCodec(vc.Role.HOST, (6, 2))
        out: list[Hashable] = []
        for c in chunks:
            host.receive_data(c)
            out.extend(_vesc_key(p) for p in host.events() if not isinstance(p, vc.RawPacket))
        return out

    return Target("VESC replies", batch, decode)


def _vesc_key(packet: Any) -> Hashable:
    if isinstance(packet, vc.Values):  # as the wire carries it (scaled integers)
        return ("values", vc.encode_values(packet, vc.Layout.V5_03))
    return packet


def vesc_requests() -> Target:
    """Host -> device: motor, servo and poll commands into the fake VESC's codec."""
    host = vc.VescCodec(vc.Role.HOST)

    def batch(rng: random.Random) -> Batch:
        frames = []
        for _ in range(16):
            packet = rng.choice([
                vc.SetRpm(rng.randint(-30000, 30000)), vc.SetServoPosition(rng.randint(0, 1000) / 1000),
                vc.SetCurrentBrake(rng.randint(0, 20000) / 1000),
                vc.SetCurrent(rng.randint(-9000, 9000) / 1000),
                vc.SetDuty(rng.randint(-95000, 95000) / 1e5), vc.GetValuesRequest(), vc.Alive(),
                vc.FwVersionRequest(), vc.GetImuDataRequest(rng.randint(0, vc.IMU_MASK_ALL))])
            frames.append(Frame(host.send(packet), (packet,)))
        return Batch(frames, FLUSH)

    def decode(chunks: list[bytes]) -> list[Hashable]:
        device = vc.VescCodec(vc.Role.DEVICE)
        out: list[Hashable] = []
        for c in chunks:
            device.receive_data(c)
            out.extend(p for p in device.events() if not isinstance(p, vc.RawPacket))
        return out

    return Target("VESC requests", batch, decode)


# --- SCIP -------------------------------------------------------------------------------------


def scip_replies() -> Target:
    """Device -> host: scans (MD, GE), TM1, %ST, VV and QT replies into the host decoder."""

    def batch(rng: random.Random) -> Batch:
        frames = []
        for _ in range(8):
            r = rng.random()
            tag = "".join(rng.choices("abcxyz", k=rng.randint(0, 4)))
            if r < 0.5:
                n = rng.randint(1, 400)
                req = scip.ScanCommand(name="MD", start=0, end=n - 1, cluster=1, tag=tag)
                dist = np.array([rng.randint(0, 30000) for _ in range(n)])
                data = scip.encode_scan(req.echo(rng.randint(0, 99)), "99", rng.randint(0, 2**24 - 1), dist)
            elif r < 0.6:
                n = rng.randint(1, 100)
                req = scip.ScanCommand(name="GE", start=0, end=n - 1, cluster=1, tag=tag)
                values = np.array([rng.randint(0, 30000) for _ in range(2 * n)])
                data = scip.encode_scan(req.line, "00", rng.randint(0, 2**24 - 1), values[::2], values[1::2])
            elif r < 0.7:
                data = scip.encode_time("TM1" + (f";{tag}" if tag else ""), rng.randint(0, 2**24 - 1))
            elif r < 0.8:
                data = scip.encode_state("%ST", f"{rng.randint(0, 999):03d}")
            elif r < 0.9:
                data = scip.encode_info("VV", {"VEND": "Hokuyo", "PROD": f"UST-{rng.randint(1, 99)}LX",
                                               "SERI": f"H{rng.randint(0, 10**7)}"})
            else:
                data = scip.encode_reply("QT" + (f";{tag}" if tag else ""), "00")
            frames.append(Frame(data, tuple(_scip_keys(_scip_decode([data])))))
        return Batch(frames, b"\n\n")

    return Target("SCIP replies", batch, lambda chunks: list(_scip_keys(_scip_decode(chunks))))


def _scip_decode(chunks: Iterable[bytes]) -> list[scip.Event]:
    d = scip.ResponseDecoder()
    out: list[scip.Event] = []
    for c in chunks:
        d.receive_data(c)
        out.extend(d)
    return out


def _scip_keys(events: Iterable[scip.Event]) -> Iterable[Hashable]:
    for e in events:
        if isinstance(e, scip.DecodeError):
            continue
        if isinstance(e, scip.ScanReply):  # what reaches the motor: geometry, time and data
            inten = None if e.intensities is None else e.intensities.tobytes()
            r = e.request  # the echo's tag, interval and remaining count are not checksummed
            yield ("scan", r.name, r.start, r.end, r.cluster, e.timestamp_ms, e.distances.tobytes(), inten)
        elif isinstance(e, scip.InfoReply):
            yield ("info", e.echo, e.status, tuple(sorted(e.fields.items())))
        else:
            yield e


def scip_commands() -> Target:
    """Host -> device: command lines into the fake Hokuyo's decoder (SCIP commands carry no
    checksum: a damaged line may read as another command, so nothing counts as invented here)."""

    def batch(rng: random.Random) -> Batch:
        frames = []
        for _ in range(16):
            r = rng.random()
            if r < 0.5:
                start = rng.randint(0, 500)
                cmd: scip.Command = scip.ScanCommand(name=rng.choice(scip.SCAN_KINDS), start=start,
                                                     end=start + rng.randint(0, 580),
                                                     cluster=rng.randint(0, 99), interval=rng.randint(0, 9),
                                                     count=rng.randint(0, 99))
            elif r < 0.7:
                cmd = scip.TimeCommand(code=rng.randint(0, 2))
            else:
                cmd = scip.Command(rng.choice(scip.SIMPLE_COMMANDS),
                                   "".join(rng.choices("abc123", k=rng.randint(0, 5))))
            frames.append(Frame(cmd.encode(), (scip.parse_command(cmd.line),)))
        return Batch(frames, b"\n")

    def decode(chunks: list[bytes]) -> list[Hashable]:
        d = scip.CommandDecoder()
        out: list[Hashable] = []
        for c in chunks:
            d.receive_data(c)
            out.extend(e for e in d if not isinstance(e, (scip.UnknownCommand, scip.InvalidCommand)))
        return out

    return Target("SCIP commands", batch, decode, lines=True)


# --- RPLIDAR ----------------------------------------------------------------------------------


def rplidar_responses() -> Target:
    """Device -> host: GET_INFO, GET_HEALTH, GET_SAMPLERATE and GET_ACC_BOARD_FLAG answers.
    (No checksum: a payload is the bytes its descriptor announces, so damage can pass.)"""

    def batch(rng: random.Random) -> Batch:
        frames = []
        for _ in range(12):
            r = rng.random()
            if r < 0.25:
                event: rp.Event = rp.DeviceInfo(rng.randint(0, 255), rng.randint(0, 3), rng.randint(0, 99),
                                                rng.randint(0, 9), rng.randbytes(16))
                data = rp.encode_info(event)
            elif r < 0.5:
                event = rp.Health(rng.randint(0, 2), rng.randint(0, 65535))
                data = rp.encode_health(event)
            elif r < 0.75:
                event = rp.SampleRate(rng.randint(50, 1000), rng.randint(50, 1000))
                data = rp.encode_samplerate(event)
            else:
                event = rp.AccBoardFlag(rng.randint(0, 1))
                data = rp.encode_acc_board_flag(event)
            frames.append(Frame(data, (event,)))
        return Batch(frames, bytes(80))  # the longest answer the decoder accepts is 64 bytes

    def decode(chunks: list[bytes]) -> list[Hashable]:
        client = rp.RplidarClient()
        out: list[Hashable] = []
        for c in chunks:
            client.receive_data(c)
            out.extend(client.events())
        return out

    return Target("RPLIDAR responses", batch, decode)


def _samples(events: Iterable[Any]) -> list[Hashable]:
    out: list[Hashable] = []
    for m in events:
        if isinstance(m, rp.Measurements):
            out.extend(zip(np.round(m.angle_deg * 64).astype(int).tolist(), m.distance_mm.tolist(),
                           strict=True))
    return out


def rplidar_nodes() -> Target:
    """Device -> host: standard scan nodes (units of 8) after the SCAN descriptor. Nodes carry
    only check bits, so damage can pass; the decoder re-locks after 4 plausible nodes."""

    def batch(rng: random.Random) -> Batch:
        n = 8 * 13
        angle0 = rng.uniform(0, 360)
        angle = (angle0 + np.arange(n) * 0.9) % 360.0
        dist = np.array([rng.randint(1, 16000) for _ in range(n)], dtype=float)
        data = rp.encode_nodes(np.zeros(n, bool), np.full(n, 47), angle, dist)
        q6 = np.round(np.mod(angle, 360.0) * 64).astype(int) % rp.FULL_TURN_Q6
        keys = list(zip(q6.tolist(), dist.tolist(), strict=True))
        frames = [Frame(data[u * 40:(u + 1) * 40], tuple(keys[u * 8:(u + 1) * 8])) for u in range(12)]
        return Batch(frames, data[12 * 40:], tuple(keys[12 * 8:]))

    def decode(chunks: list[bytes]) -> list[Hashable]:
        client = rp.RplidarClient()
        client.send(rp.Request.simple(rp.Command.SCAN))
        client.receive_data(rp.encode_scan_descriptor(False))
        for c in chunks:
            client.receive_data(c)
        return _samples(client.events())

    return Target("RPLIDAR nodes", batch, decode)


def rplidar_capsules() -> Target:
    """Device -> host: express capsules after the EXPRESS_SCAN descriptor (XOR checksum, and the
    start-angle step between neighbours). A capsule is decoded with its successor."""

    def batch(rng: random.Random) -> Batch:
        k = 14
        step = rng.uniform(15.0, 40.0)
        starts = (rng.uniform(0, 360) + np.arange(k) * step) % 360.0
        dist = np.array([rng.randint(1, 16000) for _ in range(k * 32)], dtype=float)
        data = rp.encode_capsules(starts, dist)
        caps = np.frombuffer(data, np.uint8).reshape(k, rp.CAPSULE_LEN)
        keys = _samples([rp.decode_capsules(caps)])
        frames = [Frame(data[i * 84:(i + 1) * 84], tuple(keys[i * 32:(i + 1) * 32])) for i in range(k - 2)]
        # the trailer: the last frame's successor, and one more for it
        return Batch(frames, data[(k - 2) * 84:], tuple(keys[(k - 2) * 32:]))

    def decode(chunks: list[bytes]) -> list[Hashable]:
        client = rp.RplidarClient()
        client.send(rp.Request.express_scan())
        client.receive_data(rp.encode_scan_descriptor(True))
        for c in chunks:
            client.receive_data(c)
        return _samples(client.events())

    return Target("RPLIDAR capsules", batch, decode, needs_successor=True)


def rplidar_requests() -> Target:
    """Host -> device: requests into the fake RPLIDAR's parser (only requests with a payload carry
    a checksum)."""
    simple = [rp.Command.STOP, rp.Command.RESET, rp.Command.SCAN, rp.Command.FORCE_SCAN,
              rp.Command.GET_INFO, rp.Command.GET_HEALTH, rp.Command.GET_SAMPLERATE]

    def batch(rng: random.Random) -> Batch:
        frames = []
        for _ in range(16):
            r = rng.random()
            if r < 0.5:
                req = rp.Request.simple(rng.choice(simple))
            elif r < 0.7:
                req = rp.Request.express_scan(rng.randint(0, 3))
            elif r < 0.9:
                req = rp.Request.set_motor_pwm(rng.randint(0, 1023))
            else:
                req = rp.Request(rp.Command.GET_LIDAR_CONF, rng.randbytes(rng.randint(4, 8)))
            frames.append(Frame(req.encode(), (req,)))
        return Batch(frames, bytes(260))  # a false payload length waits for at most 259 bytes

    def decode(chunks: list[bytes]) -> list[Hashable]:
        parser = rp.RequestParser()
        out: list[Hashable] = []
        for c in chunks:
            out.extend(parser.receive_data(c))
        return out

    return Target("RPLIDAR requests", batch, decode)


# --- MAVLink ----------------------------------------------------------------------------------


class _Pack:
    def __init__(self, key: bytes | None) -> None:
        self.out: list[bytes] = []
        self.mav = mavlink.MAVLink(self, 255, 190)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.timestamp = 10**12
            self.mav.signing.sign_outgoing = True

    def write(self, data: bytes) -> None:
        self.out.append(bytes(data))


def mavlink_inbound(signed: bool) -> Target:
    """Ground station -> car: datagrams into :class:`MavlinkRx` (CRC with CRC_EXTRA; signed:
    the cheap refusal of unsigned and forged single frames, SHA-256 signatures, per-stream
    timestamps, so a repeated frame is refused, and the future-timestamp window)."""
    key = bytes(range(32)) if signed else None

    def batch(rng: random.Random) -> Batch:
        pack = _Pack(key)
        m = pack.mav
        for _ in range(10):
            r = rng.random()
            if r < 0.3:
                m.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            elif r < 0.55:
                m.manual_control_send(1, rng.randint(-1000, 1000), rng.randint(-1000, 1000),
                                      rng.randint(-1000, 1000), 0, 0)
            elif r < 0.7:
                m.rc_channels_override_send(1, 1, *(rng.randint(1000, 2000) for _ in range(8)))
            elif r < 0.9:
                m.command_long_send(1, 1, rng.choice([400, 176, 512, 520]), 0,
                                    *(rng.uniform(-1e3, 1e3) for _ in range(7)))
            else:
                m.param_request_list_send(1, 1)
        return Batch([Frame(b, (b,)) for b in pack.out])

    def decode(chunks: list[bytes]) -> list[Hashable]:
        # as MavlinkGcs.handle_datagram: the cheap refusal first, then the decoder, on a clock at
        # the frames' own time with the default 60 s future window
        rx = MavlinkRx(key, 10**12 - 1000, future_window=60 * 100_000)
        return [bytes(msg.get_msgbuf()) for c in chunks if not rx.refuse_cheaply(c)
                for msg in rx.decode(c, 10**12)]

    name = "MAVLink inbound, signed" if signed else "MAVLink inbound"
    return Target(name, batch, decode, datagrams=True)


def wire_targets() -> list[Target]:
    """Every wire parser, in the order of the benchmark table."""
    return [vesc_replies(), vesc_requests(), scip_replies(), scip_commands(), rplidar_responses(),
            rplidar_nodes(), rplidar_capsules(), rplidar_requests(), mavlink_inbound(False),
            mavlink_inbound(True)]


# --- bags -------------------------------------------------------------------------------------


TOPIC = "/vesc/low_level/ackermann_cmd_mux/input/teleop"
BAG_FORMATS = ("ros1", "mcap", "sqlite3")


def write_bag(path: Path, fmt: str, commands: Sequence[tuple[int, float, float]], topic: str = TOPIC,
              stamped: bool = True, chunked: bool = True) -> Path:
    """An Ackermann bag of ``commands`` (t_ns, speed m/s, steering rad) on ``topic``, written with
    rosbags: AckermannDriveStamped, or AckermannDrive if not ``stamped``. ``chunked``: ROS 1 with
    bz2 chunks of a few messages, so a file holds several chunks. MCAP as the recorder writes it
    (chunks with their CRC-32: :class:`racecar_hw.bags.writers.Ros2Bag`)."""
    from rosbags.rosbag1 import Writer as Writer1

    from racecar_hw.bags.writers import Ros2Bag
    from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time
    from racecar_hw.rosmsg.typestore import ros1_types, ros2_types

    def msg(speed: float, steer: float) -> AckermannDrive | AckermannDriveStamped:
        drive = AckermannDrive(steering_angle=steer, speed=speed)
        return AckermannDriveStamped(Header(Time(1, 0), "base_link"), drive) if stamped else drive

    ros_type = msg(0.0, 0.0).ROS_TYPE
    if fmt == "ros1":
        types = ros1_types()
        w1 = Writer1(path)
        if chunked:
            w1.set_compression(Writer1.CompressionFormat.BZ2)
            w1.chunk_threshold = 512
        with w1:
            conn = w1.add_connection(topic, ros_type, typestore=types.store)
            for t, speed, steer in commands:
                w1.write(conn, t, types.serialize(msg(speed, steer)))
        return path
    types = ros2_types()
    with Ros2Bag(path, fmt) as w2:
        cid = w2.add_connection(topic, ros_type, types.msgdef(ros_type), types.digest(ros_type), "")
        for t, speed, steer in commands:
            w2.write(cid, t, types.serialize(msg(speed, steer)))
    return path


def _storage_file(bag: Path) -> Path:
    return bag if bag.is_file() else next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))


def _mutate_file(rng: random.Random, data: bytes) -> tuple[str, bytes]:
    kind = rng.choice(("random_bytes", "bit_flips", "truncation", "duplication", "garbage_between"))
    n = len(data)
    if kind == "random_bytes":
        at, span = rng.randrange(n), rng.randint(1, 64)
        return kind, data[:at] + rng.randbytes(span) + data[at + span:]
    if kind == "bit_flips":
        out = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            out[rng.randrange(n)] ^= 1 << rng.randrange(8)
        return kind, bytes(out)
    if kind == "truncation":
        return kind, data[:rng.randrange(n)]
    if kind == "duplication":
        at, span = rng.randrange(n), rng.randint(1, 256)
        return kind, data[:at + span] + data[at:]
    at = rng.randrange(n)
    return kind, data[:at] + rng.randbytes(rng.randint(1, 64)) + data[at:]


@dataclass
class BagFuzz:
    """Counters of a bag fuzz run; ``absurd``: loads that returned a command that is not finite or
    beyond the limits (must be 0); ``loaded``: damaged bags that still loaded (altered or not)."""

    result: FuzzResult
    loaded: int = 0
    refused: int = 0
    absurd: int = 0
    mutations: Counter[str] = field(default_factory=Counter)
    #: loads whose commands differ from the undamaged bag's, by (format, mutation): damage that
    #: went unseen (an MCAP chunk's CRC-32 catches it)
    differed: Counter[tuple[str, str]] = field(default_factory=Counter)


def fuzz_bags(workdir: Path, frames: int, seed: int = 0, max_message_bytes: int = 1 << 20) -> BagFuzz:
    """Load ``frames`` damaged bags (the three formats in turn) with the follower's loader and the
    car's default limits (5 m/s, 0.26 rad); only BagError may escape."""
    from racecar_hw.bags.follow import load_commands
    from racecar_hw.bags.validate import CommandLimits

    limits = CommandLimits(5.0, 0.26)
    rng = random.Random(seed)
    fuzz = BagFuzz(FuzzResult("bag loading"))
    originals: dict[str, tuple[Path, bytes]] = {}
    expected: dict[str, list[tuple[int, float, float]]] = {}
    for fmt in BAG_FORMATS:
        commands = [(1_700_000_000 * 10**9 + i * 50_000_000, rng.uniform(-4.0, 4.0), rng.uniform(-0.25, 0.25))
                    for i in range(40)]
        bag = write_bag(workdir / (f"original-{fmt}" + (".bag" if fmt == "ros1" else "")), fmt, commands)
        originals[fmt] = (bag, _storage_file(bag).read_bytes())
        expected[fmt] = [(c.t_ns, c.drive.speed, c.drive.steering_angle)
                         for c in load_commands(bag, TOPIC, limits=limits)]
    target = workdir / "damaged"
    started = time.perf_counter()
    result = fuzz.result
    while result.frames < frames:
        fmt = BAG_FORMATS[result.frames % len(BAG_FORMATS)]
        bag, data = originals[fmt]
        kind, damaged = _mutate_file(rng, data)
        fuzz.mutations[kind] += 1
        path = _place(target, bag, fmt, damaged)
        result.frames += 1
        try:
            got = load_commands(path, TOPIC, limits=limits, max_message_bytes=max_message_bytes)
        except BagError:
            fuzz.refused += 1
            continue
        except Exception as err:  # noqa: BLE001 - counting what escapes is the point
            result.escaped[type(err).__name__] += 1
            if len(result.examples) < 3:
                result.examples.append(f"{fmt} {kind}: " + "".join(traceback.format_exception(err)))
            continue
        fuzz.loaded += 1
        if [(c.t_ns, c.drive.speed, c.drive.steering_angle) for c in got] != expected[fmt]:
            fuzz.differed[(fmt, kind)] += 1
        bad = [c for c in got if not (math.isfinite(c.drive.speed) and math.isfinite(c.drive.steering_angle)
                                      and abs(c.drive.speed) <= 5.0 and abs(c.drive.steering_angle) <= 0.26)]
        fuzz.absurd += bool(bad)
    result.seconds = time.perf_counter() - started
    result.invented = fuzz.absurd
    return fuzz


def _place(target: Path, original: Path, fmt: str, data: bytes) -> Path:
    """Write ``data`` as the storage file of a bag like ``original`` under ``target``."""
    import shutil

    if fmt == "ros1":
        target.mkdir(parents=True, exist_ok=True)
        path = target / "damaged.bag"
        path.write_bytes(data)
        return path
    bag = target / fmt
    if not bag.exists():
        shutil.copytree(original, bag)
    _storage_file(bag).write_bytes(data)
    for journal in bag.glob("*-journal"):
        journal.unlink()
    return bag


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The fuzz table: parser, frames, escaped exceptions, recovery rate, invented, throughput."""
    lines = [f"{'parser':26} {'frames':>9} {'escaped':>8} {'recovery':>9} {'invented':>9} {'frames/s':>10}"]
    for r in rows:
        rec = "-" if math.isnan(r["recovery"]) else f"{r['recovery']:.4f}"
        lines.append(f"{r['parser']:26} {r['frames']:9d} {r['escaped']:8d} {rec:>9} {r['invented']:9d} "
                     f"{r['frames/s']:10.0f}")
    return "\n".join(lines)


__all__ = ["MUTATIONS", "BagFuzz", "FuzzResult", "Target", "format_table", "fuzz_bags", "run",
           "wire_targets", "write_bag"]
