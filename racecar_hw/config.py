"""The daemon's one configuration file: which components run, and their parameters.

This file plays the role a ROS launch file plays. Each top-level key is a section; optional
components have ``enabled``. Every parameter has a documented default
(``racecar-hw check-config --describe`` lists them all); unknown keys and bad values are refused
at start with a :class:`~racecar_hw.base.errors.ConfigError` naming the key and what is allowed.

Shipped configs: ``car.yaml`` (real devices under systemd) and ``sim.yaml`` (the fake-hardware
loopback), in the package's ``config/`` directory.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lidar_drivers.params import RPLIDAR_MODELS, LidarParams
from mux.params import InputParams, LockParams, MuxParams
from racecar_hw.bags.follow import FollowerParams
from racecar_hw.bags.record import RecorderParams
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.overrides import apply_override, key_lines, key_path, load_yaml, merge, remove_key
from racecar_hw.base.params import build, describe, param, to_dict, unknown_key
from racecar_hw.base.resources import config_file
from racecar_hw.base.topics import CMD_VEL_BUS_TOPIC, FOXGLOVE_INPUT_TOPIC
from racecar_hw.base.transforms import StaticTransform, StaticTransformParams, TfTree, build_static_transforms
from racecar_hw.net.dds_config import DdsParams
from racecar_hw.net.foxglove_params import FoxgloveParams
from racecar_hw.net.ports import Listener, free_port, port_taken
from racecar_hw.net.rosout import RosoutParams
from racecar_hw.net.topics import CMD_VEL_INPUT, CMD_VEL_PRIORITY, Topic, named, topic_table
from racecar_hw.net.web_params import WebParams
from racecar_hw.net.zenoh_config import ZenohParams, parse_endpoint
from racecar_hw.sources.figure8 import Figure8Params
from racecar_hw.sources.scan_summary import ScanSummaryParams
from racecar_hw.sources.setpoint import SetpointParams
from racecar_hw.teleop.arming import ArmingParams
from racecar_hw.teleop.gamepad import GamepadParams
from racecar_hw.teleop.keyboard import KeyboardParams
from racecar_hw.teleop.mavlink_params import MavlinkParams
from safety.params import SafetyParams
from vesc.params import VescParams


def _section(cls: type, enabled: bool, what: str) -> type:
    """``cls`` with an ``enabled`` flag first, for a component that may be switched off."""
    return dataclasses.make_dataclass(
        f"{cls.__name__.removesuffix('Params')}Section",
        [("enabled", bool, param(enabled, f"run the {what}"))],
        bases=(cls,),
    )


VescSection = _section(VescParams, True, "VESC driver")
LidarSection = _section(LidarParams, True, "lidar driver")
ScanSummarySection = _section(ScanSummaryParams, True, "/scan_range and /open_space publisher")
SetpointSection = _section(SetpointParams, False, "set-point relay (CSE490R lab 0)")
FollowerSection = _section(FollowerParams, False, "bag follower")
KeyboardSection = _section(KeyboardParams, False, "keyboard teleop in the terminal (simulation)")


@dataclass
class Figure8Section:
    """The analytical figure-8 driver; its parameters are checked only when enabled."""

    enabled: bool = param(False, "run the figure-8 driver")
    speed_mps: float = param(1.0, "speed along the figure", unit="m/s", min=-5.0, max=5.0)
    steering_angle_rad: float = param(0.3, "steering of the first loop (+ left)", unit="rad",
                                      min=-0.8, max=0.8)
    figure8s: int = param(1, "figure-8s to drive; 0 drives until stopped", min=0)
    rate_hz: float = param(20.0, "command rate", unit="Hz", min=1.0, max=200.0)
    topic: str = param("/vesc/high_level/ackermann_cmd_mux/input/nav_0", "mux input to drive", topic=True)

    def params(self, wheelbase_m: float) -> Figure8Params:
        """The driver's parameters for a car of ``wheelbase_m``."""
        try:
            return Figure8Params(speed_mps=self.speed_mps, steering_angle_rad=self.steering_angle_rad,
                                 wheelbase_m=wheelbase_m, figure8s=self.figure8s, rate_hz=self.rate_hz,
                                 topic=self.topic)
        except ConfigError as err:
            raise ConfigError(f"figure8.{err.key}", str(err).split(": ", 1)[-1]) from err


