"""YAML loading and ``--set section.key=value`` overrides, before any validation.

Overrides use dotted keys; a number segment indexes a list (``mux.inputs.1.timeout_s=0.5``).
Values are parsed as YAML scalars, so ``true``, ``0.5``, ``null`` and ``[1, 2]`` mean what they
say in the config file. A key the file does not have is taken from ``defaults`` (the documented
defaults, as plain data) before it is changed, so ``mux.inputs.1.timeout_s`` works with a config
file that leaves ``mux`` out: it changes the second of the default inputs.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import yaml

from racecar_hw.base.errors import ConfigError

#: The deepest nesting of flow collections (``[...]``, ``{...}``) a YAML text may have. PyYAML's
#: scanner takes time growing with the square of the depth (10 KB of ``[`` took it 4 s) before the
#: composer's recursion fails, so deeper text is refused as it is scanned.
MAX_FLOW_DEPTH = 64


class ShallowSafeLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing flow collections nested more than :data:`MAX_FLOW_DEPTH` deep
    (a ScannerError at the bracket that goes too deep) before its scanner slows down on them."""

    def fetch_flow_collection_start(self, TokenClass: Any) -> None:  # noqa: N803 - PyYAML's name
        if self.flow_level >= MAX_FLOW_DEPTH:
            raise yaml.scanner.ScannerError(None, None, "nested too deep", self.get_mark())
        super().fetch_flow_collection_start(TokenClass)  # type: ignore[misc]


class _UniqueKeyLoader(ShallowSafeLoader):
    """:class:`ShallowSafeLoader`, refusing a key given twice in one mapping (PyYAML keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                duplicate = key in seen
            except TypeError:  # an unhashable key: PyYAML's own error follows
                break
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark, f"found the key {key!r} twice",
                    key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str, where: str) -> Any:
    """``text`` parsed as YAML; a ConfigError in one line naming ``where`` and the line and column
    for bad YAML, a key given twice, nesting too deep to parse or an integer too long to convert."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark
        at = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        raise ConfigError("", f"{where} is not valid YAML: {at}{err.problem or err.context}") from None
    except yaml.YAMLError as err:
        raise ConfigError("", f"{where} is not valid YAML: {' '.join(str(err).split())}") from None
    except RecursionError:
        raise ConfigError("", f"{where} is not valid YAML: nested too deep") from None
    except ValueError as err:  # int() of more than 4,300 digits
        raise ConfigError("", f"{where} is not valid YAML: {err}") from None


def load_yaml(path: str | Path) -> dict[str, Any]:
    """The mapping in a YAML file; ConfigError for a missing or unreadable file, text that is not
    UTF-8, bad YAML (:func:`parse_yaml`) or a non-mapping."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise ConfigError("", f"config file not found: {p}") from err
    except OSError as err:
        raise ConfigError("", f"cannot read {p}: {err}") from err
    except UnicodeDecodeError as err:
        raise ConfigError("", f"{p} is not UTF-8 text (byte 0x{err.object[err.start]:02x} at offset "
                              f"{err.start})") from None
    data = parse_yaml(text, str(p))
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError("", f"{p} must hold a mapping of sections, not {type(data).__name__}")
    return data


def key_lines(path: str | Path) -> dict[tuple[str | int, ...], int]:
    """Where each key of a YAML file is: its path (names, and numbers for list items) -> line (from 1).

    Empty for a file that cannot be read or parsed (load_yaml reports that)."""
    try:
        root = yaml.compose(Path(path).read_text(encoding="utf-8"), Loader=ShallowSafeLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError):
        return {}
    out: dict[tuple[str | int, ...], int] = {}

    def walk(node: Any, at: tuple[str | int, ...]) -> None:
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                here = (*at, str(key.value))
                out[here] = key.start_mark.line + 1
                walk(value, here)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                out[(*at, i)] = item.start_mark.line + 1
                walk(item, (*at, i))

    walk(root, ())
    return out


def key_path(key: str) -> tuple[str | int, ...]:
    """A dotted error key as a path: ``mux.inputs[1].timeout_s`` or ``mux.inputs.1.timeout_s`` ->
    ``("mux", "inputs", 1, "timeout_s")``."""
    out: list[str | int] = []
    for token in re.findall(r"\[\d+\]|[^.\[\]]+", key):
        if token.startswith("["):
            out.append(int(token[1:-1]))
        else:
            out.append(int(token) if token.isdigit() else token)
    return tuple(out)


def remove_key(data: Any, path: tuple[str | int, ...]) -> bool:
    """Delete the value at ``path`` in ``data`` (mappings and lists); whether there was one."""
    node = data
    for part in path[:-1]:
        in_dict = isinstance(node, dict) and part in node
        if in_dict or (isinstance(node, list) and isinstance(part, int) and part < len(node)):
            node = node[part]
        else:
            return False
    last = path[-1] if path else None
    if isinstance(node, dict) and last in node:
        del node[last]
        return True
    if isinstance(node, list) and isinstance(last, int) and last < len(node):
        del node[last]
        return True
    return False


def apply_override(data: dict[str, Any], assignment: str,
                   defaults: dict[str, Any] | None = None) -> None:
    """Apply one ``dotted.key=value`` to ``data`` in place; missing sections come from ``defaults``."""
    key, sep, raw = assignment.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(assignment, "an override must look like section.key=value")
    if "" in key.split("."):
        raise ConfigError(key, "a part of the key is empty; an override must look like section.key=value")
    try:
        value = parse_yaml(raw, "the value") if raw.strip() else ""
    except ConfigError as err:
        shown = raw if len(raw) <= 60 else raw[:57] + "..."
        raise ConfigError(key, f"cannot parse value {shown!r}: {err}") from None
    parts = key.split(".")
    node: Any = data
    default: Any = defaults
    for i, part in enumerate(parts[:-1]):
        default = _default_child(default, part)
        node = _child(node, part, ".".join(parts[: i + 1]), create=True, default=default)
    last = parts[-1]
    if isinstance(node, list):
        node[_index(node, last, key)] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise ConfigError(key, f"{'.'.join(parts[:-1])} is not a section")


def merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """``base`` updated by ``extra``, recursively for mappings (lists are replaced)."""
    out = dict(base)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


def _default_child(default: Any, part: str) -> Any:
    if isinstance(default, dict):
        return default.get(part)
    if isinstance(default, list) and part.isdigit() and int(part) < len(default):
        return default[int(part)]
    return None


def _child(node: Any, part: str, where: str, create: bool, default: Any = None) -> Any:
    if isinstance(node, list):
        return node[_index(node, part, where)]
    if not isinstance(node, dict):
        raise ConfigError(where, "is not a section")
    if part not in node or node[part] is None:
        if not create:
            raise ConfigError(where, "not found")
        node[part] = copy.deepcopy(default) if isinstance(default, (dict, list)) else {}
    return node[part]


def _index(node: list[Any], part: str, where: str) -> int:
    if not part.isdigit() or int(part) >= len(node):
        items = f"the list has {len(node)} items (0..{len(node) - 1})" if node else "the list is empty"
        what = f"index {part} is out of range" if part.isdigit() else f"{part!r} is not a list index"
        raise ConfigError(where, f"{what}; {items}")
    return int(part)
