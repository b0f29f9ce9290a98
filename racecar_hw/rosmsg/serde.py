"""Direct serializers from our message dataclasses to CDR and ROS 1 bytes, for the bag recorder.

The generic path (dataclass -> rosbags message object -> rosbags serializer) costs tens of
microseconds per message, most of it building the intermediate objects. Here every message class
gets one Python function, generated once from the typestore's field definitions, that packs the
dataclass straight into bytes: nested messages are inlined, runs of fixed-size fields become one
``struct`` call with the CDR padding baked in where the offset is known statically, numeric arrays
are ``numpy`` ``tobytes()``.

The bytes are those rosbags writes (``tests/test_bag_serde.py`` proves it with hypothesis for
every class in :mod:`racecar_hw.base.messages`, CDR and ROS 1):

* CDR (little endian): the 4-byte encapsulation header ``00 01 00 00``; every primitive aligned to
  its size relative to the end of that header; strings as uint32 length including the NUL, the
  UTF-8 bytes, the NUL; sequences as a uint32 count, then the elements.
* ROS 1: no alignment, strings without NUL, a top-level ``header.seq`` from the ``seq`` argument
  (nested headers get 0, as rosbags' converter in :mod:`racecar_hw.rosmsg.typestore` does).

Values are packed as declared: anything a serializer cannot pack as is (a float in an integer
field, a wrong array length, an unencodable string, a number out of range) raises, and that is
the error :meth:`racecar_hw.rosmsg.typestore.BagTypes.serialize` raises: there is no fallback.
Shapes the generator does not handle (string arrays, fixed arrays of messages, 8-byte element
sequences, big-endian hosts) raise :class:`Unsupported` when it is asked for them: no stream type
has one (``tests/test_bag_serde.py``), and the parameter services' types, which do, are
serialized by rosbags by design (:func:`racecar_hw.rosmsg.typestore.uses_rosbags_serde`).
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable
from struct import Struct
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

Serializer = Callable[[Any, int], bytes]

_NODE_BASE, _NODE_NAME, _NODE_ARRAY, _NODE_SEQUENCE = 1, 2, 3, 4

#: struct codes and sizes as rosbags packs each ROS base type (note: ``byte`` is signed there).
_FORMATS: dict[str, tuple[str, int]] = {
    "bool": ("?", 1), "byte": ("b", 1), "char": ("B", 1), "int8": ("b", 1), "uint8": ("B", 1),
    "int16": ("h", 2), "uint16": ("H", 2), "int32": ("i", 4), "uint32": ("I", 4),
    "int64": ("q", 8), "uint64": ("Q", 8), "float32": ("f", 4), "float64": ("d", 8),
}
_DTYPES: dict[str, Any] = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "octet": np.uint8,
    "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
    "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
    "float32": np.float32, "float64": np.float64,
}
_ZEROS = tuple(bytes(n) for n in range(8))
CDR_HEADER = b"\x00\x01\x00\x00"


class Unsupported(Exception):
    """A message shape the generator does not handle."""


class ShapeMismatch(ValueError):
    """An array field of the wrong length or rank."""


def _array(value: Any, dtype: Any, length: int) -> np.ndarray:
    """``value`` as a 1-D array of ``dtype``, of ``length`` elements unless ``length`` is 0."""
    arr = np.asarray(value, dtype=dtype)
    if arr.ndim != 1 or (length and arr.shape[0] != length):
        raise ShapeMismatch(f"array of shape {arr.shape}, expected ({length or 'n'},)")
    return arr


class _Generator:
    """Emits the body of one serializer, tracking the CDR offset modulo 8 where it is known."""

    def __init__(self, store: Typestore, classes: dict[str, type], cdr: bool) -> None:
        self.store = store
        self.classes = classes
        self.cdr = cdr
        self.lines: list[str] = []
        self.env: dict[str, Any] = {"_Z": _ZEROS, "_array": _array, "_str": str}
        self.indent = "    "
        self.counter = 0
        # The offset (from the end of the CDR header) is known to be ``res`` modulo ``mod``.
        self.mod, self.res = 8, 0
        self.run_fmt: list[str] = []
        self.run_args: list[str] = []

    def name(self, prefix: str) -> str:
        self.counter += 1
        return f"{prefix}{self.counter}"

    def emit(self, line: str) -> None:
        self.lines.append(self.indent + line)

    # --- offset bookkeeping -------------------------------------------------------------------

    def advance(self, size: int) -> None:
        self.res = (self.res + size) % self.mod

    def forget(self, mod: int = 1) -> None:
        """After data of run-time size: only ``offset % mod == 0`` is known."""
        self.mod, self.res = mod, 0

    def align(self, size: int) -> None:
        """Pad to a multiple of ``size`` (CDR only), statically when the offset is known."""
        if not self.cdr or size == 1:
            return
        if self.mod >= size:
            pad = -self.res % size
            if pad:
                self.run_fmt.append(f"{pad}x")
                self.advance(pad)
            return
        self.flush()
        self.emit(f"b += _Z[(4 - len(b)) & {size - 1}]")
        self.mod, self.res = size, 0

    def flush(self) -> None:
        """Emit the pending run of fixed-size fields as one struct call."""
        if not self.run_fmt:
            return
        packer = Struct("<" + "".join(self.run_fmt))
        var = self.name("_S")
        self.env[var] = packer
        if self.run_args:
            self.emit(f"b += {var}.pack({', '.join(self.run_args)})")
        else:
            self.emit(f"b += {_ZEROS[packer.size]!r}" if packer.size < 8 else f"b += bytes({packer.size})")
        self.run_fmt, self.run_args = [], []

    # --- fields -------------------------------------------------------------------------------

    def message(self, typename: str, expr: str, seq_expr: str | None, top: bool = False) -> None:
        """Inline the fields of ``typename`` read from the object ``expr``.

        ``seq_expr`` fills a missing ``seq`` field (the top-level ROS 1 header's); ``top`` marks
        the message itself, whose ``header`` field gets the top-level ``seq``.
        """
        if typename not in self.store.fielddefs:
            raise Unsupported(f"{typename} is not in the typestore")
        _, fields = self.store.fielddefs[typename]
        if not fields:
            raise Unsupported(f"{typename} has no fields")
        cls = self.classes.get(typename)
        if cls is None:
            raise Unsupported(f"no message class for {typename}")
        present = {f.name for f in dataclasses.fields(cls)}
        for fname, (node, detail) in fields:
            if fname in present:
                self.field(node, detail, f"{expr}.{fname}", "seq" if top and fname == "header" else None)
            elif node == _NODE_BASE and detail[0] in _FORMATS:
                # A field our dataclasses lack (ROS 1 header.seq): zero, or the top-level seq.
                fmt, size = _FORMATS[detail[0]]
                self.align(size)
                self.run_fmt.append(fmt)
                self.run_args.append(seq_expr if fname == "seq" and seq_expr else
                                     ("0.0" if fmt in "fd" else "False" if fmt == "?" else "0"))
                self.advance(size)
            else:
                raise Unsupported(f"{typename}.{fname} missing from {cls.__name__}")

    def field(self, node: int, detail: Any, expr: str, seq_expr: str | None) -> None:
        if node == _NODE_NAME:
            self.message(detail, expr, seq_expr)
        elif node == _NODE_BASE:
            self.base(detail[0], expr)
        elif node == _NODE_ARRAY:
            (inner_node, inner_detail), length = detail
            if inner_node != _NODE_BASE or inner_detail[0] not in _FORMATS:
                raise Unsupported(f"fixed array of {inner_detail}")
            self.numeric_array(inner_detail[0], expr, length)
        elif node == _NODE_SEQUENCE:
            (inner_node, inner_detail), _bound = detail
            if inner_node == _NODE_NAME:
                self.message_sequence(inner_detail, expr)
            elif inner_node == _NODE_BASE and inner_detail[0] in _FORMATS:
                self.numeric_array(inner_detail[0], expr, 0)
            else:
                raise Unsupported(f"sequence of {inner_detail}")
        else:
            raise Unsupported(f"field node {node}")

    def base(self, base: str, expr: str) -> None:
        if base == "string":
            var = self.name("_s")
            self.emit(f"{var} = _str({expr}).encode()")
            self.align(4)
            self.run_fmt.append("I")
            self.run_args.append(f"len({var}) + 1" if self.cdr else f"len({var})")
            self.flush()
            self.emit(f"b += {var}")
            if self.cdr:
                self.emit("b.append(0)")
            self.forget()
            return
        if base not in _FORMATS:
            raise Unsupported(f"base type {base}")
        fmt, size = _FORMATS[base]
        self.align(size)
        self.run_fmt.append(fmt)
        self.run_args.append(expr)
        self.advance(size)

    def numeric_array(self, base: str, expr: str, length: int) -> None:
        """A fixed array (``length`` > 0, no count) or a sequence (``length`` 0, uint32 count)."""
        _, size = _FORMATS[base]
        if not length and size > 4 and self.cdr:
            # rosbags skips the element alignment of an empty sequence but then assumes it: not mimicked.
            raise Unsupported(f"sequence of {base}")
        var = self.name("_a")
        dtype = self.name("_D")
        self.env[dtype] = _DTYPES[base]
        self.emit(f"{var} = _array({expr}, {dtype}, {length})")
        if length:
            self.align(size)
            self.flush()
            self.emit(f"b += {var}.tobytes()")
            self.advance(size * length)
            return
        self.align(4)
        self.run_fmt.append("I")
        self.run_args.append(f"len({var})")
        self.flush()
        self.emit(f"b += {var}.tobytes()")
        self.forget(min(4, size) if self.cdr else 1)

    def message_sequence(self, typename: str, expr: str) -> None:
        var = self.name("_q")
        item = self.name("_e")
        self.emit(f"{var} = {expr}")
        self.align(4)
        self.run_fmt.append("I")
        self.run_args.append(f"len({var})")
        self.flush()
        self.emit(f"for {item} in {var}:")
        outer = self.indent
        self.indent += "    "
        self.forget()
        self.message(typename, item, None)
        self.flush()
        self.indent = outer
        self.forget()


def generate(store: Typestore, classes: dict[str, type], typename: str, *, cdr: bool) -> Serializer:
    """The serializer ``f(msg, seq) -> bytes`` of ``typename``: CDR (``cdr``) or ROS 1.

    ``classes`` maps type names to our dataclasses (to know which store fields they lack).
    Raises :class:`Unsupported` for shapes this module does not generate.
    """
    if sys.byteorder != "little":
        raise Unsupported("big-endian host")
    gen = _Generator(store, classes, cdr)
    gen.message(typename, "m", None, top=True)
    gen.flush()
    start = f"b = bytearray({CDR_HEADER!r})" if cdr else "b = bytearray()"
    source = "\n".join(["def serialize(m, seq):", "    " + start, *gen.lines, "    return bytes(b)"])
    namespace = dict(gen.env)
    exec(compile(source, f"<bag_serde {typename} {'cdr' if cdr else 'ros1'}>", "exec"), namespace)  # noqa: S102
    fn: Serializer = namespace["serialize"]
    fn.__doc__ = source
    return fn


# --- reading CDR -------------------------------------------------------------------------------

Deserializer = Callable[[bytes], Any]


class Malformed(ValueError):
    """Bytes that are not a CDR message of the type: they end early, a string lacks its NUL,
    bytes follow the message, another encapsulation."""


def _string(raw: bytes, p: int) -> tuple[str, int]:
    """A CDR string at ``p`` (its uint32 length, aligned, counts the NUL): the text and the end."""
    p += -(p - 4) & 3
    (n,) = _U32.unpack_from(raw, p)
    end = p + 4 + n
    if n < 1 or end > len(raw) or raw[end - 1] != 0:
        raise Malformed("string")
    return str(raw[p + 4:end - 1], "utf-8"), end


def _count(raw: bytes, p: int, size: int) -> tuple[int, int]:
    """A sequence's uint32 count at ``p`` (aligned): the count and where its elements start."""
    p += -(p - 4) & 3
    (n,) = _U32.unpack_from(raw, p)
    p += 4
    if size > 1:
        p += -(p - 4) & (size - 1)
    if p + n * size > len(raw):
        raise Malformed("sequence")
    return n, p


_U32 = Struct("<I")


class _Reader:
    """Emits the body of one CDR deserializer; like :class:`_Generator`, tracks the offset mod 8."""

    def __init__(self, store: Typestore, classes: dict[str, type]) -> None:
        import typing  # noqa: PLC0415 - only when generating

        self.typing = typing
        self.store = store
        self.classes = classes
        self.lines: list[str] = []
        self.env: dict[str, Any] = {"_string": _string, "_count": _count, "_np": np, "_T": Malformed}
        self.indent = "    "
        self.counter = 0
        self.mod, self.res = 8, 0
        self.run_fmt: list[str] = []
        self.run_vars: list[str | None] = []

    def name(self, prefix: str) -> str:
        self.counter += 1
        return f"{prefix}{self.counter}"

    def emit(self, line: str) -> None:
        self.lines.append(self.indent + line)

    def forget(self, mod: int = 1) -> None:
        self.mod, self.res = mod, 0

    def align(self, size: int) -> None:
        if size == 1:
            return
        if self.mod >= size:
            pad = -self.res % size
            if pad:
                self.run_fmt.append(f"{pad}x")
                self.run_vars.append(None)
                self.res = (self.res + pad) % self.mod
            return
        self.flush()
        self.emit(f"p += -(p - 4) & {size - 1}")
        self.mod, self.res = size, 0

    def flush(self) -> None:
        if not self.run_fmt:
            return
        packer = Struct("<" + "".join(self.run_fmt))
        var = self.name("_S")
        self.env[var] = packer
        names = [v for v in self.run_vars if v is not None]
        if names:
            self.emit(f"{', '.join(names)}, = {var}.unpack_from(raw, p)")
        else:
            self.emit(f"if p + {packer.size} > len(raw): raise _T('padding')")
        self.emit(f"p += {packer.size}")
        self.run_fmt, self.run_vars = [], []

    def message(self, typename: str) -> str:
        """Emit code reading ``typename``; returns the expression that builds the object."""
        if typename not in self.store.fielddefs:
            raise Unsupported(f"{typename} is not in the typestore")
        _, fields = self.store.fielddefs[typename]
        cls = self.classes.get(typename)
        if cls is None or not fields:
            raise Unsupported(f"no message class for {typename}")
        hints = self.typing.get_type_hints(cls, vars(sys.modules[cls.__module__]))
        present = {f.name for f in dataclasses.fields(cls)}
        if not present <= {name for name, _ in fields}:
            raise Unsupported(f"{cls.__name__} has fields {typename} lacks")
        args = []
        for fname, (node, detail) in fields:
            value = self.field(node, detail, hints.get(fname))
            if fname in present:
                args.append(f"{fname}={value}")
        var = self.name("_C")
        self.env[var] = cls
        return f"{var}({', '.join(args)})"

    def field(self, node: int, detail: Any, hint: Any) -> str:
        if node == _NODE_NAME:
            return self.message(detail)
        if node == _NODE_BASE:
            return self.base(detail[0], hint)
        if node in (_NODE_ARRAY, _NODE_SEQUENCE):
            (inner_node, inner_detail), length = detail
            if node == _NODE_SEQUENCE:
                length = 0
            if inner_node == _NODE_BASE and inner_detail[0] in _FORMATS and inner_detail[0] != "bool":
                if hint is not np.ndarray:
                    raise Unsupported(f"array field typed {hint}")
                return self.numeric_array(inner_detail[0], length)
            if inner_node == _NODE_NAME and node == _NODE_SEQUENCE:
                return self.message_sequence(inner_detail)
        raise Unsupported(f"field {node} {detail}")

    def base(self, base: str, hint: Any) -> str:
        if base == "string":
            if hint is not str and hint is not None:
                raise Unsupported(f"string typed {hint}")
            self.flush()
            var = self.name("_s")
            self.emit(f"{var}, p = _string(raw, p)")
            self.forget()
            return var
        if base not in _FORMATS:
            raise Unsupported(f"base type {base}")
        fmt, size = _FORMATS[base]
        want = {"?": bool, "f": float, "d": float}.get(fmt, int)
        if hint is not None and hint is not want:
            raise Unsupported(f"{base} typed {hint}")
        self.align(size)
        var = self.name("_v")
        self.run_fmt.append(fmt)
        self.run_vars.append(var)
        self.res = (self.res + size) % self.mod
        return var

    def numeric_array(self, base: str, length: int) -> str:
        _, size = _FORMATS[base]
        var = self.name("_a")
        dtype = self.name("_D")
        self.env[dtype] = np.dtype(_DTYPES[base]).newbyteorder("<")
        if length:
            self.align(size)
            self.flush()
            self.emit(f"if p + {size * length} > len(raw): raise _T('array')")
            self.emit(f"{var} = _np.frombuffer(raw, {dtype}, {length}, p)")
            self.emit(f"p += {size * length}")
            self.res = (self.res + size * length) % self.mod
            return var
        if size > 4:
            raise Unsupported(f"sequence of {base}")  # as the writer: rosbags' empty-sequence quirk
        self.flush()
        count = self.name("_n")
        self.emit(f"{count}, p = _count(raw, p, {size})")
        self.emit(f"{var} = _np.frombuffer(raw, {dtype}, {count}, p)")
        self.emit(f"p += {count} * {size}")
        self.forget(size)
        return var

    def message_sequence(self, typename: str) -> str:
        self.flush()
        count, var, i = self.name("_n"), self.name("_q"), self.name("_i")
        self.emit(f"{count}, p = _count(raw, p, 1)")
        self.emit(f"{var} = []")
        self.emit(f"for {i} in range({count}):")
        outer = self.indent
        self.indent += "    "
        self.forget()
        built = self.message(typename)
        self.flush()
        self.emit(f"{var}.append({built})")
        self.indent = outer
        self.forget()
        return var


def generate_reader(store: Typestore, classes: dict[str, type], typename: str) -> Deserializer:
    """The CDR deserializer ``f(raw) -> message`` of ``typename`` (little-endian CDR, its header first).

    It reads what rosbags' ``deserialize_cdr`` reads and builds our dataclass directly; numeric
    arrays are read-only ``numpy`` views of ``raw`` (no copy). Bytes that end early, a string
    without its NUL, more than 3 bytes after the message, or another encapsulation raise
    :class:`Malformed` (or the ``struct``/UTF-8 error).
    Raises :class:`Unsupported` for shapes it does not generate (as :func:`generate`).
    """
    if sys.byteorder != "little":
        raise Unsupported("big-endian host")
    reader = _Reader(store, classes)
    built = reader.message(typename)
    reader.flush()
    source = "\n".join(["def deserialize(raw):",
                        f"    if raw[:4] != {CDR_HEADER!r}: raise _T('not little-endian CDR')",
                        "    p = 4", *reader.lines,
                        "    if p + 3 < len(raw): raise _T('bytes after the message')",  # as rosbags
                        f"    return {built}"])
    namespace = dict(reader.env)
    exec(compile(source, f"<cdr reader {typename}>", "exec"), namespace)  # noqa: S102
    fn: Deserializer = namespace["deserialize"]
    fn.__doc__ = source
    return fn
