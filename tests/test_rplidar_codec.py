"""The RPLIDAR codec: worked frames, both directions, fragments, garbage and fuzzing."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lidar_drivers.rplidar_codec import (
    AccBoardFlag,
    AnswerType,
    Command,
    DeviceInfo,
    Health,
    Measurements,
    Request,
    RequestParser,
    RplidarClient,
    SampleRate,
    ScanStarted,
    decode_capsules,
    encode_acc_board_flag,
    encode_capsules,
    encode_health,
    encode_info,
    encode_nodes,
    encode_samplerate,
    encode_scan_descriptor,
)
from racecar_hw.base.errors import LocalProtocolError

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

INFO = DeviceInfo(0x18, 1, 29, 7, bytes(range(16)))


def feed(client: RplidarClient, data: bytes, pieces: list[int] | None = None) -> list[object]:
    """Feed ``data`` in pieces of the given sizes (cycled), returning every event."""
    events: list[object] = []
    i, j = 0, 0
    while i < len(data):
        n = pieces[j % len(pieces)] if pieces else len(data)
        client.receive_data(data[i:i + n])
        events += client.events()
        i, j = i + n, j + 1
    return events


def samples(events: list[object]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ms = [e for e in events if isinstance(e, Measurements)]
    if not ms:
        return np.zeros(0), np.zeros(0), np.zeros(0, bool)
    return (np.concatenate([m.angle_deg for m in ms]), np.concatenate([m.distance_mm for m in ms]),
            np.concatenate([m.start for m in ms]))


# --- requests ----------------------------------------------------------------------------------


def test_request_frames_match_the_reference():
    assert Request.set_motor_pwm(660).encode() == bytes.fromhex("a5f0029402c1")
    assert Request.simple(Command.GET_INFO).encode() == b"\xa5\x50"
    assert Request.simple(Command.STOP).encode() == b"\xa5\x25"
    assert Request.express_scan(1).encode() == bytes.fromhex("a5 82 05 01 00 00 00 00 23")  # ref. 2.9
    assert Request.express_scan(0).encode() == bytes.fromhex("a5 82 05 00 00 00 00 00 22")
    assert Request(Command.GET_LIDAR_CONF, bytes.fromhex("01000000")).encode() == \
        bytes.fromhex("a5 84 04 01 00 00 00 24")  # reference 2.9 step 2
    flag = Request.get_acc_board_flag().encode()
    assert flag[:3] == b"\xa5\xff\x04" and flag[-1] == 0xA5 ^ 0xFF ^ 0x04


def test_request_local_errors():
    with pytest.raises(LocalProtocolError):
        Request.set_motor_pwm(1024).encode()
    with pytest.raises(LocalProtocolError):
        Request(Command.STOP, b"\x01").encode()
    with pytest.raises(LocalProtocolError):
        Request(Command.GET_LIDAR_CONF, bytes(256)).encode()


def test_request_parser_fragments_garbage_and_bad_checksum():
    frames = (Request.simple(Command.GET_INFO).encode() + b"junk" + Request.set_motor_pwm(660).encode()
              + bytes.fromhex("a5f0029402c2") + Request.express_scan().encode())
    parser = RequestParser()
    got: list[Request] = []
    for b in frames:
        got += parser.receive_data(bytes([b]))
    assert [r.command for r in got] == [Command.GET_INFO, Command.SET_MOTOR_PWM, Command.EXPRESS_SCAN]
    assert got[1].payload == struct.pack("<H", 660)
    assert parser.bad_checksums == 1 and parser.garbage_bytes >= 4


# --- single responses --------------------------------------------------------------------------


@pytest.mark.parametrize(("request_", "response", "expected"), [
    (Request.simple(Command.GET_INFO), encode_info(INFO), INFO),
    (Request.simple(Command.GET_HEALTH), encode_health(Health(2, 0x1234)), Health(2, 0x1234)),
    (Request.simple(Command.GET_SAMPLERATE), encode_samplerate(SampleRate(500, 250)),
     SampleRate(500, 250)),
    (Request.get_acc_board_flag(), encode_acc_board_flag(AccBoardFlag(1)), AccBoardFlag(1)),
])
def test_single_responses_in_every_fragmentation(request_, response, expected):
    for pieces in (None, [1], [2, 5], [7, 1, 3]):
        client = RplidarClient()
        client.send(request_)
        assert feed(client, b"RP LIDAR System.\r\n" + response, pieces) == [expected]


def test_health_descriptor_and_info_fields_match_the_reference():
    assert encode_health(Health(0, 0))[:7] == bytes.fromhex("a55a0300000006")
    assert encode_info(INFO)[:7] == bytes.fromhex("a55a1400000004")
    assert INFO.model_name == "A1M8" and INFO.firmware == "1.29"
    assert INFO.serial_hex == bytes(range(16)).hex().upper()
    assert Health(2, 5).status_name == "error" and "protection stop" in Health(2, 5).meaning


def test_expected_answer_skips_other_descriptors():
    client = RplidarClient()
    client.send(Request.simple(Command.GET_HEALTH))
    events = feed(client, encode_info(INFO) + encode_health(Health(1, 7)))
    assert events == [Health(1, 7)]
    assert client.stats.garbage_bytes > 0


# --- standard scan -----------------------------------------------------------------------------


def test_worked_scan_node():
    client = RplidarClient()
    client.send(Request.simple(Command.SCAN))
    events = feed(client, bytes.fromhex("a55a0500004081") + bytes.fromhex("3d012d4a13"))
    assert events[0] == ScanStarted(express=False, answer_type=AnswerType.SCAN)
    m = events[1]
    assert isinstance(m, Measurements)
    assert m.start.tolist() == [True] and m.quality.tolist() == [15]
    assert m.angle_deg.tolist() == [90.0] and m.distance_mm.tolist() == [1234.5]
    assert encode_nodes(np.array([1]), np.array([15]), np.array([90.0]), np.array([1234.5])) == \
        bytes.fromhex("3d012d4a13")


def _node_stream(n: int, per_rev: int = 200) -> tuple[bytes, np.ndarray, np.ndarray]:
    k = np.arange(n)
    angle = (k % per_rev) * 360.0 / per_rev
    dist = 500.0 + (k * 37) % 8000
    return encode_nodes((k % per_rev) == 0, np.full(n, 47), angle, dist), angle, dist


def test_standard_nodes_one_byte_at_a_time_and_stop():
    data, angle, dist = _node_stream(300)
    client = RplidarClient()
    client.send(Request.simple(Command.FORCE_SCAN))
    events = feed(client, encode_scan_descriptor(False) + data, [1])
    a, d, s = samples(events)
    np.testing.assert_allclose(a, np.round(angle * 64) / 64)
    np.testing.assert_array_equal(d, dist)
    assert s.nonzero()[0].tolist() == [0, 200]
    assert client.streaming
    client.send(Request.simple(Command.STOP))
    assert not client.streaming
    assert feed(client, data[:50]) == []


def test_standard_nodes_resync_after_garbage_and_a_bad_check_bit():
    data, angle, dist = _node_stream(400)
    broken = bytearray(data)
    broken[100 * 5 + 1] &= 0xFE  # node 100 loses its check bit
    stream = bytes(broken[:250 * 5]) + b"\x07\x13\x99" + bytes(broken[250 * 5:])
    client = RplidarClient()
    client.send(Request.simple(Command.SCAN))
    a, d, _ = samples(feed(client, encode_scan_descriptor(False) + stream, [64]))
    assert client.stats.bad_nodes >= 2 and client.stats.resyncs >= 2
    # everything but the damaged node and at most a few around the garbage comes through
    assert len(d) >= 400 - 1 - 6
    np.testing.assert_array_equal(d[-100:], dist[-100:])
    np.testing.assert_array_equal(d[:100], dist[:100])
    assert dist[100] not in d[95:105]


def _relock_by_byte(data: bytes) -> int | None:
    """The re-lock's definition, one start offset at a time: the first offset followed by
    NODE_RESYNC_RUN plausible nodes with small angle steps (None: none in ``data``)."""
    from lidar_drivers.rplidar_codec import NODE_LEN, NODE_RESYNC_MAX_STEP_DEG, NODE_RESYNC_RUN

    for start in range(len(data) - NODE_RESYNC_RUN * NODE_LEN + 1):
        nodes = [data[start + k * NODE_LEN:start + (k + 1) * NODE_LEN] for k in range(NODE_RESYNC_RUN)]
        angles = [((n[1] | n[2] << 8) >> 1) for n in nodes]
        plausible = all(((n[0] >> 1 ^ n[0]) & 1) and n[1] & 1 and a < 360 * 64
                        for n, a in zip(nodes, angles, strict=True))
        steps = [(b - a) / 64.0 % 360.0 for a, b in zip(angles, angles[1:], strict=False)]
        if plausible and all(step < NODE_RESYNC_MAX_STEP_DEG for step in steps):
            return start
    return None


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=120), st.integers(0, 60))
def test_node_relock_takes_the_first_offset_a_byte_by_byte_search_would(noise, at):
    """The re-lock tries every offset at once (line noise must not cost the event loop a numpy
    call per byte); it locks where the byte-by-byte definition does, or keeps only a tail."""
    from lidar_drivers.rplidar_codec import NODE_LEN, NODE_RESYNC_RUN

    good, _, _ = _node_stream(8)
    data = noise[:at] + good + noise[at:]
    client = RplidarClient()
    client.send(Request.simple(Command.SCAN))
    feed(client, encode_scan_descriptor(False))
    client._buf[:] = data
    client._node_locked = False
    locked = client._relock_nodes()
    expected = _relock_by_byte(data)
    assert expected is not None  # the good nodes are in there
    assert locked and client.stats.garbage_bytes == expected and bytes(client._buf) == data[expected:]
    tail = noise[:NODE_RESYNC_RUN * NODE_LEN + 20]
    client = RplidarClient()
    client.send(Request.simple(Command.SCAN))
    feed(client, encode_scan_descriptor(False))
    client._buf[:] = tail
    client._node_locked = False
    found = _relock_by_byte(tail)
    assert client._relock_nodes() == (found is not None)
    kept = tail[found:] if found is not None else tail[max(len(tail) - NODE_RESYNC_RUN * NODE_LEN + 1, 0):]
    assert bytes(client._buf) == kept


def test_a_long_burst_of_line_noise_is_skipped_in_one_search():
    """64 KiB of noise in the node stream, then nodes: they decode, the noise counted as garbage."""
    data, _, dist = _node_stream(40)
    noise = np.random.default_rng(1).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    client = RplidarClient()
    client.send(Request.simple(Command.SCAN))
    feed(client, encode_scan_descriptor(False) + data[:50])
    _, d, _ = samples(feed(client, noise + data[50:]))
    assert client.stats.garbage_bytes >= 65536 - 40 and client.stats.resyncs >= 1
    np.testing.assert_array_equal(d[-20:], dist[-20:])


# --- express scan ------------------------------------------------------------------------------


def _capsule_stream(n_caps: int, per_rev: int = 400) -> tuple[bytes, np.ndarray, np.ndarray]:
    k = np.arange(n_caps * 32)
    angle = (k % per_rev) * 360.0 / per_rev
    dist = (300 + (k * 13) % 9000).astype(float)
    return encode_capsules(angle[::32], dist, first=True), angle, dist


def test_express_capsules_decode_with_the_next_capsule():
    data, angle, dist = _capsule_stream(30)
    client = RplidarClient()
    client.send(Request.express_scan())
    events = feed(client, encode_scan_descriptor(True) + data, [84])
    assert events[0] == ScanStarted(express=True, answer_type=AnswerType.EXPRESS)
    a, d, s = samples(events)
    assert len(d) == 29 * 32  # the last capsule waits for its successor
    np.testing.assert_array_equal(d, dist[:len(d)])
    assert np.abs(a - angle[:len(a)]).max() < 2 / 64  # q6 start angles, truncated like the SDK
    assert s.nonzero()[0].tolist() == [399, 799]  # the sample before the angle wraps, as the SDK


def test_express_bad_checksum_drops_the_capsule_and_its_neighbour_only():
    data, _, dist = _capsule_stream(20)
    broken = bytearray(data)
    broken[5 * 84 + 40] ^= 0xFF
    client = RplidarClient()
    client.send(Request.express_scan())
    _, d, _ = samples(feed(client, encode_scan_descriptor(True) + b"xx" + bytes(broken), [13]))
    assert client.stats.checksum_errors == 2  # the two stray bytes, then the broken capsule
    # capsules 0..3 (4 waits for 5, which is bad), then 6..18 (19 waits)
    np.testing.assert_array_equal(d, np.concatenate([dist[:4 * 32], dist[6 * 32:19 * 32]]))


def test_decode_capsules_applies_the_compensation_angle():
    data, _, _ = _capsule_stream(2)
    caps = np.frombuffer(data, dtype=np.uint8).reshape(2, 84).copy()
    caps[0, 4 + 4] = 0x08  # first cabin: dθ1 = 8/8 degree
    m = decode_capsules(caps)
    assert m.angle_deg[0] == pytest.approx(360 - 1.0)
    assert m.angle_deg[1] == pytest.approx(0.9, abs=1 / 64)


# --- properties --------------------------------------------------------------------------------


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=600), state=st.sampled_from(["hunt", "scan", "express", "info"]),
       piece=st.integers(1, 100))
def test_arbitrary_bytes_never_raise(data, state, piece):
    client = RplidarClient()
    if state == "scan":
        client.receive_data(encode_scan_descriptor(False))
    elif state == "express":
        client.receive_data(encode_scan_descriptor(True))
    elif state == "info":
        client.send(Request.simple(Command.GET_INFO))
    feed(client, data, [piece])
    assert client.stats.bytes_in >= len(data)
    RequestParser().receive_data(data)


@settings(max_examples=200)
@given(garbage=st.binary(max_size=200), status=st.integers(0, 2), code=st.integers(0, 0xFFFF),
       piece=st.integers(1, 30))
def test_a_response_after_garbage_is_recovered(garbage, status, code, piece):
    client = RplidarClient()
    client.send(Request.simple(Command.GET_HEALTH))
    # a response descriptor hidden in the garbage would be indistinguishable from the real one
    garbage = garbage.replace(b"\xa5\x5a", b"\xa5\x00")
    assert feed(client, garbage + encode_health(Health(status, code)), [piece]) == [Health(status, code)]


@settings(max_examples=150)
@given(garbage=st.binary(min_size=1, max_size=120), at=st.integers(1, 15), piece=st.integers(1, 200))
def test_express_capsules_after_garbage_are_recovered(garbage, at, piece):
    data, _, dist = _capsule_stream(20)
    client = RplidarClient()
    client.send(Request.express_scan())
    stream = encode_scan_descriptor(True) + data[:at * 84] + garbage + data[at * 84:]
    _, d, _ = samples(feed(client, stream, [piece]))
    # every capsule after the garbage, except the last (it waits for a successor), comes through
    tail = dist[(at + 1) * 32:19 * 32]
    assert len(d) >= len(tail)
    np.testing.assert_array_equal(d[-len(tail):], tail)


@settings(max_examples=150)
@given(garbage=st.binary(min_size=1, max_size=60), at=st.integers(1, 150), piece=st.integers(1, 97),
       offset=st.integers(0, 199))
def test_standard_nodes_after_garbage_are_recovered(garbage, at, piece, offset):
    k = np.arange(300) + offset
    angle = (k % 200) * 1.8
    dist = 500.0 + (k * 37) % 8000
    data = encode_nodes((k % 200) == 0, np.full(300, 47), angle, dist)
    client = RplidarClient()
    client.send(Request.simple(Command.SCAN))
    stream = encode_scan_descriptor(False) + data[:at * 5] + garbage + data[at * 5:]
    _, d, _ = samples(feed(client, stream, [piece]))
    np.testing.assert_array_equal(d[-100:], dist[-100:])


def _express(data: bytes) -> tuple[RplidarClient, np.ndarray, np.ndarray]:
    client = RplidarClient()
    client.send(Request.express_scan())
    a, d, _ = samples(feed(client, encode_scan_descriptor(True) + data, [84 * 3]))
    return client, a, d


def _true_angles_kept(a: np.ndarray, d: np.ndarray, angle: np.ndarray, dist: np.ndarray) -> bool:
    """Every emitted sample sits at the angle its (unique) distance was measured at."""
    where = {float(v): i for i, v in enumerate(dist)}
    truth = np.array([angle[where[float(v)]] for v in d])
    return bool(len(d)) and float(np.abs((a - truth + 180) % 360 - 180).max()) < 2 / 64


def test_a_duplicated_capsule_costs_one_pair_and_no_sample_lands_at_a_wrong_angle():
    data, angle, dist = _capsule_stream(20)
    caps = [data[i * 84:(i + 1) * 84] for i in range(20)]
    client, a, d = _express(b"".join(caps[:10] + [caps[9]] + caps[10:]))
    assert client.stats.bad_capsule_steps == 1
    np.testing.assert_array_equal(d, dist[:19 * 32])  # capsule 9's samples once, from its copy
    assert _true_angles_kept(a, d, angle, dist)


def test_reordered_capsules_are_dropped_with_their_pairs():
    data, angle, dist = _capsule_stream(20)
    caps = [data[i * 84:(i + 1) * 84] for i in range(20)]
    client, a, d = _express(b"".join(caps[:10] + [caps[11], caps[10]] + caps[12:]))
    # (9, 11) and (10, 12) step twice as far as the others, (11, 10) backwards
    assert client.stats.bad_capsule_steps == 3
    np.testing.assert_array_equal(d, np.concatenate([dist[:9 * 32], dist[12 * 32:19 * 32]]))
    assert _true_angles_kept(a, d, angle, dist)


def test_capsule_steps_follow_a_drifting_motor_and_relock_after_a_real_speed_change():
    steps = np.concatenate([np.linspace(20.0, 30.0, 60), np.full(40, 45.0)])  # +0.7 % a capsule, then +50 %
    starts = np.concatenate([[0.0], np.cumsum(steps)]) % 360.0
    dist = 300.0 + np.arange(len(starts) * 32) % 9000
    client, _, d = _express(encode_capsules(starts, dist, first=True))
    # the jump costs the relock window, then the new speed is taken
    assert client.stats.bad_capsule_steps == 8
    assert len(d) == (len(starts) - 1 - 8) * 32


def test_the_sample_rate_answer_narrows_the_capsule_step_range():
    client = RplidarClient()
    assert client.capsule_step_deg == (2.0, 150.0)
    client.send(Request.simple(Command.GET_SAMPLERATE))
    client.receive_data(encode_samplerate(SampleRate(500, 250)))
    assert client.events() == [SampleRate(500, 250)]
    lo, hi = client.capsule_step_deg  # 32 samples of 250 µs at 2-25 Hz
    assert (lo, hi) == pytest.approx((5.76, 72.0))
