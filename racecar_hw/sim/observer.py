"""What a sim run watches while it goes: where interventions start, and the control path for the plot.

Positions are in the map frame (m); times are sim time (s).
"""

from __future__ import annotations

from racecar_hw.daemon import Daemon
from racecar_hw.sim.pacer import Pacer
from racecar_hw.sim.plot_rows import ControlSample, Mark
from racecar_hw.sim.world import World

#: How often the control path is sampled for the plot (s of sim time), and at most how many samples.
SAMPLE_PERIOD_S = 0.05
MAX_SAMPLES = 200_000
#: How often the safety controller is looked at for a new intervention (s).
WATCH_PERIOD_S = 0.02


class RunObserver:
    """Looks at the daemon's safety controller and control path every 20 ms (:meth:`watch`)."""

    def __init__(self) -> None:
        #: where each intervention started (x, y in the map)
        self.interventions_at: list[tuple[float, float]] = []
        #: the interventions with their sim time, for the plot
        self.intervention_marks: list[Mark] = []
        #: the control path sampled every :data:`SAMPLE_PERIOD_S`, for the plot
        self.control_samples: list[ControlSample] = []

    async def watch(self, daemon: Daemon, world: World) -> None:
        """Note where and when interventions start, and sample the control path for the plot
        (a loop timer every 20 ms, until cancelled)."""
        seen = 0
        next_sample = 0.0

        def look(_now_ns: int) -> None:
            nonlocal seen, next_sample
            n = daemon.safety.interventions
            t = world.sim_time
            if n > seen:
                pose = world.pose
                self.interventions_at.extend([(pose.x, pose.y)] * (n - seen))
                self.intervention_marks.extend([Mark(pose.x, pose.y, t)] * (n - seen))
                seen = n
            if t >= next_sample and len(self.control_samples) < MAX_SAMPLES:
                next_sample = t + SAMPLE_PERIOD_S
                self.control_samples.append(self._control_sample(daemon, t))

        await Pacer(1.0 / WATCH_PERIOD_S).run(look)

    @staticmethod
    def _control_sample(daemon: Daemon, t: float) -> ControlSample:
        """Asked and commanded speed, allowed speed, odometry speed (m/s) and steering (rad) at ``t``."""
        out = daemon.mux.last_output
        odom = daemon.bus.latest(daemon.config.safety.odom_topic)
        asked = daemon.mux.last_command(daemon.mux.source)
        return ControlSample(t, float(asked.speed) if asked is not None else 0.0,
                             float(out.drive.speed) if out is not None else 0.0,
                             float(daemon.safety.state.allowed_speed),
                             float(odom.twist.twist.linear.x) if odom is not None else 0.0,
                             float(out.drive.steering_angle) if out is not None else 0.0)


__all__ = ["MAX_SAMPLES", "SAMPLE_PERIOD_S", "RunObserver"]
