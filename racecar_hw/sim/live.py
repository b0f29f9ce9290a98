"""What the simulator adds to the live view: the map, the true pose, and e-stop timing in the log.

* ``/map`` (``nav_msgs/OccupancyGrid``, latched) once at start, and a static ``map -> odom`` transform
  at the scenario's start pose, so odometry (``odom -> base_link`` on ``/tf``) is drawn in the map;
* ``/sim/pose`` (``geometry_msgs/PoseStamped`` in ``map``): the world's true pose, so a viewer sees
  odometry drift against ground truth;
* for every e-stop asked through a live interface (Foxglove service, status page), one log line with
  the wall time of the request and of the first motor command the fake VESC read after it, and of the
  first one that asks for a standstill (the mux's rate limiter brakes at ``max_decel_mps2``).
"""

from __future__ import annotations

import asyncio
import logging

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.messages import (
    MapMetaData,
    OccupancyGrid,
    Point,
    Pose,
    PoseStamped,
    Quaternion,
    stamp_now,
)
from racecar_hw.base.transforms import StaticTransformParams
from racecar_hw.daemon import Daemon
from racecar_hw.net.topics import DEFAULT, LATCHED, Direction, Topic
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.world import World
from vesc.codec import SetCurrent, SetCurrentBrake, SetDuty, SetRpm
from vesc.fake import FakeVesc

log = logging.getLogger(__name__)

MAP_TOPIC = "/map"
TRUE_POSE_TOPIC = "/sim/pose"
MAP_FRAME = "map"
ODOM_FRAME = "odom"
#: Rate of the true pose (Hz).
TRUE_POSE_RATE_HZ = 20.0

SIM_TOPICS = (
    Topic(MAP_TOPIC, OccupancyGrid, Direction.OUT, LATCHED, "the simulator's map"),
    Topic(TRUE_POSE_TOPIC, PoseStamped, Direction.OUT, DEFAULT, "the simulated car's true pose in map"),
)
_MOTOR = (SetRpm, SetCurrentBrake, SetCurrent, SetDuty)


def map_message(occ_map: OccupancyMap, stamp_ns: int) -> OccupancyGrid:
    """The map as ROS publishes it: rows from the origin corner (grid order), frame ``map``."""
    ox, oy, oyaw = occ_map.origin
    origin = Pose(Point(ox, oy, 0.0), Quaternion.from_yaw(oyaw))
    info = MapMetaData(stamp_now("", stamp_ns).stamp, float(occ_map.resolution), occ_map.width,
                       occ_map.height, origin)
    return OccupancyGrid(stamp_now(MAP_FRAME, stamp_ns), info, occ_map.data.ravel().copy())


def map_to_odom(start: tuple[float, float, float]) -> StaticTransformParams:
    """The static ``map -> odom`` transform: odometry starts at zero where the car starts."""
    x, y, yaw = start
    return StaticTransformParams(frame_id=MAP_FRAME, child_frame_id=ODOM_FRAME, xyz=(x, y, 0.0),
                                 ypr=(yaw, 0.0, 0.0))


async def publish_truth(bus: Bus, world: World, occ_map: OccupancyMap) -> None:
    """Publish the map once, then the true pose at :data:`TRUE_POSE_RATE_HZ` until cancelled."""
    bus.publish(MAP_TOPIC, map_message(occ_map, wall_ns()))
    while True:
        pose = world.pose
        true = Pose(Point(pose.x, pose.y, 0.0), Quaternion.from_yaw(pose.yaw))
        bus.publish(TRUE_POSE_TOPIC, PoseStamped(stamp_now(MAP_FRAME, wall_ns()), true))
        await asyncio.sleep(1.0 / TRUE_POSE_RATE_HZ)


async def log_estop_timing(daemon: Daemon, vesc: FakeVesc, timeout_s: float = 2.0) -> None:
    """Log, for each live e-stop request, when the fake VESC read its first motor command after it."""
    done = 0
    while True:
        await asyncio.sleep(0.05)
        while done < len(daemon.estop_requests):
            at_ns, who = daemon.estop_requests[done]
            first = stop = None
            while monotonic_ns() - at_ns < timeout_s * NS_PER_S:
                motor = [c for c in vesc.commands if c.t_ns >= at_ns and isinstance(c.packet, _MOTOR)]
                first = motor[0] if motor else None
                stop = next((c for c in motor if _standstill(c.packet)), None)
                if stop is not None:
                    break
                await asyncio.sleep(0.02)
            done += 1
            offset = wall_ns() - monotonic_ns()
            if first is None:
                log.error("sim: e-stop from %s at wall %.6f: the fake VESC read no motor command after it",
                          who, (at_ns + offset) / NS_PER_S)
                continue
            log.warning("sim: e-stop from %s at wall %.6f; fake VESC: first motor command at wall %.6f "
                        "(+%.1f ms), standstill command at wall %s", who, (at_ns + offset) / NS_PER_S,
                        (first.t_ns + offset) / NS_PER_S, (first.t_ns - at_ns) / 1e6,
                        "none" if stop is None else f"{(stop.t_ns + offset) / NS_PER_S:.6f} "
                                                    f"(+{(stop.t_ns - at_ns) / 1e6:.1f} ms)")


def _standstill(packet: object) -> bool:
    if isinstance(packet, SetRpm):
        return packet.erpm == 0
    if isinstance(packet, SetCurrentBrake):
        return True
    if isinstance(packet, (SetCurrent, SetDuty)):
        value = packet.current if isinstance(packet, SetCurrent) else packet.duty
        return value == 0
    return False
