"""Static transforms: 4x4 homogeneous matrices, tf2's two static forms, and a small frame tree.

A transform from ``frame_id`` (parent) to ``child_frame_id`` (child) is, as in tf2 and
``geometry_msgs/TransformStamped``, the pose of the child frame expressed in the parent frame: its
matrix ``T_parent_child`` maps a point given in child coordinates to parent coordinates,
``p_parent = T_parent_child @ p_child``. Translations are metres, angles radians, axes REP-103
(x forward, y left, z up).

tf2's ``static_transform_publisher`` takes a rotation in one of two forms, both accepted here:

* ``x y z yaw pitch roll frame_id child_frame_id``, with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``
  (yaw about z, then pitch about the new y, then roll about the newest x; tf2's ``setRPY``);
* ``x y z qx qy qz qw frame_id child_frame_id``, a unit quaternion (x, y, z, w).

Quaternions in this module are tuples ``(x, y, z, w)`` in that order, as ROS writes them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from racecar_hw.base.errors import ConfigError, RacecarError
from racecar_hw.base.messages import (
    Header,
    Quaternion,
    TFMessage,
    Time,
    Transform,
    TransformStamped,
    Vector3,
)
from racecar_hw.base.params import build, param

QuaternionTuple = tuple[float, float, float, float]

#: How far from 1 a configured quaternion's norm may be before it is refused (rounding in YAML).
QUATERNION_NORM_TOLERANCE = 1e-3


class TransformNotFound(RacecarError, LookupError):
    """Two frames are not connected by the known transforms."""


# --- rotations and homogeneous matrices -------------------------------------------------------


def rotation_from_ypr(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """The 3x3 rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (radians), tf2's convention."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def rotation_from_quaternion(q: Sequence[float]) -> np.ndarray:
    """The 3x3 rotation of the quaternion ``(x, y, z, w)``; it is normalised first.

    Raises ValueError for a zero or non-finite quaternion.
    """
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {tuple(q)} has no direction")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_rotation(rotation: np.ndarray) -> QuaternionTuple:
    """The unit quaternion ``(x, y, z, w)`` of a 3x3 rotation (or a 4x4 transform), with ``w >= 0``."""
    r = np.asarray(rotation, dtype=np.float64)[:3, :3]
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    # Shepperd's method: divide by the largest of the four candidates for numerical stability.
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        w, x = 0.25 * s, (r[2, 1] - r[1, 2]) / s
        y, z = (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        w, x = (r[2, 1] - r[1, 2]) / s, 0.25 * s
        y, z = (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 0.0))
        w, x = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s
        y, z = 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 0.0))
        w, x = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s
        y, z = (r[1, 2] + r[2, 1]) / s, 0.25 * s
    n = math.sqrt(x * x + y * y + z * z + w * w)
    sign = -1.0 if w < 0.0 else 1.0
    return (sign * x / n, sign * y / n, sign * z / n, sign * w / n)


def quaternion_from_ypr(yaw: float, pitch: float, roll: float) -> QuaternionTuple:
    """The unit quaternion ``(x, y, z, w)`` of tf2's yaw, pitch, roll (radians)."""
    return quaternion_from_rotation(rotation_from_ypr(yaw, pitch, roll))


def ypr_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in radians with pitch in [-pi/2, pi/2]; roll is 0 at gimbal lock."""
    r = np.asarray(rotation, dtype=np.float64)[:3, :3]
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) > 1.0 - 1e-12:
        return math.atan2(-r[0, 1], r[1, 1]), pitch, 0.0
    return math.atan2(r[1, 0], r[0, 0]), pitch, math.atan2(r[2, 1], r[2, 2])


def from_translation_rotation(translation: Sequence[float], rotation: np.ndarray) -> np.ndarray:
    """The 4x4 homogeneous transform with ``translation`` (m) and a 3x3 ``rotation``."""
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return m


def from_ypr(translation: Sequence[float], yaw: float = 0.0, pitch: float = 0.0,
             roll: float = 0.0) -> np.ndarray:
    """The 4x4 transform of a translation (m) and tf2's yaw, pitch, roll (rad)."""
    return from_translation_rotation(translation, rotation_from_ypr(yaw, pitch, roll))


