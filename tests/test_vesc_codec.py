"""The VESC codec: known frames, every GET_VALUES layout, resync, refusal, fuzzing, pyvesc cross-check."""

from __future__ import annotations

import binascii
import dataclasses
import math
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from racecar_hw.base.errors import LocalProtocolError
from vesc import codec
from vesc.codec import (
    IMU_FIELDS,
    MAX_PAYLOAD,
    Alive,
    FwVersion,
    FwVersionRequest,
    GetImuDataRequest,
    GetValuesRequest,
    ImuData,
    Layout,
    RawPacket,
    Role,
    SetCurrent,
    SetCurrentBrake,
    SetDuty,
    SetPosition,
    SetRpm,
    SetServoPosition,
    Values,
    VescCodec,
    decode_imu_data,
    decode_values,
    encode_payload,
    encode_values,
    frame,
    known_firmware,
    values_layout,
)

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

KNOWN_FRAMES = [
    (SetRpm(5000), "02 05 08 00 00 13 88 44 8D 03"),
    (SetServoPosition(0.5), "02 03 0C 01 F4 E9 CB 03"),
    (GetValuesRequest(), "02 01 04 40 84 03"),
    (Alive(), "02 01 1E F3 FF 03"),
    (FwVersionRequest(), "02 01 00 00 00 03"),
    (SetCurrent(5.0), "02 05 06 00 00 13 88 8B 25 03"),
]

SAMPLE = Values(
    temp_fet=41.3, temp_motor=38.2, current_motor=-12.34, current_input=3.21, avg_id=-0.5,
    avg_iq=12.0, duty=-0.345, erpm=-23250, v_in=15.9, amp_hours=1.2345, amp_hours_charged=0.0123,
    watt_hours=18.5, watt_hours_charged=0.25, tachometer=-123456, tachometer_abs=987654, fault=0,
    pid_pos=123.456789, controller_id=7, temp_mos1=40.1, temp_mos2=41.3, temp_mos3=39.9,
    avg_vd=-0.123, avg_vq=5.432, status=1, temp_pcb=0.0)

#: Fields present in each layout, beyond those of 3.07.
LAYOUT_FIELDS = {
    Layout.V3_07: set(),
    Layout.V3_34: {"pid_pos"},
    Layout.V3_40: {"pid_pos", "controller_id"},
    Layout.V3_48: {"pid_pos", "controller_id", "temp_mos1", "temp_mos2", "temp_mos3"},
    Layout.V3_60: {"pid_pos", "controller_id", "temp_mos1", "temp_mos2", "temp_mos3", "avg_vd", "avg_vq"},
    Layout.V5_03: {"pid_pos", "controller_id", "temp_mos1", "temp_mos2", "temp_mos3", "avg_vd", "avg_vq",
                   "status"},
}
OPTIONAL = LAYOUT_FIELDS[Layout.V5_03] | {"temp_pcb"}


def host() -> VescCodec:
    return VescCodec(Role.HOST)


def device(firmware: tuple[int, int] | None = None) -> VescCodec:
    return VescCodec(Role.DEVICE, firmware)


@pytest.mark.parametrize(("packet", "hexframe"), KNOWN_FRAMES)
def test_known_frames(packet, hexframe):
    assert host().send(packet) == bytes.fromhex(hexframe)


@pytest.mark.parametrize(("packet", "hexframe"), KNOWN_FRAMES)
def test_device_decodes_known_frames(packet, hexframe):
    codec = device()
    codec.receive_data(bytes.fromhex(hexframe))
    assert codec.events() == [packet]
    assert codec.stats.frames == 1


def test_crc_is_xmodem():
    assert binascii.crc_hqx(b"123456789", 0) == 0x31C3
    assert frame(b"123456789")[-3:-1] == b"\x31\xc3"


@pytest.mark.parametrize("packet", [SetDuty(-0.25), SetCurrent(-7.5), SetCurrentBrake(12.0), SetRpm(-1234),
                                    SetPosition(359.5), SetServoPosition(0.15), SetServoPosition(1.0)])
