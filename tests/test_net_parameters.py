"""The read-only parameter services without I/O (racecar_hw.net.parameters), and their message types
checked against the official rcl_interfaces package (the ``ros-rcl-interfaces`` wheel's .srv, .msg
and JSON type descriptions)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.base.messages import Log
from racecar_hw.base.parameter_messages import (
    PARAMETER_BOOL,
    PARAMETER_DOUBLE,
    PARAMETER_DOUBLE_ARRAY,
    PARAMETER_INTEGER,
    PARAMETER_INTEGER_ARRAY,
    PARAMETER_NOT_SET,
    PARAMETER_STRING,
    PARAMETER_STRING_ARRAY,
    SERVICE_TYPE_HASHES,
    DescribeParametersRequest,
    GetParametersRequest,
    GetParameterTypesRequest,
    ListParametersRequest,
    Parameter,
    SetParametersAtomicallyRequest,
    SetParametersRequest,
)
from racecar_hw.base.params import describe, to_dict
from racecar_hw.config import Config, load_config
from racecar_hw.net import rmw
from racecar_hw.net.parameters import HIDDEN, PARAMETER_SERVICES, ParameterService, flatten, parameter_value
from racecar_hw.net.zenoh_config import ROS_DISTROS
from racecar_hw.rosmsg.typestore import ros2_types

SHARE = Path(sys.prefix) / "share" / "rcl_interfaces"
TREE = {
    "mux": {"rate_hz": 50.0, "inputs": [{"name": "nav_0", "priority": 20}],
            "footprint": {"width_m": 0.3, "front_m": 0.4}},
    "zenoh": {"listen": ["tcp/127.0.0.1:7447"], "domain_id": None, "remap": {"/scan": "/car/scan"},
              "auth": {"password": "s3cret", "user": ""}},
    "web": {"token": "", "port": 8080, "enabled": True},
    "xyz": [0.265, 0, 0.1],
    "ids": [1, 2, 3],
}


@pytest.fixture
def service() -> ParameterService:
    return ParameterService(TREE, {"mux.rate_hz": "output rate (Hz)"})


def test_values_become_ros_parameter_types_and_secrets_never_leave():
    flat = flatten(TREE)
    assert flat["zenoh.auth.password"] == HIDDEN and flat["web.token"] == ""
    assert "s3cret" not in json.dumps(flat)
    assert flat["mux.footprint.width_m"] == 0.3
    assert parameter_value(flat["mux.rate_hz"]).type == PARAMETER_DOUBLE
    assert parameter_value(flat["web.port"]).type == PARAMETER_INTEGER
    assert parameter_value(flat["web.enabled"]).type == PARAMETER_BOOL
    assert parameter_value(flat["zenoh.listen"]).string_array_value == ["tcp/127.0.0.1:7447"]
    assert parameter_value(flat["zenoh.domain_id"]).type == PARAMETER_NOT_SET
    assert parameter_value(flat["xyz"]).type == PARAMETER_DOUBLE_ARRAY
    assert parameter_value(flat["xyz"]).double_array_value == [0.265, 0.0, 0.1]
    assert parameter_value(flat["ids"]).type == PARAMETER_INTEGER_ARRAY
    # a list of mappings, and a mapping of topic names, are JSON text
    assert json.loads(parameter_value(flat["mux.inputs"]).string_value) == TREE["mux"]["inputs"]
    assert json.loads(parameter_value(flat["zenoh.remap"]).string_value) == {"/scan": "/car/scan"}
    assert parameter_value([]).type == PARAMETER_STRING_ARRAY


def test_list_filters_by_prefix_and_depth_as_rclcpp_does(service):
    def names(prefixes=(), depth=0):
        return service.handle("list_parameters", ListParametersRequest(list(prefixes), depth)).result

    everything = names()
    assert set(everything.names) == set(flatten(TREE))
    assert {"mux", "mux.footprint", "zenoh", "zenoh.auth", "web"} <= set(everything.prefixes)
    assert names(depth=1).names == ["xyz", "ids"]  # no separator: depth 1
    assert sorted(names(["mux"]).names) == ["mux.footprint.front_m", "mux.footprint.width_m", "mux.inputs",
                                            "mux.rate_hz"]
    # rclcpp counts the separators after the prefix, its own included: depth 2 is one level below
    assert sorted(names(["mux"], 2).names) == ["mux.inputs", "mux.rate_hz"]
    assert names(["mux.rate_hz"]).names == ["mux.rate_hz"]
    assert names(["mu"]).names == []


def test_get_describe_and_types_answer_per_name_and_nothing_for_an_unknown_one(service):
    got = service.handle("get_parameters", GetParametersRequest(["mux.rate_hz", "web.port"]))
    assert [v.double_value for v in got.values][:1] == [50.0] and got.values[1].integer_value == 8080
    types = service.handle("get_parameter_types", GetParameterTypesRequest(["mux.rate_hz", "mux.inputs"]))
    assert types.types == [PARAMETER_DOUBLE, PARAMETER_STRING]
    (desc,) = service.handle("describe_parameters", DescribeParametersRequest(["mux.rate_hz"])).descriptors
    assert desc.read_only and desc.type == PARAMETER_DOUBLE and desc.description == "output rate (Hz)"
    # rclcpp and rclpy answer an empty list when a name was never declared
    assert service.handle("get_parameters", GetParametersRequest(["mux.rate_hz", "nope"])).values == []
    assert service.handle("get_parameter_types", GetParameterTypesRequest(["nope"])).types == []
    assert service.handle("describe_parameters", DescribeParametersRequest(["nope"])).descriptors == []


def test_every_set_is_refused_with_the_way_to_change_it(service):
    results = service.handle("set_parameters", SetParametersRequest(
        [Parameter("mux.rate_hz"), Parameter("no.such")])).results
    assert [r.successful for r in results] == [False, False]
    assert "--set mux.rate_hz=" in results[0].reason and "read-only" in results[0].reason
    assert "no parameter 'no.such'" in results[1].reason
    atomic = service.handle("set_parameters_atomically", SetParametersAtomicallyRequest(
        [Parameter("mux.rate_hz"), Parameter("web.port")])).result
    assert not atomic.successful and "read-only" in atomic.reason


def test_a_request_of_the_wrong_type_or_service_is_refused(service):
    with pytest.raises(TypeError):
        service.handle("get_parameters", ListParametersRequest())
    with pytest.raises(KeyError):
        service.handle("delete_parameters", ListParametersRequest())


def test_the_daemons_config_is_served_with_its_documentation():
    config = load_config(None)
    service = ParameterService(to_dict(config), {name: doc for name, _, doc in describe(Config)})
    assert "zenoh.ros_distro" in service.values and "rosout.level" in service.values
    request = DescribeParametersRequest(["zenoh.ros_distro"])
    (desc,) = service.handle("describe_parameters", request).descriptors
    assert "humble" in desc.description and "TypeHashNotSupported" in desc.description
    assert service.values["zenoh.ros_distro"].string_value == "jazzy"
    assert ROS_DISTROS == rmw.ROS_DISTROS


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=200), which=st.sampled_from([s.name for s in PARAMETER_SERVICES]))
def test_any_request_bytes_either_fail_to_decode_or_get_an_answer(data, which):
    spec = next(s for s in PARAMETER_SERVICES if s.name == which)
    types = ros2_types()
    service = ParameterService(TREE)
    try:
        request = types.deserialize(data, spec.request)
    except Exception:  # noqa: BLE001 - the bridge counts these as malformed
        return
    response = service.handle(which, request)
    assert isinstance(response, spec.response)
    types.serialize(response)


# --- against the official rcl_interfaces package -------------------------------------------------


def _official(kind: str, name: str, suffix: str) -> Path:
    path = SHARE / kind / f"{name}.{suffix}"
    if not path.exists():
        pytest.skip(f"{path} absent: install the test extra (the ros-rcl-interfaces wheel)")
    return path


def _fields(text: str) -> list[tuple[str, str]]:
    """(type, name) of each field of a .msg/.srv half, comments, constants and package names dropped."""
    out = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        parts = line.split()
        if len(parts) < 2 or "=" in line[len(parts[0]):]:
            continue
        out.append((re.sub(r"^rcl_interfaces/", "", parts[0]), parts[1]))
    return out


@pytest.mark.parametrize("spec", PARAMETER_SERVICES, ids=lambda s: s.name)
def test_service_types_match_the_official_definitions_and_hashes(spec):
    short = spec.srv_type.rsplit("/", 1)[1]
    request, response = _official("srv", short, "srv").read_text().split("---", 1)
    assert _fields(spec.request.MSGDEF) == _fields(request)
    assert _fields(spec.response.MSGDEF) == _fields(response)
    official = json.loads(_official("srv", short, "json").read_text())["type_hashes"][0]
    assert official["type_name"] == spec.srv_type
    assert SERVICE_TYPE_HASHES[spec.srv_type] == official["hash_string"] == rmw.type_hash(spec.srv_type)


@pytest.mark.parametrize("name", ["Log", "ParameterValue", "Parameter", "ParameterDescriptor",
                                  "ListParametersResult", "SetParametersResult", "FloatingPointRange",
                                  "IntegerRange"])
def test_message_types_match_the_official_definitions_and_hashes(name):
    from racecar_hw.base.parameter_messages import PARAMETER_CLASSES  # noqa: PLC0415

    cls = Log if name == "Log" else PARAMETER_CLASSES[f"rcl_interfaces/msg/{name}"]
    assert _fields(cls.MSGDEF) == _fields(_official("msg", name, "msg").read_text())
    official = json.loads(_official("msg", name, "json").read_text())["type_hashes"][0]
    assert rmw.type_hash(cls.ROS_TYPE) == official["hash_string"]


def test_cdr_answers_are_the_services_answers_cached_and_warmed(service):
    from racecar_hw.base.parameter_messages import GetParametersResponse  # noqa: PLC0415
    from racecar_hw.net.parameters import CdrAnswers  # noqa: PLC0415

    types = ros2_types()
    answers = CdrAnswers(service)
    answers.warm()
    assert len(answers._warm) == 4 and answers.cached_bytes == 0  # list; get, types, describe of all
    names = list(service.values)
    raw = answers.answer("get_parameters", types.serialize(GetParametersRequest(names)))
    assert types.deserialize(raw, GetParametersResponse) == service.handle(
        "get_parameters", GetParametersRequest(names))
    assert len(answers._cache) == 0  # that one was warm
    one = answers.answer("get_parameters", types.serialize(GetParametersRequest(["web.port"])))
    assert types.deserialize(one, GetParametersResponse).values[0].integer_value == 8080
    assert len(answers._cache) == 1
    with pytest.raises(Exception):  # noqa: B017, PT011 - whatever the decoder raises; the bridge counts it
        answers.answer("get_parameters", b"\x00\x01\x00\x00\xff\xff\xff\x7f")


def test_a_request_too_large_is_refused_before_any_work_and_the_cache_stays_bounded(service):
    """A client's request is bounded (bytes, names); the remembered answers are bounded in bytes,
    the warm ones kept. One describe_parameters naming a parameter 20,000 times once built 15 MB
    of answer in Zenoh's thread and kept it."""
    from racecar_hw.net.parameters import CdrAnswers, RequestRefused  # noqa: PLC0415

    types = ros2_types()
    answers = CdrAnswers(service)
    answers.warm()
    many = types.serialize(DescribeParametersRequest(["web.port"] * (CdrAnswers.MAX_REQUEST_ITEMS + 1)))
    with pytest.raises(RequestRefused, match="names"):
        answers.answer("describe_parameters", many)
    huge = types.serialize(ListParametersRequest(["x" * 1000] * 100))
    with pytest.raises(RequestRefused, match="bytes"):
        answers.answer("list_parameters", huge)
    assert answers.cached_bytes == 0
    for i in range(300):  # varied requests: each answered, the memory of them bounded
        request = DescribeParametersRequest(["web.port"] * (CdrAnswers.MAX_REQUEST_ITEMS - i))
        answers.answer("describe_parameters", types.serialize(request))
        assert answers.cached_bytes <= CdrAnswers.MAX_CACHED_BYTES
    assert len(answers._warm) == 4
    full = types.serialize(GetParametersRequest(list(service.values)))
    assert answers.answer("get_parameters", full) is answers._warm[("get_parameters", full)]
