"""Message types that mirror ROS messages field for field.

Each class names its ROS 2 type (``ROS_TYPE``, the ``pkg/msg/Type`` form rosbags uses) and carries
its ``.msg`` definition (``MSGDEF``), so bags can be written and read with rosbags and opened by the
ROS tools and Foxglove. Headers follow ROS 2 (no ``seq``); the ROS 1 bag writer adds ``seq``.

Units are SI (metres, radians, seconds, m/s), axes REP-103 (x forward, y left, z up), frames
REP-105 (``map``, ``odom``, ``base_link``, ``laser``). Numeric arrays are numpy arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from racecar_hw.base.clock import NS_PER_S


def _zeros(n: int):  # noqa: ANN202 - a dataclass default factory
    return lambda: np.zeros(n, dtype=np.float64)


def _empty_f32() -> np.ndarray:
    return np.zeros(0, dtype=np.float32)


class Message:
    """Base class: ``ROS_TYPE`` is the rosbags type name, ``MSGDEF`` the ``.msg`` text."""

    ROS_TYPE: ClassVar[str] = ""
    MSGDEF: ClassVar[str] = ""


# --- builtin_interfaces / std_msgs -------------------------------------------------------------


@dataclass
class Time(Message):
    """builtin_interfaces/Time: seconds and nanoseconds since the Unix epoch."""

    ROS_TYPE: ClassVar[str] = "builtin_interfaces/msg/Time"
    MSGDEF: ClassVar[str] = "int32 sec\nuint32 nanosec\n"

    sec: int = 0
    nanosec: int = 0

    @classmethod
    def from_ns(cls, ns: int) -> Time:
        """A stamp from integer nanoseconds."""
        sec, nanosec = divmod(int(ns), NS_PER_S)
        return cls(sec, nanosec)

    def to_ns(self) -> int:
        """This stamp in integer nanoseconds."""
        return self.sec * NS_PER_S + self.nanosec


@dataclass
class Header(Message):
    """std_msgs/Header: a stamp and the frame the data is expressed in."""

    ROS_TYPE: ClassVar[str] = "std_msgs/msg/Header"
    MSGDEF: ClassVar[str] = "builtin_interfaces/Time stamp\nstring frame_id\n"

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Bool(Message):
    """std_msgs/Bool (mux locks, e-stop)."""

    ROS_TYPE: ClassVar[str] = "std_msgs/msg/Bool"
    MSGDEF: ClassVar[str] = "bool data\n"

    data: bool = False


@dataclass
class String(Message):
    """std_msgs/String."""

    ROS_TYPE: ClassVar[str] = "std_msgs/msg/String"
    MSGDEF: ClassVar[str] = "string data\n"

    data: str = ""


@dataclass
class Float64(Message):
    """std_msgs/Float64."""

    ROS_TYPE: ClassVar[str] = "std_msgs/msg/Float64"
    MSGDEF: ClassVar[str] = "float64 data\n"

    data: float = 0.0


# --- geometry_msgs ----------------------------------------------------------------------------


@dataclass
class Vector3(Message):
    """geometry_msgs/Vector3."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/Vector3"
    MSGDEF: ClassVar[str] = "float64 x\nfloat64 y\nfloat64 z\n"

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass
class Point(Message):
    """geometry_msgs/Point, metres."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/Point"
    MSGDEF: ClassVar[str] = "float64 x\nfloat64 y\nfloat64 z\n"

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass
class Quaternion(Message):
    """geometry_msgs/Quaternion (x, y, z, w); the default is the identity rotation."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/Quaternion"
    MSGDEF: ClassVar[str] = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0

    @classmethod
    def from_yaw(cls, yaw: float) -> Quaternion:
        """A rotation of ``yaw`` radians about z (counter-clockwise seen from above)."""
        return cls(0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))

    def yaw(self) -> float:
        """The rotation about z, radians in (-pi, pi]."""
        return math.atan2(2.0 * (self.w * self.z + self.x * self.y),
                          1.0 - 2.0 * (self.y * self.y + self.z * self.z))


@dataclass
class Pose(Message):
    """geometry_msgs/Pose."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/Pose"
    MSGDEF: ClassVar[str] = "Point position\nQuaternion orientation\n"

    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseWithCovariance(Message):
    """geometry_msgs/PoseWithCovariance; covariance is row-major 6x6 (x, y, z, rotX, rotY, rotZ)."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/PoseWithCovariance"
    MSGDEF: ClassVar[str] = "Pose pose\nfloat64[36] covariance\n"

    pose: Pose = field(default_factory=Pose)
    covariance: np.ndarray = field(default_factory=_zeros(36))