def test_commands_round_trip(packet):
    codec = device()
    codec.receive_data(host().send(packet))
    assert codec.events() == [packet]


def test_scaling_on_the_wire():
    h = host()
    assert h.send(SetDuty(0.5))[3:7] == struct.pack(">i", 50000)
    assert h.send(SetCurrentBrake(2.5))[3:7] == struct.pack(">i", 2500)
    assert h.send(SetPosition(90.0))[3:7] == struct.pack(">i", 90_000_000)
    assert h.send(SetServoPosition(0.123))[3:5] == struct.pack(">h", 123)


@pytest.mark.parametrize("packet", [
    SetRpm(math.nan), SetRpm(math.inf), SetRpm(-math.inf), SetRpm(2.0**31), SetDuty(1.01), SetDuty(math.nan),
    SetCurrent(math.nan), SetCurrent(3e6), SetCurrentBrake(math.inf), SetPosition(math.nan),
    SetServoPosition(-0.01), SetServoPosition(1.2), SetServoPosition(math.nan),
])
def test_encoding_refuses_unsendable_values(packet):
    with pytest.raises(LocalProtocolError):
        host().send(packet)


def test_roles_refuse_the_other_sides_packets():
    with pytest.raises(LocalProtocolError):
        host().send(FwVersion(6, 2))
    with pytest.raises(LocalProtocolError):
        host().send(Values())
    with pytest.raises(LocalProtocolError):
        device().send(SetRpm(0))
    with pytest.raises(LocalProtocolError):
        frame(b"")


def test_firmware_selects_layout():
    assert values_layout((2, 18)) is Layout.PRE_3_07
    assert values_layout((3, 7)) is Layout.V3_07
    assert values_layout((3, 33)) is Layout.V3_07
    assert values_layout((3, 34)) is Layout.V3_34
    assert values_layout((3, 40)) is Layout.V3_40
    assert values_layout((3, 48)) is Layout.V3_48
    assert values_layout((3, 60)) is Layout.V3_60
    assert values_layout((5, 2)) is Layout.V3_60
    assert values_layout((5, 3)) is Layout.V5_03
    assert values_layout((6, 2)) is Layout.V5_03
    assert values_layout(None) is Layout.V5_03


def _approx_equal(a: Values, b: Values, fields: set[str]) -> None:
    for name in fields:
        assert getattr(a, name) == pytest.approx(getattr(b, name), abs=1e-6), name


@pytest.mark.parametrize("fw", [(3, 7), (3, 34), (3, 40), (3, 48), (3, 60), (5, 2), (5, 3), (6, 2), (6, 5)])
def test_values_every_layout_round_trip(fw):
    layout = values_layout(fw)
    payload = encode_values(SAMPLE, layout)
    assert len(payload) == layout.value
    assert payload[23:27] == struct.pack(">i", -23250)  # rpm at offset 23 since 3.07
    got = decode_values(payload, fw)
    assert isinstance(got, Values)
    present = {f for f in Values.__dataclass_fields__ if f not in OPTIONAL} | LAYOUT_FIELDS[layout]
    _approx_equal(got, SAMPLE, present)
    for absent in OPTIONAL - present:
        assert getattr(got, absent) == 0


def test_values_pre_3_07_layout():
    payload = encode_values(SAMPLE, Layout.PRE_3_07)
    assert len(payload) == 56
    assert payload[25:29] == struct.pack(">i", -23250)  # rpm at offset 25 before 3.07
    got = decode_values(payload, (2, 18))
    assert isinstance(got, Values)
    _approx_equal(got, SAMPLE, {"current_motor", "current_input", "duty", "erpm", "v_in", "amp_hours",
                                "watt_hours", "tachometer", "tachometer_abs", "fault", "temp_mos1",
                                "temp_mos2", "temp_mos3", "temp_fet"})


