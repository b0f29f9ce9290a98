"""Blind sectors: runs of unusable beams wide enough to hide an obstacle on the car's path.

A beam is unusable when its range is NaN (a device fault, an RPLIDAR beam no sample fell on) or
below ``range_min`` (dust or a hand on the window). Single unusable beams are common and are
ignored: the beams beside them still see what is there. A run of consecutive unusable beams
spanning at least :data:`BLIND_GAP_RAD` is a sector the lidar cannot see into; the safety
controller puts an obstacle on each of its rays just outside the car's body
(:func:`blind_radius`), so a path heading into it is not taken as free. The run is found in beam
order; a run across the two ends of a full-turn scan counts as two.
"""

from __future__ import annotations

import math

import numpy as np

#: The narrowest run of unusable beams that is a blind sector (rad): 5 degrees, 20 beams of a
#: UST-10LX, 5-6 of an RPLIDAR. A 0.1 m post subtends more than that within 1.1 m.
BLIND_GAP_RAD = math.radians(5.0)
#: How far outside the body's farthest corner (from the laser) a blind sector's obstacles sit (m).
BLIND_CLEARANCE_M = 0.02


def blind_beams(usable: np.ndarray, angle_increment: float, min_gap_rad: float = BLIND_GAP_RAD) -> np.ndarray:
    """Indices of the beams in runs of consecutive unusable beams (``usable`` False) that span at
    least ``min_gap_rad`` at ``angle_increment`` rad per beam; empty when there are none."""
    if usable.all():  # the usual scan: about 1 us
        return np.empty(0, dtype=np.intp)
    bad = ~usable
    need = max(1, math.ceil(min_gap_rad / abs(angle_increment) - 1e-9))
    edges = np.flatnonzero(np.diff(np.concatenate(([False], bad, [False])).astype(np.int8)))
    starts, ends = edges[0::2], edges[1::2]
    wide = (ends - starts) >= need
    if not wide.any():
        return np.empty(0, dtype=np.intp)
    return np.concatenate([np.arange(s, e) for s, e in zip(starts[wide], ends[wide], strict=True)])


def blind_radius(origin: complex, front_m: float, rear_m: float, half_width_m: float) -> float:
    """The distance (m) from the laser at ``origin`` (base_link, x + iy) beyond every corner of the
    body, so that a point that far along any ray lies outside it."""
    corners = (complex(front_m, half_width_m), complex(front_m, -half_width_m),
               complex(-rear_m, half_width_m), complex(-rear_m, -half_width_m))
    return max(abs(c - origin) for c in corners) + BLIND_CLEARANCE_M
