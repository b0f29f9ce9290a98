"""Typed, documented parameters built from plain mappings (YAML), refusing unknown keys.

A component declares its parameters as a dataclass whose fields use :func:`param`::

    @dataclass
    class VescParams:
        port: str = param("/dev/vesc", "serial port path or pyserial URL")
        poll_rate_hz: float = param(50.0, "telemetry poll rate", unit="Hz", min=1.0, max=500.0)

:func:`build` turns a mapping into an instance. Unknown keys, wrong types, values out of range
and values outside ``choices`` raise :class:`~racecar_hw.base.errors.ConfigError` naming the full
dotted key and what is allowed. Nested dataclasses, lists of dataclasses, tuples, ``X | None``
and ``dict[str, X]`` fields are supported. :func:`describe` lists every parameter with its default
and documentation, for ``check-config`` and the docs.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import typing
from collections.abc import Iterable, Iterator, Mapping
from typing import Any, TypeVar

from racecar_hw.base.errors import ConfigError

T = TypeVar("T")

_MISSING = dataclasses.MISSING


class _Mismatch(ConfigError):
    """A value of the wrong type or shape (not one out of range): for ``X | Y`` fields, where
    only a value that fits no option's type is said to fit none."""


def param(
    default: Any,
    doc: str,
    *,
    unit: str | None = None,
    min: float | None = None,  # noqa: A002 - reads naturally at the call site
    max: float | None = None,  # noqa: A002
    choices: tuple[Any, ...] | None = None,
    topic: bool = False,
    nonempty: bool = False,
) -> Any:
    """A dataclass field with a default, documentation, an optional unit, range and choices.

    A string with ``topic`` must be an absolute topic name (``/scan``); one with ``nonempty`` must
    not be empty (a frame id, a device path). Mutable defaults (lists, dicts, dataclass instances)
    are copied for each instance.
    """
    meta = {"doc": doc, "unit": unit, "min": min, "max": max, "choices": choices, "topic": topic,
            "nonempty": nonempty}
    if isinstance(default, (list, dict, set)) or dataclasses.is_dataclass(default):
        import copy

        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def unknown_key(name: str, allowed: Iterable[str], what: str = "key") -> str:
    """The message for an unknown ``name``: the close match (difflib) when there is one, else
    every allowed name."""
    choices = sorted(allowed)
    close = difflib.get_close_matches(name, choices, n=1, cutoff=0.6)
    if close:
        return f"unknown {what}; did you mean {close[0]}?"
    return f"unknown {what}; allowed {what}s: {', '.join(choices)}"


