"""No module touches rosbags' internals: rosbags reads bags and provides the type definitions
(typestores); every file racecar-hw writes is written by its own writers or the ``mcap`` library.

Checked over the source of every package (AST, not text): no import of a private rosbags module or
name, none of rosbags' writers or storage plugins, and in a module that imports rosbags no
attribute with a private name read from anything but ``self``/``cls``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("racecar_hw", "vesc", "lidar_drivers", "mux", "safety")
#: rosbags modules and names that write bags: racecar-hw writes its own.
WRITERS = {("rosbags.rosbag1", "Writer"), ("rosbags.rosbag2", "Writer")}
WRITER_MODULES = ("rosbags.rosbag2.storage_mcap", "rosbags.rosbag2.storage_sqlite3", "rosbags.rosbag1.writer",
                  "rosbags.rosbag2.writer")


def sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def problems(path: Path, root: Path = ROOT) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf8"), str(path))
    found: list[str] = []
    uses_rosbags = False
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "rosbags":
                    uses_rosbags = True
                    if any(part.startswith("_") for part in alias.name.split(".")):
                        found.append(f"imports private module {alias.name}")
                    if alias.name.startswith(WRITER_MODULES):
                        found.append(f"imports rosbags' writer module {alias.name}")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "rosbags":
            uses_rosbags = True
            if any(part.startswith("_") for part in node.module.split(".")):
                found.append(f"imports from private module {node.module}")
            if node.module.startswith(WRITER_MODULES):
                found.append(f"imports from rosbags' writer module {node.module}")
            for alias in node.names:
                if alias.name.startswith("_"):
                    found.append(f"imports private name {node.module}.{alias.name}")
                if (node.module, alias.name) in WRITERS:
                    found.append(f"imports rosbags' writer {node.module}.{alias.name}")
    if uses_rosbags:
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load)
                    and node.attr.startswith("_") and not node.attr.startswith("__")
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
                found.append(f"line {node.lineno}: reads private attribute .{node.attr}")
    return [f"{path.relative_to(root)}: {p}" for p in found]


def test_no_module_touches_rosbags_internals_or_writers() -> None:
    assert len(sources()) > 50
    assert [p for path in sources() for p in problems(path)] == []


@pytest.mark.parametrize("code", [
    "from rosbags.rosbag2 import Writer\n",
    "from rosbags.rosbag2.storage_mcap import McapWriter\n",
    "import rosbags.rosbag1.writer\n",
    "from rosbags.typesys.store import _private\n",
    "from rosbags.typesys import get_typestore\nx = get_typestore(1)._cache\n",
])
def test_the_check_finds_each_kind(tmp_path: Path, code: str) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text(code)
    assert problems(probe, tmp_path), code
    probe.write_text("from rosbags.typesys import get_typestore\nx = get_typestore(1).fielddefs\n")
    assert problems(probe, tmp_path) == []