@dataclass
class StatusSection:
    """The live console status panel."""

    enabled: bool = param(True, "show the live status panel on the console")
    refresh_hz: float = param(4.0, "panel refresh rate", unit="Hz", min=0.2, max=30.0)


def _default_transforms() -> list[StaticTransformParams]:
    return [StaticTransformParams(frame_id="base_link", child_frame_id="laser", xyz=(0.265, 0.0, 0.1))]


@dataclass
class Config:
    """The whole daemon configuration."""

    vesc: VescSection = field(default_factory=VescSection)  # type: ignore[valid-type]
    lidar: LidarSection = field(default_factory=LidarSection)  # type: ignore[valid-type]
    mux: MuxParams = field(default_factory=MuxParams)
    safety: SafetyParams = field(default_factory=SafetyParams)
    static_transforms: list[StaticTransformParams] = field(default_factory=_default_transforms)
    scan_summary: ScanSummarySection = field(default_factory=ScanSummarySection)  # type: ignore[valid-type]
    setpoint: SetpointSection = field(default_factory=SetpointSection)  # type: ignore[valid-type]
    figure8: Figure8Section = field(default_factory=Figure8Section)
    follower: FollowerSection = field(default_factory=FollowerSection)  # type: ignore[valid-type]
    recorder: RecorderParams = field(default_factory=RecorderParams)
    arming: ArmingParams = field(default_factory=ArmingParams)
    gamepad: GamepadParams = field(default_factory=GamepadParams)
    keyboard: KeyboardSection = field(default_factory=KeyboardSection)  # type: ignore[valid-type]
    mavlink: MavlinkParams = field(default_factory=MavlinkParams)
    status: StatusSection = field(default_factory=StatusSection)
    zenoh: ZenohParams = field(default_factory=ZenohParams)
    dds: DdsParams = field(default_factory=DdsParams)
    rosout: RosoutParams = field(default_factory=RosoutParams)
    foxglove: FoxgloveParams = field(default_factory=FoxgloveParams)
    web: WebParams = field(default_factory=WebParams)


_SECTIONS: dict[str, type] = {
    "vesc": VescSection, "lidar": LidarSection, "mux": MuxParams, "safety": SafetyParams,
    "scan_summary": ScanSummarySection, "setpoint": SetpointSection, "figure8": Figure8Section,
    "follower": FollowerSection, "recorder": RecorderParams, "arming": ArmingParams,
    "gamepad": GamepadParams, "keyboard": KeyboardSection, "mavlink": MavlinkParams,
    "status": StatusSection,
    "foxglove": FoxgloveParams, "web": WebParams, "zenoh": ZenohParams, "dds": DdsParams,
    "rosout": RosoutParams,
}

#: Said after ``sim: unknown section``: the simulated car and world are a scenario's, not the daemon's.
_SIM_HINT = ("; the simulated car's true values and its world are set in a scenario "
             "(racecar-hw sim --scenario FILE; the format: racecar_hw/sim/scenario.py)")

#: The mux input Foxglove's Teleop panel drives through (when foxglove.teleop is on).
FOXGLOVE_INPUT = "foxglove"