def test_values_ignore_trailing_bytes_and_refuse_short():
    payload = encode_values(SAMPLE, Layout.V3_40) + b"\x99" * 20
    got = decode_values(payload, (3, 40))
    assert isinstance(got, Values) and got.controller_id == 7 and got.temp_mos1 == 0
    # an unknown firmware decodes every field the payload carries
    full = decode_values(encode_values(SAMPLE, Layout.V5_03) + b"\x00\x01", None)
    assert isinstance(full, Values) and full.status == 1
    short = decode_values(encode_values(SAMPLE, Layout.V5_03)[:40], (6, 2))
    assert isinstance(short, RawPacket) and "54" in short.reason


def test_the_layout_is_the_callers_choice_never_a_decoded_fw_version():
    dev = device((3, 40))
    h = host()
    h.receive_data(dev.send(FwVersion(3, 40, "410", bytes(range(12)))))
    assert h.events() == [FwVersion(3, 40, "410", bytes(range(12)))]
    assert h.firmware is None  # the driver's handshake decides whether to believe it
    h.firmware = (3, 40)
    h.receive_data(dev.send(SAMPLE))
    (values,) = h.events()
    assert isinstance(values, Values) and values.controller_id == 7 and values.erpm == -23250
    # line noise: an all-zero payload has CRC 0 and would read as FW_VERSION 0.0; it is dropped
    h.receive_data(b"\x02\x03\x00\x00\x00\x00\x00\x03" + dev.send(FwVersion(0, 1)))
    assert h.events() == [FwVersion(0, 1)] and h.firmware == (3, 40)
    assert h.stats.zero_payloads == 1


def test_a_device_decodes_the_one_zero_byte_fw_version_request():
    d = device()
    d.receive_data(b"\x02\x01\x00\x00\x00\x03")
    assert d.events() == [FwVersionRequest()] and d.stats.zero_payloads == 0


@pytest.mark.parametrize(("version", "known"), [
    ((0, 0), False), ((1, 99), False), ((2, 18), True), ((3, 40), True), ((6, 5), True), ((7, 0), True),
    ((8, 0), False), ((6, 100), False), ((255, 255), False)])
def test_known_firmware(version, known):
    assert known_firmware(version) is known


@pytest.mark.parametrize("reply", [
    FwVersion(2, 18), FwVersion(3, 7, "40"), FwVersion(3, 40, "410", bytes(range(12))),
    FwVersion(5, 2, "60", bytes(range(12)), b"\x00\x00\x00\x00"),
    FwVersion(6, 5, "60_MK6", bytes(range(12)), b"\x00\x00\x00\x00\x00\x00\x00\x00fw\x00\x12\x34\x56\x78"),
])
def test_fw_version_round_trip(reply):
    h = host()
    h.receive_data(device().send(reply))
    assert h.events() == [reply]


def test_long_frames_and_three_byte_lengths():
    payload = bytes([0x15]) + b"x" * 299  # a long PRINT
    long = frame(payload)
    assert long[:3] == b"\x03\x01\x2c"
    huge = b"\x04\x00\x00\x05" + b"\x08\x00\x00\x03\xe8" + struct.pack(">H", binascii.crc_hqx(
        b"\x08\x00\x00\x03\xe8", 0)) + b"\x03"
    h, d = host(), device()
    h.receive_data(long)
    assert h.events() == [RawPacket(payload)]
    d.receive_data(huge)
    assert d.events() == [SetRpm(1000)]


def test_unknown_and_malformed_packets_are_raw_events():
    d = device()
    d.receive_data(frame(b"\x63\x01\x02") + frame(b"\x08\x00") + frame(b"\x0c"))
    unknown, short_rpm, short_servo = d.events()
    assert unknown == RawPacket(b"\x63\x01\x02") and unknown.command_id == 0x63
    assert isinstance(short_rpm, RawPacket) and short_rpm.reason != "unknown"
    assert isinstance(short_servo, RawPacket)
    assert d.stats.raw_packets == 3 and d.stats.frames == 3


def test_resync_after_garbage_bad_crc_and_bad_end_byte():
    good = host().send(SetRpm(777))
    bad_crc = bytearray(good)
    bad_crc[-2] ^= 0x01
    bad_end = bytearray(good)
    bad_end[-1] = 0x00
    d = device()
    d.receive_data(b"\xff\x00\x13" + bytes(bad_crc) + bytes(bad_end) + good)
    assert d.events() == [SetRpm(777)]
    assert d.stats.crc_errors == 1
    assert d.stats.frames == 1
    assert d.stats.resyncs == 1
    assert d.stats.dropped_bytes == 3 + 2 * len(good)


