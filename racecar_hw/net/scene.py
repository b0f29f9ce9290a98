"""The safety controller made visible: the swept footprint along the commanded arc, in base_link.

Geometry (the model of :mod:`safety.arc`): base_link, the centre of the rear axle, moves on a circle
of radius ``R = wheelbase / tan(steering)`` (straight when the steering is 0). Over the stopping
distance the car's rectangle sweeps a band whose inner edge is traced by the inner end of the rear
axle (radius ``R - half_width``, the point nearest the turn centre) and whose outer edge by the
leading outer corner (the front one, the rear one in reverse). Straight ahead the band is the
rectangle from the leading bumper on.

:func:`swept_band` gives the two edges as points; :func:`scene_update` wraps them, the car's body,
the limiting obstacle and a label into a ``foxglove.SceneUpdate`` coloured by the safety state. The
status page draws the same band from :func:`swept_band`.
"""

from __future__ import annotations

import math

import numpy as np
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

from racecar_hw.net.control import CLEAR, LIMITING, STOPPED, CarShape, LiveState
from safety.arc import SweptFootprint

#: RGBA per safety colour: green, orange, red.
COLOURS: dict[str, tuple[float, float, float, float]] = {
    CLEAR: (0.18, 0.75, 0.3, 0.35), LIMITING: (1.0, 0.6, 0.0, 0.45), STOPPED: (0.9, 0.1, 0.1, 0.5),
}
#: Samples along the arc.
STATIONS = 24
FRAME = "base_link"


def body_corners(shape: CarShape) -> np.ndarray:
    """The footprint's corners (4, 2) in base_link, counter-clockwise from the front left."""
    f, r, w = shape.front_m, shape.rear_m, shape.half_width_m
    return np.array([[f, w], [-r, w], [-r, -w], [f, -w]])


def swept_band(shape: CarShape, steering_rad: float, length_m: float,
               reverse: bool = False, stations: int = STATIONS) -> tuple[np.ndarray, np.ndarray]:
    """The band the footprint sweeps over ``length_m`` of path: (inner edge, outer edge), each (n, 2).

    The edges run side by side from the car outwards: point k of each is where the car's edge points
    are after the same stretch of path, so consecutive pairs make the band's quads.
    """
    sweep = SweptFootprint(shape.front_m, shape.rear_m, shape.half_width_m, shape.wheelbase_m)
    radius = sweep.turn_radius(steering_rad if math.isfinite(steering_rad) else 0.0)
    lead = -shape.rear_m if reverse else shape.front_m
    s = np.linspace(0.0, max(length_m, 0.0), stations) * (-1.0 if reverse else 1.0)
    if math.isinf(radius):
        x = lead + s
        w = shape.half_width_m
        return np.column_stack([x, np.full_like(x, w)]), np.column_stack([x, np.full_like(x, -w)])
    turn = math.copysign(1.0, radius)
    theta = s / radius
    px, py = radius * np.sin(theta), radius * (1.0 - np.cos(theta))
    c, sn = np.cos(theta), np.sin(theta)

    def carried(bx: float, by: float) -> np.ndarray:
        return np.column_stack([px + bx * c - by * sn, py + bx * sn + by * c])

    return carried(0.0, turn * shape.half_width_m), carried(lead, -turn * shape.half_width_m)


def band_polygon(inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """The band's outline: the inner edge out, the outer edge back."""
    return np.vstack([inner, outer[::-1]])


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