@dataclass
class Twist(Message):
    """geometry_msgs/Twist: linear m/s and angular rad/s."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/Twist"
    MSGDEF: ClassVar[str] = "Vector3 linear\nVector3 angular\n"

    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistWithCovariance(Message):
    """geometry_msgs/TwistWithCovariance; covariance is row-major 6x6."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/TwistWithCovariance"
    MSGDEF: ClassVar[str] = "Twist twist\nfloat64[36] covariance\n"

    twist: Twist = field(default_factory=Twist)
    covariance: np.ndarray = field(default_factory=_zeros(36))


@dataclass
class Transform(Message):
    """geometry_msgs/Transform: translation in metres, rotation as a quaternion."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/Transform"
    MSGDEF: ClassVar[str] = "Vector3 translation\nQuaternion rotation\n"

    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(Message):
    """geometry_msgs/TransformStamped: the pose of ``child_frame_id`` in ``header.frame_id``."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/TransformStamped"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(Message):
    """tf2_msgs/TFMessage, carried on ``/tf`` and ``/tf_static``."""

    ROS_TYPE: ClassVar[str] = "tf2_msgs/msg/TFMessage"
    MSGDEF: ClassVar[str] = "geometry_msgs/TransformStamped[] transforms\n"

    transforms: list[TransformStamped] = field(default_factory=list)


# --- ackermann_msgs ---------------------------------------------------------------------------


@dataclass
class AckermannDrive(Message):
    """ackermann_msgs/AckermannDrive.

    ``steering_angle`` is the angle of a virtual front wheel at the centre of the front axle,
    radians, positive to the left. ``speed`` is m/s at the rear axle, negative in reverse.
    Acceleration (m/s^2) and jerk (m/s^3) are limits; racecar-hw's VESC path ignores them, as the
    ROS vesc_ackermann does.
    """

    ROS_TYPE: ClassVar[str] = "ackermann_msgs/msg/AckermannDrive"
    MSGDEF: ClassVar[str] = (
        "float32 steering_angle\n"
        "float32 steering_angle_velocity\n"
        "float32 speed\n"
        "float32 acceleration\n"
        "float32 jerk\n"
    )

    steering_angle: float = 0.0
    steering_angle_velocity: float = 0.0
    speed: float = 0.0
    acceleration: float = 0.0
    jerk: float = 0.0


@dataclass
class AckermannDriveStamped(Message):
    """ackermann_msgs/AckermannDriveStamped."""

    ROS_TYPE: ClassVar[str] = "ackermann_msgs/msg/AckermannDriveStamped"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nAckermannDrive drive\n"

    header: Header = field(default_factory=Header)
    drive: AckermannDrive = field(default_factory=AckermannDrive)


# --- sensor_msgs ------------------------------------------------------------------------------


@dataclass
class LaserScan(Message):
    """sensor_msgs/LaserScan, counter-clockwise angles in the ``laser`` frame.

    ``angle_min`` and ``angle_max`` are the first and last beam (radians, 0 straight ahead);
    there are ``round((angle_max - angle_min) / angle_increment) + 1`` beams. ``time_increment``
    is the time between beams and ``scan_time`` between scans (seconds); ranges are metres, with
    invalid readings as documented by the driver (``inf`` for no return, ``nan`` for an error).
    """

    ROS_TYPE: ClassVar[str] = "sensor_msgs/msg/LaserScan"
    MSGDEF: ClassVar[str] = (
        "std_msgs/Header header\n"
        "float32 angle_min\n"
        "float32 angle_max\n"
        "float32 angle_increment\n"
        "float32 time_increment\n"
        "float32 scan_time\n"
        "float32 range_min\n"
        "float32 range_max\n"
        "float32[] ranges\n"
        "float32[] intensities\n"
    )

    header: Header = field(default_factory=Header)
    angle_min: float = 0.0
    angle_max: float = 0.0
    angle_increment: float = 0.0
    time_increment: float = 0.0
    scan_time: float = 0.0
    range_min: float = 0.0
    range_max: float = 0.0
    ranges: np.ndarray = field(default_factory=_empty_f32)
    intensities: np.ndarray = field(default_factory=_empty_f32)

    def angles(self) -> np.ndarray:
        """The angle of every beam, radians."""
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))


@dataclass
class Imu(Message):
    """sensor_msgs/Imu; a covariance whose first element is -1 means "not provided"."""

    ROS_TYPE: ClassVar[str] = "sensor_msgs/msg/Imu"
    MSGDEF: ClassVar[str] = (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    )

    header: Header = field(default_factory=Header)
    orientation: Quaternion = field(default_factory=Quaternion)
    orientation_covariance: np.ndarray = field(default_factory=_zeros(9))
    angular_velocity: Vector3 = field(default_factory=Vector3)
    angular_velocity_covariance: np.ndarray = field(default_factory=_zeros(9))
    linear_acceleration: Vector3 = field(default_factory=Vector3)
    linear_acceleration_covariance: np.ndarray = field(default_factory=_zeros(9))


