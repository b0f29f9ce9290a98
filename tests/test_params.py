"""Parameter dataclasses: defaults, type and range checks, errors that name the key."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build, describe, param, to_dict

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


@dataclass
class Inner:
    name: str = param("teleop", "input name")
    priority: int = param(10, "priority", min=0, max=255)


@dataclass
class Outer:
    rate_hz: float = param(50.0, "output rate", unit="Hz", min=1.0, max=1000.0)
    mode: str = param("rpm", "brake mode", choices=("rpm", "current"))
    port: str | None = param(None, "serial port")
    enabled: bool = param(True, "run this component")
    inputs: list[Inner] = param([Inner()], "mux inputs")
    xyz: tuple[float, float, float] = param((0.0, 0.0, 0.0), "translation", unit="m")
    inner: Inner = param(Inner(), "one inner")


def test_defaults_and_values():
    p = build(Outer, {"rate_hz": 20, "port": "/dev/vesc", "inputs": [{"name": "nav_0", "priority": 3}],
                      "xyz": [1, 2, 3]})
    assert p.rate_hz == 20.0 and isinstance(p.rate_hz, float)
    assert p.port == "/dev/vesc"
    assert p.inputs == [Inner("nav_0", 3)]
    assert p.xyz == (1.0, 2.0, 3.0)
    assert build(Outer, None) == Outer()


def test_mutable_defaults_are_not_shared():
    a, b = Outer(), Outer()
    a.inputs.append(Inner("x", 1))
    assert b.inputs == [Inner()]


@pytest.mark.parametrize(("data", "key", "words"), [
    ({"rate": 1}, "mux.rate", "unknown key; did you mean rate_hz?"),  # the close match (difflib)
    ({"qqq": 1}, "mux.qqq", "unknown key; allowed keys: enabled, inner, inputs"),  # none close
    ({"rate_hz": "fast"}, "mux.rate_hz", "expected a number"),
    ({"rate_hz": 0.5}, "mux.rate_hz", "out of range; allowed: 1.0 to 1000.0"),
    ({"rate_hz": float("nan")}, "mux.rate_hz", "NaN"),
    ({"mode": "coast"}, "mux.mode", "allowed values: rpm, current"),
    ({"enabled": "yes"}, "mux.enabled", "expected true or false"),
    ({"inputs": [{"priority": 300}]}, "mux.inputs[0].priority", "out of range"),
    ({"inputs": {"name": "x"}}, "mux.inputs", "expected a list"),
    ({"xyz": [1, 2]}, "mux.xyz", "expected 3 values"),
    ({"inner": {"bogus": 1}}, "mux.inner.bogus", "unknown key"),
    ({"inner": 5}, "mux.inner", "expected a mapping"),
    ({"port": 5}, "mux.port", "fits none of str"),
])
def test_errors_name_the_key(data, key, words):
    with pytest.raises(ConfigError) as info:
        build(Outer, data, "mux")
    assert info.value.key == key
    assert words in str(info.value)
    assert str(info.value).startswith(key)


def test_bool_is_not_a_number():
    with pytest.raises(ConfigError, match="expected a number"):
        build(Outer, {"rate_hz": True})


def test_describe_and_to_dict():
    rows = {key: (default, doc) for key, default, doc in describe(Outer, "mux")}
    assert rows["mux.rate_hz"] == (50.0, "output rate (Hz; range 1.0..1000.0)")
    assert rows["mux.mode"][1] == "brake mode (one of rpm, current)"
    assert rows["mux.inner.priority"][0] == 10
    assert to_dict(Outer())["inputs"] == [{"name": "teleop", "priority": 10}]


def test_a_bare_off_is_the_choice_off():
    """YAML 1.1 reads `mode: off` and `--set safety.mode=off` as false; the choice named off is meant."""
    from racecar_hw.config import load_config

    assert load_config(None, ["safety.mode=off"]).safety.mode == "off"
    with pytest.raises(ConfigError, match="expected a string, got False"):
        load_config(None, ["lidar.model=off"])  # no choice named off there


@dataclass
class Named:
    topic: str = param("/scan", "scan input", topic=True)
    frame_id: str = param("laser", "frame of the scans", nonempty=True)


@pytest.mark.parametrize(("data", "key", "words"), [
    ({"topic": ""}, "lidar.topic", "'' is not an absolute topic name"),
    ({"topic": "scan"}, "lidar.topic", "'scan' is not an absolute topic name"),
    ({"frame_id": ""}, "lidar.frame_id", "must not be empty")])
def test_a_topic_must_be_absolute_and_a_nonempty_string_not_empty(data, key, words):
    with pytest.raises(ConfigError) as info:
        build(Named, data, "lidar")
    assert str(info.value) == f"{key}: {words}"
    assert build(Named, {"topic": "/car1/scan", "frame_id": "car1/laser"}) == Named("/car1/scan",
                                                                                    "car1/laser")
    rows = {key: doc for key, _, doc in describe(Named)}
    assert rows == {"topic": "scan input (an absolute topic name)",
                    "frame_id": "frame of the scans (not empty)"}