def test_false_start_inside_a_frame_is_skipped_one_byte_at_a_time():
    # "02 FF" announces 255 bytes; the real frame starts one byte later and must still be found
    good = host().send(SetServoPosition(0.25))
    d = device()
    d.receive_data(b"\x02" + good + bytes(260))
    assert d.events() == [SetServoPosition(0.25)]


def test_partial_frame_waits():
    data = host().send(SetRpm(-42))
    d = device()
    for b in data[:-1]:
        d.receive_data(bytes([b]))
        assert d.next_event() is None
    d.receive_data(data[-1:])
    assert d.next_event() == SetRpm(-42)
    assert d.next_event() is None
    assert d.stats.dropped_bytes == 0


# --- properties --------------------------------------------------------------------------------

requests = st.one_of(
    st.builds(SetRpm, st.integers(-(2**31), 2**31 - 1)),
    st.builds(SetDuty, st.integers(-100000, 100000).map(lambda i: i / 1e5)),
    st.builds(SetCurrent, st.integers(-(2**31), 2**31 - 1).map(lambda i: i / 1e3)),
    st.builds(SetCurrentBrake, st.integers(0, 2**31 - 1).map(lambda i: i / 1e3)),
    st.builds(SetPosition, st.integers(0, 360_000_000).map(lambda i: i / 1e6)),
    st.builds(SetServoPosition, st.integers(0, 1000).map(lambda i: i / 1000)),
    st.just(Alive()), st.just(GetValuesRequest()), st.just(FwVersionRequest()),
    st.builds(GetImuDataRequest, st.integers(0, 0xFFFF)),
)
#: Garbage that cannot start a frame, so frames after it are never swallowed by a false start.
no_start = st.binary(max_size=40).map(lambda b: bytes(x for x in b if x not in (2, 3, 4)))


def _chunks(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in zip(points, points[1:], strict=False)]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=2000), st.lists(st.integers(0, 4000), max_size=20), st.sampled_from(Role))
def test_decoder_never_raises(data, cuts, role):
    codec = VescCodec(role, firmware=(5, 2))
    for chunk in _chunks(data, cuts):
        codec.receive_data(chunk)
        for event in codec.events():
            assert event is not None
    assert codec.buffered <= len(data)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(no_start, requests), min_size=1, max_size=8), no_start,
       st.lists(st.integers(0, 5000), max_size=30))
def test_frames_between_garbage_are_all_recovered(pairs, tail, cuts):
    h = host()
    wire = b"".join(g + h.send(p) for g, p in pairs) + tail
    d = device()
    out = []
    for chunk in _chunks(wire, cuts):
        d.receive_data(chunk)
        out += d.events()
    assert out == [p for _, p in pairs]


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), requests, st.lists(st.integers(0, 5000), max_size=10))
def test_frame_after_arbitrary_garbage_and_a_gap_is_recovered(garbage, packet, cuts):
    # Arbitrary garbage may hold false starts (or even valid frames); a gap of idle bytes longer than
    # the longest frame lets every false start fail before the real frame begins, so the real
    # frame is always the last event.
    gap = bytes(MAX_PAYLOAD + 8)
    wire = garbage + gap + host().send(packet)
    d = device()
    out = []
    for chunk in _chunks(wire, cuts):
        d.receive_data(chunk)
        out += d.events()
    assert out and out[-1] == packet


@settings(deadline=None)
@given(requests)
def test_requests_round_trip_byte_exact(packet):
    wire = host().send(packet)
    d = device()
    d.receive_data(wire)
    (back,) = d.events()
    assert back == packet
    assert host().send(back) == wire


# --- cross-check against pyvesc (an independent implementation, test-time only) ----------------


