"""The layer contract (pyproject.toml, docs/architecture.md) holds, and a wrong import is reported.

``lint-imports`` runs on a copy of the source tree with one module added, so the real tree is never
touched.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("racecar_hw", "vesc", "lidar_drivers", "mux", "safety")
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"

pytestmark = pytest.mark.skipif(not LINT_IMPORTS.exists(), reason="import-linter is not installed "
                                "(it is in the [test] extra)")


def _lint(tree: Path) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}
    return subprocess.run([str(LINT_IMPORTS), "--config", str(tree / "pyproject.toml"), "--no-cache"],
                          capture_output=True, text=True, cwd=tree, env=env, timeout=120)


@pytest.fixture
def tree(tmp_path):
    for name in PACKAGES:
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_source_tree_keeps_the_contracts(tree):
    proc = _lint(tree)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


@pytest.mark.parametrize(("module", "imports", "contract"), [
    ("vesc/_probe.py", "racecar_hw.daemon", "Layers"),           # a driver importing the daemon
    ("safety/_probe.py", "racecar_hw.bags.record", "Layers"),    # the safety stop importing bag I/O
    ("racecar_hw/base/_probe.py", "mux.node", "Layers"),          # the base importing a layer above
    ("racecar_hw/teleop/_probe.py", "racecar_hw.sim.world", "Layers"),  # only the top imports the sim
    ("lidar_drivers/_probe.py", "racecar_hw.rosmsg.serde", "stand on the base"),
    ("racecar_hw/sim/_probe.py", "racecar_hw.commands.sim", "command line"),
])
def test_a_wrong_import_is_reported(tree, module, imports, contract):
    (tree / module).write_text(f"import {imports}  # noqa\n")
    proc = _lint(tree)
    assert proc.returncode != 0
    probe = module.removesuffix(".py").replace("/", ".")
    assert re.search(rf"{re.escape(contract)}.*BROKEN", proc.stdout), proc.stdout
    assert probe in proc.stdout


def test_the_architecture_table_matches_the_contract():
    """docs/architecture.md's layer table lists the contract's layers, top to bottom."""
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = contracts[0]["layers"]
    doc = (ROOT / "docs" / "architecture.md").read_text()
    table = doc.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    documented = [sorted(re.findall(r"`([a-z_.]+)`", row.split("|")[1])) for row in rows]
    assert documented == [sorted(part.strip() for part in layer.split("|")) for layer in layers]