def from_quaternion(translation: Sequence[float], quaternion: Sequence[float]) -> np.ndarray:
    """The 4x4 transform of a translation (m) and a quaternion ``(x, y, z, w)`` (normalised)."""
    return from_translation_rotation(translation, rotation_from_quaternion(quaternion))


def to_quaternion(transform: np.ndarray) -> QuaternionTuple:
    """The rotation of a 4x4 transform as a unit quaternion ``(x, y, z, w)`` with ``w >= 0``."""
    return quaternion_from_rotation(transform)


def translation_of(transform: np.ndarray) -> tuple[float, float, float]:
    """The translation (m) of a 4x4 transform."""
    t = np.asarray(transform)[:3, 3]
    return (float(t[0]), float(t[1]), float(t[2]))


def yaw_of(transform: np.ndarray) -> float:
    """The heading (rad, about z, in (-pi, pi]) of a transform's x axis projected on the xy plane."""
    m = np.asarray(transform)
    return math.atan2(float(m[1, 0]), float(m[0, 0]))


def compose(*transforms: np.ndarray) -> np.ndarray:
    """The product of transforms, left to right: ``compose(T_a_b, T_b_c)`` is ``T_a_c``."""
    out = np.eye(4)
    for t in transforms:
        out = out @ np.asarray(t, dtype=np.float64)
    return out