def test_pyvesc_byte_equality():
    import pyvesc
    from pyvesc import GetValues, SetDutyCycle, SetRPM
    from pyvesc import SetCurrent as PvSetCurrent
    from pyvesc import SetCurrentBrake as PvSetCurrentBrake

    h = host()
    assert h.send(SetRpm(5000)) == pyvesc.encode(SetRPM(5000))
    assert h.send(SetRpm(-23250)) == pyvesc.encode(SetRPM(-23250))
    assert h.send(SetCurrent(5.0)) == pyvesc.encode(PvSetCurrent(5000))  # pyvesc takes mA
    assert h.send(SetCurrent(-1.5)) == pyvesc.encode(PvSetCurrent(-1500))
    assert h.send(SetCurrentBrake(20.0)) == pyvesc.encode(PvSetCurrentBrake(20000))
    assert h.send(SetDuty(0.25)) == pyvesc.encode(SetDutyCycle(25000))  # pyvesc takes duty x 1e5
    assert h.send(SetDuty(-1.0)) == pyvesc.encode(SetDutyCycle(-100000))
    assert h.send(GetValuesRequest()) == pyvesc.encode_request(GetValues)


def test_pyvesc_decodes_our_pre_3_07_values_reply():
    import pyvesc

    wire = VescCodec(Role.DEVICE, firmware=(2, 18)).send(SAMPLE)
    msg, consumed = pyvesc.decode(wire)
    assert consumed == len(wire)
    assert msg.rpm == -23250
    assert msg.v_in == pytest.approx(15.9)
    assert msg.tachometer == -123456
    assert msg.current_motor == pytest.approx(-12.34)


# --- COMM_GET_IMU_DATA (id 65) ----------------------------------------------------------------

def _imu_payload(values: dict[int, float], controller_id: int | None = None) -> bytes:
    """The reply as comm/commands.c lays it out: id, the mask (u16 big-endian), then one big-endian
    float32 per set bit in ascending bit order, then (6.05 on) the controller id byte."""
    mask = 0
    for bit in values:
        mask |= 1 << bit
    out = bytes([65, mask >> 8, mask & 0xFF])
    for bit in sorted(values):
        out += struct.pack(">f", values[bit])
    return out + (bytes([controller_id]) if controller_id is not None else b"")


#: Every field, in firmware units: rad, g, deg/s, µT, quaternion; values exact in float32.
FULL_IMU = {0: 0.015625, 1: -0.03125, 2: 1.5, 3: 0.125, 4: -0.0625, 5: 0.984375, 6: 0.5, 7: -0.25,
            8: 45.75, 9: 0.0, 10: 0.0, 11: 0.0, 12: 0.75, 13: 0.0, 14: 0.0, 15: -0.5}


@pytest.mark.parametrize("fw, controller_id", [((5, 2), None), ((6, 2), None), ((6, 5), 0), ((6, 6), 0)])
def test_imu_full_mask_byte_for_byte(fw, controller_id):
    reply = ImuData(**{IMU_FIELDS[bit]: v for bit, v in FULL_IMU.items()})
    payload = encode_payload(reply, fw)
    expected = _imu_payload(FULL_IMU, controller_id)
    assert payload == expected
    assert len(payload) == (68 if controller_id is not None else 67)
    host = VescCodec(Role.HOST, fw)
    host.receive_data(frame(expected))
    (back,) = host.events()
    assert back == dataclasses.replace(reply, controller_id=controller_id)
    assert back.gyro_z == 45.75 and back.acc_z == 0.984375 and back.q0 == 0.75


@pytest.mark.parametrize("controller_id", [None, 7])
def test_imu_partial_mask_byte_for_byte(controller_id):
    # gyro z and the quaternion only (bits 8, 12-15): what odometry needs
    values = {8: -12.5, 12: 1.0, 13: 0.0, 14: 0.0, 15: 0.0}
    expected = _imu_payload(values, controller_id)
    assert expected[1:3] == bytes([0xF1, 0x00])
    back = decode_imu_data(expected)
    assert back == ImuData(gyro_z=-12.5, q0=1.0, q1=0.0, q2=0.0, q3=0.0, controller_id=controller_id)
    assert back.mask == 0xF100
    device = VescCodec(Role.DEVICE, (6, 5) if controller_id is not None else (6, 2))
    sent = encode_payload(back, device.firmware)
    assert sent == _imu_payload(values, controller_id)


