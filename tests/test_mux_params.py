"""Mux parameters: defaults, documentation, and validation errors that name the key."""

from __future__ import annotations

import dataclasses

import pytest

from mux.params import InputParams, LockParams, MuxParams
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import build, describe
from racecar_hw.base.topics import FOXGLOVE_INPUT_TOPIC, MUX_SAFETY_TOPIC, TELEOP_TOPIC

LOW = "/vesc/low_level/ackermann_cmd_mux"
HIGH = "/vesc/high_level/ackermann_cmd_mux"


def _inputs(*priorities: int) -> list[dict]:
    return [{"name": f"in{i}", "topic": f"/in{i}", "priority": p} for i, p in enumerate(priorities)]


def test_defaults_keep_ros_racecar_topics_and_order():
    p = build(MuxParams, {}, "mux")
    assert [(i.name, i.topic, i.timeout_s) for i in p.inputs] == [
        ("safety", f"{LOW}/input/safety", 0.2),
        ("teleop", f"{LOW}/input/teleop", 0.2),
        ("nav_0", f"{HIGH}/input/nav_0", 0.2),
        ("nav_1", f"{HIGH}/input/nav_1", 0.2),
        ("nav_2", f"{HIGH}/input/nav_2", 0.2),
        ("nav_3", f"{HIGH}/input/nav_3", 0.2),
    ]
    priorities = [i.priority for i in p.inputs]
    assert priorities == sorted(priorities, reverse=True)
    assert len(set(priorities)) == len(priorities)
    assert p.output_topic == f"{LOW}/output"
    assert (p.rate_hz, p.hold_steering_when_idle, p.limiter_enabled) == (50.0, False, True)
    assert (p.max_accel_mps2, p.max_decel_mps2, p.max_steering_rate_radps) == (2.5, 8.0, 3.2)
    assert p.locks == []
    assert p.estop_topic != p.estop_release_topic


def test_instances_do_not_share_default_lists():
    a, b = MuxParams(), MuxParams()
    a.inputs.pop()
    assert len(b.inputs) == 6


def test_every_field_is_documented():
    for cls in (MuxParams, InputParams, LockParams):
        for f in dataclasses.fields(cls):
            assert f.metadata.get("doc"), f"{cls.__name__}.{f.name}"
    keys = [key for key, _default, _doc in describe(MuxParams, "mux")]
    assert "mux.max_decel_mps2" in keys


def test_duplicate_priority_names_the_key():
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": _inputs(30, 20, 30)}, "mux")
    assert err.value.key == "mux.inputs[2].priority"
    assert "mux.inputs[0]" in str(err.value)


def test_duplicate_name_and_topic_name_the_key():
    data = _inputs(3, 2, 1)
    data[1]["name"] = "in0"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": data}, "mux")
    assert err.value.key == "mux.inputs[1].name"
    data = _inputs(3, 2, 1)
    data[2]["topic"] = "/in0"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": data}, "mux")
    assert err.value.key == "mux.inputs[2].topic"


def test_input_on_the_output_topic_is_refused():
    data = _inputs(3)
    data[0]["topic"] = f"{LOW}/output"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": data}, "mux")
    assert err.value.key == "mux.inputs[0].topic"
    assert "mux.output_topic" in str(err.value)


def test_reserved_and_empty_names_are_refused():
    for bad in ("idle", "estop", "fault", ""):
        data = _inputs(3)
        data[0]["name"] = bad
        with pytest.raises(ConfigError) as err:
            build(MuxParams, {"inputs": data}, "mux")
        assert err.value.key == "mux.inputs[0].name"


def test_missing_and_out_of_range_fields_name_the_key():
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": [{"name": "a", "priority": 1}]}, "mux")
    assert err.value.key == "mux.inputs[0].topic"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": [{"name": "a", "topic": "/a", "timeout_s": -1}]}, "mux")
    assert err.value.key == "mux.inputs[0].timeout_s"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": [{"name": "a", "topic": "/a", "priority": 1.5}]}, "mux")
    assert err.value.key == "mux.inputs[0].priority"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"max_decel_mps2": 0.0}, "mux")
    assert err.value.key == "mux.max_decel_mps2"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"rate_hz": 0}, "mux")
    assert err.value.key == "mux.rate_hz"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"hold_steering_when_idel": True}, "mux")
    assert err.value.key == "mux.hold_steering_when_idel"