def build_config(data: dict[str, Any]) -> Config:
    """A validated :class:`Config` from a plain mapping (a parsed YAML file)."""
    allowed = sorted([*_SECTIONS, "static_transforms"])
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        message = unknown_key(unknown[0], allowed, "section")
        if unknown[0] == "sim":
            message += _SIM_HINT
        raise ConfigError(unknown[0], message)
    values: dict[str, Any] = {}
    for name, cls in _SECTIONS.items():
        if name in data:
            values[name] = build(cls, data[name], name)
    if "static_transforms" in data:
        values["static_transforms"] = build_static_transforms(data["static_transforms"],
                                                              "static_transforms")
    config = Config(**values)
    config.mux.locks.extend(added_locks(config.gamepad, config.mux.locks))
    config.mux.inputs.extend(added_inputs(config.foxglove, config.zenoh, config.mux.inputs, config.dds))
    config.mux.validate("mux")
    if config.zenoh.enabled or config.dds.enabled:
        config.zenoh.validate("zenoh")
        network_topics(config)
    if config.dds.enabled:
        config.dds.validate("dds")
    _check_scan_timing(config)
    _check_braking(config)
    _check_transform_tree(config)
    _check_imu_mount(config)
    if config.figure8.enabled:
        config.figure8.params(config.vesc.wheelbase_m)
    return config


#: The timeout (s) of the mux input ``cmd_vel``: a ROS 2 node's velocity commands, as nav_0's.
CMD_VEL_TIMEOUT_S = 0.2


def added_inputs(fox: FoxgloveParams, zenoh: ZenohParams, inputs: list[InputParams] | list[dict[str, Any]],
                 dds: DdsParams | None = None) -> list[InputParams]:
    """The mux inputs the features add after the configured ``inputs``, unless one of them has the
    name already: ``foxglove`` for Foxglove's Teleop panel (``foxglove.teleop``, its priority and
    timeout from ``foxglove.teleop_priority`` and ``teleop_timeout_s``; closed to Zenoh and DDS),
    then ``cmd_vel`` for ROS 2's /cmd_vel over Zenoh or DDS (``zenoh.cmd_vel``, priority 18, 0.2 s)."""
    names = {i["name"] if isinstance(i, dict) else i.name for i in inputs}
    added = []
    if fox.enabled and fox.teleop and FOXGLOVE_INPUT not in names:
        # the Foxglove server's Teleop panel is its only source, not a Zenoh or DDS session
        added.append(InputParams(FOXGLOVE_INPUT, FOXGLOVE_INPUT_TOPIC, fox.teleop_priority,
                                 fox.teleop_timeout_s, network=False))
    ros = zenoh.enabled or (dds is not None and dds.enabled)
    if ros and zenoh.cmd_vel and CMD_VEL_INPUT not in names:
        added.append(InputParams(CMD_VEL_INPUT, CMD_VEL_BUS_TOPIC, CMD_VEL_PRIORITY, CMD_VEL_TIMEOUT_S))
    return added


def added_locks(gamepad: GamepadParams, locks: list[LockParams] | list[dict[str, Any]]) -> list[LockParams]:
    """The mux locks the features add after the configured ``locks``: the gamepad's autonomy lock
    (``gamepad.autonomy_lock``, with the gamepad on), unless a lock is on its topic already."""
    if not (gamepad.enabled and gamepad.autonomy_lock):
        return []
    lock = gamepad.lock_params()
    topics = {item.get("topic") if isinstance(item, dict) else item.topic for item in locks}
    return [] if lock.topic in topics else [lock]


def cmd_vel_input_topic(config: Config) -> str | None:
    """The bus topic of the mux input ``cmd_vel``, or None when there is none."""
    return next((i.topic for i in config.mux.inputs if i.name == CMD_VEL_INPUT), None)


def network_topics(config: Config) -> list[Topic]:
    """The topic table the network interfaces (Zenoh, DDS, Foxglove) offer, named by ``zenoh.profile``
    and ``zenoh.remap``: one table, two wires."""
    z = config.zenoh
    summary = config.scan_summary
    rows = topic_table(
        config.mux, config.safety, scan_topic=config.lidar.topic,
        scan_range_topic=summary.scan_range_topic if summary.enabled else None,
        open_space_topic=summary.open_space_topic if summary.enabled else None,
        cmd_vel_topic=z.cmd_vel_topic if z.cmd_vel and cmd_vel_input_topic(config) else None,
        rosout=config.rosout.enabled)
    first: dict[str, Topic] = {}
    for row in rows:
        other = first.setdefault(row.bus, row)
        if other is not row:
            key, keys = topic_keys(config, row.bus) or ("zenoh.profile", [])
            raise ConfigError(key, f"{row.bus} would be both {other.what} and {row.what}; each needs a "
                                   f"topic of its own (keys set to {row.bus}: {', '.join(keys)})")
    return named(rows, config.mux, z.profile, z.remap, "zenoh")


