"""ROS 2's parameter services over the daemon's effective configuration, read-only, without I/O.

A ROS 2 node answers ``list_parameters``, ``describe_parameters``, ``get_parameters``,
``get_parameter_types``, ``set_parameters`` and ``set_parameters_atomically`` under its own name
(``/<namespace>/<node>/<service>``); ``ros2 param list /racecar_hw`` and ``ros2 param get`` call
them. racecar-hw's parameters are its configuration, flattened to dotted names
(``mux.rate_hz``, ``zenoh.listen``), and they never change while it runs: a set is answered with
``successful: false`` and a reason that says how to change one (edit the config, or restart with
``--set key=value``).

:class:`ParameterService` maps a request message to its response message
(:mod:`racecar_hw.base.parameter_messages`); each network interface (Zenoh now, DDS) only carries
the bytes. The behaviour follows rclcpp's parameter service: ``list_parameters`` filters by prefix
and depth exactly as ``NodeParameters::list_parameters``; a name the node does not have makes
``describe``, ``get`` and ``get_types`` answer an empty list (rclcpp and rclpy answer so for an
undeclared parameter).

Values as ROS parameter types: bool, integer, double and string as they are; a list of bools,
integers, numbers or strings as the matching array (integers mixed with floats as doubles, an
empty list as an empty string array); ``None`` (unset, e.g. ``zenoh.domain_id``) as NOT_SET; a
mapping whose keys are names is flattened further, anything else (lists of mappings, a mapping of
topic names) is JSON text. Values of keys naming a secret (:data:`SECRET_WORDS`) are never sent:
``(set, hidden)`` or empty.
"""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from racecar_hw.base.messages import Message
from racecar_hw.base.parameter_messages import (
    PARAMETER_BOOL,
    PARAMETER_BOOL_ARRAY,
    PARAMETER_DOUBLE,
    PARAMETER_DOUBLE_ARRAY,
    PARAMETER_INTEGER,
    PARAMETER_INTEGER_ARRAY,
    PARAMETER_NOT_SET,
    PARAMETER_STRING,
    PARAMETER_STRING_ARRAY,
    DescribeParametersRequest,
    DescribeParametersResponse,
    GetParametersRequest,
    GetParametersResponse,
    GetParameterTypesRequest,
    GetParameterTypesResponse,
    ListParametersRequest,
    ListParametersResponse,
    ListParametersResult,
    ParameterDescriptor,
    ParameterValue,
    SetParametersAtomicallyRequest,
    SetParametersAtomicallyResponse,
    SetParametersRequest,
    SetParametersResponse,
    SetParametersResult,
)
from racecar_hw.net.topics import DEFAULT, Qos
from racecar_hw.rosmsg.typestore import ros2_types

#: Parameters whose value a client never sees (the web page's token, the relay's, Zenoh's password).
SECRET_WORDS = ("token", "password", "secret")
#: What a secret that is set shows instead of its value.
HIDDEN = "(set, hidden)"
#: The separator of parameter names (rclcpp's ``.``).
SEPARATOR = "."
#: The QoS ROS 2 gives services (``rmw_qos_profile_services_default``: reliable, volatile, keep last 10).
SERVICE_QOS: Qos = DEFAULT

READ_ONLY_REASON = ("racecar-hw's parameters are read-only while it runs: edit the config file, or "
                    "restart it with --set {name}=VALUE")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


@dataclass(frozen=True)
class ServiceSpec:
    """One parameter service: its name under the node, ROS 2 service type and message classes."""

    name: str                   #: e.g. ``list_parameters``; the full name is ``<node>/<name>``
    srv_type: str               #: e.g. ``rcl_interfaces/srv/ListParameters``
    request: type[Message]
    response: type[Message]


#: The six services every ROS 2 node with parameters answers, in rclcpp's order.
PARAMETER_SERVICES: tuple[ServiceSpec, ...] = (
    ServiceSpec("describe_parameters", "rcl_interfaces/srv/DescribeParameters",
                DescribeParametersRequest, DescribeParametersResponse),
    ServiceSpec("get_parameter_types", "rcl_interfaces/srv/GetParameterTypes",
                GetParameterTypesRequest, GetParameterTypesResponse),
    ServiceSpec("get_parameters", "rcl_interfaces/srv/GetParameters",
                GetParametersRequest, GetParametersResponse),
    ServiceSpec("list_parameters", "rcl_interfaces/srv/ListParameters",
                ListParametersRequest, ListParametersResponse),
    ServiceSpec("set_parameters", "rcl_interfaces/srv/SetParameters",
                SetParametersRequest, SetParametersResponse),
    ServiceSpec("set_parameters_atomically", "rcl_interfaces/srv/SetParametersAtomically",
                SetParametersAtomicallyRequest, SetParametersAtomicallyResponse),
)


def service_name(namespace: str, node_name: str, service: str) -> str:
    """The full name of one of a node's services: ``/<namespace>/<node>/<service>``."""
    return f"{namespace}/{node_name}/{service}"


# --- values -------------------------------------------------------------------------------------


