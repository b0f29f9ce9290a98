"""ROS 2 parameter messages and services (``rcl_interfaces``), field for field.

A ROS 2 node answers six parameter services under its own name (``/<ns>/<node>/list_parameters``,
...); ``ros2 param`` and rqt call them. These classes mirror ``rcl_interfaces/msg/Parameter*`` and
the request and response halves of ``rcl_interfaces/srv/*Parameters*`` as the rest of the message
model mirrors its types (:mod:`racecar_hw.base.messages`): ``ROS_TYPE`` and ``MSGDEF``, serialized by
:mod:`racecar_hw.rosmsg` into the same CDR as rclpy. The request and response types are named as
rosidl names them (``rcl_interfaces/srv/ListParameters_Request``); the service type itself
(``rcl_interfaces/srv/ListParameters``) has no message of its own, only a RIHS01 hash
(:data:`SERVICE_TYPE_HASHES`), which ROS 2 computes over the request, the response and the service
event message together.

The definitions are those of rcl_interfaces 2.x (Humble to Rolling: unchanged).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from racecar_hw.base.messages import Message

# --- rcl_interfaces/msg ------------------------------------------------------------------------

#: ``rcl_interfaces/msg/ParameterType`` values.
PARAMETER_NOT_SET = 0
PARAMETER_BOOL = 1
PARAMETER_INTEGER = 2
PARAMETER_DOUBLE = 3
PARAMETER_STRING = 4
PARAMETER_BYTE_ARRAY = 5
PARAMETER_BOOL_ARRAY = 6
PARAMETER_INTEGER_ARRAY = 7
PARAMETER_DOUBLE_ARRAY = 8
PARAMETER_STRING_ARRAY = 9


@dataclass
class ParameterValue(Message):
    """rcl_interfaces/ParameterValue: ``type`` says which one field holds the value."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/ParameterValue"
    MSGDEF: ClassVar[str] = (
        "uint8 type\nbool bool_value\nint64 integer_value\nfloat64 double_value\nstring string_value\n"
        "byte[] byte_array_value\nbool[] bool_array_value\nint64[] integer_array_value\n"
        "float64[] double_array_value\nstring[] string_array_value\n"
    )

    type: int = PARAMETER_NOT_SET
    bool_value: bool = False
    integer_value: int = 0
    double_value: float = 0.0
    string_value: str = ""
    byte_array_value: list[int] = field(default_factory=list)
    bool_array_value: list[bool] = field(default_factory=list)
    integer_array_value: list[int] = field(default_factory=list)
    double_array_value: list[float] = field(default_factory=list)
    string_array_value: list[str] = field(default_factory=list)


@dataclass
class Parameter(Message):
    """rcl_interfaces/Parameter: a name and its value."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/Parameter"
    MSGDEF: ClassVar[str] = "string name\nrcl_interfaces/ParameterValue value\n"

    name: str = ""
    value: ParameterValue = field(default_factory=ParameterValue)


@dataclass
class FloatingPointRange(Message):
    """rcl_interfaces/FloatingPointRange: ``from_value`` .. ``to_value`` in steps of ``step`` (0: any)."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/FloatingPointRange"
    MSGDEF: ClassVar[str] = "float64 from_value\nfloat64 to_value\nfloat64 step\n"

    from_value: float = 0.0
    to_value: float = 0.0
    step: float = 0.0


@dataclass
class IntegerRange(Message):
    """rcl_interfaces/IntegerRange: ``from_value`` .. ``to_value`` in steps of ``step`` (0: any)."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/IntegerRange"
    MSGDEF: ClassVar[str] = "int64 from_value\nint64 to_value\nuint64 step\n"

    from_value: int = 0
    to_value: int = 0
    step: int = 0


@dataclass
class ParameterDescriptor(Message):
    """rcl_interfaces/ParameterDescriptor: what a parameter is, and whether it may change."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/ParameterDescriptor"
    MSGDEF: ClassVar[str] = (
        "string name\nuint8 type\nstring description\nstring additional_constraints\n"
        "bool read_only\nbool dynamic_typing\n"
        "rcl_interfaces/FloatingPointRange[<=1] floating_point_range\n"
        "rcl_interfaces/IntegerRange[<=1] integer_range\n"
    )

    name: str = ""
    type: int = PARAMETER_NOT_SET
    description: str = ""
    additional_constraints: str = ""
    read_only: bool = False
    dynamic_typing: bool = False
    floating_point_range: list[FloatingPointRange] = field(default_factory=list)
    integer_range: list[IntegerRange] = field(default_factory=list)


@dataclass
class ListParametersResult(Message):
    """rcl_interfaces/ListParametersResult: parameter names and the prefixes among them."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/ListParametersResult"
    MSGDEF: ClassVar[str] = "string[] names\nstring[] prefixes\n"

    names: list[str] = field(default_factory=list)
    prefixes: list[str] = field(default_factory=list)


@dataclass
class SetParametersResult(Message):
    """rcl_interfaces/SetParametersResult: whether a set succeeded, and why not."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/SetParametersResult"
    MSGDEF: ClassVar[str] = "bool successful\nstring reason\n"

    successful: bool = False
    reason: str = ""


# --- rcl_interfaces/srv: requests and responses ------------------------------------------------


@dataclass
class ListParametersRequest(Message):
    """rcl_interfaces/srv/ListParameters request: names under ``prefixes`` (all if empty), ``depth``
    dot-separated levels below them (0: any)."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/ListParameters_Request"
    MSGDEF: ClassVar[str] = "uint64 DEPTH_RECURSIVE=0\nstring[] prefixes\nuint64 depth\n"
    DEPTH_RECURSIVE: ClassVar[int] = 0

    prefixes: list[str] = field(default_factory=list)
    depth: int = 0


@dataclass
class ListParametersResponse(Message):
    """rcl_interfaces/srv/ListParameters response."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/ListParameters_Response"
    MSGDEF: ClassVar[str] = "rcl_interfaces/ListParametersResult result\n"

    result: ListParametersResult = field(default_factory=ListParametersResult)