def topic_keys(config: Config, topic: str) -> tuple[str, list[str]] | None:
    """The key to name for a clash on ``topic`` (the first key set to it that is not so by default)
    and every key set to it; None when no key is."""
    keys = keys_set_to(config, topic)
    if not keys:
        return None
    default = keys_set_to(Config(), topic)
    return next((k for k in keys if k not in default), keys[0]), keys


def keys_set_to(config: Config, value: str) -> list[str]:
    """The dotted keys of ``config`` whose value is ``value`` (``mux.inputs.0.topic``), in order."""
    found: list[str] = []

    def walk(node: Any, key: str) -> None:
        if dataclasses.is_dataclass(node) and not isinstance(node, type):
            for f in dataclasses.fields(node):
                walk(getattr(node, f.name), f"{key}.{f.name}" if key else f.name)
        elif isinstance(node, (list, tuple)):
            for i, item in enumerate(node):
                walk(item, f"{key}.{i}")
        elif isinstance(node, dict):
            for k, item in node.items():
                walk(item, f"{key}.{k}")
        elif node == value and isinstance(node, str):
            found.append(key)

    walk(config, "")
    return found


#: An RPLIDAR's sweep period (s): about 10 Hz revolutions (A1 5.5 Hz at the slowest).
RPLIDAR_SWEEP_S = 0.1


#: Zenoh protocols that listen on a TCP port (the ones a port clash can hit).
_TCP_PROTOCOLS = ("tcp", "tls", "ws")


def listeners(config: Config) -> list[Listener]:
    """Every port the configuration listens on: Zenoh's listen endpoints, the Foxglove live view,
    the status page (TCP), the MAVLink link (UDP); enabled ones, port 0 (any free port) left out."""
    out: list[Listener] = []
    if config.zenoh.enabled:
        for i, endpoint in enumerate(config.zenoh.listen):
            key = f"zenoh.listen[{i}]"
            proto, host, port = parse_endpoint(endpoint, key)
            if proto in _TCP_PROTOCOLS and port:
                out.append(Listener(key, "Zenoh (ROS 2 topics)", host, port))
    if config.foxglove.enabled and config.foxglove.port:
        out.append(Listener("foxglove.port", "the Foxglove live view", config.foxglove.host,
                            config.foxglove.port))
    if config.web.enabled and config.web.port:
        out.append(Listener("web.port", "the status page", config.web.host, config.web.port))
    if config.mavlink.enabled and config.mavlink.bind_port:
        host, port = config.mavlink.bind
        out.append(Listener("mavlink.bind_port", "the MAVLink ground-station link", host, port, "udp"))
    return out


def taken_listeners(config: Config) -> list[Listener]:
    """The listeners whose port another program holds now (:func:`racecar_hw.net.ports.port_taken`)."""
    return [item for item in listeners(config) if port_taken(item.host, item.port, item.kind)]


