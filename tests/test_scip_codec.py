"""The SCIP 2.0 codec: spec examples, round trips, fragments, garbage and fuzzing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from lidar_drivers.scip import (
    ChecksumMismatch,
    Command,
    CommandDecoder,
    InfoReply,
    InvalidCommand,
    MalformedResponse,
    ResponseDecoder,
    ScanCommand,
    ScanReply,
    SensorParams,
    StateReply,
    StatusReply,
    TimeCommand,
    TimeReply,
    UnknownCommand,
    checksum,
    data_lines,
    decode_int,
    decode_values,
    encode_info,
    encode_int,
    encode_reply,
    encode_scan,
    encode_state,
    encode_time,
    encode_values,
    is_hardware_fault,
    join_data_lines,
    parse_command,
    status_meaning,
)
from racecar_hw.base.errors import LocalProtocolError, RemoteProtocolError

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

GD_EXCHANGE = (b"GD0540056101\n00P\n018dm\n"
               b"0H40H50H60H70H80H90H:0H;0H<0H=0H>0H?0H@0HA0HB0HC0HD0HE0HF0HG0HH0N\nHIA\n\n")


def decode_all(*chunks: bytes) -> list:
    d = ResponseDecoder()
    out = []
    for c in chunks:
        d.receive_data(c)
        out.extend(d)
    return out


def md_frame(values: list[int], remaining: int = 0, tag: str = "", stamp: int = 4660) -> bytes:
    req = ScanCommand(name="MD", start=0, end=len(values) - 1, cluster=1, tag=tag)
    return encode_scan(req.echo(remaining), "99", stamp, np.array(values))


# --- spec examples --------------------------------------------------------------------------


def test_character_encoding_spec_examples():
    assert encode_int(1234, 2) == b"CB"
    assert encode_int(5432, 3) == b"1Dh"
    assert encode_int(16000000, 4) == b"m2@0"
    assert decode_int(b"CB") == 1234 and decode_int(b"1Dh") == 5432 and decode_int(b"m2@0") == 16000000
    with pytest.raises(LocalProtocolError):
        encode_int(4096, 2)
    with pytest.raises(ValueError):
        decode_int(b"0\x7f")


@pytest.mark.parametrize(("line", "expected"), [
    (b"DMIN:20", "4"), (b"AMIN:44", "7"), (b"SCAN:600", "e"), (b"00", "P"), (b"99", "b"),
    (b"0E", "e")])
def test_checksum_table(line, expected):
    assert chr(checksum(line)) == expected


def test_worked_gd_exchange_with_a_straddling_value():
    [reply] = decode_all(GD_EXCHANGE)
    assert isinstance(reply, ScanReply)
    assert reply.command == "GD" and reply.status == "00" and reply.ok
    assert reply.request == ScanCommand(name="GD", start=540, end=561, cluster=1)
    assert reply.timestamp_ms == 4660
    assert reply.distances.tolist() == list(range(1540, 1562))
    assert reply.intensities is None
    assert reply.nbytes == len(GD_EXCHANGE)
    # the device side produces the same bytes
    assert encode_scan("GD0540056101", "00", 4660, np.arange(1540, 1562)) == GD_EXCHANGE


def test_worked_md_exchange_with_a_tag():
    cmd = ScanCommand(name="MD", start=540, end=543, cluster=1, interval=0, count=2, tag="abc")
    assert cmd.encode() == b"MD0540054301002;abc\n"
    assert encode_reply(cmd.line, "00") == b"MD0540054301002;abc\n00P\n\n"
    frame = encode_scan(cmd.echo(1), "99", decode_int(b"019="), np.array([1000, 1001, 1002, 1003]))
    assert frame == b"MD0540054301001;abc\n99b\n019=G\n0?X0?Y0?Z0?[R\n\n"
    ack, first = decode_all(b"MD0540054301002;abc\n00P\n\n" + frame)
    assert isinstance(ack, StatusReply) and ack.echo == cmd.line and ack.tag == "abc"
    assert isinstance(first, ScanReply) and first.request.count == 1 and first.tag == "abc"
    assert first.distances.tolist() == [1000, 1001, 1002, 1003]


# --- replies of every command ----------------------------------------------------------------


def test_info_replies_exclude_the_semicolon_from_the_checksum():
    raw = encode_info("PP", {"MODL": "URG-04LX", "DMIN": 20, "SCAN": 600})
    assert b"DMIN:20;4\n" in raw and b"SCAN:600;e\n" in raw
    [pp] = decode_all(raw)
    assert isinstance(pp, InfoReply) and pp.command == "PP"
    assert dict(pp.fields) == {"MODL": "URG-04LX", "DMIN": "20", "SCAN": "600"}
    vv, ii = decode_all(encode_info("VV", {"VEND": "Hokuyo", "FIRM": "1.0"}),
                        encode_info("II", {"STAT": "ok"}))
    assert vv.fields["FIRM"] == "1.0" and ii.fields["STAT"] == "ok"


@pytest.mark.parametrize("cmd", [Command("BM"), Command("QT"), Command("RS"), Command("RT"),
                                 TimeCommand(code=0), TimeCommand(code=2)])
def test_status_only_replies(cmd):
    [reply] = decode_all(encode_reply(cmd.line, "00"))
    assert isinstance(reply, StatusReply) and reply.command == cmd.body and reply.ok


def test_time_and_state_replies():
    tm1, state = decode_all(encode_time("TM1", 16000000 + (1 << 24)), encode_state("%ST", "004"))
    assert isinstance(tm1, TimeReply) and tm1.time_ms == 16000000  # 24-bit counter wraps
    assert isinstance(state, StateReply) and state.state == "004"


def test_me_frame_carries_intensities():
    req = ScanCommand(name="ME", start=10, end=40, cluster=1)
    dist = np.arange(31) * 1000 + 20
    inten = np.arange(31) * 7
    [frame] = decode_all(encode_scan(req.echo(0), "99", 5, dist, inten))
    assert frame.request.intensities and frame.distances.tolist() == dist.tolist()
    assert frame.intensities.tolist() == inten.tolist()


def test_gs_uses_two_characters_and_cluster_counts_groups():
    req = ScanCommand(name="GS", start=0, end=9, cluster=3)
    assert req.values == 4
    [frame] = decode_all(encode_scan(req.line, "00", 0, np.array([1, 4095, 300, 20]), width=2))
    assert frame.distances.tolist() == [1, 4095, 300, 20]


@pytest.mark.parametrize(("command", "status", "words"), [
    ("MD", "00", "ok"), ("MD", "99", "streaming"), ("XX", "0E", "unknown command"),
    ("GD", "10", "laser is off"), ("MD", "04", "end step out of range"),
    ("MD", "05", "smaller than start"), ("BM", "02", "already on"),
    ("TM1", "04", "TM1 outside"), ("MD", "55", "hardware fault"), ("MD", "30", "processing stopped"),
    ("GD", "07", "number of scans")])
def test_status_meanings(command, status, words):
    assert words in status_meaning(command, status)


def test_error_statuses_reach_the_host_with_their_meaning():
    unknown, laser_off, fault = decode_all(encode_reply("XY", "0E"),
                                           encode_reply("GD0000108001", "10"),
                                           encode_reply("MD0000108001000", "52"))
    assert unknown.command == "XY" and not unknown.ok and unknown.meaning == "unknown command"
    assert laser_off.command == "GD" and laser_off.meaning == "laser is off"
    assert is_hardware_fault(fault.status) and "hardware fault" in fault.meaning


# --- commands, both directions ------------------------------------------------------------------


ALL_COMMANDS = [Command("VV"), Command("PP"), Command("II"), Command("BM"), Command("QT"),
                Command("RS"), Command("%ST"), TimeCommand(code=0), TimeCommand(code=1),
                TimeCommand(code=2), ScanCommand(name="GD", start=44, end=725, cluster=1),
                ScanCommand(name="MD", start=0, end=1080, cluster=3, interval=2, count=5),
                ScanCommand(name="ME", start=0, end=1080, cluster=1, tag="hello")]


@pytest.mark.parametrize("cmd", ALL_COMMANDS, ids=lambda c: c.line)
def test_commands_round_trip_through_the_device_decoder(cmd):
    dec = CommandDecoder()
    dec.receive_data(cmd.encode())
    assert list(dec) == [cmd]


def test_command_line_ends_lf_cr_crlf_in_fragments():
    dec = CommandDecoder()
    for b in b"VV\rPP\r\nII\n\nQT;x\n":
        dec.receive_data(bytes([b]))
    assert [c.line for c in dec] == ["VV", "PP", "II", "QT;x"]


@pytest.mark.parametrize(("line", "status"), [
    ("MD00x0108001000", "01"), ("MD0000x08001000", "02"), ("MD000010800x000", "03"),
    ("MD0000108001x00", "06"), ("MD000010800100x", "07"), ("GD0100000001", "05"),
    ("GD000010", "0H"), ("GD00001080011", "0D"), ("TM7", "01"), ("VV;" + "x" * 17, "0G")])
def test_bad_parameters_give_the_spec_status(line, status):
    cmd = parse_command(line)
    assert isinstance(cmd, InvalidCommand) and cmd.status == status


def test_unknown_commands_and_refused_encodings():
    assert isinstance(parse_command("XX"), UnknownCommand)
    with pytest.raises(LocalProtocolError):
        Command("VV", tag="x" * 17).encode()
    with pytest.raises(LocalProtocolError):
        TimeCommand(code=3).encode()
    with pytest.raises(LocalProtocolError):
        ScanCommand(name="MD", start=0, end=10, interval=10).encode()


# --- data lines ----------------------------------------------------------------------------------


def test_data_lines_are_64_characters_with_their_own_checksum():
    payload = encode_values(np.arange(100) * 300, 3)  # 300 characters: 4 full lines + 44
    framed = data_lines(payload)
    lines = framed.rstrip(b"\n").split(b"\n")
    assert [len(line) for line in lines] == [65, 65, 65, 65, 45]
    assert all(checksum(line[:-1]) == line[-1] for line in lines)
    joined = join_data_lines(framed[:-1])
    assert joined.tobytes() == payload
    assert decode_values(joined, 3).tolist() == (np.arange(100) * 300).tolist()


@given(st.integers(2, 4).flatmap(lambda w: st.tuples(
    st.just(w), st.lists(st.integers(0, (1 << (6 * w)) - 1), min_size=1, max_size=400))))
def test_values_round_trip(case):
    width, values = case
    for v in values[:3]:
        assert decode_int(encode_int(v, width)) == v
    payload = data_lines(encode_values(np.array(values), width))
    assert decode_values(join_data_lines(payload[:-1]), width).tolist() == values


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=3000).map(lambda b: bytes(0x30 + (c & 0x3F) for c in b)))
def test_every_data_line_carries_the_checksum_of_its_characters(payload):
    framed = data_lines(payload)
    lines = framed.split(b"\n")[:-1] if payload else []
    assert [line[:-1] for line in lines] == [payload[k:k + 64] for k in range(0, len(payload), 64)]
    assert [line[-1] for line in lines] == [checksum(line[:-1]) for line in lines]
    assert framed == b"".join(line + b"\n" for line in lines)


@settings(max_examples=100, deadline=None)
@given(st.integers(2, 4).flatmap(lambda w: st.tuples(
    st.just(w), st.lists(st.tuples(st.integers(0, (1 << (6 * w)) - 1), st.integers(0, (1 << (6 * w)) - 1)),
                         max_size=600))))
def test_a_frame_with_intensities_holds_distance_intensity_pairs_in_turn(case):
    width, pairs = case
    dist = np.array([d for d, _ in pairs], dtype=np.int64)
    inten = np.array([i for _, i in pairs], dtype=np.int64)
    flat = np.array([v for pair in pairs for v in pair], dtype=np.int64)
    assert encode_scan("ME0000108001000", "99", 5, dist, inten, width) == encode_scan(
        "ME0000108001000", "99", 5, flat, None, width)


def test_distances_and_intensities_that_do_not_pair_up_are_refused():
    with pytest.raises(ValueError, match="do not pair up"):
        encode_scan("ME0000000201000", "99", 5, np.arange(3), np.arange(2))


# --- robustness: fragments, line ends, garbage, bad checksums -----------------------------------


@given(st.lists(st.integers(0, 65535), min_size=1, max_size=1200), st.data())
@settings(max_examples=60, deadline=None)
def test_frames_decode_in_any_fragmentation(values, data):
    raw = md_frame(values) * 2
    cuts = sorted(data.draw(st.lists(st.integers(0, len(raw)), max_size=30)))
    chunks = [raw[a:b] for a, b in zip([0, *cuts], [*cuts, len(raw)], strict=True)]
    events = decode_all(*chunks)
    assert [e.distances.tolist() for e in events] == [values, values]


def test_crlf_line_ends_split_between_chunks():
    crlf = GD_EXCHANGE.replace(b"\n", b"\r\n")
    i = crlf.index(b"\r\n") + 1
    [reply] = decode_all(crlf[:i], crlf[i:])
    assert reply.distances.tolist() == list(range(1540, 1562))


def test_bad_checksum_is_counted_and_the_next_frame_survives():
    good = md_frame(list(range(100, 200)))
    bad = bytearray(good)
    i = bad.index(b"\n", len("MD0000009901000\n99b\n") + 6) - 1
    bad[i] = ((bad[i] - 0x30 + 1) & 0x3F) + 0x30
    d = ResponseDecoder()
    d.receive_data(bytes(bad) + good)
    first, second = list(d)
    assert isinstance(first, ChecksumMismatch) and d.checksum_errors == 1
    assert isinstance(second, ScanReply) and second.distances.tolist() == list(range(100, 200))


def test_garbage_before_a_reply_is_dropped_and_counted():
    d = ResponseDecoder()
    d.receive_data(b"\x00\xffnoise" + GD_EXCHANGE + b"junk\n\n" + GD_EXCHANGE)
    events = list(d)
    kinds = [type(e) for e in events]
    assert kinds == [MalformedResponse, ScanReply, MalformedResponse, ScanReply]
    assert events[0].raw == b"\x00\xffnoise" and d.resyncs == 2


def test_truncated_frames_are_error_events_not_exceptions():
    frame = md_frame(list(range(300)))
    whole_lines = frame[:frame.index(b"\n", 100) + 1] + b"\n"  # too few readings
    mid_line = frame[:200] + b"\n\n"  # the cut line fails its checksum
    short, cut = decode_all(whole_lines, mid_line)
    assert isinstance(short, MalformedResponse)
    assert isinstance(cut, ChecksumMismatch)


@pytest.mark.parametrize("readings", [150, 400])
def test_a_frame_of_the_wrong_length_says_how_many_readings_it_had(readings):
    """Whole lines, every checksum right, the wrong number of readings: the drop's reason says so
    (the driver's reconnect warning quotes it), not just "a damaged reply"."""
    echo = md_frame(list(range(300))).split(b"\n", 1)[0]  # asks for 300 readings
    body = md_frame(list(range(readings))).split(b"\n", 1)[1]
    (event,) = decode_all(echo + b"\n" + body)
    assert isinstance(event, MalformedResponse)
    assert event.reason == f"{readings} readings, expected 300"


def test_endless_noise_is_bounded():
    d = ResponseDecoder()
    for _ in range(5):
        d.receive_data(b"x" * 100_000)
        list(d)
    assert d.resyncs >= 1 and len(d._buf) < 300_000


@given(st.binary(max_size=3000))
@settings(max_examples=300, deadline=None)
def test_arbitrary_device_bytes_never_raise(blob):
    d = ResponseDecoder()
    for i in range(0, len(blob), 97):
        d.receive_data(blob[i:i + 97])
        for event in d:
            assert isinstance(event, (StatusReply, InfoReply, TimeReply, StateReply, ScanReply,
                                      ChecksumMismatch, MalformedResponse))
    d.receive_data(b"\n\n")
    list(d)


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_arbitrary_host_bytes_never_raise(blob):
    d = CommandDecoder()
    d.receive_data(blob + b"\n")
    for cmd in d:
        assert isinstance(cmd, (Command, UnknownCommand, InvalidCommand))


@given(st.lists(st.tuples(st.binary(max_size=80), st.lists(st.integers(0, 99999), min_size=1,
                                                            max_size=150)),
                min_size=1, max_size=6),
       st.booleans())
@settings(max_examples=150, deadline=None)
def test_valid_frames_inside_garbage_are_recovered(pieces, end_garbage_with_lf):
    """Garbage ending in a line break never costs a frame; garbage glued to the echo line (no ';'
    in it, so it cannot pose as a tag) is cut off by the resync search."""
    stream = b""
    expected = []
    for garbage, values in pieces:
        garbage = garbage + b"\n" if end_garbage_with_lf else garbage.replace(b";", b"")
        stream += garbage + md_frame(values, tag="t")
        expected.append(values)
    d = ResponseDecoder()
    for i in range(0, len(stream), 61):
        d.receive_data(stream[i:i + 61])
    got = [e.distances.tolist() for e in d if isinstance(e, ScanReply)]
    assert got == expected


@settings(max_examples=400, deadline=None)
@given(st.sampled_from([2, 3, 4]).flatmap(
           lambda w: st.tuples(st.just(w), st.lists(st.integers(0, 64**w - 1), max_size=200))),
       st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=3),
       st.booleans())