@dataclass
class DescribeParametersRequest(Message):
    """rcl_interfaces/srv/DescribeParameters request."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/DescribeParameters_Request"
    MSGDEF: ClassVar[str] = "string[] names\n"

    names: list[str] = field(default_factory=list)


@dataclass
class DescribeParametersResponse(Message):
    """rcl_interfaces/srv/DescribeParameters response: one descriptor per name asked for."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/DescribeParameters_Response"
    MSGDEF: ClassVar[str] = "rcl_interfaces/ParameterDescriptor[] descriptors\n"

    descriptors: list[ParameterDescriptor] = field(default_factory=list)


@dataclass
class GetParametersRequest(Message):
    """rcl_interfaces/srv/GetParameters request."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/GetParameters_Request"
    MSGDEF: ClassVar[str] = "string[] names\n"

    names: list[str] = field(default_factory=list)


@dataclass
class GetParametersResponse(Message):
    """rcl_interfaces/srv/GetParameters response: one value per name (NOT_SET when unknown)."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/GetParameters_Response"
    MSGDEF: ClassVar[str] = "rcl_interfaces/ParameterValue[] values\n"

    values: list[ParameterValue] = field(default_factory=list)


@dataclass
class GetParameterTypesRequest(Message):
    """rcl_interfaces/srv/GetParameterTypes request."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/GetParameterTypes_Request"
    MSGDEF: ClassVar[str] = "string[] names\n"

    names: list[str] = field(default_factory=list)


@dataclass
class GetParameterTypesResponse(Message):
    """rcl_interfaces/srv/GetParameterTypes response: one ParameterType value per name."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/GetParameterTypes_Response"
    MSGDEF: ClassVar[str] = "uint8[] types\n"

    types: list[int] = field(default_factory=list)


@dataclass
class SetParametersRequest(Message):
    """rcl_interfaces/srv/SetParameters request."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/SetParameters_Request"
    MSGDEF: ClassVar[str] = "rcl_interfaces/Parameter[] parameters\n"

    parameters: list[Parameter] = field(default_factory=list)


@dataclass
class SetParametersResponse(Message):
    """rcl_interfaces/srv/SetParameters response: one result per parameter."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/SetParameters_Response"
    MSGDEF: ClassVar[str] = "rcl_interfaces/SetParametersResult[] results\n"

    results: list[SetParametersResult] = field(default_factory=list)


@dataclass
class SetParametersAtomicallyRequest(Message):
    """rcl_interfaces/srv/SetParametersAtomically request."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/SetParametersAtomically_Request"
    MSGDEF: ClassVar[str] = "rcl_interfaces/Parameter[] parameters\n"

    parameters: list[Parameter] = field(default_factory=list)


@dataclass
class SetParametersAtomicallyResponse(Message):
    """rcl_interfaces/srv/SetParametersAtomically response: one result for them all."""

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/srv/SetParametersAtomically_Response"
    MSGDEF: ClassVar[str] = "rcl_interfaces/SetParametersResult result\n"

    result: SetParametersResult = field(default_factory=SetParametersResult)


#: The request/response types no rosbags typestore ships (the rcl_interfaces messages it does ship).
SERVICE_MESSAGE_TYPES: tuple[type[Message], ...] = (
    ListParametersRequest, ListParametersResponse, DescribeParametersRequest,
    DescribeParametersResponse, GetParametersRequest, GetParametersResponse, GetParameterTypesRequest,
    GetParameterTypesResponse, SetParametersRequest, SetParametersResponse,
    SetParametersAtomicallyRequest, SetParametersAtomicallyResponse,
)

#: Every message class of this module, by ROS type name.
PARAMETER_CLASSES: dict[str, type[Message]] = {
    cls.ROS_TYPE: cls for cls in (
        ParameterValue, Parameter, FloatingPointRange, IntegerRange, ParameterDescriptor,
        ListParametersResult, SetParametersResult, *SERVICE_MESSAGE_TYPES)
}

#: RIHS01 hashes of the service types, from the official type descriptions (the ``ros-rcl-interfaces``
#: 2.3.0 wheel's ``share/rcl_interfaces/srv/*.json``; tests/test_net_parameters.py compares them).
#: They cover request, response and the service event message, which no typestore here models.
SERVICE_TYPE_HASHES: dict[str, str] = {
    "rcl_interfaces/srv/ListParameters":
        "RIHS01_3e6062bfbb27bfb8730d4cef2558221f51a11646d78e7bb30a1e83afac3aad9d",
    "rcl_interfaces/srv/DescribeParameters":
        "RIHS01_845b484d71eb0673dae682f2e3ba3c4851a65a3dcfb97bddd82c5b57e91e4cff",
    "rcl_interfaces/srv/GetParameters":
        "RIHS01_bf9803d5c74cf989a5de3e0c2e99444599a627c7ff75f97b8c05b01003675cbc",
    "rcl_interfaces/srv/GetParameterTypes":
        "RIHS01_da199c878688b3e530bdfe3ca8f74cb9fa0c303101e980a9e8f260e25e1c80ca",
    "rcl_interfaces/srv/SetParameters":
        "RIHS01_56eed9a67e169f9cb6c1f987bc88f868c14a8fc9f743a263bc734c154015d7e0",
    "rcl_interfaces/srv/SetParametersAtomically":
        "RIHS01_0e192ef259c07fc3c07a13191d27002222e65e00ccec653ca05e856f79285fcd",
}