def move_to_free_ports(config: Config, avoid: Collection[int] = ()) -> list[tuple[Listener, str]]:
    """Move every listener whose port is taken (or in ``avoid``: ports promised to another daemon of
    this process that has not bound them yet) to a free port, in ``config``; returns each moved one
    with where it listens now (an endpoint or URL to print). What ``racecar-hw sim`` does."""
    moved: list[tuple[Listener, str]] = []
    clashing = [item for item in listeners(config) if item.port in avoid]
    for item in clashing + [item for item in taken_listeners(config) if item not in clashing]:
        port = free_port(item.host, item.kind)
        while port in avoid:  # free now, but promised: ask again
            port = free_port(item.host, item.kind)
        where = f"{item.host}:{port}"
        if item.key.startswith("zenoh.listen["):
            i = int(item.key[len("zenoh.listen["):-1])
            endpoint = config.zenoh.listen[i]
            proto, _, rest = endpoint.partition("/")
            address, sep, tail = rest.partition("#")
            host_part = address.rpartition(":")[0]
            config.zenoh.listen[i] = where = f"{proto}/{host_part}:{port}" + (sep + tail if sep else "")
        elif item.key == "mavlink.bind_port":
            config.mavlink.bind_port = port
            where = f"udp {where}"
        elif item.key == "foxglove.port":
            config.foxglove.port = port
            where = f"ws://{item.host}:{port}"
        else:
            config.web.port = port
            where = f"http://{item.host}:{port}/"
        moved.append((item, where))
    return moved


def _check_scan_timing(config: Config) -> None:
    """Refuse a safety timing that would hold an RPLIDAR car still forever (stale every scan)."""
    lidar, safety = config.lidar, config.safety
    if not lidar.enabled or safety.mode != "arc" or lidar.model not in RPLIDAR_MODELS:
        return
    if safety.scan_timeout_s < 2.5 * RPLIDAR_SWEEP_S:
        raise ConfigError("safety.scan_timeout_s", f"{safety.scan_timeout_s} s is shorter than two "
                          f"sweeps of an RPLIDAR ({lidar.model}, about 10 Hz): every scan would count "
                          "as stale and the car would never move; set safety.scan_timeout_s: 0.25 "
                          "(or more) and safety.scan_period_s: 0.1")
    if safety.scan_period_s < RPLIDAR_SWEEP_S:
        raise ConfigError("safety.scan_period_s", f"{safety.scan_period_s} s is shorter than an "
                          f"RPLIDAR's sweep ({lidar.model}, about 0.1 s): the stopping distance would "
                          "be underestimated; set safety.scan_period_s: 0.1")


def _check_braking(config: Config) -> None:
    """Refuse a mux limiter that brakes more gently than the safety controller counts on."""
    mux, safety = config.mux, config.safety
    if mux.limiter_enabled and safety.mode != "off" and mux.max_decel_mps2 < safety.max_decel_mps2:
        raise ConfigError("mux.max_decel_mps2", f"{mux.max_decel_mps2} m/s^2 is below "
                          f"safety.max_decel_mps2 ({safety.max_decel_mps2}): the safety controller's "
                          "stopping distances assume the car brakes at that rate, and the limiter, "
                          "which runs after it (and ramps down a timed-out input or a stale scan), "
                          "would brake more gently; raise it, or lower safety.max_decel_mps2")


#: Largest tilt (rad) of the IMU frame's z axis from base_link's that is accepted: the driver takes
#: the IMU's z rate as the yaw rate, which a tilt scales by cos(tilt) (0.5 % at this bound).
IMU_TILT_MAX_RAD = 0.1


def _check_transform_tree(config: Config) -> None:
    """Refuse a static transform that gives a frame a second parent or closes a cycle, naming its
    item (``static_transforms[N]``) as an item's own errors do: check-config gives its line, and
    reports it with the others rather than once they are fixed and the daemon builds the tree."""
    tree = TfTree()
    for index, params in enumerate(config.static_transforms):
        try:
            tree.add(StaticTransform.from_params(params))
        except ConfigError as err:
            raise ConfigError(f"static_transforms[{index}]", str(err).split(": ", 1)[-1]) from err


