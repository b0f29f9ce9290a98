"""What the simulator adds to the live view: the map, the true pose, and e-stop timing in the log.

* ``/map`` (``nav_msgs/OccupancyGrid``, latched) once at start, and a static ``map -> odom`` transform
  at the scenario's start pose, so odometry (``odom -> base_link`` on ``/tf``) is drawn in the map;
* ``/sim/pose`` (``geometry_msgs/PoseStamped`` in ``map``): the world's true pose, so a viewer sees
  odometry drift against ground truth;
* for every e-stop asked through a live interface (Foxglove service, status page), one log line with
  the wall time of the request and of the brake the fake VESC read, and whether that brake was the
  first motor command written after the request (it must be: the mux's e-stop bypasses the limiter).
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
from racecar_hw.base.topics import LATCHED_TOPICS, MAP_TOPIC
from racecar_hw.base.transforms import StaticTransformParams
from racecar_hw.control.path import EstopRequest
from racecar_hw.daemon import Daemon
from racecar_hw.net.topics import DEFAULT, Direction, Topic
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.pacer import Pacer
from racecar_hw.sim.world import World
from vesc.codec import SetCurrent, SetCurrentBrake, SetDuty, SetRpm
from vesc.fake import CommandRecord, FakeVesc

log = logging.getLogger(__name__)

TRUE_POSE_TOPIC = "/sim/pose"
MAP_FRAME = "map"
ODOM_FRAME = "odom"
#: Rate of the true pose (Hz).
TRUE_POSE_RATE_HZ = 20.0

SIM_TOPICS = (
    Topic(MAP_TOPIC, OccupancyGrid, Direction.OUT, LATCHED_TOPICS[MAP_TOPIC], "the simulator's map"),
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

    def publish(_now_ns: int) -> None:
        pose = world.pose
        true = Pose(Point(pose.x, pose.y, 0.0), Quaternion.from_yaw(pose.yaw))
        bus.publish(TRUE_POSE_TOPIC, PoseStamped(stamp_now(MAP_FRAME, wall_ns()), true))

    await Pacer(TRUE_POSE_RATE_HZ).run(publish)


async def log_estop_timing(daemon: Daemon, vesc: FakeVesc, timeout_s: float = 2.0) -> None:
    """Log, for each live e-stop request, when the fake VESC read its brake, and whether at once.

    The fake numbers the frames it reads (:attr:`~vesc.fake.CommandRecord.seq`); the request
    carries how many the driver had written before it, so the first motor command written after
    the request is known exactly, whatever was still in flight when it came. That command must
    be the brake (SET_RPM 0 or SET_CURRENT_BRAKE); otherwise the log says how many motor commands
    came first (an e-stop that ramps down instead of braking). Frame numbers match while no
    frame is lost between the driver and the fake (no unplug during the run); a mismatch is
    logged as such.
    """
    while True:
        await asyncio.sleep(0.05)
        while daemon.estop_requests:
            request = daemon.estop_requests.popleft()
            after: list[CommandRecord] = []
            brake = None
            if request.vesc_frames_before is not None:
                while brake is None and monotonic_ns() - request.at_ns < timeout_s * NS_PER_S:
                    after = [c for c in vesc.commands
                             if c.seq > request.vesc_frames_before and isinstance(c.packet, _MOTOR)]
                    brake = next((c for c in after if _is_brake(c.packet)), None)
                    if brake is None:
                        await asyncio.sleep(0.02)
            _log_estop(request, after, brake, timeout_s)


def _log_estop(request: EstopRequest, after: list[CommandRecord], brake: CommandRecord | None,
               timeout_s: float) -> None:
    offset = wall_ns() - monotonic_ns()
    asked = f"sim: e-stop from {request.who} at wall {(request.at_ns + offset) / NS_PER_S:.6f}"
    if brake is None:
        log.error("%s: the fake VESC read no brake command within %g s after it (%d other motor "
                  "commands)", asked, timeout_s, len(after))
        return
    if after and after[0].t_ns < request.at_ns:
        log.error("%s: the fake VESC's frame numbers do not match the driver's (a frame was lost); "
                  "no timing", asked)
        return
    before = after.index(brake)
    how = ("the first motor command written after the request" if before == 0 else
           f"after {before} other motor commands written after the request: the e-stop did not brake "
           "at once")
    log.warning("%s; fake VESC: brake %s at wall %.6f (+%.1f ms), %s", asked, _name(brake.packet),
                (brake.t_ns + offset) / NS_PER_S, (brake.t_ns - request.at_ns) / 1e6, how)


def _name(packet: object) -> str:
    if isinstance(packet, SetRpm):
        return f"SET_RPM {packet.erpm}"
    if isinstance(packet, SetCurrentBrake):
        return f"SET_CURRENT_BRAKE {packet.current:g} A"
    return type(packet).__name__


def _is_brake(packet: object) -> bool:
    """What the driver brakes with: SET_RPM 0 (the speed loop holds the wheels) or SET_CURRENT_BRAKE.

    A zero current or duty releases the motor (the car coasts): not a brake.
    """
    return (isinstance(packet, SetRpm) and packet.erpm == 0) or isinstance(packet, SetCurrentBrake)
