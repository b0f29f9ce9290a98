"""ROS 2 message types as Cyclone DDS topic types that carry raw CDR: one message model, not two.

ROS 2's DDS middlewares name a message type ``pkg::msg::dds_::Name_`` and put it on the wire as
plain CDR (XCDR1, little endian, the 4-byte encapsulation header ``00 01 00 00``): the same bytes
rosbags writes (:mod:`racecar_hw.rosmsg`). Cyclone's Python API wants an ``IdlStruct`` class per
topic, for two things: the type's name and structure (its XTypes type information, announced in
discovery) and the (de)serialization of samples. Here the class is *generated* from the typestore's
field definitions, the ones the recorder and the Zenoh bridge serialize with, declared ``@final``
(plain XCDR1: ``@appendable`` would make Fast DDS report an incompatible data representation), and
its (de)serialization is replaced by pass-through of bytes:

* :func:`raw_sample` wraps CDR bytes made by :mod:`racecar_hw.rosmsg` so ``DataWriter.write`` sends
  them as they are;
* a ``DataReader`` of such a topic returns :class:`RawSample` objects holding the received CDR
  bytes (header included), which :mod:`racecar_hw.rosmsg` decodes into our dataclasses.

So the project keeps one serializer, and Cyclone never builds Python objects of the messages. This
relies on ``DataWriter.write`` calling ``sample.serialize()`` and ``DataReader.take`` calling
``data_type.deserialize()`` (cyclonedds 11; the version is bounded in pyproject.toml, and
tests/test_dds.py checks a round trip through a real Cyclone writer and reader).
"""

from __future__ import annotations

import functools
from typing import Any

from rosbags.typesys.store import Typestore

from racecar_hw.net.rmw import dds_type

#: ROS 2 base types -> the names of their ``cyclonedds.idl.types`` (``str`` for strings).
_BASE = {
    "bool": "bool", "byte": "byte", "octet": "byte", "char": "uint8",
    "int8": "int8", "uint8": "uint8", "int16": "int16", "uint16": "uint16",
    "int32": "int32", "uint32": "uint32", "int64": "int64", "uint64": "uint64",
    "float32": "float32", "float64": "float64",
}
_NODE_BASE, _NODE_NAME, _NODE_ARRAY, _NODE_SEQUENCE = 1, 2, 3, 4


class RawSample:
    """One received sample: its CDR bytes (with the encapsulation header) and Cyclone's sample info."""

    __slots__ = ("data", "sample_info")

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.sample_info: Any = None


def _serialize_raw(self: Any, buffer: Any = None, endianness: Any = None, use_version_2: Any = None) -> bytes:
    return self._cdr  # type: ignore[no-any-return]


def _deserialize_raw(cls: Any, data: bytes, has_header: bool = True, use_version_2: Any = None) -> RawSample:
    return RawSample(bytes(data))


class TypeFactory:
    """Cyclone topic types for the ROS 2 types of one rosbags typestore (built once per type)."""

    def __init__(self, store: Typestore) -> None:
        self.store = store
        self._structs: dict[str, Any] = {}

    def struct(self, ros_type: str) -> Any:
        """The ``@final`` IdlStruct of ``ros_type`` (``pkg/msg/Name``), with its nested types."""
        if ros_type not in self._structs:
            self._structs[ros_type] = self._make(ros_type)
        return self._structs[ros_type]

    def topic_type(self, ros_type: str) -> Any:
        """The type of a topic of ``ros_type``: the same structure, samples are raw CDR both ways.

        A class of its own (not a subclass: Cyclone builds no type object for an inherited struct),
        so the same type nested in another keeps Cyclone's own serialization.
        """
        key = "raw:" + ros_type
        if key not in self._structs:
            cls = self._make(ros_type)
            cls.serialize = _serialize_raw
            cls.deserialize = classmethod(_deserialize_raw)
            self._structs[key] = cls
        return self._structs[key]

    def _make(self, ros_type: str) -> Any:
        from cyclonedds.idl import make_idl_struct  # noqa: PLC0415 - loads Cyclone's C library
        from cyclonedds.idl.annotations import final  # noqa: PLC0415

        _, fields = self.store.fielddefs[ros_type]
        annotations = {name: self._field(node, detail) for name, (node, detail) in fields}
        return final(make_idl_struct(ros_type.rsplit("/", 1)[1] + "_", dds_type(ros_type), annotations))

    def _field(self, node: int, detail: Any) -> Any:
        from cyclonedds.idl import types  # noqa: PLC0415

        if node == _NODE_BASE:
            name, bound = detail
            if name == "string":
                return types.bounded_str[bound] if bound else str
            if name == "wstring":
                raise TypeError("wstring fields are not supported")
            return bool if name == "bool" else getattr(types, _BASE[name])
        if node == _NODE_NAME:
            return self.struct(detail)
        inner, size = detail
        element = self._field(*inner)
        if node == _NODE_ARRAY:
            return types.array[element, size]
        return types.sequence[element, size] if size else types.sequence[element]


def raw_sample(topic_type: Any, cdr: bytes) -> Any:
    """An instance of a :meth:`TypeFactory.topic_type` that ``DataWriter.write`` sends as ``cdr``."""
    sample = object.__new__(topic_type)
    sample._cdr = cdr
    return sample


@functools.cache
def ros2_factory() -> TypeFactory:
    """The factory for racecar-hw's ROS 2 typestore (:func:`racecar_hw.rosmsg.typestore.ros2_types`)."""
    from racecar_hw.rosmsg.typestore import ros2_types  # noqa: PLC0415

    return TypeFactory(ros2_types().store)
