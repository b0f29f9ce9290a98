"""rosbags typestores for racecar-hw messages, and conversion between our dataclasses and rosbags.

Two stores are used:

* ROS 2: ``Stores.ROS2_HUMBLE``, the distribution of the F1TENTH ``humble-devel`` stack. The
  message definitions racecar-hw writes (Header, LaserScan, Odometry, TFMessage, ...) are identical
  in Humble and Jazzy, so the RIHS01 hashes and CDR bytes are the same; Humble is named in the bag
  metadata only through the definitions, not as a distro string.
* ROS 1: ``Stores.ROS1_NOETIC``, plus ``tf2_msgs/msg/TFMessage``, which that store lacks.

Both get ackermann_msgs, vesc_msgs (the f1tenth/vesc ROS 2 ``VescState``) and racecar_msgs,
registered from the ``MSGDEF`` of :data:`racecar_hw.base.messages.CUSTOM_TYPES`. The ROS 1 store also
gets ``rcl_interfaces/msg/Log`` (the daemon's ``/rosout``); the ROS 2 store the request and response
types of the parameter services (:mod:`racecar_hw.base.parameter_messages`), under rosidl's names
(``rcl_interfaces/srv/ListParameters_Request``), and :meth:`BagTypes.digest` knows their service
types' RIHS01 hashes.

:meth:`BagTypes.serialize` packs the stream types' dataclasses directly (:mod:`racecar_hw.rosmsg.serde`,
generated from this store's definitions); the conversion below is the reference the tests compare
it with byte for byte, the path of the parameter services' types, and serves reading ROS 1 and
other stores' objects. Neither path falls back to the other. Conversion is generic over
dataclass fields, driven by the store's field definitions and cached
per type: nested messages recurse, numeric arrays become numpy arrays of the ROS element type,
fields our dataclasses lack (the ROS 1 ``header.seq``) are filled with zero on the way out and
dropped on the way in.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import sys
import typing
from collections.abc import Callable
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from racecar_hw.base import messages
from racecar_hw.base.errors import BagError
from racecar_hw.base.messages import CUSTOM_TYPES, Log, Message, TFMessage
from racecar_hw.base.parameter_messages import PARAMETER_CLASSES, SERVICE_MESSAGE_TYPES, SERVICE_TYPE_HASHES
from racecar_hw.rosmsg import serde

ROS2_STORE = Stores.ROS2_HUMBLE
ROS1_STORE = Stores.ROS1_NOETIC

#: Every message dataclass by its ROS 2 type name (``pkg/msg/Type``).
MESSAGE_CLASSES: dict[str, type[Message]] = {
    cls.ROS_TYPE: cls
    for _, cls in inspect.getmembers(messages, inspect.isclass)
    if issubclass(cls, Message) and cls is not Message and cls.ROS_TYPE
}


def uses_rosbags_serde(cls: type[Message]) -> bool:
    """Whether ``cls`` is serialized and read by rosbags rather than a generated serializer: the
    parameter services' request and response types (:mod:`racecar_hw.base.parameter_messages`),
    a few messages a minute, some with shapes the generator does not handle (string arrays,
    sequences of 8-byte numbers). Every stream type (:data:`MESSAGE_CLASSES`) is generated."""
    return PARAMETER_CLASSES.get(cls.ROS_TYPE) is cls


_NODE_BASE, _NODE_NAME, _NODE_ARRAY, _NODE_SEQUENCE = 1, 2, 3, 4

_DTYPES: dict[str, type[np.generic]] = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "octet": np.uint8,
    "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
    "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
    "float32": np.float32, "float64": np.float64,
}
_FLOATS = {"float32", "float64"}

ToRos = Callable[[Any], Any]
FromRos = Callable[[Any], Any]


class BagTypes:
    """One typestore with our custom types, and cached converters for our message classes.

    ``ros_version`` 1 serializes ROS 1 bytes (with ``header.seq``), 2 serializes CDR.
    """

    def __init__(self, ros_version: int) -> None:
        if ros_version not in (1, 2):
            raise ValueError(f"ros_version must be 1 or 2, not {ros_version}")
        self.ros_version = ros_version
        self.store: Typestore = get_typestore(ROS1_STORE if ros_version == 1 else ROS2_STORE)
        add: dict[str, Any] = {}
        if ros_version == 1:
            add.update(get_types_from_msg(TFMessage.MSGDEF, TFMessage.ROS_TYPE))
            add.update(get_types_from_msg(Log.MSGDEF, Log.ROS_TYPE))
        for cls in CUSTOM_TYPES:
            add.update(get_types_from_msg(cls.MSGDEF, cls.ROS_TYPE))
        if ros_version == 2:
            for cls in SERVICE_MESSAGE_TYPES:
                # rosbags files a pkg/srv/Name under pkg/srv/msg/Name: keep rosidl's name
                (fields,) = get_types_from_msg(cls.MSGDEF, cls.ROS_TYPE).values()
                add[cls.ROS_TYPE] = fields
        self.store.register(add)
        self._to: dict[str, ToRos] = {}
        self._from: dict[str, FromRos] = {}
        self._fast: dict[type[Message], serde.Serializer | None] = {}
        self._readers: dict[type[Message], serde.Deserializer | None] = {}

    # --- type information ---------------------------------------------------------------------

    def has(self, typename: str) -> bool:
        """Whether the store knows ``typename`` (``pkg/msg/Type``)."""
        return typename in self.store.fielddefs

    def msgdef(self, typename: str) -> str:
        """The definition bags store: ROS 1 with dependencies, or ROS 2 concatenated."""
        if self.ros_version == 1:
            return self.store.generate_msgdef(typename)[0]
        return self.store.generate_msgdef(typename, ros_version=2)[0]

    def digest(self, typename: str) -> str:
        """The ROS 1 md5sum or the ROS 2 RIHS01 type hash (of a message, or a parameter service)."""
        if self.ros_version == 2 and typename in SERVICE_TYPE_HASHES:
            return SERVICE_TYPE_HASHES[typename]
        if self.ros_version == 1:
            return self.store.generate_msgdef(typename)[1]
        return self.store.hash_rihs01(typename)

    # --- conversion ---------------------------------------------------------------------------

    def to_ros(self, msg: Message, seq: int = 0) -> Any:
        """``msg`` as a rosbags message object of this store; ``seq`` fills ROS 1 headers."""
        obj = self._to_converter(msg.ROS_TYPE)(msg)
        if seq and self.ros_version == 1 and hasattr(obj, "header"):
            obj.header.seq = seq
        return obj

    def from_ros(self, obj: Any, cls: type[Message] | None = None) -> Message:
        """A rosbags message object (from any store) as our dataclass ``cls``.

        Without ``cls`` the class is looked up from the object's ``__msgtype__``.
        """
        if cls is None:
            typename = getattr(obj, "__msgtype__", "")
            try:
                cls = MESSAGE_CLASSES[typename]
            except KeyError:
                raise BagError(f"no racecar-hw message class for {typename!r}") from None
        return _from_converter(cls)(obj)

    def serialize(self, msg: Message, seq: int = 0) -> bytes:
        """``msg`` serialized for a bag of this store: ROS 1 bytes or CDR (with its header).

        Stream types (:data:`MESSAGE_CLASSES`) use their generated serializer
        (:mod:`racecar_hw.rosmsg.serde`), which gives rosbags' bytes (``tests/test_bag_serde.py``);
        whatever it raises is the error: there is no second try. The parameter services' request
        and response types (a handful per minute) always take rosbags' serializer
        (:meth:`serialize_generic`).
        """
        try:
            fast = self._fast[type(msg)]
        except KeyError:
            fast = self.fast_serializer(type(msg))
        if fast is None:
            return self.serialize_generic(msg, seq)
        return fast(msg, seq)

    def fast_serializer(self, cls: type[Message]) -> serde.Serializer | None:
        """The generated serializer of ``cls`` for this store (built once).

        None for the types that use rosbags' serializer by design (:func:`uses_rosbags_serde`).
        A stream type the generator cannot handle raises :class:`BagError`: a generator failure
        is an error, never a silent switch to the slow path.
        """
        if cls in self._fast:
            return self._fast[cls]
        fast: serde.Serializer | None = None
        if not uses_rosbags_serde(cls):
            if cls.ROS_TYPE not in self.store.fielddefs:
                raise BagError(f"type {cls.ROS_TYPE} is not in the {self.store} typestore")
            classes: dict[str, type] = {**MESSAGE_CLASSES, cls.ROS_TYPE: cls}
            try:
                fast = serde.generate(self.store, classes, cls.ROS_TYPE, cdr=self.ros_version == 2)
            except serde.Unsupported as err:
                raise BagError(f"no serializer for {cls.ROS_TYPE}: {err}") from err
        self._fast[cls] = fast
        return fast

    def serialize_generic(self, msg: Message, seq: int = 0) -> bytes:
        """``msg`` serialized through a rosbags message object (the reference for the fast path)."""
        obj = self.to_ros(msg, seq)
        if self.ros_version == 1:
            return bytes(self.store.serialize_ros1(obj, msg.ROS_TYPE))
        return bytes(self.store.serialize_cdr(obj, msg.ROS_TYPE))

    def deserialize(self, raw: bytes | memoryview, cls: type[Message]) -> Message:
        """Bytes of ``cls.ROS_TYPE`` (ROS 1 or CDR, per this store) as our dataclass.

        CDR of a stream type is read by its generated reader
        (:func:`racecar_hw.rosmsg.serde.generate_reader`); its numeric arrays are then read-only
        views of ``raw``. Bytes it refuses raise (:class:`racecar_hw.rosmsg.serde.Malformed`, or
        the ``struct``/UTF-8 error): no second try. ROS 1 bytes and the parameter services' types
        are read by rosbags (:meth:`deserialize_generic`).
        """
        if self.ros_version == 2:
            try:
                reader = self._readers[cls]
            except KeyError:
                reader = self.fast_reader(cls)
            if reader is not None:
                return reader(raw)
        return self.deserialize_generic(raw, cls)

    def fast_reader(self, cls: type[Message]) -> serde.Deserializer | None:
        """The generated CDR reader of ``cls`` (built once; ROS 2 stores only), or None where rosbags
        reads (ROS 1, :func:`uses_rosbags_serde`). A stream type the generator cannot handle raises
        :class:`BagError`."""
        if cls in self._readers:
            return self._readers[cls]
        reader: serde.Deserializer | None = None
        if self.ros_version == 2 and not uses_rosbags_serde(cls):
            if cls.ROS_TYPE not in self.store.fielddefs:
                raise BagError(f"type {cls.ROS_TYPE} is not in the {self.store} typestore")
            classes: dict[str, type] = {**MESSAGE_CLASSES, cls.ROS_TYPE: cls}
            try:
                reader = serde.generate_reader(self.store, classes, cls.ROS_TYPE)
            except serde.Unsupported as err:
                raise BagError(f"no CDR reader for {cls.ROS_TYPE}: {err}") from err
        self._readers[cls] = reader
        return reader

    def deserialize_generic(self, raw: bytes | memoryview, cls: type[Message]) -> Message:
        """Bytes as our dataclass through a rosbags message object (the reference for the fast path)."""
        if self.ros_version == 1:
            obj = self.store.deserialize_ros1(raw, cls.ROS_TYPE)
        else:
            obj = self.store.deserialize_cdr(raw, cls.ROS_TYPE)
        return _from_converter(cls)(obj)

    def _to_converter(self, typename: str) -> ToRos:
        conv = self._to.get(typename)
        if conv is None:
            conv = self._build_to(typename)
            self._to[typename] = conv
        return conv

    def _build_to(self, typename: str) -> ToRos:
        if typename not in self.store.fielddefs:
            raise BagError(f"type {typename} is not in the {self.store} typestore")
        rostype = self.store.types[typename]
        _, fields = self.store.fielddefs[typename]
        steps: list[tuple[str, Callable[[Any], Any] | None, Any]] = []
        for name, (node, detail) in fields:
            steps.append((name, self._field_to(node, detail), _zero(node, detail)))

        def convert(msg: Any) -> Any:
            kwargs = {}
            for name, conv, zero in steps:
                value = getattr(msg, name, _ABSENT)
                if value is _ABSENT:
                    if zero is _ABSENT:
                        raise BagError(f"{typename}.{name}: {type(msg).__name__} has no such field")
                    kwargs[name] = zero
                else:
                    kwargs[name] = conv(value) if conv else value
            return rostype(**kwargs)

        return convert

    def _field_to(self, node: int, detail: Any) -> Callable[[Any], Any] | None:
        if node == _NODE_BASE:
            base = detail[0]
            if base in _FLOATS:
                return float
            if base == "bool":
                return bool
            if base == "string" or base == "wstring":
                return str
            return int
        if node == _NODE_NAME:
            return lambda v, _n=detail: self._to_converter(_n)(v)
        (inner_node, inner_detail), _length = detail
        if inner_node == _NODE_BASE and inner_detail[0] in _DTYPES:
            dtype = _DTYPES[inner_detail[0]]
            return lambda v, _d=dtype: np.asarray(v, dtype=_d)
        if inner_node == _NODE_NAME:
            return lambda v, _n=inner_detail: [self._to_converter(_n)(x) for x in v]
        return list


class _Absent:
    pass


_ABSENT = _Absent()


def _zero(node: int, detail: Any) -> Any:
    if node == _NODE_BASE:
        base = detail[0]
        if base in _FLOATS:
            return 0.0
        if base == "bool":
            return False
        if base in ("string", "wstring"):
            return ""
        return 0
    return _ABSENT


@functools.cache
def _from_converter(cls: type[Message]) -> FromRos:
    hints = typing.get_type_hints(cls, vars(sys.modules[cls.__module__]))
    steps: list[tuple[str, Callable[[Any], Any]]] = []
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        steps.append((f.name, _field_from(hints[f.name])))

    def convert(obj: Any) -> Message:
        return cls(**{name: conv(getattr(obj, name)) for name, conv in steps})

    return convert


def _field_from(hint: Any) -> Callable[[Any], Any]:
    if isinstance(hint, type) and issubclass(hint, Message):
        return lambda v, _c=hint: _from_converter(_c)(v)
    if hint is np.ndarray:
        return lambda v: np.array(v)
    origin = typing.get_origin(hint)
    if origin is list:
        (inner,) = typing.get_args(hint)
        if isinstance(inner, type) and issubclass(inner, Message):
            return lambda v, _c=inner: [_from_converter(_c)(x) for x in v]
        return list
    if hint is float:
        return float
    if hint is bool:
        return bool
    if hint is int:
        return int
    if hint is str:
        return str
    return lambda v: v


@functools.cache
def ros1_types() -> BagTypes:
    """The shared ROS 1 (Noetic + tf2_msgs + custom) store."""
    return BagTypes(1)


@functools.cache
def ros2_types() -> BagTypes:
    """The shared ROS 2 (Humble + custom) store."""
    return BagTypes(2)


def types_for(ros_version: int) -> BagTypes:
    """The shared store of ``ros_version`` (1 or 2)."""
    return ros1_types() if ros_version == 1 else ros2_types()
