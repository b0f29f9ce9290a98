"""``/clock`` in simulation: the time ROS 2 nodes with ``use_sim_time`` (and :class:`racecar_hw.client.Car`
with ``use_sim_time=True``) follow.

Every ``1 / rate_hz`` seconds of simulation time the simulator publishes ``rosgraph_msgs/msg/Clock``
carrying :func:`racecar_hw.base.clock.wall_ns` at that moment: the time base of every stamp the
daemon writes. In the real-time simulation that is Unix time (so a node on sim time and one on the
wall clock agree); in lockstep it is the virtual clock, and nodes on sim time run as fast or as slow
as the simulation. The rate is the scenario's ``world.clock_rate_hz`` (100 Hz; 0: no ``/clock``).
In a fleet (several cars in one process) every car's daemon publishes it on its own interfaces: a
client connected to one car gets that car's, and all carry the one virtual clock.

How ROS does it, and what is kept here (docs/sim.md, "/clock"):

* **Name**: ``/clock`` is absolute: ROS 2's time source subscribes to ``/clock`` whatever the node's
  namespace (rclcpp and rclpy ``TimeSource``), and a simulator publishes one for the world, so the row
  is ``absolute`` and keeps its name when ``zenoh.namespace`` is set.
* **QoS**: reliable, volatile, keep last 1. Nodes subscribe with ``ClockQoS`` (best effort, keep
  last 1); a reliable writer matches a best-effort reader and a reliable one (``ros2 topic echo``,
  a recorder asking for reliable), where a best-effort writer would match only the first.
* **Rate**: 100 Hz of simulation time. Gazebo's bridge publishes once per physics step, which
  here would be 200 Hz; at 100 Hz time on a node advances in 10 ms steps, finer than the lidar's
  40 Hz scans, the mux's 50 Hz control tick and the timers of a navigation stack on this car (so a
  timer fires at most 10 ms of simulation time late), for half the messages.
"""

from __future__ import annotations

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.messages import Clock, Time
from racecar_hw.base.topics import CLOCK_TOPIC
from racecar_hw.config import Config
from racecar_hw.daemon import Daemon
from racecar_hw.net.topics import CLOCK_ROW
from racecar_hw.sim.pacer import Pacer


def clock_message(now_ns: int) -> Clock:
    """``/clock`` at ``now_ns`` (ns in the stamps' time base)."""
    return Clock(Time.from_ns(now_ns))


async def publish_clock(bus: Bus, rate_hz: float) -> None:
    """Publish ``/clock`` at ``rate_hz`` (simulation time) until cancelled, the first at once.

    On the process's clock (the virtual one in lockstep), from a loop timer on the rate's grid
    (:class:`~racecar_hw.sim.pacer.Pacer`) rather than a sleeping task: one event-loop callback per
    message instead of a timer and a task's wake-up."""
    await Pacer(rate_hz).run(lambda _now_ns: bus.publish(CLOCK_TOPIC, clock_message(wall_ns())))


def carried(config: Config) -> bool:
    """Whether anything would carry ``/clock``: a network interface (Zenoh, DDS, the live view) or
    the recorder. The step API turns them all off: its episodes then have no publisher to run."""
    return config.zenoh.enabled or config.dds.enabled or config.foxglove.enabled or config.recorder.enabled


def add_clock(daemon: Daemon, rate_hz: float) -> None:
    """Offer ``/clock`` on the daemon's network interfaces and publish it at ``rate_hz`` (0, or
    nothing to carry it: neither).

    Before the daemon runs: its interfaces read the topic table when they open.
    """
    if rate_hz <= 0 or not carried(daemon.config):
        return
    daemon.live_topics.append(CLOCK_ROW)
    daemon.add_task(publish_clock(daemon.bus, rate_hz))


__all__ = ["add_clock", "carried", "clock_message", "publish_clock"]
