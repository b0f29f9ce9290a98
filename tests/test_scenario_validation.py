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


@pytest.mark.parametrize(("text", "key", "words"), [
    ("start: [.inf, 0, 0]", "scenario.start", "must be finite"),
    ("start: [0, 0, .nan]", "scenario.start[2]", "NaN"),
    ("cars: [{name: a}, {name: b, start: [.inf, 0, 0]}]", "scenario.cars[1].start",
     "must be finite"),
    ("drivers: [{type: script, steps: [[0, 1, 0], [-5, 1, 0]]}]", "scenario.drivers[0].steps[1].t_s",
     "not a time"),
    ("drivers: [{type: script, steps: [[0, 1, 0], [1, 1, 0], [2, 99, 0]]}]",
     "scenario.drivers[0].steps[2].speed_mps", "out of range"),
    ("drivers: [{type: script, steps: [[0, .inf, 0]]}]", "scenario.drivers[0].steps[0].speed_mps",
     "out of range"),
    ("drivers: [{type: script, steps: [[0, 1, 7]]}]", "scenario.drivers[0].steps[0].steering_rad",
     "out of range"),
    ("drivers: [{type: script, steps: [[.inf, 1, 0]]}]", "scenario.drivers[0].steps[0].t_s", "not a time"),
    ("drivers: [{type: constant, until_s: -3}]", "scenario.drivers[0].until_s", "out of range"),
    ("world: {noise_std_m: .inf}", "scenario.world.noise_std_m", "out of range"),
    ("obstacles: [{at: [.inf, 0]}]", "scenario.obstacles[0].at", "must be finite"),
    ("obstacles: [{at: [3, 0], velocity_mps: [.inf, 0]}]", "scenario.obstacles[0].velocity_mps[0]",
     "out of range"),
    ("obstacles: [{at: [3, 0], yaw_rad: .inf}]", "scenario.obstacles[0].yaw_rad", "must be finite"),
    ("obstacles: [{at: [3, 0], waypoints: [[1, 1], [.inf, 0]]}]", "scenario.obstacles[0].waypoints[1]",
     "must be finite"),
    ("obstacles: [{shape: box, at: [3, 0], size_m: [.inf, 1]}]", "scenario.obstacles[0].size_m",
     "must be finite"),
])
def test_values_out_of_range_or_not_finite_are_refused_naming_the_key(tmp_path, text, key, words):
    with pytest.raises(ConfigError) as info:
        _load(tmp_path, f"map: room\nduration_s: 1\n{text}\n")
    assert info.value.key == key
    assert str(info.value).startswith(f"{key}: ") and words in str(info.value)
    assert "\n" not in str(info.value)


def test_values_in_range_still_load(tmp_path):
    sc = _load(tmp_path, "map: room\nstart: [1, 2, -3.1]\ndrivers: [{type: script, until_s: 0, steps: "
                         "[[0, -10, -1], [0.5, 10, 1]]}]\nworld: {noise_std_m: 1.0}\n"
                         "obstacles: [{at: [3, 0], velocity_mps: [-50, 50]},\n"
                         "            {at: [3, 0], waypoints: [[1, 1]]}]\n")
    assert sc.start == (1.0, 2.0, -3.1) and sc.drivers[0].steps[1] == (0.5, 10.0, 1.0)
