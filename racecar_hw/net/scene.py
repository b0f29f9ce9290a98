"""The safety controller made visible in Foxglove: the swept footprint along the commanded arc.

:func:`~racecar_hw.net.band.swept_band` gives the band's two edges as points (the geometry is in
:mod:`racecar_hw.net.band`); :func:`scene_update` wraps them, the car's body,
the limiting obstacle and a label into a ``foxglove.SceneUpdate`` coloured by the safety state. The
status page draws the same band.
"""

from __future__ import annotations

import math

from foxglove.messages import (
    Color,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    TriangleListPrimitive,
    Vector3,
)

from racecar_hw.net.band import body_corners, swept_band
from racecar_hw.net.control import CLEAR, LIMITING, STOPPED, CarShape, LiveState

#: RGBA per safety colour: green, orange, red.
COLOURS: dict[str, tuple[float, float, float, float]] = {
    CLEAR: (0.18, 0.75, 0.3, 0.35), LIMITING: (1.0, 0.6, 0.0, 0.45), STOPPED: (0.9, 0.1, 0.1, 0.5),
}
FRAME = "base_link"


def _colour(rgba: tuple[float, float, float, float]) -> Color:
    r, g, b, a = rgba
    return Color(r=r, g=g, b=b, a=a)


def _p(x: float, y: float, z: float = 0.02) -> Point3:
    return Point3(x=float(x), y=float(y), z=z)


def scene_update(state: LiveState, shape: CarShape, stamp_ns: int) -> SceneUpdate:
    """The safety scene for ``state``: body, swept band, obstacle and a label, in base_link."""
    stamp = Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
    colour = state.safety_colour
    rgba = COLOURS[colour]
    speed = state.commanded_mps if math.isfinite(state.commanded_mps) else 0.0
    inner, outer = swept_band(shape, state.steering_rad, shape.stopping_distance(speed), speed < 0.0)
    points: list[Point3] = []
    for k in range(len(inner) - 1):
        a, b, c, d = inner[k], outer[k], outer[k + 1], inner[k + 1]
        points += [_p(*a), _p(*b), _p(*c), _p(*a), _p(*c), _p(*d)]
    edge = _colour(rgba[:3] + (1.0,))
    body = [_p(x, y, 0.03) for x, y in body_corners(shape)]
    entity = SceneEntity(
        timestamp=stamp, frame_id=FRAME, id="safety",
        triangles=[TriangleListPrimitive(points=points, color=_colour(rgba))],
        lines=[LinePrimitive(type=LinePrimitiveLineType.LineLoop, points=body, thickness=0.02, color=edge),
               LinePrimitive(type=LinePrimitiveLineType.LineStrip, points=[_p(*q) for q in outer],
                             thickness=0.015, color=edge),
               LinePrimitive(type=LinePrimitiveLineType.LineStrip, points=[_p(*q) for q in inner],
                             thickness=0.015, color=edge)],
        texts=[TextPrimitive(pose=Pose(position=Vector3(x=-shape.rear_m, y=0.0, z=0.3),
                                       orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                             billboard=True, font_size=14.0, scale_invariant=True, color=edge,
                             text=label(state))],
    )
    entities = [entity]
    if state.obstacle is not None:
        x, y = state.obstacle
        mark = STOPPED if colour == STOPPED else LIMITING
        entities.append(SceneEntity(
            timestamp=stamp, frame_id=FRAME, id="obstacle",
            spheres=[SpherePrimitive(pose=Pose(position=Vector3(x=x, y=y, z=0.05),
                                               orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                                     size=Vector3(x=0.12, y=0.12, z=0.12),
                                     color=_colour(COLOURS[mark][:3] + (1.0,)))],
        ))
    else:
        entities.append(SceneEntity(timestamp=stamp, frame_id=FRAME, id="obstacle"))
    return SceneUpdate(entities=entities)


def label(state: LiveState) -> str:
    """One line for the 3D view: the safety state, its reason and the allowed speed."""
    allowed = "no limit" if math.isinf(state.allowed_mps) else f"allowed {state.allowed_mps:.2f} m/s"
    text = f"{state.safety_colour}: {state.safety_reason}, {allowed}"
    if state.mux_state != "running":
        text += f" ({state.mux_state}: {state.mux_reason})"
    elif not state.armed:
        text += " (disarmed)"
    return text