def invert(transform: np.ndarray) -> np.ndarray:
    """The inverse of a rigid transform (``T_b_a`` from ``T_a_b``), exact for rotations."""
    m = np.asarray(transform, dtype=np.float64)
    r_t = m[:3, :3].T
    out = np.eye(4)
    out[:3, :3] = r_t
    out[:3, 3] = -r_t @ m[:3, 3]
    return out


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` (shape ``(3,)``, ``(N, 3)``, ``(2,)`` or ``(N, 2)``, metres) moved by ``transform``.

    2D points are taken at z = 0 and returned as 2D (x, y), e.g. laser scan points on the floor
    plane moved from ``laser`` to ``base_link``.
    """
    m = np.asarray(transform, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    dim = p.shape[-1]
    if dim not in (2, 3) or p.ndim not in (1, 2):
        raise ValueError(f"points must have shape (3,), (N, 3), (2,) or (N, 2), not {p.shape}")
    flat = p.reshape(-1, dim)
    if dim == 2:
        flat = np.hstack([flat, np.zeros((len(flat), 1))])
    moved = flat @ m[:3, :3].T + m[:3, 3]
    return moved[:, :dim].reshape(p.shape)


# --- messages ---------------------------------------------------------------------------------


def to_transform_stamped(transform: np.ndarray, frame_id: str, child_frame_id: str,
                         stamp_ns: int = 0) -> TransformStamped:
    """``T_frame_child`` as a ``TransformStamped`` stamped ``stamp_ns`` (Unix ns)."""
    x, y, z = translation_of(transform)
    qx, qy, qz, qw = to_quaternion(transform)
    return TransformStamped(
        header=Header(Time.from_ns(stamp_ns), frame_id),
        child_frame_id=child_frame_id,
        transform=Transform(Vector3(x, y, z), Quaternion(qx, qy, qz, qw)),
    )


def from_transform_stamped(msg: TransformStamped) -> np.ndarray:
    """The 4x4 matrix ``T_parent_child`` of a ``TransformStamped`` (its quaternion is normalised)."""
    t, q = msg.transform.translation, msg.transform.rotation
    return from_quaternion((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


# --- configuration ----------------------------------------------------------------------------


@dataclass
class StaticTransformParams:
    """One static transform, as tf2's static_transform_publisher takes it.

    Give the rotation as ``ypr`` or as ``quaternion``, not both; neither means no rotation.
    """

    frame_id: str = param("base_link", "parent frame")
    child_frame_id: str = param("laser", "child frame, whose pose in frame_id this is")
    xyz: tuple[float, float, float] = param((0.0, 0.0, 0.0), "translation of the child in the parent",
                                            unit="m")
    ypr: tuple[float, float, float] | None = param(
        None, "rotation as yaw (about z), pitch (about y), roll (about x); R = Rz Ry Rx", unit="rad")
    quaternion: tuple[float, float, float, float] | None = param(
        None, "rotation as a unit quaternion qx, qy, qz, qw")

    def __post_init__(self) -> None:
        if not self.frame_id:
            raise ConfigError("frame_id", "must not be empty")
        if not self.child_frame_id:
            raise ConfigError("child_frame_id", "must not be empty")
        if self.frame_id == self.child_frame_id:
            raise ConfigError("child_frame_id", f"must differ from frame_id ({self.frame_id!r})")
        for key, values in (("xyz", self.xyz), ("ypr", self.ypr), ("quaternion", self.quaternion)):
            if values is not None and not all(math.isfinite(v) for v in values):
                raise ConfigError(key, f"every value must be finite, got {list(values)}")
        if self.ypr is not None and self.quaternion is not None:
            raise ConfigError("quaternion", "give the rotation as ypr or as quaternion, not both")
        if self.quaternion is not None:
            norm = math.sqrt(sum(v * v for v in self.quaternion))
            if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
                raise ConfigError("quaternion", f"must be a unit quaternion (qx, qy, qz, qw); "
                                                f"its norm is {norm:.6g}")

    def matrix(self) -> np.ndarray:
        """``T_frame_child`` as a 4x4 homogeneous matrix."""
        if self.quaternion is not None:
            return from_quaternion(self.xyz, self.quaternion)
        yaw, pitch, roll = self.ypr if self.ypr is not None else (0.0, 0.0, 0.0)
        return from_ypr(self.xyz, yaw, pitch, roll)


def build_static_transform(data: object, key: str = "") -> StaticTransformParams:
    """:class:`StaticTransformParams` from a mapping; every error names the full dotted ``key``."""
    try:
        return build(StaticTransformParams, data, key)  # type: ignore[arg-type]
    except ConfigError as err:
        if not key or err.key == key or err.key.startswith((key + ".", key + "[")):
            raise
        # raised by __post_init__, which does not know where in the file it sits
        message = str(err)[len(err.key) + 2:] if err.key else str(err)
        raise ConfigError(f"{key}.{err.key}", message) from err


def build_static_transforms(data: object, key: str = "static_transforms") -> list[StaticTransformParams]:
    """A list of :class:`StaticTransformParams` from a YAML list, errors naming ``key[i]...``."""
    if data is None:
        return []
    if not isinstance(data, (list, tuple)):
        raise ConfigError(key, f"expected a list of transforms, got {type(data).__name__}")
    return [build_static_transform(item, f"{key}[{i}]") for i, item in enumerate(data)]


_YPR_FLAGS = ("--yaw", "--pitch", "--roll")
_QUAT_FLAGS = ("--qx", "--qy", "--qz", "--qw")
_FLAGS = ("--x", "--y", "--z", *_YPR_FLAGS, *_QUAT_FLAGS, "--frame-id", "--child-frame-id")


def parse_static_transform_args(args: Sequence[str]) -> StaticTransformParams:
    """A static_transform_publisher command line (without the program name) as parameters.

    Accepts ``x y z yaw pitch roll frame_id child_frame_id``, ``x y z qx qy qz qw frame_id
    child_frame_id``, or the named flags ``--x --y --z --yaw --pitch --roll --qx --qy --qz --qw
    --frame-id --child-frame-id`` (omitted numbers are 0, ``--qw`` 1). Raises ConfigError naming
    the offending argument.
    """
    tokens = list(args)
    if any(t.startswith("--") for t in tokens):
        return _parse_flags(tokens)
    if len(tokens) not in (8, 9):
        raise ConfigError("args", f"expected 'x y z yaw pitch roll frame_id child_frame_id' or "
                                  f"'x y z qx qy qz qw frame_id child_frame_id', got {len(tokens)} "
                                  f"arguments")
    names = ("x", "y", "z", "yaw", "pitch", "roll") if len(tokens) == 8 else (
        "x", "y", "z", "qx", "qy", "qz", "qw")
    numbers = [_number(name, text) for name, text in zip(names, tokens, strict=False)]
    frame_id, child = tokens[-2], tokens[-1]
    xyz = (numbers[0], numbers[1], numbers[2])
    if len(tokens) == 8:
        return StaticTransformParams(frame_id, child, xyz, ypr=(numbers[3], numbers[4], numbers[5]))
    return StaticTransformParams(frame_id, child, xyz,
                                 quaternion=(numbers[3], numbers[4], numbers[5], numbers[6]))


def _parse_flags(tokens: list[str]) -> StaticTransformParams:
    values: dict[str, str] = {}
    i = 0
    while i < len(tokens):
        flag = tokens[i]
        if flag not in _FLAGS:
            raise ConfigError(flag, "unknown argument; allowed: " + " ".join(_FLAGS))
        if i + 1 >= len(tokens):
            raise ConfigError(flag, "missing value")
        values[flag] = tokens[i + 1]
        i += 2
    for flag in ("--frame-id", "--child-frame-id"):
        if flag not in values:
            raise ConfigError(flag, "required")

    def num(flag: str, default: float) -> float:
        return _number(flag, values[flag]) if flag in values else default

    xyz = (num("--x", 0.0), num("--y", 0.0), num("--z", 0.0))
    has_ypr = any(f in values for f in _YPR_FLAGS)
    has_quat = any(f in values for f in _QUAT_FLAGS)
    if has_ypr and has_quat:
        raise ConfigError("--qx", "give --yaw/--pitch/--roll or --qx/--qy/--qz/--qw, not both")
    ypr = (num("--yaw", 0.0), num("--pitch", 0.0), num("--roll", 0.0)) if has_ypr else None
    quat = (num("--qx", 0.0), num("--qy", 0.0), num("--qz", 0.0), num("--qw", 1.0)) if has_quat else None
    try:
        return StaticTransformParams(values["--frame-id"], values["--child-frame-id"], xyz, ypr, quat)
    except ConfigError as err:
        flag = {"frame_id": "--frame-id", "child_frame_id": "--child-frame-id"}.get(err.key, err.key)
        raise ConfigError(flag, str(err)[len(err.key) + 2:]) from err


def to_static_transform_args(p: StaticTransformParams) -> list[str]:
    """The positional static_transform_publisher arguments that give ``p`` (for ROS users)."""
    if p.quaternion is not None:
        rotation = list(p.quaternion)
    else:
        rotation = list(p.ypr if p.ypr is not None else (0.0, 0.0, 0.0))
    return [repr(float(v)) for v in (*p.xyz, *rotation)] + [p.frame_id, p.child_frame_id]


def _number(name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(name, f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise ConfigError(name, f"must be finite, got {text!r}")
    return value


# --- defaults ---------------------------------------------------------------------------------

#: The seeds' cameras (MIT Lab 1C, question 9): 0.05 m either side of base_link, identity rotation.
#: REP-103 puts +y to the left; the lab's simulator called +x "right", which this does not follow.
SEED_CAMERA_TRANSFORMS: tuple[StaticTransformParams, ...] = (
    StaticTransformParams("base_link", "left_cam", (0.0, 0.05, 0.0)),
    StaticTransformParams("base_link", "right_cam", (0.0, -0.05, 0.0)),
)


def default_static_transforms() -> list[StaticTransformParams]:
    """base_link -> laser (at base_link until configured) and the seeds' two cameras."""
    return [StaticTransformParams(), *SEED_CAMERA_TRANSFORMS]


# --- the frame tree ---------------------------------------------------------------------------


@dataclass(frozen=True)
class StaticTransform:
    """``T_frame_child``: the pose of ``child_frame_id`` in ``frame_id`` as a 4x4 matrix."""

    frame_id: str
    child_frame_id: str
    matrix: np.ndarray

    @classmethod
    def from_params(cls, p: StaticTransformParams) -> StaticTransform:
        """The transform a configuration entry describes."""
        return cls(p.frame_id, p.child_frame_id, p.matrix())

    @classmethod
    def from_msg(cls, msg: TransformStamped) -> StaticTransform:
        """The transform a ``TransformStamped`` carries."""
        return cls(msg.header.frame_id, msg.child_frame_id, from_transform_stamped(msg))

    def to_msg(self, stamp_ns: int = 0) -> TransformStamped:
        """This transform as a ``TransformStamped`` stamped ``stamp_ns`` (Unix ns)."""
        return to_transform_stamped(self.matrix, self.frame_id, self.child_frame_id, stamp_ns)


class TfTree:
    """A set of static transforms forming a tree (one parent per frame), looked up by composition.

    ``lookup(target, source)`` follows tf2's ``lookupTransform``: the matrix that maps points
    given in ``source`` coordinates to ``target`` coordinates, e.g. ``lookup("base_link",
    "laser")`` moves scan points into ``base_link``.
    """

    def __init__(self, transforms: Iterable[StaticTransform] = ()) -> None:
        self._parent: dict[str, StaticTransform] = {}
        for t in transforms:
            self.add(t)

    @classmethod
    def from_params(cls, params: Iterable[StaticTransformParams]) -> TfTree:
        """A tree of every configured transform."""
        return cls(StaticTransform.from_params(p) for p in params)

    def add(self, transform: StaticTransform) -> None:
        """Add or replace ``transform``; a second parent for a frame or a cycle is a ConfigError."""
        child, parent = transform.child_frame_id, transform.frame_id
        known = self._parent.get(child)
        if known is not None and known.frame_id != parent:
            raise ConfigError(child, f"frame {child!r} already has parent {known.frame_id!r}; "
                                     f"a frame cannot also be a child of {parent!r}")
        frame: str | None = parent
        while frame is not None:
            if frame == child:
                raise ConfigError(child, f"{parent!r} -> {child!r} would close a cycle")
            up = self._parent.get(frame)
            frame = up.frame_id if up is not None else None
        self._parent[child] = transform

    def frames(self) -> set[str]:
        """Every frame named by a transform."""
        return {t.frame_id for t in self._parent.values()} | set(self._parent)

    def transforms(self) -> list[StaticTransform]:
        """Every transform, in the order they were first added."""
        return list(self._parent.values())

    def can_transform(self, target_frame: str, source_frame: str) -> bool:
        """Whether both frames are known and connected."""
        try:
            self.lookup(target_frame, source_frame)
        except TransformNotFound:
            return False
        return True

    def lookup(self, target_frame: str, source_frame: str) -> np.ndarray:
        """``T_target_source``: maps points in ``source_frame`` to ``target_frame`` coordinates."""
        if target_frame == source_frame:
            return np.eye(4)
        for frame in (target_frame, source_frame):
            if frame not in self.frames():
                raise TransformNotFound(f"unknown frame {frame!r}; known: {sorted(self.frames())}")
        root_t, t_root_target = self._to_root(target_frame)
        root_s, t_root_source = self._to_root(source_frame)
        if root_t != root_s:
            raise TransformNotFound(f"{source_frame!r} and {target_frame!r} are not connected "
                                    f"(trees rooted at {root_s!r} and {root_t!r})")
        return invert(t_root_target) @ t_root_source

    def to_tf_message(self, stamp_ns: int = 0) -> TFMessage:
        """Every transform, for the latched ``/tf_static``."""
        return TFMessage([t.to_msg(stamp_ns) for t in self._parent.values()])

    def _to_root(self, frame: str) -> tuple[str, np.ndarray]:
        m = np.eye(4)
        while frame in self._parent:
            up = self._parent[frame]
            m = up.matrix @ m
            frame = up.frame_id
        return frame, m


#: The name the daemon may prefer for a set of static transforms.
StaticTransforms = TfTree
