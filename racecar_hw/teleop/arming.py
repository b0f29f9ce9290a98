"""The car's armed state, shared by the gamepad, the keyboard and the ground station.

Disarmed means zero speed and centred steering whatever the inputs say. The daemon puts
:meth:`Arming.filter` first among the mux filters (right after arbitration), so every source -
teleop, navigation, bag follower - is stopped while the car is disarmed; the mux's limiter then
brakes at its deceleration limit.

The simulation starts armed (``start_armed: true``); the real car starts disarmed and must be armed
by the gamepad's START button or the ground station (MAV_CMD_COMPONENT_ARM_DISARM).

Use from the bus's event-loop thread only.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from racecar_hw.base.clock import monotonic_ns
from racecar_hw.base.messages import AckermannDrive
from racecar_hw.base.params import param

log = logging.getLogger(__name__)


@dataclass
class ArmingParams:
    """Whether the car starts armed."""

    start_armed: bool = param(False, "start armed (simulation) instead of disarmed (car)")


@dataclass(frozen=True)
class ArmingChange:
    """One transition: the new state, who asked (``gamepad``, ``gcs``, ...), why, and when (monotonic ns)."""

    armed: bool
    source: str
    reason: str
    time_ns: int


ArmingCallback = Callable[[ArmingChange], None]


class Arming:
    """Armed or disarmed, with the source and reason of the last change and change callbacks."""

    def __init__(self, start_armed: bool = False, *, clock: Callable[[], int] = monotonic_ns) -> None:
        self._clock = clock
        self._armed = bool(start_armed)
        self.source = "config"
        self.reason = "start_armed" if start_armed else "starts disarmed"
        self.changed_ns = clock()
        self._callbacks: list[ArmingCallback] = []
        #: commands the filter stopped because the car was disarmed (non-zero ones only)
        self.blocked = 0
        #: arm/disarm transitions so far
        self.changes = 0

    @classmethod
    def from_params(cls, params: ArmingParams, **kwargs: Callable[[], int]) -> Arming:
        """An Arming state as ``params`` says it starts."""
        return cls(params.start_armed, **kwargs)

    @property
    def armed(self) -> bool:
        """True while the car may move."""
        return self._armed

    def arm(self, source: str, reason: str = "") -> bool:
        """Arm; returns True when this changed the state."""
        return self._set(True, source, reason or f"armed by {source}")

    def disarm(self, source: str, reason: str = "") -> bool:
        """Disarm; returns True when this changed the state."""
        return self._set(False, source, reason or f"disarmed by {source}")

    def on_change(self, callback: ArmingCallback) -> Callable[[], None]:
        """Call ``callback(change)`` after every transition; returns a function that removes it."""
        self._callbacks.append(callback)

        def remove() -> None:
            if callback in self._callbacks:
                self._callbacks.remove(callback)
        return remove

    def _set(self, armed: bool, source: str, reason: str) -> bool:
        if armed == self._armed:
            return False
        self._armed = armed
        self.source = source
        self.reason = reason
        self.changed_ns = self._clock()
        self.changes += 1
        log.warning("%s: %s", "ARMED" if armed else "DISARMED", reason)
        change = ArmingChange(armed, source, reason, self.changed_ns)
        for callback in list(self._callbacks):
            try:
                callback(change)
            except Exception:
                log.exception("arming change callback failed")
        return True

    def filter(self, drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
        """Mux filter: ``drive`` unchanged while armed, a stop (speed 0, steering 0) while disarmed."""
        if self._armed:
            return drive
        if drive.speed != 0.0 or drive.steering_angle != 0.0:
            self.blocked += 1
        return AckermannDrive()
