"""The car's past: its state after every world step, and where it was at any monotonic time.

Each step's :class:`~racecar_hw.sim.trajectory.TrajectorySample` (sim time s, rear-axle x, y in
m and yaw in rad in the map frame, speed m/s, steering rad) is kept with the world's monotonic
clock (ns) at that step, so a fake lidar can ask where the car was when its scan was stamped.
Not thread-safe: the world guards it with its lock.
"""

from __future__ import annotations

import bisect

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.sim.car import Pose2D, advance, wrap_angle
from racecar_hw.sim.trajectory import TrajectorySample

#: A lidar asking for a time later than the last step sees the car extrapolated this far at most (s).
MAX_EXTRAPOLATION_S = 0.1


class PoseHistory:
    """Every step since the start (or the last reset), beginning at rest at ``pose``, ``time_ns``.

    Its first time is sim time zero, its last the world's clock now.
    """

    def __init__(self, pose: Pose2D, time_ns: int) -> None:
        self.samples: list[TrajectorySample] = [TrajectorySample(0.0, pose.x, pose.y, pose.yaw, 0.0, 0.0)]
        self.times_ns: list[int] = [time_ns]

    def append(self, sample: TrajectorySample, time_ns: int) -> None:
        self.samples.append(sample)
        self.times_ns.append(time_ns)

    @property
    def time_ns(self) -> int:
        """The world's clock (monotonic ns) at the last step."""
        return self.times_ns[-1]

    @property
    def stepped(self) -> bool:
        """Whether the world has stepped since the start or the last reset."""
        return len(self.times_ns) > 1

    def sim_time_at(self, stamp_ns: int) -> float:
        """Sim time (s) at monotonic ``stamp_ns``."""
        return (stamp_ns - self.times_ns[0]) / NS_PER_S

    def restart(self, time_ns: int) -> None:
        """Sim time zero is ``time_ns`` (the world starts running now; only before a step)."""
        assert not self.stepped
        self.times_ns[0] = time_ns

    def pose_at(self, stamp_ns: int, wheelbase: float) -> Pose2D:
        """The rear-axle pose at monotonic time ``stamp_ns``: interpolated between steps, the first
        pose before the history, extrapolated (at most MAX_EXTRAPOLATION_S, with the bicycle of
        ``wheelbase`` m) after the last step."""
        times, samples = self.times_ns, self.samples
        k = bisect.bisect_right(times, stamp_ns)
        if k == 0:
            s = samples[0]
            return Pose2D(s.x, s.y, s.yaw)
        if k == len(times):
            s, last_ns = samples[-1], times[-1]
            ahead = min((stamp_ns - last_ns) / NS_PER_S, MAX_EXTRAPOLATION_S)
            return advance(Pose2D(s.x, s.y, s.yaw), s.speed, s.steering, ahead, wheelbase)
        a, b = samples[k - 1], samples[k]
        ta, tb = times[k - 1], times[k]
        f = (stamp_ns - ta) / (tb - ta) if tb > ta else 1.0
        return Pose2D(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y),
                      wrap_angle(a.yaw + f * wrap_angle(b.yaw - a.yaw)))


__all__ = ["MAX_EXTRAPOLATION_S", "PoseHistory"]