def is_secret(key: str) -> bool:
    """Whether a key names a secret whose value is never shown."""
    return any(word in key.lower() for word in SECRET_WORDS)


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Dotted names to plain values (see the module documentation); secrets hidden."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if is_secret(str(key)):
            out[name] = HIDDEN if value else ""
        elif isinstance(value, Mapping) and value and all(
                isinstance(k, str) and _NAME.fullmatch(k) for k in value):
            out.update(flatten(value, name + SEPARATOR))
        else:
            out[name] = value
    return out


def parameter_value(value: Any) -> ParameterValue:
    """A plain value as a ROS ``ParameterValue`` (see the module documentation)."""
    if value is None:
        return ParameterValue(type=PARAMETER_NOT_SET)
    if isinstance(value, bool):
        return ParameterValue(type=PARAMETER_BOOL, bool_value=value)
    if isinstance(value, int):
        return ParameterValue(type=PARAMETER_INTEGER, integer_value=value)
    if isinstance(value, float):
        return ParameterValue(type=PARAMETER_DOUBLE, double_value=value)
    if isinstance(value, str):
        return ParameterValue(type=PARAMETER_STRING, string_value=value)
    if isinstance(value, (list, tuple)):
        items = list(value)
        if not items or all(isinstance(v, str) for v in items):
            return ParameterValue(type=PARAMETER_STRING_ARRAY, string_array_value=items)
        if all(isinstance(v, bool) for v in items):
            return ParameterValue(type=PARAMETER_BOOL_ARRAY, bool_array_value=items)
        if all(isinstance(v, int) and not isinstance(v, bool) for v in items):
            return ParameterValue(type=PARAMETER_INTEGER_ARRAY, integer_array_value=items)
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            return ParameterValue(type=PARAMETER_DOUBLE_ARRAY, double_array_value=[float(v) for v in items])
    return ParameterValue(type=PARAMETER_STRING, string_value=json.dumps(value, default=str))


# --- the service --------------------------------------------------------------------------------


class ParameterService:
    """The read-only parameter services of one node: request message in, response message out.

    ``tree`` is the effective configuration (a nested mapping, as ``to_dict(config)``); ``docs``
    maps dotted names to their documentation (the descriptors' ``description``). Immutable after
    construction: :meth:`handle` may be called from any thread.
    """

    def __init__(self, tree: Mapping[str, Any], docs: Mapping[str, str] | None = None) -> None:
        self.values: dict[str, ParameterValue] = {
            name: parameter_value(value) for name, value in flatten(tree).items()}
        self.docs = dict(docs or {})
        self._handlers: dict[str, Callable[[Any], Message]] = {
            "list_parameters": self.list_parameters,
            "describe_parameters": self.describe_parameters,
            "get_parameters": self.get_parameters,
            "get_parameter_types": self.get_parameter_types,
            "set_parameters": self.set_parameters,
            "set_parameters_atomically": self.set_parameters_atomically,
        }

    def handle(self, service: str, request: Message) -> Message:
        """The response of ``service`` (a :data:`PARAMETER_SERVICES` name) to ``request``.

        Raises ``KeyError`` for an unknown service and ``TypeError`` for a request of the wrong type.
        """
        spec = _SPECS[service]
        if not isinstance(request, spec.request):
            raise TypeError(f"{service} takes {spec.request.ROS_TYPE}, not {type(request).__name__}")
        return self._handlers[service](request)

    def list_parameters(self, request: ListParametersRequest) -> ListParametersResponse:
        """Names under the prefixes (all without), at most ``depth`` levels below (0: any); rclcpp's rule."""
        depth, prefixes = int(request.depth), [str(p) for p in request.prefixes]
        result = ListParametersResult()
        for name in self.values:
            get_all = not prefixes and (depth == 0 or name.count(SEPARATOR) < depth)
            if get_all or any(_under(name, prefix, depth) for prefix in prefixes):
                result.names.append(name)
                head, sep, _ = name.rpartition(SEPARATOR)
                if sep and head not in result.prefixes:
                    result.prefixes.append(head)
        return ListParametersResponse(result)

    def describe_parameters(self, request: DescribeParametersRequest) -> DescribeParametersResponse:
        """A read-only descriptor per name; an empty list if any name is unknown."""
        if not self._known(request.names):
            return DescribeParametersResponse()
        return DescribeParametersResponse([
            ParameterDescriptor(name=name, type=self.values[name].type, description=self.docs.get(name, ""),
                                additional_constraints=READ_ONLY_REASON.format(name=name), read_only=True)
            for name in request.names])

    def get_parameters(self, request: GetParametersRequest) -> GetParametersResponse:
        """The values of the names; an empty list if any name is unknown."""
        if not self._known(request.names):
            return GetParametersResponse()
        return GetParametersResponse([self.values[name] for name in request.names])

    def get_parameter_types(self, request: GetParameterTypesRequest) -> GetParameterTypesResponse:
        """The ParameterType of each name; an empty list if any name is unknown."""
        if not self._known(request.names):
            return GetParameterTypesResponse()
        return GetParameterTypesResponse([self.values[name].type for name in request.names])

    def set_parameters(self, request: SetParametersRequest) -> SetParametersResponse:
        """Every set refused, each with the reason."""
        return SetParametersResponse([self._refusal(p.name) for p in request.parameters])

    def set_parameters_atomically(self, request: SetParametersAtomicallyRequest
                                  ) -> SetParametersAtomicallyResponse:
        """The set refused as a whole."""
        names = [p.name for p in request.parameters]
        return SetParametersAtomicallyResponse(self._refusal(names[0] if len(names) == 1 else "KEY"))

    def _refusal(self, name: str) -> SetParametersResult:
        if name not in self.values and name != "KEY":
            return SetParametersResult(False, f"racecar-hw has no parameter {name!r}; "
                                              "ros2 param list shows them")
        return SetParametersResult(False, READ_ONLY_REASON.format(name=name))

    def _known(self, names: Iterable[str]) -> bool:
        return all(name in self.values for name in names)


