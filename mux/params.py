"""Parameters of the priority Ackermann command mux.

Priorities: a larger number wins. Timeouts are measured from the arrival of the last message on
the topic (monotonic clock), never from its header stamp. The defaults keep the ROS racecar topic
names (MIT ``mux.launch`` layout, flattened into one mux): safety above teleop above ``nav_0`` ..
``nav_3``, each with a 0.2 s timeout, and a zero command when nothing is fresh. An input on the
operator's topics (``safety``, ``teleop``, ``foxglove``: :data:`OPERATOR_TOPICS`) takes no network
commands unless its ``network`` says so: only the daemon's own sources drive it.

Build from YAML with ``racecar_hw.base.params.build(MuxParams, mapping, "mux")``. Cross-field rules
(unique priorities, names and topics) are checked when the instance is created and raise
:class:`~racecar_hw.base.errors.ConfigError` naming the key under the prefix ``mux``; call
:meth:`MuxParams.validate` with another prefix when the mux sits elsewhere in a larger config.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from mux.estop import OPERATORS, RELEASE_SOURCES
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.params import param
from racecar_hw.base.topics import (
    FOXGLOVE_INPUT_TOPIC,
    MUX_ACTIVE_TOPIC,
    MUX_HIGH,
    MUX_LOW,
    MUX_SAFETY_TOPIC,
    TELEOP_TOPIC,
)

#: The topics the daemon's own operator sources drive (the gamepad, keyboard and ground station's
#: teleop, the cone safety node's safety input, Foxglove's Teleop panel): an input on one of them
#: takes no network commands unless its ``network`` says so.
OPERATOR_TOPICS = frozenset((TELEOP_TOPIC, MUX_SAFETY_TOPIC, FOXGLOVE_INPUT_TOPIC))
#: Source names the mux uses for itself; an input may not take one of them.
RESERVED_SOURCES: tuple[str, ...] = ("idle", "estop", "fault")

_LOW, _HIGH = MUX_LOW, MUX_HIGH
#: An input's timeout (s) is within these: a source that never expired (0, once "never") or
#: expired only after many seconds would hold its last command, driving a car nobody commands.
MIN_INPUT_TIMEOUT_S, MAX_INPUT_TIMEOUT_S = 0.01, 5.0


@dataclass
class InputParams:
    """One command source: ackermann_msgs/AckermannDriveStamped on ``topic``."""

    name: str = field(metadata={"doc": "source name shown in diagnostics and switch logs"})
    topic: str = field(metadata={"doc": "topic carrying AckermannDriveStamped commands"})
    priority: int = param(0, "larger wins; unique among inputs", min=0, max=255)
    timeout_s: float = param(0.2, "the source expires this long after its last message (every source "
                             "expires: the mux never holds a command)", unit="s",
                             min=MIN_INPUT_TIMEOUT_S, max=MAX_INPUT_TIMEOUT_S)
    network: bool | None = param(None, "network sessions (Zenoh, DDS) may command this input; false: "
                                 "only the daemon's own sources (gamepad, keyboard, MAVLink, Foxglove "
                                 "teleop, calibration, the safety controller) drive it, and a network "
                                 "sample on its topic is refused and counted; null (the default): "
                                 "false on the operator's topics (the teleop, safety and foxglove "
                                 "inputs' shipped topics), true on any other")

    def __post_init__(self) -> None:
        if self.network is None:  # a config listing its inputs does not open the operator's
            self.network = self.topic not in OPERATOR_TOPICS


@dataclass
class LockParams:
    """A lock on std_msgs/Bool: while engaged it masks every input of strictly lower priority.

    Engaged while the last message said true, or (deadman) when ``timeout_s`` > 0 and nothing
    arrived for longer than that, including a publisher that never spoke.
    """

    name: str = field(metadata={"doc": "lock name shown in diagnostics"})
    topic: str = field(metadata={"doc": "topic carrying std_msgs/Bool; true engages the lock"})
    priority: int = param(0, "inputs of strictly lower priority are masked while engaged",
                          min=0, max=255)
    timeout_s: float = param(0.0, "engage when silent for longer than this (deadman); 0 = never",
                             unit="s", min=0.0)


def _default_inputs() -> list[InputParams]:
    inputs = [
        # the operator's inputs: the safety controller and the gamepad (keyboard, ground station)
        # drive them from inside the daemon; nobody on the network may override the operator
        InputParams("safety", f"{_LOW}/input/safety", 100, 0.2, network=False),
        InputParams("teleop", f"{_LOW}/input/teleop", 90, 0.2, network=False),
    ]
    for n, priority in enumerate((20, 15, 10, 5)):
        inputs.append(InputParams(f"nav_{n}", f"{_HIGH}/input/nav_{n}", priority, 0.2))
    return inputs


@dataclass
class MuxParams:
    """The command mux: inputs, locks, e-stop, output rate and the rate limiter."""

    inputs: list[InputParams] = param(
        _default_inputs(), "command sources; priorities, names and topics unique")
    locks: list[LockParams] = param([], "locks masking lower-priority inputs (std_msgs/Bool)")
    estop_topic: str = param("/estop", "std_msgs/Bool; true engages the latched e-stop")
    estop_release_topic: str = param(
        "/estop_release", "std_msgs/Bool; true releases the e-stop, refused while estop_topic "
        "still says true, and refused unless only the e-stop topic engaged it (see "
        "estop_release_sources)")
    estop_release_sources: list[str] = param(
        list(RELEASE_SOURCES),
        "who may release the latched e-stop: operator surfaces (" + ", ".join(OPERATORS) + ") "
        "release any latch; 'network' (estop_release_topic from a Zenoh/DDS session) and 'local' "
        "(estop_release_topic from code in the daemon) release only a latch that the e-stop topic "
        "alone engaged; leave one out to refuse its releases")
    start_estopped: bool = param(False, "start with the e-stop engaged (release before driving)")
    rate_hz: float = param(50.0, "output rate; also the limiter's fixed step", unit="Hz",
                           min=1.0, max=1000.0)
    output_topic: str = param(f"{_LOW}/output", "AckermannDriveStamped output, frame base_link")
    active_topic: str = param(MUX_ACTIVE_TOPIC,
                              "std_msgs/String naming the active source, published on switches")
    hold_steering_when_idle: bool = param(
        False, "when no input is fresh keep the last steering angle (speed is still zero)")
    diagnostics_topic: str = param("/diagnostics", "diagnostic_msgs/DiagnosticArray output")
    diagnostics_rate_hz: float = param(2.0, "diagnostics publish rate", unit="Hz",
                                       min=0.1, max=50.0)
    limiter_enabled: bool = param(True, "apply the acceleration and steering-rate limits")
    max_accel_mps2: float = param(2.5, "largest speed change away from zero", unit="m/s^2",
                                  min=1e-3)
    max_decel_mps2: float = param(8.0, "largest speed change toward zero (vehicle braking)",
                                  unit="m/s^2", min=1e-3)
    max_steering_rate_radps: float = param(3.2, "largest steering angle change", unit="rad/s",
                                           min=1e-3)

    def __post_init__(self) -> None:
        self.validate("mux")

    def validate(self, key: str = "mux") -> None:
        """Check cross-field rules; raise ConfigError naming the first offending key."""
        for name in ("rate_hz", "diagnostics_rate_hz", "max_accel_mps2", "max_decel_mps2",
                     "max_steering_rate_radps"):
            value = getattr(self, name)
            if not value > 0.0:  # also refuses NaN
                raise ConfigError(f"{key}.{name}", f"{value!r} must be greater than 0")
        if not math.isfinite(self.rate_hz):
            raise ConfigError(f"{key}.rate_hz", "must be finite")
        topics: dict[str, str] = {}

        def claim(topic: str, where: str) -> None:
            if not topic.startswith("/"):
                raise ConfigError(where, f"{topic!r} is not an absolute topic name")
            if topic in topics:
                raise ConfigError(where, f"{topic} is already used by {topics[topic]}")
            topics[topic] = where

        seen: set[str] = set()
        for i, source in enumerate(self.estop_release_sources):
            if source not in RELEASE_SOURCES:
                raise ConfigError(f"{key}.estop_release_sources[{i}]",
                                  f"{source!r} is not a release source; allowed: "
                                  + ", ".join(RELEASE_SOURCES))
            if source in seen:
                raise ConfigError(f"{key}.estop_release_sources[{i}]", f"{source!r} is listed twice")
            seen.add(source)
        for name in ("output_topic", "estop_topic", "estop_release_topic", "active_topic",
                     "diagnostics_topic"):
            claim(getattr(self, name), f"{key}.{name}")
        names: dict[str, str] = {}
        priorities: dict[int, str] = {}
        for i, inp in enumerate(self.inputs):
            where = f"{key}.inputs[{i}]"
            if not inp.name:
                raise ConfigError(f"{where}.name", "must not be empty")
            if inp.name in RESERVED_SOURCES:
                raise ConfigError(f"{where}.name", f"{inp.name!r} is reserved; reserved names: "
                                                   + ", ".join(RESERVED_SOURCES))
            if inp.name in names:
                raise ConfigError(f"{where}.name", f"{inp.name!r} is already used by {names[inp.name]}")
            names[inp.name] = where
            if inp.priority in priorities:
                raise ConfigError(f"{where}.priority",
                                  f"{inp.priority} is already used by {priorities[inp.priority]}; "
                                  "input priorities must be unique")
            priorities[inp.priority] = where
            if not MIN_INPUT_TIMEOUT_S <= inp.timeout_s <= MAX_INPUT_TIMEOUT_S:
                raise ConfigError(f"{where}.timeout_s", f"{inp.timeout_s} s: every input must expire, "
                                  f"{MIN_INPUT_TIMEOUT_S} to {MAX_INPUT_TIMEOUT_S} s (the mux never "
                                  "holds a command)")
            claim(inp.topic, f"{where}.topic")
        lock_names: dict[str, str] = {}
        for i, lock in enumerate(self.locks):
            where = f"{key}.locks[{i}]"
            if not lock.name:
                raise ConfigError(f"{where}.name", "must not be empty")
            if lock.name in lock_names:
                raise ConfigError(f"{where}.name",
                                  f"{lock.name!r} is already used by {lock_names[lock.name]}")
            lock_names[lock.name] = where
            if not math.isfinite(lock.timeout_s):
                raise ConfigError(f"{where}.timeout_s", "must be finite (0 means never expires)")
            claim(lock.topic, f"{where}.topic")
