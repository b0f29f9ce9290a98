"""What differs between RPLIDAR models: baud rate, motor control, range limits, scan modes.

Each model lists the scan modes a unit with current firmware reports through GET_LIDAR_CONF (id,
name, µs per sample, maximum distance, answer type) and its typical mode; the fake lidar answers
with exactly this table and the legacy GET_SAMPLERATE with the Standard and Express periods.
docs/lidars.md ("RPLIDAR models") gives the source of every row and says which values are
assumptions. Two constraints hold for every row: a mode's byte stream fits the model's baud rate
(5 bytes a sample for standard nodes, 84/32 for express, 132/96 for ultra, 84/40 for dense
capsules), and legacy express capsules carry at most 16.383 m.

Baud rates: reference ``lidars.md`` 2.8. Range limits: Slamtec datasheets.
"""

from __future__ import annotations

from dataclasses import dataclass

from lidar_drivers.rplidar_codec import AnswerType, ScanMode
from racecar_hw.base.errors import ConfigError

STANDARD, EXPRESS = AnswerType.SCAN, AnswerType.EXPRESS
ULTRA, DENSE = AnswerType.ULTRA_CAPSULED, AnswerType.DENSE_CAPSULED


@dataclass(frozen=True)
class RplidarModel:
    """One model's fixed parameters."""

    name: str
    model_id: int  # GET_INFO model byte: series << 4 | sub-model
    baudrate: int
    range_min: float  # m
    range_max: float  # m
    modes: tuple[ScanMode, ...]
    typical: int  # id of the typical scan mode
    pwm_motor: bool  # accessory board motor PWM (GET_ACC_BOARD_FLAG bit 0)
    hardware: int = 7
    firmware: tuple[int, int] = (1, 29)
    desired_rpm: int = 600  # GET_LIDAR_CONF DESIRED_ROT_FREQ: rpm, and the PWM that gives it
    desired_pwm: int = 660

    def mode(self, mode_id: int) -> ScanMode | None:
        """The scan mode with id ``mode_id``, or None."""
        return next((m for m in self.modes if m.id == mode_id), None)

    def _first(self, answer_type: int) -> ScanMode | None:
        return next((m for m in self.modes if m.answer_type == answer_type), None)

    @property
    def standard_us(self) -> int:
        """µs per sample of a SCAN (standard nodes), as GET_SAMPLERATE reports it."""
        m = self._first(STANDARD)
        return round(m.us_per_sample) if m else 0

    @property
    def express_us(self) -> int:
        """µs per sample of a legacy EXPRESS_SCAN (mode 0), as GET_SAMPLERATE reports it."""
        m = self._first(EXPRESS) or self._first(STANDARD)
        return round(m.us_per_sample) if m else 0


def _modes(max_m: float, *rows: tuple[str, float, int]) -> tuple[ScanMode, ...]:
    return tuple(ScanMode(i, name, us, max_m, kind) for i, (name, us, kind) in enumerate(rows))


#: A-series triangulation units with the 16 k samples/s core (A2M7, A2M12, A3): the A3's table.
def _fast_a_series(max_m: float) -> tuple[ScanMode, ...]:
    return _modes(max_m, ("Standard", 250, STANDARD), ("Express", 126, EXPRESS),
                  ("Boost", 63, ULTRA), ("Sensitivity", 63, ULTRA), ("Stability", 100, ULTRA))


MODELS: dict[str, RplidarModel] = {
    "a1": RplidarModel("A1M8", 0x18, 115200, 0.15, 12.0, _modes(
        12.0, ("Standard", 500, STANDARD), ("Express", 250, EXPRESS), ("Boost", 125, ULTRA)),
        typical=2, pwm_motor=False),
    "a2m8": RplidarModel("A2M8", 0x28, 115200, 0.15, 12.0, _modes(
        12.0, ("Standard", 500, STANDARD), ("Express", 250, EXPRESS), ("Boost", 125, ULTRA),
        ("Sensitivity", 125, ULTRA), ("Stability", 250, ULTRA)), typical=3, pwm_motor=True),
    "a2m7": RplidarModel("A2M7", 0x27, 256000, 0.15, 16.0, _fast_a_series(16.0), typical=3,
                         pwm_motor=True),
    "a2m12": RplidarModel("A2M12", 0x2C, 256000, 0.20, 12.0, _fast_a_series(12.0), typical=3,
                          pwm_motor=True),
    "a3": RplidarModel("A3M1", 0x31, 256000, 0.20, 25.0, _fast_a_series(25.0), typical=3,
                       pwm_motor=True),
    "s1": RplidarModel("S1M1", 0x61, 256000, 0.10, 40.0, _modes(
        40.0, ("Standard", 200, STANDARD), ("DenseBoost", 108.75, DENSE)), typical=1,
        pwm_motor=False),
    "c1": RplidarModel("C1M1", 0x41, 460800, 0.05, 12.0, _modes(
        12.0, ("Standard", 200, STANDARD), ("DenseBoost", 200, DENSE)), typical=1,
        pwm_motor=False, hardware=18, firmware=(1, 2)),
}


def model(name: str) -> RplidarModel:
    """The parameters of model ``name`` (``a1``, ``a2m8`` ... as in LidarParams.model)."""
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise ConfigError("model", f"{name!r} is not an RPLIDAR model; choose from "
                                   f"{', '.join(MODELS)}") from None


def uses_pwm_motor_control(model_id: int) -> bool:
    """A2-A3 (and C) series: motor speed by SET_MOTOR_PWM when the accessory board says so."""
    return 2 <= (model_id >> 4) <= 5


def uses_dtr_motor_control(model_id: int) -> bool:
    """A1: the motor runs while DTR is cleared and stops while it is asserted."""
    return (model_id >> 4) == 1


def has_self_driven_motor(model_id: int) -> bool:
    """C series: the unit runs its motor itself. The SDK still treats it like an A2 (PWM if the
    accessory board flag says so, else DTR cleared), which the C1 ignores."""
    return (model_id >> 4) == 4


def uses_rpm_motor_control(model_id: int) -> bool:
    """S series and newer: the motor speed is set in rpm (SET_MOTOR_RPM)."""
    return (model_id >> 4) >= 6