def test_fast_data_line_decoder_agrees_with_the_line_by_line_one(width_values, edits, drop):
    width, values = width_values
    from lidar_drivers.scip import (
        data_lines,
        decode_data_lines,
        decode_values,
        encode_values,
        join_data_lines,
    )

    region = bytearray(data_lines(encode_values(np.array(values, dtype=np.int64), width))[:-1])
    for pos, byte in edits:
        if region:
            region[pos % len(region)] = byte
    if drop and region:
        del region[len(region) // 2]
    region_b = bytes(region)
    fast = decode_data_lines(region_b, width)
    try:
        slow = decode_values(join_data_lines(region_b), width)
    except ValueError:
        slow = None
    if not edits and not drop and values:
        assert fast is not None  # clean lines always take the fast path
    if fast is not None:
        assert slow is not None and fast.dtype == np.float64 and np.array_equal(fast, slow)


# --- PP: sensor parameters ---------------------------------------------------------------------


def test_pp_reply_decodes_into_sensor_params_and_back():
    fields = {"MODL": "UST-10LX", "DMIN": 20, "DMAX": 30000, "ARES": 1440, "AMIN": 0, "AMAX": 1080,
              "AFRT": 540, "SCAN": 2400}
    reply = ResponseDecoder()
    reply.receive_data(encode_info("PP", fields))
    event = reply.next_event()
    assert isinstance(event, InfoReply)
    pp = SensorParams.from_fields(event.fields)
    assert pp == SensorParams("UST-10LX", 20, 30000, 1440, 0, 1080, 540, 2400)
    assert pp.fields() == fields
    assert pp.steps == 1081 and pp.scan_period_s == pytest.approx(0.025)
    assert pp.angle_of(540) == 0.0 and pp.angle_of(0) == pytest.approx(-0.75 * np.pi)
    assert pp.step_of(pp.angle_of(123)) == pytest.approx(123)


@given(st.dictionaries(st.sampled_from(["MODL", "DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT",
                                        "SCAN", "XXXX"]),
                       st.one_of(st.integers(-10**6, 10**6).map(str), st.text(max_size=6))))
@settings(max_examples=300)
def test_sensor_params_from_any_fields_is_a_record_or_a_named_error(fields):
    try:
        pp = SensorParams.from_fields(fields)
    except RemoteProtocolError as err:
        assert "PP reply" in str(err)
    else:
        assert pp.fields()["DMIN"] == int(fields["DMIN"])
        # a record is a sensor: its timing and angles compute
        assert math.isfinite(pp.scan_period_s) and pp.step_time_s > 0 and pp.steps >= 1
        assert math.isfinite(pp.angle_of(pp.amax)) and pp.angle_of(pp.afrt) == 0.0


def test_a_status_line_with_non_ascii_bytes_and_a_valid_checksum_is_an_event():
    """The generic (unknown command) path once decoded such a status as ASCII and raised."""
    status = bytes([0xB0, 0x41])
    events = decode_all(b"XX\n" + status + bytes([checksum(status)]) + b"\n\n")
    assert [type(e) for e in events] == [MalformedResponse]


REPLIES = [md_frame(list(range(100, 400)), tag="a"), encode_time("TM1", 123456), encode_reply("QT", "00"),
           encode_state("%ST", "004"), encode_info("VV", {"VEND": "Hokuyo", "PROD": "UST-10LX"}),
           md_frame([7] * 40, remaining=3)]


@given(st.sampled_from(REPLIES), st.sampled_from(REPLIES), st.floats(0.0, 1.0), st.integers(1, 97))
@settings(max_examples=400, deadline=None)
@example(REPLIES[0], REPLIES[2], 0.6, 1)  # cut in a data line
def test_a_damaged_reply_costs_itself_and_never_the_next_one(damaged, good, where, chunk):
    """Cut anywhere (down to missing only its final line feed), a reply runs into the next one;
    the decoder finds the next reply's echo and status and decodes it."""
    cut = damaged[:int(where * (len(damaged) - 1))]  # never the whole reply
    # cut inside its echo's tag (after the ';'), the next reply's echo line reads as the rest of that
    # tag: b"MD0000029901000;" + b"QT\n00P\n\n" is a whole, valid MD status reply with tag "QT"
    assume(not (b";" in cut and b"\n" not in cut))
    stream = cut + good
    d = ResponseDecoder()
    events = []
    for i in range(0, len(stream), chunk):
        d.receive_data(stream[i:i + chunk])
        events.extend(d)
    expected = decode_all(good)[0]
    decoded = [e for e in events if not isinstance(e, (MalformedResponse, ChecksumMismatch))]
    assert decoded[-1:] == [expected] or (isinstance(expected, ScanReply) and decoded
                                          and decoded[-1].distances.tolist() == expected.distances.tolist())
    assert len(decoded) <= 2  # at most the damaged one, when only its final line feed was missing


def test_a_reply_cut_inside_its_tag_and_the_next_echo_read_as_one_reply():
    """The one cut the test above leaves out: the bytes are a valid reply of their own (an MD
    acknowledgement whose tag is the next echo), and that is what they decode to, not an error."""
    stream = md_frame(list(range(100, 400)), tag="a")[:16] + encode_reply("QT", "00")
    assert stream == b"MD0000029901000;QT\n00P\n\n"
    assert decode_all(stream) == [StatusReply(echo="MD0000029901000;QT", command="MD", status="00", tag="QT")]


def test_a_reply_missing_only_its_final_line_feed_is_still_decoded():
    first, second = md_frame(list(range(50)), tag="1"), md_frame(list(range(60)), tag="2")
    events = decode_all(first[:-1] + second)
    assert [e.tag for e in events] == ["1", "2"] and all(isinstance(e, ScanReply) for e in events)