def _check_imu_mount(config: Config) -> None:
    """Refuse a ``base_link -> imu`` with roll or pitch: the driver (``odometry_yaw_rate: imu``, the
    gyro bias) and ``racecar-hw calibrate`` take the IMU's z rate as the car's yaw rate, untransformed,
    so the firmware's mounting rotation must make z point up (docs/vesc.md, "The IMU")."""
    vesc = config.vesc
    if not (vesc.enabled and vesc.imu):
        return
    try:
        tree = TfTree.from_params(config.static_transforms)
    except ConfigError:
        return  # a malformed tree is reported where the daemon builds it
    if not tree.can_transform("base_link", vesc.imu_frame_id):
        return
    z_up = float(tree.lookup("base_link", vesc.imu_frame_id)[2, 2])
    tilt = math.acos(max(-1.0, min(1.0, z_up)))
    if tilt > IMU_TILT_MAX_RAD:
        index = next(i for i, t in enumerate(config.static_transforms)
                     if t.child_frame_id == vesc.imu_frame_id)
        raise ConfigError(f"static_transforms[{index}]", f"base_link -> {vesc.imu_frame_id} tilts the "
                          f"IMU's z axis {math.degrees(tilt):.0f} deg from up (roll or pitch), but the "
                          "driver and calibrate read its z rate as the yaw rate: set VESC Tool's IMU "
                          "mounting rotation so z points up, and give only xyz and yaw here")


def load_config(path: str | Path | None, overrides: list[str] | tuple[str, ...] = (),
                extra: dict[str, Any] | None = None) -> Config:
    """The config in ``path`` (None: the shipped car config), merged with ``extra``, then ``--set``s."""
    return build_config(_assemble(path, overrides, extra))


def _assemble(path: str | Path | None, overrides: list[str] | tuple[str, ...] = (),
              extra: dict[str, Any] | None = None,
              problems: list[ConfigProblem] | None = None) -> dict[str, Any]:
    """The config's plain data: the file (None: the shipped car config), ``extra``, the ``--set``s.

    With ``problems``, a ``--set`` that cannot be applied is added there (and left out) instead of
    raised."""
    data = load_yaml(path if path is not None else shipped_config("car"))
    if extra:
        data = merge(data, extra)
    defaults = to_dict(Config()) if overrides else None
    later = []  # --set mux.inputs.N... (or locks) not among the configured ones: one the features add
    for assignment in overrides:
        item = _mux_item(assignment)
        if item is not None and not _among(item[1], _mux_list(data, defaults, item[0])):
            later.append(assignment)
        else:
            _apply(data, assignment, defaults, problems)
    if later:
        _set_added(data, defaults, later, problems)
    return data


def _apply(data: dict[str, Any], assignment: str, defaults: dict[str, Any] | None,
           problems: list[ConfigProblem] | None, items: list[Any] | None = None) -> None:
    """:func:`apply_override`; with ``problems``, its error goes there, from the ``--set``. With
    ``items`` (the mux's inputs or locks, the added ones included), an index not among them is
    refused naming them."""
    try:
        item = _mux_item(assignment)
        if items is not None and item is not None and not _among(item[1], items):
            raise _no_such_item(assignment, items)
        apply_override(data, assignment, defaults)
    except ConfigError as err:
        if problems is None:
            raise
        problems.append(ConfigProblem(f"--set {assignment}", err))


@dataclass(frozen=True)
class ConfigProblem:
    """One error of a config, with where its value came from: ``FILE:LINE``, ``--set K=V``, or the
    file alone (a rule across keys, or a key the file does not name)."""

    where: str
    error: ConfigError

    def __str__(self) -> str:
        if self.where.startswith("--set "):
            return f"{self.error} (from {self.where})"
        return f"{self.where}: {self.error}"


#: At most this many errors are collected from one config.
MAX_PROBLEMS = 50