def test_the_operators_inputs_take_no_network_commands_and_the_rest_do():
    """safety and teleop (the safety controller's and the gamepad's) are closed to Zenoh and DDS by
    default; an input listed without ``network`` is open, unless it is on one of the operator's
    topics: a config that lists its inputs as docs/mux.md's example did before the key existed
    opened safety and teleop to any network session. ``network: true`` opens one on purpose."""
    p = build(MuxParams, {}, "mux")
    assert {i.name: i.network for i in p.inputs} == {
        "safety": False, "teleop": False, "nav_0": True, "nav_1": True, "nav_2": True, "nav_3": True}
    inputs = [{"name": "op", "topic": "/op", "priority": 9, "network": False},
              {"name": "auto", "topic": "/auto", "priority": 5, "network": True},
              {"name": "old", "topic": "/old", "priority": 1}]
    assert [i.network for i in build(MuxParams, {"inputs": inputs}, "mux").inputs] == [False, True, True]
    listed = [{"name": name, "topic": topic, "priority": k}
              for k, (name, topic) in enumerate([("safety", MUX_SAFETY_TOPIC), ("teleop", TELEOP_TOPIC),
                                                 ("foxglove", FOXGLOVE_INPUT_TOPIC), ("bag", "/bag")])]
    def network() -> list[bool | None]:
        return [i.network for i in build(MuxParams, {"inputs": listed}, "mux").inputs]

    assert network() == [False, False, False, True]
    listed[1]["network"] = True  # a ROS teleop node on the car (F1TENTH's joy_teleop), on purpose
    assert network() == [False, True, False, True]


@pytest.mark.parametrize("value", ["no", 0, 1, [False]])
def test_a_network_flag_that_is_not_a_bool_names_the_key(value):
    inputs = [{"name": "a", "topic": "/a", "priority": 1},
              {"name": "b", "topic": "/b", "priority": 2, "network": value}]
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": inputs}, "mux")
    assert err.value.key == "mux.inputs[1].network"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"inputs": [{"name": "a", "topic": "/a", "networks": False}]}, "mux")
    assert err.value.key == "mux.inputs[0].networks"


@pytest.mark.parametrize("timeout", [0.0, 5.5, 100000.0])
def test_every_input_expires_within_bounds(timeout):
    """No input may hold its last command: 0 (twist_mux's "never") and long timeouts are refused,
    in the config and in code alike (a nav input at 0 drove on at 1 m/s after its source fell
    silent)."""
    with pytest.raises(ConfigError, match="out of range; allowed: 0.01 to 5.0") as err:
        build(MuxParams, {"inputs": [{"name": "a", "topic": "/a", "timeout_s": timeout}]}, "mux")
    assert err.value.key == "mux.inputs[0].timeout_s"
    with pytest.raises(ConfigError, match="every input must expire") as err:
        MuxParams(inputs=[InputParams("a", "/a", 1, timeout)])
    assert err.value.key == "mux.inputs[0].timeout_s"


def test_direct_construction_is_validated_too():
    with pytest.raises(ConfigError) as err:
        MuxParams(max_accel_mps2=float("nan"))
    assert err.value.key == "mux.max_accel_mps2"
    with pytest.raises(ConfigError) as err:
        MuxParams(inputs=[InputParams("a", "/a", 1), InputParams("b", "/b", 1)])
    assert err.value.key == "mux.inputs[1].priority"


def test_validate_with_another_prefix():
    p = MuxParams()
    p.inputs[3].priority = p.inputs[0].priority
    with pytest.raises(ConfigError) as err:
        p.validate("daemon.mux")
    assert err.value.key == "daemon.mux.inputs[3].priority"


def test_locks_are_built_and_checked():
    p = build(MuxParams, {"locks": [{"name": "pause", "topic": "/pause", "priority": 50},
                                    {"name": "deadman", "topic": "/deadman", "priority": 95,
                                     "timeout_s": 0.5}]}, "mux")
    assert p.locks[1] == LockParams("deadman", "/deadman", 95, 0.5)
    assert p.locks[0].timeout_s == 0.0
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"locks": [{"name": "a", "topic": "/a"}, {"name": "a", "topic": "/b"}]}, "mux")
    assert err.value.key == "mux.locks[1].name"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"locks": [{"name": "a", "topic": "/estop"}]}, "mux")
    assert err.value.key == "mux.locks[0].topic"
    with pytest.raises(ConfigError) as err:
        build(MuxParams, {"locks": [{"name": "a", "topic": "relative"}]}, "mux")
    assert err.value.key == "mux.locks[0].topic"
