"""The shipped Foxglove layouts are what racecar_hw.net.layout builds, and name what the server serves."""

from __future__ import annotations

import json

import pytest

from racecar_hw.base.resources import config_file
from racecar_hw.config import build_config
from racecar_hw.net.foxglove_server import (
    LOG_TOPIC,
    SCENE_TOPIC,
    SERVICE_PREFIX,
    SPEEDS_TOPIC,
    FoxgloveParams,
)
from racecar_hw.net.layout import FILES, LEGACY_PANEL_TYPES, layout_json, legacy_layout, main
from racecar_hw.net.topics import topic_table
from racecar_hw.sim.live import SIM_TOPICS

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


def _panels(node):
    if "panelType" in node:
        yield node
        return
    for item in node.get("items", []):
        yield from _panels(item["content"])


def test_the_shipped_layouts_are_the_built_ones(tmp_path):
    assert config_file("foxglove", FILES[0]).read_text() == layout_json()
    assert json.loads(config_file("foxglove", FILES[1]).read_text()) == legacy_layout()
    assert main([str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(FILES)


def test_the_layout_names_topics_and_services_the_server_offers():
    config = build_config({})
    served = {t.ros for t in topic_table(config.mux, config.safety)} | {t.bus for t in SIM_TOPICS}
    served |= {SCENE_TOPIC, SPEEDS_TOPIC, LOG_TOPIC}
    panels = {p["panelType"]: p for p in _panels(json.loads(layout_json())["content"])}
    assert set(panels) >= {"ThreeDee", "Plot", "StateTransitions", "DiagnosticsSummary", "Log", "Teleop",
                           "ServiceCall"}
    assert set(panels["ThreeDee"]["config"]["topics"]) <= served | {"/map", "/sim/pose"}
    assert {"/scan", SCENE_TOPIC} <= set(panels["ThreeDee"]["config"]["topics"])
    teleop = panels["Teleop"]["config"]
    assert teleop["topic"] == FoxgloveParams().teleop_topic and teleop["publishRate"] >= 10
    # at 10 Hz a Twist arrives well within the foxglove mux input's timeout
    assert 1.0 / teleop["publishRate"] < FoxgloveParams().teleop_timeout_s / 2
    text = layout_json()
    for path in ("commanded", "allowed", "measured", "steering"):
        assert f'"{SPEEDS_TOPIC}.{path}"' in text
    assert f'"{SERVICE_PREFIX}estop"' in text and f'"{SERVICE_PREFIX}release"' in text
    assert '"/vesc/low_level/ackermann_cmd_mux/active.data"' in text and config.mux.active_topic in served


def test_the_lichtblick_layout_is_a_binary_split_tree_of_known_panels():
    legacy = legacy_layout()
    leaves = []

    def walk(node):
        if isinstance(node, str):
            leaves.append(node)
            return
        assert node["direction"] in ("row", "column") and 0 < node["splitPercentage"] < 100
        walk(node["first"])
        walk(node["second"])

    walk(legacy["layout"])
    assert sorted(leaves) == sorted(legacy["configById"])
    kinds = {leaf.split("!")[0] for leaf in leaves}
    assert kinds >= set(LEGACY_PANEL_TYPES.values()) | {"Plot", "Teleop", "StateTransitions"}
    # the panel titles under the key each viewer reads (Lichtblick ignores Foxglove's)
    configs = legacy["configById"].values()
    assert {"car", "speed (m/s)", "e-stop"} <= {config.get("lichtblickPanelTitle") for config in configs}
    assert all(c.get("lichtblickPanelTitle") == c.get("foxglovePanelTitle") for c in configs)
    # the scan keeps its flat colour: without a colour field the viewers switch to a colour map
    scan = next(c for k, c in legacy["configById"].items() if k.startswith("3D!"))["topics"]["/scan"]
    assert scan["colorMode"] == "flat" and scan["colorField"]


def test_help_is_help_not_a_folder_named_help(tmp_path, monkeypatch, capsys):
    """``python -m racecar_hw.net.layout --help`` wrote the layouts into a new folder ``--help``."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    assert "usage: python -m racecar_hw.net.layout" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []
