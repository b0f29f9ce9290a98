"""bag_serde: the generated serializers give rosbags' bytes for every message class, CDR and ROS 1.

Random messages are drawn per class from its dataclass fields and the store's field definitions
(string contents, array lengths, nested message lists, extreme numbers). For each, the direct
serializer and the generic rosbags path must agree: the same bytes, or both refuse the message.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from racecar_hw.base import messages
from racecar_hw.base.messages import (
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    KeyValue,
    LaserScan,
    Message,
    Odometry,
    String,
    TFMessage,
    Time,
    TransformStamped,
)
from racecar_hw.rosmsg.serde import Unsupported, generate
from racecar_hw.rosmsg.typestore import MESSAGE_CLASSES, BagTypes, ros1_types, ros2_types

STORES = {1: ros1_types, 2: ros2_types}
_INT_RANGES = {
    "bool": (0, 1), "byte": (-128, 127), "char": (0, 255), "int8": (-128, 127), "uint8": (0, 255),
    "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1), "int32": (-2**31, 2**31 - 1),
    "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1),
}
texts = st.text(st.characters(codec="utf-8"), max_size=12)


def _floats(base: str, valid: bool) -> st.SearchStrategy[float]:
    if base == "float32":
        if valid:
            return st.floats(width=32)
        # mostly representable, sometimes too large for float32 (both refuse)
        return st.one_of(st.floats(width=32), st.floats(width=32),
                         st.floats(allow_nan=True, allow_infinity=True))
    return st.floats(allow_nan=True, allow_infinity=True)


def _ints(base: str, valid: bool) -> st.SearchStrategy[int]:
    lo, hi = _INT_RANGES[base]
    if valid:
        return st.integers(lo, hi)
    return st.one_of(st.integers(lo, hi), st.integers(lo, hi), st.sampled_from([lo, hi, lo - 1, hi + 1]))


def _array(base: str, length: int, valid: bool) -> st.SearchStrategy[np.ndarray]:
    elems = _floats(base, valid) if base.startswith("float") else _ints(base, valid)
    size = st.just(length) if length else st.integers(0, 60)
    if length and not valid:  # now and then a wrong length: both paths must refuse it
        size = st.one_of(st.just(length), st.just(length), st.just(length), st.just(length + 1))
    dtype = np.float64 if base.startswith("float") else np.int64
    return size.flatmap(lambda n: st.lists(elems, min_size=n, max_size=n)).map(
        lambda v: np.array(v, dtype=dtype))


def messages_of(cls: type[Message], types: BagTypes, depth: int = 0,
                valid: bool = False) -> st.SearchStrategy[Message]:
    """Random instances of ``cls``, driven by the store's definition of ``cls.ROS_TYPE``.

    With ``valid``, every value fits its field. Otherwise any field may hold a value that does not
    fit (an integer out of range, a float too large for float32, a fixed array of the wrong length):
    a message with many fields then rarely fits as a whole.
    """
    hints = typing.get_type_hints(cls, vars(messages))
    _, fields = types.store.fielddefs[cls.ROS_TYPE]
    defs = dict(fields)
    kwargs: dict[str, st.SearchStrategy[Any]] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        node, detail = defs[f.name]
        hint = hints[f.name]
        if node == 1:  # base
            base = detail[0]
            if base == "string":
                kwargs[f.name] = texts
            elif base == "bool":
                kwargs[f.name] = st.booleans()
            elif base.startswith("float"):
                kwargs[f.name] = _floats(base, valid)
            else:
                kwargs[f.name] = _ints(base, valid)
        elif node == 2:  # nested message
            kwargs[f.name] = messages_of(hint, types, depth + 1, valid)
        elif node == 3:  # fixed array
            (_, (base, _)), length = detail
            kwargs[f.name] = _array(base, length, valid)
        else:  # sequence
            (inner_node, inner), _ = detail
            if inner_node == 2:
                (inner_cls,) = typing.get_args(hint)
                kwargs[f.name] = st.lists(messages_of(inner_cls, types, depth + 1, valid),
                                          max_size=3 if depth < 2 else 1)
            else:
                kwargs[f.name] = _array(inner[0], 0, valid)
    return st.builds(cls, **kwargs)


def outcome(fn: Any, *args: Any) -> bytes | type[BaseException]:
    try:
        return bytes(fn(*args))
    except Exception as err:  # noqa: BLE001 - compared between the two paths
        return type(err)


@pytest.mark.parametrize("version", [1, 2])
def test_every_message_class_has_a_direct_serializer(version: int) -> None:
    types = STORES[version]()
    for typename, cls in MESSAGE_CLASSES.items():
        assert types.fast_serializer(cls) is not None, typename


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")  # inf, both paths
@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("typename", sorted(MESSAGE_CLASSES))
def test_random_messages_serialize_as_rosbags_does(version: int, typename: str) -> None:
    types = STORES[version]()
    cls = MESSAGE_CLASSES[typename]
    fast = types.fast_serializer(cls)
    assert fast is not None
    serialized = 0

    @settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(msg=st.one_of(messages_of(cls, types, valid=True), messages_of(cls, types)),
           seq=st.integers(0, 2**32 - 1))
    def check(msg: Message, seq: int) -> None:
        nonlocal serialized
        generic = outcome(types.serialize_generic, msg, seq)
        direct = outcome(fast, msg, seq)
        if isinstance(generic, bytes):
            assert direct == generic
            assert types.serialize(msg, seq) == generic
            back = types.deserialize(generic, cls)
            assert type(back) is cls
            serialized += 1
        else:  # the generic path refuses: so does the direct one, and serialize() raises its error
            assert not isinstance(direct, bytes)
            with pytest.raises(generic):
                types.serialize(msg, seq)

    check()
    assert serialized >= 5  # most draws are valid messages: the comparison is not vacuous


def test_header_seq_only_on_the_top_level_ros1_header() -> None:
    tf = TFMessage([TransformStamped(Header(Time(1, 2), "odom"), "base_link")])
    odom = Odometry(Header(Time(3, 4), "odom"), "base_link")
    for msg in (tf, odom, Header(Time(5, 6), "x")):
        for seq in (0, 9):
            assert ros1_types().serialize(msg, seq) == ros1_types().serialize_generic(msg, seq)
    assert ros1_types().serialize(odom, 9)[:4] == (9).to_bytes(4, "little")
    assert ros1_types().serialize(Header(Time(5, 6), "x"), 9)[:4] == bytes(4)  # no header field


@pytest.mark.parametrize("version", [1, 2])
def test_unusual_values_fall_back_to_the_generic_path(version: int) -> None:
    types = STORES[version]()
    odd = [
        String(5),  # type: ignore[arg-type]  # str() of a non-string, as the generic path does
        Header(Time(1.0, 2), "x"),  # type: ignore[arg-type]  # int(1.0) in the generic path only
        LaserScan(ranges=[1.0, 2.0], intensities=(3, 4)),  # type: ignore[arg-type]  # lists
        LaserScan(ranges=np.arange(6, dtype=np.float64)[::2]),  # strided, converted to float32
        DiagnosticArray(status=(DiagnosticStatus(values=[KeyValue("k", "v")]),)),  # type: ignore[arg-type]
    ]
    for msg in odd:
        assert types.serialize(msg, 2) == types.serialize_generic(msg, 2)
    bad = [Odometry(pose=messages.PoseWithCovariance(covariance=np.zeros(35))),
           Header(Time(2**40, 0), "x"), DiagnosticStatus(level=300)]
    for msg in bad:
        with pytest.raises(Exception) as generic:
            types.serialize_generic(msg)
        with pytest.raises(type(generic.value)):
            types.serialize(msg)


def test_unsupported_shapes_are_not_generated() -> None:
    types = ros2_types()
    for typename in ("sensor_msgs/msg/JointState", "std_msgs/msg/Float64MultiArray"):
        with pytest.raises(Unsupported):
            generate(types.store, MESSAGE_CLASSES, typename, cdr=True)


def test_cdr_alignment_after_strings() -> None:
    # frame_id lengths 0..8 move every later field across all offsets modulo 8.
    for n in range(9):
        odom = Odometry(Header(Time(1, 2), "f" * n), "c" * (8 - n))
        odom.pose.pose.position.x = math.pi
        data = ros2_types().serialize(odom)
        assert data == ros2_types().serialize_generic(odom)
        assert repr(ros2_types().deserialize(data, Odometry)) == repr(odom)


# --- the direct CDR reader -------------------------------------------------------------------


def same_message(a: Any, b: Any) -> bool:
    """Field by field: equal numbers (NaN equal to NaN), strings, arrays (values and dtype)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, list):
        return len(a) == len(b) and all(same_message(x, y) for x, y in zip(a, b, strict=True))
    if dataclasses.is_dataclass(a):
        return all(same_message(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, float) and math.isnan(a):
        return math.isnan(b)
    return bool(a == b)


def read_outcome(fn: Any, raw: bytes, cls: type[Message]) -> Any:
    try:
        return fn(raw, cls)
    except Exception as err:  # noqa: BLE001 - compared between the two paths
        return err


def test_every_message_class_has_a_direct_reader() -> None:
    for typename, cls in MESSAGE_CLASSES.items():
        assert ros2_types().fast_reader(cls) is not None, typename


@pytest.mark.parametrize("typename", sorted(MESSAGE_CLASSES))
def test_random_and_damaged_bytes_read_as_rosbags_reads_them(typename: str) -> None:
    """Valid messages read back the same by the direct reader and rosbags; damaged bytes (cut,
    flipped, extended) either read the same on both paths or the direct reader refuses them and
    :meth:`BagTypes.deserialize` gives rosbags' result or error."""
    types = ros2_types()
    cls = MESSAGE_CLASSES[typename]
    reader = types.fast_reader(cls)
    assert reader is not None
    read = 0

    @settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(msg=messages_of(cls, types, valid=True), data=st.data())
    def check(msg: Message, data: st.DataObject) -> None:
        nonlocal read
        raw = types.serialize(msg)
        direct = reader(raw)
        assert same_message(direct, types.deserialize_generic(raw, cls))
        read += 1
        damage = data.draw(st.sampled_from(["cut", "flip", "extend", "none"]))
        if damage == "cut":
            raw = raw[:data.draw(st.integers(0, len(raw)))]
        elif damage == "flip" and len(raw) > 4:
            i = data.draw(st.integers(4, len(raw) - 1))
            raw = raw[:i] + bytes([raw[i] ^ data.draw(st.integers(1, 255))]) + raw[i + 1:]
        elif damage == "extend":
            raw += data.draw(st.binary(max_size=9))
        generic = read_outcome(types.deserialize_generic, raw, cls)
        fast = read_outcome(lambda r, _c: reader(r), raw, cls)
        if not isinstance(fast, Exception):  # what the direct reader accepts, rosbags reads the same
            assert not isinstance(generic, Exception), (raw, generic)
            assert same_message(fast, generic)
        chosen = read_outcome(types.deserialize, raw, cls)
        if isinstance(generic, Exception):
            assert type(chosen) is type(generic)
        else:
            assert same_message(chosen, generic)

    check()
    assert read >= 30


def test_direct_reader_views_without_copying() -> None:
    scan = LaserScan(Header(Time(1, 2), "laser"), ranges=np.arange(1081, dtype=np.float32))
    raw = ros2_types().serialize(scan)
    back = ros2_types().deserialize(raw, LaserScan)
    assert isinstance(back, LaserScan) and back.ranges.base is not None
    assert np.array_equal(back.ranges, scan.ranges) and not back.ranges.flags.writeable
    with pytest.raises(Exception):  # noqa: B017, PT011 - big-endian CDR: not the direct reader's
        ros2_types().fast_reader(LaserScan)(b"\x00\x00\x00\x00" + raw[4:])  # type: ignore[misc]
