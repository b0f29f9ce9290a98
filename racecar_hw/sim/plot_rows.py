"""The rows a run's plot is drawn from, without matplotlib: what a run collects while it goes
(:class:`ControlSample`, :class:`Mark`), so the run need not import the plotting library
(:mod:`racecar_hw.sim.plot` draws them, possibly in another process: :mod:`racecar_hw.sim.plot_worker`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple


class ControlSample(NamedTuple):
    """One sample of the control path during a run (sim time ``t`` in seconds, speeds in m/s).

    ``commanded``: what the active source asked for; ``output``: what the mux sent to the VESC after
    the safety controller and the rate limiter; ``allowed``: the safety controller's allowed speed
    (inf when it does not limit); ``measured``: the odometry speed; ``steering``: the output steering
    angle (rad, + left).
    """

    t: float
    commanded: float
    output: float
    allowed: float
    measured: float
    steering: float


@dataclass(frozen=True)
class Mark:
    """A point event on the map and, when its time is known, on the time axis."""

    x: float
    y: float
    t: float | None = None
    label: str = ""


__all__ = ["ControlSample", "Mark"]
