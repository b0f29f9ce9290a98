"""What differs between RPLIDAR models: baud rate, motor control, range limits, scan modes.

Each model lists the scan modes a unit with current firmware reports through GET_LIDAR_CONF (id,
name, µs per sample, maximum distance, answer type) and its typical mode; where public logs show
an older firmware listing other modes (the A1), :attr:`RplidarModel.older` holds that table and
:meth:`RplidarModel.for_firmware` picks the one a given firmware reports. The fake lidar answers
with exactly this table and the legacy GET_SAMPLERATE with the Standard and Express periods, and
models that say so answer MIN_ROT_FREQ / MAX_ROT_FREQ (rpm). docs/lidars.md ("RPLIDAR models")
gives the source of every row and says which values are assumptions. Two constraints hold for
every row: a mode's byte stream fits the model's baud rate (5 bytes a sample for standard nodes,
84/32 for express, 132/96 for ultra, 84/40 for dense capsules), and legacy express capsules carry
at most 16.383 m.

Baud rates: reference ``lidars.md`` 2.8. Range limits (``range_min``/``range_max``, what the
driver publishes): Slamtec datasheets; a mode's maximum distance is what the unit reports for it
and may be larger.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from lidar_drivers.rplidar_codec import AnswerType, ScanMode
from racecar_hw.base.errors import ConfigError

STANDARD, EXPRESS = AnswerType.SCAN, AnswerType.EXPRESS
ULTRA, DENSE = AnswerType.ULTRA_CAPSULED, AnswerType.DENSE_CAPSULED


@dataclass(frozen=True)
class OlderFirmware:
    """The scan modes units with firmware before ``before`` list instead of the model's own."""

    before: tuple[int, int]
    modes: tuple[ScanMode, ...]
    typical: int
    hardware: int


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
    #: GET_LIDAR_CONF MIN_ROT_FREQ / MAX_ROT_FREQ (rpm), None: the unit does not answer them
    rot_freq_range: tuple[int, int] | None = None
    #: tables of older firmware, oldest first (see :meth:`for_firmware`)
    older: tuple[OlderFirmware, ...] = ()

    def for_firmware(self, firmware: tuple[int, int]) -> RplidarModel:
        """The model as a unit running ``firmware`` reports itself: that firmware's scan-mode
        table, typical mode and hardware revision (firmware older than every listed table gets
        the oldest; it only matters there for GET_SAMPLERATE's periods)."""
        for old in self.older:
            if firmware < old.before:
                return replace(self, modes=old.modes, typical=old.typical,
                               hardware=old.hardware, firmware=firmware, older=())
        return replace(self, firmware=firmware, older=())

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


def _modes(*rows: tuple[str, float, float, int]) -> tuple[ScanMode, ...]:
    """Scan modes with ids in order from 0: (name, µs per sample, maximum distance m, type)."""
    return tuple(ScanMode(i, name, us, max_m, kind) for i, (name, us, max_m, kind) in enumerate(rows))


#: A-series triangulation units with the 16 k samples/s core (A2M7, A2M12, A3): the A3's table.
def _fast_a_series(max_m: float) -> tuple[ScanMode, ...]:
    return _modes(("Standard", 250, max_m, STANDARD), ("Express", 126, max_m, EXPRESS),
                  ("Boost", 63, max_m, ULTRA), ("Sensitivity", 63, max_m, ULTRA),
                  ("Stability", 100, max_m, ULTRA))


MODELS: dict[str, RplidarModel] = {
    # firmware 1.29 (hardware 7); hardware 5 units: 1.27 lists four modes, 1.24 three
    "a1": RplidarModel("A1M8", 0x18, 115200, 0.15, 12.0, _modes(
        ("Standard", 435, 12.0, STANDARD), ("Express", 250, 12.0, EXPRESS),
        ("Boost", 126, 12.0, ULTRA), ("Sensitivity", 126, 12.0, ULTRA),
        ("Stability", 200, 12.0, ULTRA)), typical=3, pwm_motor=False, older=(
            OlderFirmware((1, 27), _modes(
                ("Standard", 500, 12.0, STANDARD), ("Express", 250, 12.0, EXPRESS),
                ("Boost", 125, 12.0, ULTRA)), typical=0, hardware=5),
            OlderFirmware((1, 29), _modes(
                ("Standard", 500, 12.0, STANDARD), ("Express", 250, 12.0, EXPRESS),
                ("Boost", 125, 12.0, ULTRA), ("Stability", 250, 12.0, ULTRA)), typical=0,
                hardware=5))),
    "a2m8": RplidarModel("A2M8", 0x28, 115200, 0.15, 12.0, _modes(
        ("Standard", 500, 12.0, STANDARD), ("Express", 250, 12.0, EXPRESS),
        ("Boost", 125, 12.0, ULTRA), ("Sensitivity", 125, 12.0, ULTRA),
        ("Stability", 250, 12.0, ULTRA)), typical=3, pwm_motor=True),
    "a2m7": RplidarModel("A2M7", 0x27, 256000, 0.15, 16.0, _fast_a_series(16.0), typical=3,
                         pwm_motor=True),
    "a2m12": RplidarModel("A2M12", 0x2C, 256000, 0.20, 12.0, _fast_a_series(16.0), typical=3,
                          pwm_motor=True),
    "a3": RplidarModel("A3M1", 0x31, 256000, 0.20, 25.0, _fast_a_series(25.0), typical=3,
                       pwm_motor=True),
    "s1": RplidarModel("S1M1", 0x61, 256000, 0.10, 40.0, _modes(
        ("Standard", 200, 40.0, STANDARD), ("DenseBoost", 108.75, 40.0, DENSE)), typical=1,
        pwm_motor=False, rot_freq_range=(300, 900)),
    "c1": RplidarModel("C1M1", 0x41, 460800, 0.05, 12.0, _modes(
        ("Standard", 200, 16.0, STANDARD), ("DenseBoost", 200, 40.0, DENSE)), typical=1,
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