@dataclass
class PoseStamped(Message):
    """geometry_msgs/PoseStamped: a pose in ``header.frame_id`` (the simulator's true pose in map)."""

    ROS_TYPE: ClassVar[str] = "geometry_msgs/msg/PoseStamped"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nPose pose\n"

    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


# --- nav_msgs ---------------------------------------------------------------------------------


@dataclass
class MapMetaData(Message):
    """nav_msgs/MapMetaData: cell size (m), grid size (cells), pose of cell (0, 0)'s corner in map."""

    ROS_TYPE: ClassVar[str] = "nav_msgs/msg/MapMetaData"
    MSGDEF: ClassVar[str] = (
        "builtin_interfaces/Time map_load_time\n"
        "float32 resolution\n"
        "uint32 width\n"
        "uint32 height\n"
        "geometry_msgs/Pose origin\n"
    )

    map_load_time: Time = field(default_factory=Time)
    resolution: float = 0.0
    width: int = 0
    height: int = 0
    origin: Pose = field(default_factory=Pose)


@dataclass
class OccupancyGrid(Message):
    """nav_msgs/OccupancyGrid: int8 cells row-major from the origin; 0 free, 100 occupied, -1 unknown."""

    ROS_TYPE: ClassVar[str] = "nav_msgs/msg/OccupancyGrid"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nMapMetaData info\nint8[] data\n"

    header: Header = field(default_factory=Header)
    info: MapMetaData = field(default_factory=MapMetaData)
    data: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))


@dataclass
class Odometry(Message):
    """nav_msgs/Odometry: pose in ``header.frame_id`` (odom), twist in ``child_frame_id`` (base_link)."""

    ROS_TYPE: ClassVar[str] = "nav_msgs/msg/Odometry"
    MSGDEF: ClassVar[str] = (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n"
    )

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


# --- vesc_msgs (the f1tenth/vesc ROS 2 definitions) -------------------------------------------


@dataclass
class VescState(Message):
    """vesc_msgs/VescState as the f1tenth/vesc ROS 2 branch defines it.

    Temperatures in degrees Celsius, currents in A, ``duty_cycle`` in -1..1, ``speed`` in electrical
    RPM (ERPM), voltages in V, charge in Ah, energy in Wh, ``displacement`` and
    ``distance_traveled`` in tachometer counts, ``pid_pos_now`` in degrees.
    """

    ROS_TYPE: ClassVar[str] = "vesc_msgs/msg/VescState"
    MSGDEF: ClassVar[str] = (
        "int32 FAULT_CODE_NONE=0\n"
        "int32 FAULT_CODE_OVER_VOLTAGE=1\n"
        "int32 FAULT_CODE_UNDER_VOLTAGE=2\n"
        "int32 FAULT_CODE_DRV8302=3\n"
        "int32 FAULT_CODE_ABS_OVER_CURRENT=4\n"
        "int32 FAULT_CODE_OVER_TEMP_FET=5\n"
        "int32 FAULT_CODE_OVER_TEMP_MOTOR=6\n"
        "float64 temp_fet\n"
        "float64 temp_motor\n"
        "float64 current_motor\n"
        "float64 current_input\n"
        "float64 avg_id\n"
        "float64 avg_iq\n"
        "float64 duty_cycle\n"
        "float64 speed\n"
        "float64 voltage_input\n"
        "float64 charge_drawn\n"
        "float64 charge_regen\n"
        "float64 energy_drawn\n"
        "float64 energy_regen\n"
        "int32 displacement\n"
        "int32 distance_traveled\n"
        "int32 fault_code\n"
        "float64 pid_pos_now\n"
        "int32 controller_id\n"
        "float64 ntc_temp_mos1\n"
        "float64 ntc_temp_mos2\n"
        "float64 ntc_temp_mos3\n"
        "float64 avg_vd\n"
        "float64 avg_vq\n"
    )

    temp_fet: float = 0.0
    temp_motor: float = 0.0
    current_motor: float = 0.0
    current_input: float = 0.0
    avg_id: float = 0.0
    avg_iq: float = 0.0
    duty_cycle: float = 0.0
    speed: float = 0.0
    voltage_input: float = 0.0
    charge_drawn: float = 0.0
    charge_regen: float = 0.0
    energy_drawn: float = 0.0
    energy_regen: float = 0.0
    displacement: int = 0
    distance_traveled: int = 0
    fault_code: int = 0
    pid_pos_now: float = 0.0
    controller_id: int = 0
    ntc_temp_mos1: float = 0.0
    ntc_temp_mos2: float = 0.0
    ntc_temp_mos3: float = 0.0
    avg_vd: float = 0.0
    avg_vq: float = 0.0


