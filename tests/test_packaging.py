"""Packaging: every package directory is installed, shipped data is found, the CLI starts."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import tomllib

from racecar_hw.base.resources import config_dir
from racecar_hw.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_directory_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = set()
    for top in ("racecar_hw", "vesc", "lidar_drivers", "mux", "safety"):
        for init in (ROOT / top).rglob("__init__.py"):
            found.add(".".join(init.parent.relative_to(ROOT).parts))
    found.add("racecar_hw.shipped")
    assert found == listed


def test_shipped_config_dir_is_found():
    assert (config_dir() / "__init__.py").exists()


def test_every_subcommand_has_help():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert len(sub.choices) >= len(COMMANDS)
    top = parser.format_help()
    for name, subparser in sub.choices.items():
        assert name in top
        assert subparser.format_help().startswith(f"usage: racecar-hw {name}")


def test_console_script_runs():
    out = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "--version"], capture_output=True,
                         text=True, check=True)
    assert out.stdout.startswith("racecar-hw ")


def test_sim_help_names_the_config_it_uses():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    text = " ".join(sub.choices["sim"].format_help().split())
    assert "default: the shipped sim config, config/sim.yaml" in text
    assert "shipped car config" not in text


def test_the_demo_output_is_ignored_by_git():
    assert "sim-out/" in (ROOT / ".gitignore").read_text().split()
