"""Scenario files with values out of range or not finite: refused in one line naming the key."""

from __future__ import annotations

import pytest

from racecar_hw.base.errors import ConfigError
from racecar_hw.sim.scenario import load_scenario


def _load(tmp_path, text: str, overrides: tuple[str, ...] = ()):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return load_scenario(str(path), list(overrides))


def test_a_negative_world_seed_is_refused_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"^scenario\.world\.seed: -1 .* out of range"):
        load_scenario("wall", ["world.seed=-1"])
    with pytest.raises(ConfigError, match=r"^scenario\.world\.seed: "):
        _load(tmp_path, "map: room\nworld: {seed: -5}\n")
    assert load_scenario("wall", ["world.seed=0"]).world.seed == 0
