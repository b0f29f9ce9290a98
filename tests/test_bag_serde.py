"""bag_serde: the generated serializers give rosbags' bytes for every message class, CDR and ROS 1.

Random messages are drawn per class from its dataclass fields and the store's field definitions
(string contents, array lengths, nested message lists, extreme numbers). For each, the direct
serializer and the generic rosbags path must agree: the same bytes, or both refuse the message.
Every type a live interface or a bag carries is a class here; the dataclasses equal the store's
definitions field for field; a serializer or generator error is raised, never retried elsewhere.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, ClassVar

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mux.params import MuxParams
from racecar_hw.base import messages
from racecar_hw.base.errors import BagError
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
from racecar_hw.base.parameter_messages import PARAMETER_CLASSES
from racecar_hw.net.topics import topic_table
from racecar_hw.rosmsg.serde import Malformed, Unsupported, generate
from racecar_hw.rosmsg.typestore import (
    MESSAGE_CLASSES,
    BagTypes,
    ros1_types,
    ros2_types,
    uses_rosbags_serde,
)
from safety.params import SafetyParams

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

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
            assert outcome(types.serialize, msg, seq) is direct

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
def test_unusual_values_serialize_as_rosbags_does_or_raise(version: int) -> None:
    types = STORES[version]()
    odd = [
        String(5),  # type: ignore[arg-type]  # str() of a non-string, as the generic path does
        LaserScan(ranges=[1.0, 2.0], intensities=(3, 4)),  # type: ignore[arg-type]  # lists
        LaserScan(ranges=np.arange(6, dtype=np.float64)[::2]),  # strided, converted to float32
        DiagnosticArray(status=(DiagnosticStatus(values=[KeyValue("k", "v")]),)),  # type: ignore[arg-type]
        Header(Time(np.int64(1), np.uint32(2)), "x"),  # type: ignore[arg-type]  # numpy integers
    ]
    for msg in odd:
        assert types.serialize(msg, 2) == types.serialize_generic(msg, 2)
    bad = [Odometry(pose=messages.PoseWithCovariance(covariance=np.zeros(35))),
           Header(Time(2**40, 0), "x"), DiagnosticStatus(level=300)]
    for msg in bad:
        with pytest.raises(Exception):  # noqa: B017, PT011 - rosbags' error
            types.serialize_generic(msg)
        with pytest.raises(Exception):  # noqa: B017, PT011 - the generated serializer's own error
            types.serialize(msg)
    # A float in an integer field: rosbags' converter would int() it; the generated serializer
    # packs values as declared and raises (the error reaches the caller: no second try).
    with pytest.raises(Exception):  # noqa: B017, PT011 - struct.error
        types.serialize(Header(Time(1.0, 2), "x"))  # type: ignore[arg-type]


def test_every_live_and_bag_type_is_a_generated_class() -> None:
    """Every type a live interface offers (the topic table, both directions) is a stream class with
    generated serializers (so the hypothesis tests above cover it); the bag recorder writes bus
    messages, which are these classes. Only the parameter services' types take rosbags' path."""
    rows = topic_table(MuxParams(), SafetyParams())
    assert rows
    for row in rows:
        assert MESSAGE_CLASSES.get(row.msgtype.ROS_TYPE) is row.msgtype, row
        assert not uses_rosbags_serde(row.msgtype)
    for cls in MESSAGE_CLASSES.values():
        assert not uses_rosbags_serde(cls)
        assert ros2_types().fast_serializer(cls) is not None
        assert ros2_types().fast_reader(cls) is not None
        assert ros1_types().fast_serializer(cls) is not None
    for cls in PARAMETER_CLASSES.values():
        assert uses_rosbags_serde(cls)
        assert ros2_types().fast_serializer(cls) is None and ros2_types().fast_reader(cls) is None


def test_dataclasses_equal_the_store_definitions_field_for_field() -> None:
    """The hand-written dataclasses are the bus's message model; the typestore is the wire's. They
    must name the same fields in the same order with matching kinds (the ROS 1 store adds only the
    top-level ``Header.seq``, which the ROS 1 writer fills)."""
    scalar = {"bool": bool, "string": str, "float32": float, "float64": float}
    for version in (1, 2):
        types = STORES[version]()
        for typename, cls in {**MESSAGE_CLASSES, **PARAMETER_CLASSES}.items():
            if not types.has(typename):
                assert version == 1 and cls in PARAMETER_CLASSES.values(), typename
                continue
            _, fields = types.store.fielddefs[typename]
            names = [name for name, _ in fields]
            if version == 1 and typename == "std_msgs/msg/Header":
                assert names[0] == "seq"
                fields = fields[1:]
            hints = typing.get_type_hints(cls, vars(__import__(cls.__module__, fromlist=["_"])))
            assert [f.name for f in dataclasses.fields(cls)] == [n for n, _ in fields], typename
            for name, (node, detail) in fields:
                hint = hints[name]
                if node == 1:
                    assert hint is scalar.get(detail[0], int), (typename, name, hint)
                elif node == 2:
                    assert detail == hint.ROS_TYPE, (typename, name)
                else:
                    (inner_node, inner), _n = detail
                    if inner_node == 2:
                        (inner_cls,) = typing.get_args(hint)
                        assert inner == inner_cls.ROS_TYPE, (typename, name)
                    elif inner[0] == "string":
                        assert typing.get_args(hint) == (str,), (typename, name, hint)
                    elif typename in MESSAGE_CLASSES:  # stream types: numbers as numpy arrays
                        assert hint is np.ndarray, (typename, name, hint)
                    else:  # the parameter services' types: lists of the element kind
                        assert typing.get_args(hint) == (scalar.get(inner[0], int),), (typename, name)


def test_a_generator_failure_is_an_error() -> None:
    """A stream class the generator cannot handle raises at once: there is no silent slow path."""

    @dataclasses.dataclass
    class Odd(Message):  # a sequence of strings: a shape the generator does not handle
        ROS_TYPE: ClassVar[str] = "sensor_msgs/msg/JointState"
        header: Header = dataclasses.field(default_factory=Header)
        name: list[str] = dataclasses.field(default_factory=list)

    for types in (BagTypes(2), BagTypes(1)):
        with pytest.raises(BagError):
            types.fast_serializer(Odd)
        with pytest.raises(BagError):
            types.serialize(Odd())  # type: ignore[arg-type]
    with pytest.raises(BagError):
        BagTypes(2).fast_reader(Odd)

    @dataclasses.dataclass
    class Unknown(Message):
        ROS_TYPE: ClassVar[str] = "nobody_msgs/msg/Nothing"
        x: int = 0

    with pytest.raises(BagError):
        BagTypes(2).serialize(Unknown())


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
    flipped, extended) either read the same on both paths or the direct reader refuses them, and
    :meth:`BagTypes.deserialize` then raises the reader's error (no second try with rosbags)."""
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
        if isinstance(fast, Exception):
            assert type(chosen) is type(fast)
        else:
            assert same_message(chosen, fast)

    check()
    assert read >= 30


def test_direct_reader_views_without_copying() -> None:
    scan = LaserScan(Header(Time(1, 2), "laser"), ranges=np.arange(1081, dtype=np.float32))
    raw = ros2_types().serialize(scan)
    back = ros2_types().deserialize(raw, LaserScan)
    assert isinstance(back, LaserScan) and back.ranges.base is not None
    assert np.array_equal(back.ranges, scan.ranges) and not back.ranges.flags.writeable
    with pytest.raises(Malformed):  # big-endian CDR: not the direct reader's, and no second try
        ros2_types().deserialize(b"\x00\x00\x00\x00" + raw[4:], LaserScan)