def test_imu_request_on_the_wire():
    assert host().send(GetImuDataRequest()) == frame(bytes([65, 0xFF, 0xFF]))
    assert host().send(GetImuDataRequest(0x0100)) == frame(bytes([65, 0x01, 0x00]))
    d = device()
    d.receive_data(frame(bytes([65, 0xFF, 0xFF])) + frame(bytes([65])))
    request, short = d.events()
    assert request == GetImuDataRequest(0xFFFF)
    assert isinstance(short, RawPacket) and "mask" in short.reason
    with pytest.raises(LocalProtocolError):
        host().send(GetImuDataRequest(0x10000))


def test_imu_short_or_non_finite_replies_are_raw():
    assert isinstance(decode_imu_data(bytes([65, 0xFF])), RawPacket)
    short = decode_imu_data(_imu_payload(FULL_IMU)[:-1])
    assert isinstance(short, RawPacket) and "needs 67" in short.reason
    nan = decode_imu_data(bytes([65, 0x01, 0x00]) + struct.pack(">f", math.nan))
    assert isinstance(nan, RawPacket) and "gyro_z" in nan.reason
    with pytest.raises(LocalProtocolError):
        encode_payload(ImuData(gyro_z=math.inf))
    with pytest.raises(LocalProtocolError):
        encode_payload(ImuData(gyro_z=1e39))


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_imu_non_finite_unused_fields_are_left_out_and_the_rest_kept(bad):
    """A NaN in the magnetometer or the firmware's roll/pitch/yaw (nothing publishes them) reads as
    absent; the rates, accelerations and quaternion of the same reply are kept. A NaN in any of
    those still refuses the reply."""
    values = dict(FULL_IMU)
    values[2], values[9], values[11] = bad, bad, -bad  # yaw, mag_x, mag_z
    back = decode_imu_data(_imu_payload(values))
    assert isinstance(back, ImuData)
    assert back.yaw is None and back.mag_x is None and back.mag_z is None
    assert back.roll == FULL_IMU[0] and back.mag_y == 0.0
    assert (back.gyro_z, back.acc_z, back.q0) == (45.75, 0.984375, 0.75)
    for bit in (3, 6, 12):  # acc_x, gyro_x, q0
        refused = decode_imu_data(_imu_payload({**values, bit: bad}))
        assert isinstance(refused, RawPacket) and IMU_FIELDS[bit] in refused.reason


def test_imu_trailing_bytes_after_the_id_are_ignored():
    back = decode_imu_data(_imu_payload({8: 3.0}, 2) + b"\x99\x98")
    assert back == ImuData(gyro_z=3.0, controller_id=2)


@pytest.mark.parametrize("fw", [(3, 52), (5, 2), (6, 2)])
def test_imu_trailing_bytes_before_6_05_are_not_a_controller_id(fw):
    """Firmware before 6.05 sends no id byte: whatever follows the fields is ignored, not read as
    one (the reference: decode by the echoed mask, ignore trailing bytes)."""
    payload = _imu_payload({8: 3.0}, 2) + b"\x99"
    assert decode_imu_data(payload, fw) == ImuData(gyro_z=3.0)
    host = VescCodec(Role.HOST, fw)
    host.receive_data(frame(payload))
    assert host.events() == [ImuData(gyro_z=3.0)]
    assert decode_imu_data(payload, (6, 5)) == ImuData(gyro_z=3.0, controller_id=2)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_imu_decoder_never_raises(body):
    event = decode_imu_data(bytes([65]) + body)
    assert isinstance(event, (ImuData, RawPacket))
    if isinstance(event, ImuData):
        assert all(math.isfinite(getattr(event, n)) for n in IMU_FIELDS if getattr(event, n) is not None)


# --- the one-struct fast path of GET_VALUES against the field-by-field definition -----------------