def build(cls: type[T], data: Mapping[str, Any] | None, key: str = "") -> T:
    """An instance of the parameter dataclass ``cls`` from ``data``; ``key`` prefixes error keys."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise _Mismatch(key, f"expected a mapping of parameters, got {_show(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(_join(key, str(unknown[0])), unknown_key(str(unknown[0]), fields, "key"))
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is _MISSING and f.default_factory is _MISSING:
                raise ConfigError(_join(key, name), "required")
            continue
        values[name] = _convert(hints[name], data[name], _join(key, name), f.metadata)
    try:
        return cls(**values)
    except ConfigError as err:
        # a check of the dataclass's own naming its field (or a part of it: ``steps[2].speed_mps``)
        if key and re.split(r"[.\[]", err.key, maxsplit=1)[0] in fields:
            raise ConfigError(_join(key, err.key), str(err).removeprefix(f"{err.key}: ")) from None
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(key, str(err)) from err


def to_dict(obj: Any) -> Any:
    """A parameter dataclass (or anything inside one) as plain YAML-ready data."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def describe(cls: type, key: str = "") -> Iterator[tuple[str, Any, str]]:
    """Every parameter of ``cls`` as (dotted key, default, documentation with unit and range)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        name = _join(key, f.name)
        if f.default is not _MISSING:
            default = f.default
        elif f.default_factory is not _MISSING:
            default = f.default_factory()
        else:
            default = None
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            yield from describe(hint, name)
            continue
        meta = f.metadata
        doc = meta.get("doc", "")
        extras = []
        if meta.get("unit"):
            extras.append(meta["unit"])
        if meta.get("min") is not None or meta.get("max") is not None:
            lo, hi = meta.get("min"), meta.get("max")
            extras.append(f"range {'-inf' if lo is None else lo}..{'inf' if hi is None else hi}")
        if meta.get("choices"):
            extras.append("one of " + ", ".join(map(str, meta["choices"])))
        if meta.get("topic"):
            extras.append("an absolute topic name")
        if meta.get("nonempty"):
            extras.append("not empty")
        if extras:
            doc = f"{doc} ({'; '.join(extras)})"
        yield name, to_dict(default), doc


def _convert(hint: Any, value: Any, key: str, meta: Mapping[str, Any]) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        for option in inner:
            try:
                return _convert(option, value, key, meta)
            except _Mismatch:
                continue  # not this type: try the next
            # any other ConfigError: the value has this option's type but is wrong (out of range)
        raise _Mismatch(key, f"{_show(value)} fits none of {', '.join(map(_name, inner))}")
    if dataclasses.is_dataclass(hint):
        return build(hint, value, key)
    if origin is list:
        if not isinstance(value, (list, tuple)):
            raise _Mismatch(key, f"expected a list, got {_show(value)}")
        return [_convert(args[0], v, f"{key}[{i}]", {}) for i, v in enumerate(value)]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _Mismatch(key, f"expected a list, got {_show(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]", meta) for i, v in enumerate(value))
        if len(value) != len(args):
            raise _Mismatch(key, f"expected {len(args)} values, got {len(value)}")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(a, v, f"{key}[{i}]", meta) for i, (a, v) in pairs)
    if origin is dict:
        if not isinstance(value, Mapping):
            raise _Mismatch(key, f"expected a mapping, got {_show(value)}")
        return {str(k): _convert(args[1], v, _join(key, str(k)), {}) for k, v in value.items()}
    if hint is Any:
        return value
    return _scalar(hint, value, key, meta)


def _scalar(hint: Any, value: Any, key: str, meta: Mapping[str, Any]) -> Any:
    if hint is bool:
        if not isinstance(value, bool):
            raise _Mismatch(key, f"expected true or false, got {_show(value)}")
        out: Any = value
    elif hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Mismatch(key, f"expected an integer, got {_show(value)}")
        out = value
    elif hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _Mismatch(key, f"expected a number, got {_show(value)}")
        out = float(value)
        if math.isnan(out):
            raise ConfigError(key, "NaN is not allowed")
    elif hint is str:
        choices = meta.get("choices") or ()
        if isinstance(value, bool) and {True: "on", False: "off"}[value] in choices:
            value = "on" if value else "off"  # YAML 1.1 reads a bare `off` (`--set safety.mode=off`) as false
        if not isinstance(value, str):
            raise _Mismatch(key, f"expected a string, got {_show(value)}")
        if meta.get("topic") and not value.startswith("/"):
            raise ConfigError(key, f"{value!r} is not an absolute topic name")
        if meta.get("nonempty") and not value:
            raise ConfigError(key, "must not be empty")
        out = value
    else:
        raise ConfigError(key, f"unsupported parameter type {_name(hint)}")
    choices = meta.get("choices")
    if choices is not None and out not in choices:
        raise ConfigError(key, f"{_show(out)} is not allowed; allowed values: "
                               + ", ".join(map(str, choices)))
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None and out < lo or hi is not None and out > hi:
        raise ConfigError(key, f"{_show(out)} is out of range; allowed: "
                               f"{'-inf' if lo is None else lo} to {'inf' if hi is None else hi}")
    return out


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _name(hint: Any) -> str:
    return getattr(hint, "__name__", str(hint))


def _show(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"