@dataclass
class VescStateStamped(Message):
    """vesc_msgs/VescStateStamped."""

    ROS_TYPE: ClassVar[str] = "vesc_msgs/msg/VescStateStamped"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nVescState state\n"

    header: Header = field(default_factory=Header)
    state: VescState = field(default_factory=VescState)


# --- diagnostic_msgs --------------------------------------------------------------------------


@dataclass
class KeyValue(Message):
    """diagnostic_msgs/KeyValue."""

    ROS_TYPE: ClassVar[str] = "diagnostic_msgs/msg/KeyValue"
    MSGDEF: ClassVar[str] = "string key\nstring value\n"

    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(Message):
    """diagnostic_msgs/DiagnosticStatus; ``level`` is OK 0, WARN 1, ERROR 2, STALE 3."""

    ROS_TYPE: ClassVar[str] = "diagnostic_msgs/msg/DiagnosticStatus"
    MSGDEF: ClassVar[str] = (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n"
        "byte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n"
    )
    OK: ClassVar[int] = 0
    WARN: ClassVar[int] = 1
    ERROR: ClassVar[int] = 2
    STALE: ClassVar[int] = 3

    level: int = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: list[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(Message):
    """diagnostic_msgs/DiagnosticArray."""

    ROS_TYPE: ClassVar[str] = "diagnostic_msgs/msg/DiagnosticArray"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nDiagnosticStatus[] status\n"

    header: Header = field(default_factory=Header)
    status: list[DiagnosticStatus] = field(default_factory=list)


# --- rcl_interfaces: the node's log (/rosout) ---------------------------------------------------


@dataclass
class Log(Message):
    """rcl_interfaces/Log: one log record of a node, as ROS 2 nodes publish on ``/rosout``.

    ``level`` uses ROS's values, which equal Python's: DEBUG 10, INFO 20, WARN 30, ERROR 40, FATAL 50;
    ``name`` is the logger (``<node>.<module>``), ``file``/``function``/``line`` where it was logged.
    """

    ROS_TYPE: ClassVar[str] = "rcl_interfaces/msg/Log"
    MSGDEF: ClassVar[str] = (
        "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\nbyte FATAL=50\n"
        "builtin_interfaces/Time stamp\nuint8 level\nstring name\nstring msg\nstring file\n"
        "string function\nuint32 line\n"
    )
    DEBUG: ClassVar[int] = 10
    INFO: ClassVar[int] = 20
    WARN: ClassVar[int] = 30
    ERROR: ClassVar[int] = 40
    FATAL: ClassVar[int] = 50

    stamp: Time = field(default_factory=Time)
    level: int = 0
    name: str = ""
    msg: str = ""
    file: str = ""
    function: str = ""
    line: int = 0


# --- rosgraph_msgs: the simulation's clock (/clock) ---------------------------------------------


@dataclass
class Clock(Message):
    """rosgraph_msgs/Clock: the time ROS 2 nodes with ``use_sim_time`` follow, on ``/clock``.

    ``clock`` is in the time base of every stamp the daemon writes (:func:`racecar_hw.base.clock.wall_ns`):
    Unix time in the real-time simulation, the simulation's own time in lockstep.
    """

    ROS_TYPE: ClassVar[str] = "rosgraph_msgs/msg/Clock"
    MSGDEF: ClassVar[str] = "builtin_interfaces/Time clock\n"

    clock: Time = field(default_factory=Time)


# --- racecar_msgs: the seeds' scan summaries --------------------------------------------------


@dataclass
class ScanRange(Message):
    """racecar_msgs/ScanRange: the closest and farthest valid range of one scan, metres."""

    ROS_TYPE: ClassVar[str] = "racecar_msgs/msg/ScanRange"
    MSGDEF: ClassVar[str] = "std_msgs/Header header\nfloat32 closest\nfloat32 farthest\n"

    header: Header = field(default_factory=Header)
    closest: float = 0.0
    farthest: float = 0.0


@dataclass
class OpenSpace(Message):
    """racecar_msgs/OpenSpace: the angle (radians, laser frame), then distance (m), of the longest return."""

    ROS_TYPE: ClassVar[str] = "racecar_msgs/msg/OpenSpace"
    MSGDEF: ClassVar[str] = "float32 angle\nfloat32 distance\n"

    angle: float = 0.0
    distance: float = 0.0


#: Packages that no rosbags typestore ships; bag writers register these from ``MSGDEF``.
CUSTOM_TYPES: tuple[type[Message], ...] = (
    AckermannDrive, AckermannDriveStamped, VescState, VescStateStamped, ScanRange, OpenSpace,
)


def stamp_now(frame_id: str, ns: int) -> Header:
    """A header stamped ``ns`` nanoseconds since the epoch, in ``frame_id``."""
    return Header(Time.from_ns(ns), frame_id)