def _reference_encode(values: Values, layout: Layout) -> bytes:
    """GET_VALUES (3.07 and later) as the field table defines it, one field at a time."""
    out = bytearray([codec.CommandId.GET_VALUES])
    for name, fmt, scale in codec._NEW_FIELDS:
        if len(out) >= layout.value:
            break
        out += codec._pack_field(getattr(values, name), fmt, scale, name)
    return bytes(out)


def _reference_decode(payload: bytes, layout: Layout) -> Values:
    end, offset, fields = min(len(payload), layout.value), 1, {}
    for name, fmt, scale in codec._NEW_FIELDS:
        if offset + fmt.size > end:
            break
        fields[name] = codec._unpack_field(fmt, scale, payload, offset)
        offset += fmt.size
    return Values(**fields)


_NEW_LAYOUTS = [layout for layout in Layout if layout is not Layout.PRE_3_07]
_FW_OF = {Layout.V3_07: (3, 7), Layout.V3_34: (3, 34), Layout.V3_40: (3, 40), Layout.V3_48: (3, 48),
          Layout.V3_60: (3, 60), Layout.V5_03: (5, 3)}


@settings(max_examples=150, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                          st.integers(-(2**33), 2**33), st.booleans()),
                min_size=len(dataclasses.fields(Values)), max_size=len(dataclasses.fields(Values))),
       st.sampled_from(_NEW_LAYOUTS), st.integers(0, 30))
def test_values_fast_path_is_the_field_by_field_codec(raw, layout, cut):
    values = Values(**{f.name: v for f, v in zip(dataclasses.fields(Values), raw, strict=True)})
    try:
        expected: bytes | type[BaseException] = _reference_encode(values, layout)
    except (LocalProtocolError, OverflowError) as err:
        expected = type(err)
    if isinstance(expected, bytes):
        assert encode_values(values, layout) == expected
        # decoding: the whole payload, and one cut short (down to the 54 bytes every layout has)
        for payload in (expected, expected[:max(Layout.V3_07.value, len(expected) - cut)]):
            assert decode_values(payload, _FW_OF[layout]) == _reference_decode(payload, layout)
    else:
        with pytest.raises(expected):
            encode_values(values, layout)


def _reference_decode_imu(payload: bytes) -> ImuData | RawPacket:
    """GET_IMU_DATA read one field at a time, as the mask defines it."""
    if len(payload) < 3:
        return RawPacket(payload, "GET_IMU_DATA reply without its mask")
    mask = struct.unpack_from(">H", payload, 1)[0]
    names = [name for i, name in enumerate(IMU_FIELDS) if mask >> i & 1]
    end = 3 + 4 * len(names)
    if len(payload) < end:
        return RawPacket(payload, f"GET_IMU_DATA reply of {len(payload)} bytes, its mask {mask:#06x} "
                                  f"needs {end}")
    fields: dict = {}
    for k, name in enumerate(names):
        value = struct.unpack_from(">f", payload, 3 + 4 * k)[0]
        if not math.isfinite(value):
            if name in codec.IMU_LENIENT_FIELDS:
                continue
            return RawPacket(payload, f"GET_IMU_DATA {name} is not finite")
        fields[name] = value
    if len(payload) > end:
        fields["controller_id"] = payload[end]
    return ImuData(**fields)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 0xFFFF), st.binary(min_size=0, max_size=80), st.booleans())
def test_imu_reply_read_in_one_call_is_the_field_by_field_reading(mask, body, finite_floats):
    if finite_floats:  # mostly well-formed replies; otherwise any bytes (NaN, inf, short)
        n = bin(mask).count("1")
        body = b"".join(struct.pack(">f", (k * 0.37) % 5 - 2.5) for k in range(n)) + body[:2]
    payload = bytes([codec.CommandId.GET_IMU_DATA]) + struct.pack(">H", mask) + body
    got, want = decode_imu_data(payload), _reference_decode_imu(payload)
    assert got == want
    if isinstance(want, ImuData):  # and written back: the same fields, the same bytes
        again = decode_imu_data(codec.encode_imu_data(want, (6, 5) if want.controller_id is not None
                                                      else None))
        assert again == want
