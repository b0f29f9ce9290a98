"""The RPLIDAR codec's newer half: GET_LIDAR_CONF, SET_MOTOR_RPM, ultra and dense capsules.

Worked values follow Slamtec's SDK (``sl_lidar_cmd.h``, ``handler_capsules.cpp``); the fake and
the SDK itself meet in tests/test_rplidar_sdk.py.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lidar_drivers import rplidar_capsules as caps
from lidar_drivers.rplidar_codec import (
    AnswerType,
    Command,
    ConfKey,
    DeviceInfo,
    LidarConf,
    Measurements,
    Request,
    RequestParser,
    RplidarClient,
    ScanMode,
    ScanStarted,
    encode_lidar_conf,
    encode_scan_descriptor,
    parse_conf_request,
    supports_conf_commands,
)
from racecar_hw.base.errors import LocalProtocolError


def feed(client: RplidarClient, data: bytes, piece: int | None = None) -> list[object]:
    out: list[object] = []
    step = piece or len(data) or 1
    for i in range(0, len(data), step):
        client.receive_data(data[i:i + step])
        out += client.events()
    return out


def samples(events: list[object]) -> tuple[np.ndarray, np.ndarray]:
    ms = [e for e in events if isinstance(e, Measurements)]
    if not ms:
        return np.zeros(0), np.zeros(0)
    return np.concatenate([m.angle_deg for m in ms]), np.concatenate([m.distance_mm for m in ms])


# --- configuration commands ---------------------------------------------------------------------


def test_conf_requests_on_the_wire():
    # the SDK's start-up asks the desired motor speed this way (reference lidars.md 2.9 step 2)
    assert Request.get_lidar_conf(ConfKey.DESIRED_ROT_FREQ).encode() == \
        bytes.fromhex("a5 84 04 01 00 00 00 24")
    per_mode = Request.get_lidar_conf(ConfKey.SCAN_MODE_NAME, 3)
    assert per_mode.payload == struct.pack("<IH", 0x7F, 3)
    assert parse_conf_request(per_mode) == (0x7F, 3)
    assert parse_conf_request(Request.get_lidar_conf(ConfKey.SCAN_MODE_COUNT)) == (0x70, None)
    assert parse_conf_request(Request(Command.GET_LIDAR_CONF, b"\x70")) is None
    assert Request.set_motor_rpm(600).encode() == bytes.fromhex("a5 a8 02 58 02") + \
        bytes((0xA5 ^ 0xA8 ^ 0x02 ^ 0x58 ^ 0x02,))
    with pytest.raises(LocalProtocolError):
        Request.get_lidar_conf(ConfKey.SCAN_MODE_NAME)  # needs the mode id
    with pytest.raises(LocalProtocolError):
        Request.get_lidar_conf(ConfKey.SCAN_MODE_TYPICAL, 1)  # takes none
    with pytest.raises(LocalProtocolError):
        Request.set_motor_rpm(70000)


def test_conf_answers_in_any_fragmentation():
    answers = [
        (Request.get_lidar_conf(ConfKey.SCAN_MODE_COUNT), struct.pack("<H", 5)),
        (Request.get_lidar_conf(ConfKey.SCAN_MODE_US_PER_SAMPLE, 2), struct.pack("<I", 63 * 256)),
        (Request.get_lidar_conf(ConfKey.SCAN_MODE_NAME, 3), b"Sensitivity\0"),
    ]
    for request, value in answers:
        key = parse_conf_request(request)[0]
        wire = encode_lidar_conf(key, value)
        assert wire[:7] == bytes.fromhex("a55a") + struct.pack("<I", 4 + len(value)) + b"\x20"
        for piece in (1, 3, None):
            client = RplidarClient()
            client.send(request)
            [conf] = feed(client, b"stale bytes" + wire, piece)
            assert conf == LidarConf(key, value)
    assert LidarConf(0x7F, b"Boost\0junk").text == "Boost"
    assert LidarConf(0x71, struct.pack("<I", 16128)).number(4) == 16128
    assert LidarConf(0x70, b"\x05").number(2) is None


def test_which_devices_have_the_configuration_commands():
    """As the SDK decides: C/S series always, A series from firmware 1.24."""
    a1 = DeviceInfo(0x18, 1, 24, 7, bytes(16))
    assert supports_conf_commands(a1)
    assert not supports_conf_commands(DeviceInfo(0x18, 1, 23, 7, bytes(16)))
    assert supports_conf_commands(DeviceInfo(0x41, 1, 2, 18, bytes(16)))  # C1, firmware 1.02
    assert supports_conf_commands(DeviceInfo(0x61, 1, 0, 7, bytes(16)))  # S1


def test_scan_mode_description():
    mode = ScanMode(3, "Sensitivity", 63.0, 25.0, AnswerType.ULTRA_CAPSULED)
    assert mode.describe() == "Sensitivity (id 3): 15.9 k samples/s, 25 m, ultra capsules (0x84)"


def test_the_fake_side_parses_conf_and_rpm_requests():
    wire = (Request.get_lidar_conf(ConfKey.SCAN_MODE_ANS_TYPE, 4).encode()
            + Request.set_motor_rpm(720).encode())
    got = RequestParser().receive_data(wire)
    assert [r.command for r in got] == [Command.GET_LIDAR_CONF, Command.SET_MOTOR_RPM]
    assert parse_conf_request(got[0]) == (0x75, 4) and got[1].payload == struct.pack("<H", 720)


# --- ultra capsules -----------------------------------------------------------------------------


def test_variable_bit_scale_matches_the_sdk_bands():
    scaled = np.array([0, 511, 512, 1279, 1280, 1791, 1792, 3327, 3328, 4095])
    mm, level = caps.varbitscale_decode(scaled)
    assert mm.tolist() == [0, 511, 512, 2046, 2048, 4092, 4096, 16376, 16384, 28656]
    assert level.tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert caps.ULTRA_MAX_MM == 28656
    every = np.arange(4096)
    assert np.array_equal(caps.varbitscale_encode(caps.varbitscale_decode(every)[0]), every)


def test_ultra_beam_lag_follows_the_sdk_formula():
    # below 50 mm (and no return): 7.5 degrees; at 1 m: 8 degrees less k2 << 6 (k2 = 98361 // 4000)
    lag = caps.ultra_angle_offset_q16(np.array([0, 199, 4000])) / 65536
    assert lag[0] == lag[1] == pytest.approx(7.5, abs=0.001)
    assert lag[2] == pytest.approx(np.degrees((9150 - (24 << 6)) / 65536), abs=1e-3)


def _ultra_stream(n_caps: int, per_rev: int = 800):
    k = np.arange((n_caps + 1) * 96)
    rotor = ((k % per_rev) + 0.5) * 360.0 / per_rev
    dist = 2300.0 + 2000.0 * np.sin(k / 50.0)  # 0.3 .. 4.3 m, crossing four scale bands
    dist[5] = 0.0  # no return on a predicted sample
    dist[9] = 0.0  # and on a cabin's first: its second is predicted from the next cabin's first
    data = caps.encode_ultra(rotor[:-96:96], dist[:-96], dist[-96], first=True)
    return data, rotor[:-96], dist[:-96]


def test_ultra_capsules_round_trip_with_the_sdk_decoding():
    data, rotor, dist = _ultra_stream(12)
    client = RplidarClient()
    client.send(Request.express_scan(2), AnswerType.ULTRA_CAPSULED)
    events = feed(client, encode_scan_descriptor(True, AnswerType.ULTRA_CAPSULED) + data, 100)
    assert events[0] == ScanStarted(express=True, answer_type=AnswerType.ULTRA_CAPSULED)
    angle, got = samples(events)
    n = len(got)
    assert n == 11 * 96  # the last capsule waits for its successor
    held = [e.held_back for e in events if isinstance(e, Measurements)]
    assert set(held) == {96}
    # distances within the scale's step, no return kept as 0; sample 8 is predicted from cabin
    # 3's first, a no return: the format cannot carry it, so it goes out as no return too
    _, level = caps.varbitscale_decode(caps.varbitscale_encode(dist[:n]))
    want = dist[:n].copy()
    want[8] = 0.0
    assert np.all(np.abs(got - want) <= (1 << level) + 1)
    assert got[5] == got[8] == got[9] == 0.0
    # angles: the rotor angle less the beam lag of the decoded distance
    want = np.mod(rotor[:n] - caps.ultra_beam_lag_deg(got), 360.0)
    err = np.abs((angle - want + 180.0) % 360.0 - 180.0)
    assert err.max() < 0.05


def test_ultra_capsule_with_a_bad_checksum_is_dropped_and_the_stream_relocks():
    data, _, _ = _ultra_stream(10)
    broken = bytearray(data)
    broken[4 * caps.ULTRA_LEN + 20] ^= 0xFF
    client = RplidarClient()
    client.send(Request.express_scan(2), AnswerType.ULTRA_CAPSULED)
    _, got = samples(feed(client, encode_scan_descriptor(True, AnswerType.ULTRA_CAPSULED)
                          + bytes(broken), 64))
    # capsule 3 lost its successor, capsule 4 is bad: 9 - 2 capsules' samples come through
    assert len(got) == 7 * 96
    assert client.stats.checksum_errors == 1 and client.stats.resyncs == 1


# --- dense capsules -----------------------------------------------------------------------------


def test_dense_capsules_round_trip():
    per_rev = 920
    k = np.arange(30 * 40)
    theta = (k % per_rev) * 360.0 / per_rev
    dist = 100.0 + (k * 13) % 39000
    data = caps.encode_dense(theta[::40], dist)
    assert len(data) == 30 * caps.DENSE_LEN
    client = RplidarClient()
    client.send(Request.express_scan(1), AnswerType.DENSE_CAPSULED)
    events = feed(client, encode_scan_descriptor(True, AnswerType.DENSE_CAPSULED) + data, 33)
    angle, got = samples(events)
    assert len(got) == 29 * 40
    np.testing.assert_array_equal(got, dist[:29 * 40])
    err = np.abs((angle - theta[:29 * 40] + 180.0) % 360.0 - 180.0)
    assert err.max() < 1 / 32  # interpolated between q6 start angles, truncated to q6
    starts = np.flatnonzero(np.concatenate([e.start for e in events if isinstance(e, Measurements)]))
    assert per_rev in starts and set(starts) <= {0, per_rev}  # the stream itself starts at 0


def test_a_duplicated_or_reordered_dense_capsule_costs_its_pairs_not_wrong_angles():
    """The express capsules' start-angle step check holds for dense (and ultra) capsules too."""
    per_rev = 920
    k = np.arange(30 * 40)
    theta = (k % per_rev) * 360.0 / per_rev
    dist = 100.0 + (k * 13) % 39000  # unique per sample: each tells where it was measured
    data = caps.encode_dense(theta[::40], dist)
    frames = [data[i * caps.DENSE_LEN:(i + 1) * caps.DENSE_LEN] for i in range(30)]
    for stream, dropped in ((frames[:10] + [frames[9]] + frames[10:], 1),
                            (frames[:10] + [frames[11], frames[10]] + frames[12:], 3)):
        client = RplidarClient()
        client.send(Request.express_scan(1), AnswerType.DENSE_CAPSULED)
        angle, got = samples(feed(client, encode_scan_descriptor(True, AnswerType.DENSE_CAPSULED)
                                  + b"".join(stream), 84 * 3))
        assert client.stats.bad_capsule_steps == dropped
        where = {float(v): i for i, v in enumerate(dist)}
        truth = np.array([theta[where[float(v)]] for v in got])
        assert len(got) >= (29 - dropped) * 40
        assert np.abs((angle - truth + 180.0) % 360.0 - 180.0).max() < 1 / 32


@settings(max_examples=150, deadline=None)
@given(noise=st.binary(max_size=600), piece=st.integers(1, 200),
       kind=st.sampled_from([AnswerType.ULTRA_CAPSULED, AnswerType.DENSE_CAPSULED]))
def test_capsule_streams_never_raise_on_noise(noise, piece, kind):
    client = RplidarClient()
    client.send(Request.express_scan(1), kind)
    events = feed(client, encode_scan_descriptor(True, kind) + noise, piece)
    for e in events:
        if isinstance(e, Measurements):
            assert np.all((e.angle_deg >= 0) & (e.angle_deg < 360)) and np.all(e.distance_mm >= 0)