def check_config(path: str | Path | None, overrides: list[str] | tuple[str, ...] = (), *,
                 build: Callable[[Config], object] | None = None
                 ) -> tuple[Config | None, list[ConfigProblem]]:
    """Every error of a config at once (``racecar-hw check-config``): the config (None when it has
    errors) and each error with the file and line (or the ``--set``) its value came from.

    After an error its key is taken out (for an element of a list of values, the list), so its
    default applies, and the config is checked again, until it builds or an error's key cannot be
    taken out (a rule across keys: then that error is the last). A file that cannot be read or
    parsed is one error; a ``--set`` that cannot be applied is one, and the others are checked.
    ``build`` (the daemon's constructor) then builds what the config describes, without starting
    it: a ConfigError only the components see (two of them declaring one topic with two types) is
    reported as the others are.
    """
    file = Path(path) if path is not None else shipped_config("car")
    lines = key_lines(file)
    sets = {key_path(o.partition("=")[0].strip()): o for o in overrides}
    problems: list[ConfigProblem] = []
    try:
        data = _assemble(file, overrides, problems=problems)
    except ConfigError as err:
        if not err.key:  # the file cannot be read: the message names it
            raise
        return None, [*problems, ConfigProblem(_source(key_path(err.key), file, lines, sets), err)]
    seen: set[str] = set()
    while len(problems) < MAX_PROBLEMS:
        try:
            config = build_config(copy.deepcopy(data))
            if build is not None and not problems:
                build(config)
        except ConfigError as err:
            if err.key in seen:  # taking it out did not help: a rule across keys
                break
            seen.add(err.key)
            where = key_path(err.key)
            problems.append(ConfigProblem(_source(where, file, lines, sets), err))
            path = _value_path(data, where)
            if not err.key or _renumbers(data, path) or not remove_key(data, path):
                break
            continue
        return (None, problems) if problems else (config, [])
    return None, problems


def _value_path(data: dict[str, Any], where: tuple[str | int, ...]) -> tuple[str | int, ...]:
    """The key to take out after an error at ``where``: the whole value when ``where`` is an element
    of a list of values (``static_transforms[0].xyz[0]``: the xyz), whose length may be checked
    (taking one element out would be a second error, of a shortened list); else ``where``."""
    node = _parent(data, where)
    if isinstance(where[-1] if where else None, int) and isinstance(node, list) and not all(
            isinstance(item, dict) for item in node):
        return where[:-1]
    return where


def _renumbers(data: dict[str, Any], path: tuple[str | int, ...]) -> bool:
    """Whether taking out the value at ``path`` would renumber others: an item of a list with items
    after it (``static_transforms[2]`` of five), whose later errors would then name the wrong item
    and line. The check stops there instead."""
    node = _parent(data, path)
    last = path[-1] if path else None
    return isinstance(last, int) and isinstance(node, list) and last < len(node) - 1


def _parent(data: dict[str, Any], path: tuple[str | int, ...]) -> Any:
    """The value that holds the one at ``path`` (None when the path does not lead there)."""
    node: Any = data
    for part in path[:-1]:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            return None
    return node


def _source(where: tuple[str | int, ...], file: Path, lines: dict[tuple[str | int, ...], int],
            sets: dict[tuple[str | int, ...], str]) -> str:
    """Where the value at ``where`` came from: the --set that named it (or a section above it),
    else the file's line of the key, else a --set of a key below it (``--set foo.bar=1`` made the
    section ``foo``), else the file's line of the closest section above it, else the file."""
    for n in range(len(where), 0, -1):
        if where[:n] in sets:
            return f"--set {sets[where[:n]]}"
    if where in lines:
        return f"{file}:{lines[where]}"
    below = [assignment for path, assignment in sets.items() if where and path[:len(where)] == where]
    if below:
        return f"--set {below[0]}"
    for n in range(len(where), 0, -1):
        if where[:n] in lines:
            return f"{file}:{lines[where[:n]]}"
    return str(file)


def _mux_item(assignment: str) -> tuple[str, str] | None:
    """(``inputs`` or ``locks``, N) of a ``mux.inputs.N...=value`` or ``mux.locks.N...``; None for
    any other key."""
    parts = assignment.partition("=")[0].strip().split(".")
    return (parts[1], parts[2]) if len(parts) > 2 and parts[0] == "mux" and parts[1] in _ADDED else None


def _among(index: str, items: list[Any]) -> bool:
    """Whether ``index`` (a --set's key part) numbers one of ``items``."""
    return index.isdigit() and int(index) < len(items)


