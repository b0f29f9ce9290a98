"""The ground station's sticks: MANUAL_CONTROL and RC_CHANNELS_OVERRIDE to a drive request.

MANUAL_CONTROL (ArduPilot Rover: ``y`` steering, +1000 = full right; ``z`` throttle, -1000..1000
with 0 = stop; ``x`` instead of ``z`` when ``throttle_axis: x``) and RC_CHANNELS_OVERRIDE (ch1
steering, ch3 throttle, PWM µs; 0 releases a channel, 65535 leaves a live value unchanged; a value
expires ``rc_override_time_s`` after it was sent, ArduPilot's ``RC_OVERRIDE_TIME``) become a speed
(m/s) and a steering angle (rad, + left, REP-103) that drive while fresher than ``input_timeout_s``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.messages import AckermannDrive
from racecar_hw.teleop.mavlink_dialect import INT16_MAX, UINT16_MAX

if TYPE_CHECKING:
    from racecar_hw.teleop.mavlink_params import MavlinkParams


@dataclass
class ManualInput:
    """The ground station's latest teleop request: speed (m/s), steering (rad, + left), arrival (ns)."""

    speed: float
    steering: float
    received_ns: int
    kind: str


class Sticks:
    """The latest teleop request of the ground station, with RC override channels and expiry.

    ``accept`` is asked whether an input may drive now (and counts it either way); times are
    monotonic ns.
    """

    def __init__(self, params: MavlinkParams, accept: Callable[[], bool]) -> None:
        self.params = params
        self._accept = accept
        self.manual: ManualInput | None = None
        self._rc: dict[int, tuple[int, int] | None] = {1: None, 3: None}  # channel: (µs, set at ns)

    def take_manual_control(self, msg: Any, now: int) -> None:
        """A MANUAL_CONTROL message (addressed to us) arrived at ``now``."""
        if not self._accept():
            return
        throttle = msg.z if self.params.throttle_axis == "z" else msg.x
        self.manual = ManualInput(_axis(throttle) * self.params.max_speed_mps,
                                  -_axis(msg.y) * self.params.max_steering_rad, now, "manual_control")

    def take_rc_override(self, msg: Any, now: int) -> None:
        """An RC_CHANNELS_OVERRIDE message (addressed to us) arrived at ``now``. A release (0) always
        counts; a value only from an input that may drive now: one refused (the station lost, not
        MANUAL) is not kept for a later 65535 ("unchanged") to bring back."""
        accepted = self._accept()
        for channel, raw in ((1, msg.chan1_raw), (3, msg.chan3_raw)):
            if raw == 0:
                self._rc[channel] = None
            elif raw != UINT16_MAX and accepted:
                self._rc[channel] = (raw, now)
        steering, throttle = self._rc_value(1, now), self._rc_value(3, now)
        if steering is None and throttle is None:
            if self.manual is not None and self.manual.kind == "rc_override":
                self.manual = None  # both channels released or expired: stop driving now
            return
        if not accepted:
            return
        self.manual = ManualInput(self._pwm(throttle) * self.params.max_speed_mps,
                                  -self._pwm(steering) * self.params.max_steering_rad, now, "rc_override")

    def forget(self) -> None:
        """Drop the input and every override channel (the station lost, or not in MANUAL): nothing
        held from before comes back with a later 65535 ("unchanged")."""
        self.manual = None
        self._rc = dict.fromkeys(self._rc)

    def drive(self, now: int, allowed: bool) -> AckermannDrive | None:
        """The command to publish at ``now``: None while there is no fresh input or driving is not
        ``allowed`` (no fresh station heartbeat, or not MANUAL)."""
        manual = self.live(now)
        if manual is None or not allowed:
            return None
        if not self.fresh(manual, now):
            return None
        return AckermannDrive(steering_angle=manual.steering, speed=manual.speed)

    def fresh(self, manual: ManualInput | None, now: int) -> bool:
        """True when ``manual`` arrived at most ``input_timeout_s`` before ``now``."""
        return (manual is not None
                and now - manual.received_ns <= round(self.params.input_timeout_s * NS_PER_S))

    def live(self, now: int) -> ManualInput | None:
        """The latest teleop input with RC override expiry applied at ``now`` (on every tick and
        command, not only when a new RC message comes): an expired channel is at rest, and with both
        channels released or expired the override ends."""
        manual = self.manual
        if manual is None or manual.kind != "rc_override":
            return manual
        steering, throttle = self._rc_value(1, now), self._rc_value(3, now)
        if steering is None and throttle is None:
            self.manual = None
        else:
            self.manual = dataclasses.replace(manual, speed=self._pwm(throttle) * self.params.max_speed_mps,
                                              steering=-self._pwm(steering) * self.params.max_steering_rad)
        return self.manual

    def _rc_value(self, channel: int, now: int) -> int | None:
        """The live override of ``channel`` (µs), or None when released or expired."""
        held = self._rc[channel]
        if held is None:
            return None
        if now - held[1] > round(self.params.rc_override_time_s * NS_PER_S):
            self._rc[channel] = None  # expired: 65535 cannot bring it back
            return None
        return held[0]

    def _pwm(self, raw: int | None) -> float:
        """-1..1 from a PWM width (µs); None (released) is 0."""
        if raw is None:
            return 0.0
        p = self.params
        if raw >= p.rc_trim_us:
            return min(1.0, (raw - p.rc_trim_us) / (p.rc_max_us - p.rc_trim_us))
        return max(-1.0, (raw - p.rc_trim_us) / (p.rc_trim_us - p.rc_min_us))


def _axis(value: int) -> float:
    """A MANUAL_CONTROL axis (-1000..1000; INT16_MAX = unused, taken as centred) to -1..1."""
    if value == INT16_MAX:
        return 0.0
    return max(-1.0, min(1.0, value / 1000.0))


__all__ = ["ManualInput", "Sticks"]