class RequestRefused(ValueError):
    """A parameter request this daemon will not answer (too large); the message says why."""


class CdrAnswers:
    """:class:`ParameterService` over CDR bytes, for a network interface: request bytes in, response
    bytes out, from any thread, remembered per request.

    Serializing 250 parameter values costs tens of milliseconds of Python (the generic rosbags path:
    ``ParameterValue``'s string and 8-byte arrays have no direct serializer), so the answers are
    cached (the configuration never changes), and :meth:`warm` computes the ones ``ros2 param list``,
    ``ros2 param dump`` and rqt ask for before anyone asks: the whole list, and every name's value,
    type and description in the list's order. Those stay; other answers are remembered up to
    :attr:`MAX_CACHED_BYTES` (requests and answers together), then forgotten.

    A client chooses its request, so it is bounded before any work: at most
    :attr:`MAX_REQUEST_BYTES` of CDR and :attr:`MAX_REQUEST_ITEMS` names, prefixes or parameters
    (the configuration has a few hundred names); a larger one raises :class:`RequestRefused`.
    Without the bounds one describe_parameters call naming one parameter 20,000 times built 15 MB
    of answer in Zenoh's thread, holding the GIL the control loop needs, and kept it.
    """

    MAX_CACHED_BYTES = 1 << 20
    MAX_REQUEST_BYTES = 64 * 1024
    MAX_REQUEST_ITEMS = 1024

    def __init__(self, service: ParameterService) -> None:
        self.service = service
        self._types = ros2_types()
        self._warm: dict[tuple[str, bytes], bytes] = {}
        self._cache: dict[tuple[str, bytes], bytes] = {}
        self._cached_bytes = 0
        self._lock = threading.Lock()

    def answer(self, name: str, request: bytes) -> bytes:
        """The CDR response of service ``name`` to the CDR ``request``; raises on a malformed request
        (:class:`RequestRefused` for one too large to answer)."""
        key = (name, bytes(request))
        cached = self._warm.get(key) or self._cache.get(key)
        if cached is not None:
            return cached
        if len(key[1]) > self.MAX_REQUEST_BYTES:
            raise RequestRefused(f"request of {len(key[1])} bytes (at most {self.MAX_REQUEST_BYTES})")
        spec = _SPECS[name]
        request_msg = self._types.deserialize(key[1], spec.request)
        items = sum(len(getattr(request_msg, f)) for f in ("names", "prefixes", "parameters")
                    if hasattr(request_msg, f))
        if items > self.MAX_REQUEST_ITEMS:
            raise RequestRefused(f"request of {items} names (at most {self.MAX_REQUEST_ITEMS})")
        response = self._types.serialize(self.service.handle(name, request_msg))
        size = len(key[1]) + len(response)
        with self._lock:
            if self._cached_bytes + size > self.MAX_CACHED_BYTES:
                self._cache.clear()
                self._cached_bytes = 0
            if size <= self.MAX_CACHED_BYTES:
                self._cache[key] = response
                self._cached_bytes += size
        return response

    def warm(self) -> None:
        """Compute the common answers now (at start, off the event loop); they are kept."""
        names = list(self.service.values)
        for name, request in (("list_parameters", ListParametersRequest()),
                              ("get_parameters", GetParametersRequest(names)),
                              ("get_parameter_types", GetParameterTypesRequest(names)),
                              ("describe_parameters", DescribeParametersRequest(names))):
            data = self._types.serialize(request)
            response = self.answer(name, data)
            with self._lock:
                self._warm[(name, bytes(data))] = response
                if self._cache.pop((name, bytes(data)), None) is not None:
                    self._cached_bytes -= len(data) + len(response)

    @property
    def cached_bytes(self) -> int:
        """Bytes of the answers remembered beyond the warm ones (requests included)."""
        return self._cached_bytes


def _under(name: str, prefix: str, depth: int) -> bool:
    """rclcpp's prefix match: the name itself, or below ``prefix.`` within ``depth`` levels."""
    if name == prefix:
        return True
    if not name.startswith(prefix + SEPARATOR):
        return False
    return depth == 0 or name[len(prefix):].count(SEPARATOR) < depth


_SPECS = {spec.name: spec for spec in PARAMETER_SERVICES}