def _mux_list(data: dict[str, Any], defaults: dict[str, Any] | None, name: str) -> list[Any]:
    """The configured mux ``inputs`` or ``locks``, as plain data: the file's, or the defaults'."""
    mux = data.get("mux")
    items = mux.get(name) if isinstance(mux, dict) else None
    if items is None:
        items = (defaults or to_dict(Config()))["mux"][name]
    return items if isinstance(items, list) else []


def _set_added(data: dict[str, Any], defaults: dict[str, Any] | None, assignments: list[str],
               problems: list[ConfigProblem] | None = None) -> None:
    """Apply ``--set mux.inputs.N...`` and ``mux.locks.N...`` to the lists check-config shows: the
    configured inputs (locks), then those the features add (:func:`added_inputs`,
    :func:`added_locks`, from the settings after every other ``--set``), which are written into
    the data as configured ones first."""
    mux = data.get("mux")
    named = {name: copy.deepcopy(_mux_list(data, defaults, name)) for name in _ADDED}
    data["mux"] = mux = dict(mux) if isinstance(mux, dict) else {}
    wanted = {item[0] for item in map(_mux_item, assignments) if item is not None}
    if "inputs" in wanted:
        inputs = named["inputs"]
        fox = build(FoxgloveParams, data.get("foxglove") or {}, "foxglove")
        zenoh = build(ZenohParams, data.get("zenoh") or {}, "zenoh")
        dds = build(DdsParams, data.get("dds") or {}, "dds")
        added = added_inputs(fox, zenoh, [i for i in inputs if isinstance(i, dict) and "name" in i], dds)
        mux["inputs"] = [*inputs, *to_dict(added)]
    if "locks" in wanted:
        locks = [lock for lock in named["locks"] if isinstance(lock, dict)]
        gamepad = build(GamepadParams, data.get("gamepad") or {}, "gamepad")
        mux["locks"] = [*named["locks"], *to_dict(added_locks(gamepad, locks))]
    for assignment in assignments:
        item = _mux_item(assignment)
        _apply(data, assignment, defaults, problems, mux[item[0]] if item is not None else None)


#: The mux's lists the features add to, and what adds each item (said when a --set names no item).
_ADDED = {
    "inputs": "foxglove is added by foxglove.teleop, cmd_vel by zenoh.cmd_vel (with zenoh or dds on), "
              "when the config names no input so",
    "locks": "autonomy is added by gamepad.autonomy_lock (with the gamepad on), when no lock is on "
             "gamepad.autonomy_lock_topic",
}


def _no_such_item(assignment: str, items: list[Any]) -> ConfigError:
    """The error of a ``--set mux.inputs.N...`` (or locks) not among the mux's ``items``, naming them."""
    key = assignment.partition("=")[0].strip()
    name, index = _mux_item(assignment) or ("inputs", "?")
    listed = "".join(f"{', ' if i else ': '}{i} {item.get('name', '?') if isinstance(item, dict) else '?'}"
                     for i, item in enumerate(items))
    count = f"{len(items)} {name if len(items) != 1 else name[:-1]}"
    return ConfigError(key, f"no mux {name[:-1]} {index if index.isdigit() else repr(index)}; the mux "
                            f"has {count}{listed} (check-config lists them; {_ADDED[name]})")


def shipped_config(name: str) -> Path:
    """The path of a shipped config: ``car`` or ``sim``."""
    return config_file(f"{name}.yaml")


def dump_config(config: Config) -> str:
    """The effective configuration as YAML."""
    return yaml.safe_dump(to_dict(config), sort_keys=False, default_flow_style=None)


def describe_config() -> list[tuple[str, Any, str]]:
    """Every parameter of every section: (dotted key, default, documentation)."""
    rows: list[tuple[str, Any, str]] = []
    for name, cls in _SECTIONS.items():
        rows.extend(describe(cls, name))
    rows.extend(describe(StaticTransformParams, "static_transforms[]"))
    return rows
