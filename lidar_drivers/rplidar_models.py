"""What differs between RPLIDAR models: baud rate, motor control, range limits, sample rates.

Baud rates come from the reference (``lidars.md`` 2.8). Range limits and sample periods are
Slamtec datasheet values (not in the reference; the ``GET_LIDAR_CONF`` max-distance key would
report the real one); the fake lidar reports these sample periods through GET_SAMPLERATE.
Express sample rates are kept within what each baud rate can carry in 84-byte capsules.
"""

from __future__ import annotations

from dataclasses import dataclass

from racecar_hw.base.errors import ConfigError


@dataclass(frozen=True)
class RplidarModel:
    """One model's fixed parameters."""

    name: str
    model_id: int  # GET_INFO model byte: series << 4 | sub-model
    baudrate: int
    range_min: float  # m
    range_max: float  # m
    standard_us: int  # µs per sample, standard scan
    express_us: int  # µs per sample, express scan
    pwm_motor: bool  # accessory board motor PWM (GET_ACC_BOARD_FLAG bit 0)
    hardware: int = 7
    firmware: tuple[int, int] = (1, 29)


MODELS: dict[str, RplidarModel] = {
    "a1": RplidarModel("A1M8", 0x18, 115200, 0.15, 12.0, 500, 250, False),
    "a2m8": RplidarModel("A2M8", 0x28, 115200, 0.15, 12.0, 500, 250, True),
    "a2m7": RplidarModel("A2M7", 0x27, 256000, 0.15, 16.0, 250, 125, True),
    "a2m12": RplidarModel("A2M12", 0x2C, 256000, 0.20, 12.0, 250, 125, True),
    "a3": RplidarModel("A3M1", 0x31, 256000, 0.20, 25.0, 250, 125, True),
    "s1": RplidarModel("S1M1", 0x61, 256000, 0.10, 40.0, 109, 109, False),
    "c1": RplidarModel("C1M1", 0x41, 460800, 0.05, 12.0, 200, 200, False),
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
