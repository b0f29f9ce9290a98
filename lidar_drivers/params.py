"""Parameters of the lidar component, the same for every model."""

from __future__ import annotations

from dataclasses import dataclass

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.link import parse_host_port
from racecar_hw.base.memlink import is_memory
from racecar_hw.base.params import param

#: Models racecar-hw drives, by family.
HOKUYO_MODELS = ("urg-04lx", "ust-10lx", "ust-20lx", "utm-30lx", "utm-30lx-ew")
#: Hokuyo models on USB (serial); the others are Ethernet units.
HOKUYO_USB_MODELS = ("urg-04lx", "utm-30lx")
#: Models with an Ethernet port (``tcp``); every other one is reached on a serial port (``port``).
ETHERNET_MODELS = tuple(m for m in HOKUYO_MODELS if m not in HOKUYO_USB_MODELS)
RPLIDAR_MODELS = ("a1", "a2m8", "a2m7", "a2m12", "a3", "s1", "c1")
MODELS = HOKUYO_MODELS + RPLIDAR_MODELS


@dataclass
class LidarParams:
    """How to reach the lidar and how to shape its scans."""

    model: str = param("ust-10lx", "lidar model", choices=MODELS)
    port: str | None = param(None, "serial port path or pyserial URL (URG-04LX, UTM-30LX, RPLIDAR); "
                                   "not empty")
    tcp: str | None = param(None, "HOST:PORT of an Ethernet Hokuyo (UST, UTM-30LX-EW: "
                                  "192.168.0.10:10940)")
    baudrate: int | None = param(None, "serial baud rate; default: the model's own", min=9600)
    frame_id: str = param("laser", "frame_id of the published scans", nonempty=True)
    topic: str = param("/scan", "topic of the published sensor_msgs/LaserScan", topic=True)
    intensities: bool = param(False, "also publish intensities (Hokuyo ME, RPLIDAR quality)")
    angle_min: float | None = param(None, "crop: first beam angle; default the device's", unit="rad")
    angle_max: float | None = param(None, "crop: last beam angle; default the device's", unit="rad")
    cluster: int = param(1, "Hokuyo: merge this many adjacent steps into one beam", min=1, max=99)
    skip: int = param(0, "Hokuyo: skip this many scans between published scans", min=0, max=9)
    scan_mode: str | None = param(None, "RPLIDAR scan mode, by the name the device lists (e.g. "
                                        "Standard, Express, Boost, Sensitivity, Stability, "
                                        "DenseBoost; any case); default: the device's typical mode")
    motor_pwm: int = param(660, "RPLIDAR A2/A3 motor PWM when the accessory board allows", min=0,
                           max=1023)
    stale_timeout_s: float = param(0.5, "no scan for this long counts as a lost device and "
                                        "triggers a reconnect", unit="s", min=0.05)
    reconnect_backoff_min_s: float = param(0.1, "first reconnect delay", unit="s", min=0.01)
    reconnect_backoff_max_s: float = param(1.0, "longest reconnect delay", unit="s", min=0.05)

    def __post_init__(self) -> None:
        if self.port == "":  # nonempty= would be lost in `str | None`'s "fits none of str"
            raise ConfigError("port", "must not be empty")
        if self.tcp is not None and self.model.lower() not in ETHERNET_MODELS:
            kind = "a USB lidar" if self.model.lower() in HOKUYO_MODELS else "a serial lidar"
            raise ConfigError("tcp", f"the {self.model} is {kind} with no Ethernet port; set lidar.port "
                                     "for it and lidar.tcp: null")
        if self.port is not None and self.tcp is not None:
            raise ConfigError("tcp", "lidar.port and lidar.tcp are both set; set one: lidar.port for USB, "
                                     "lidar.tcp for Ethernet; the other null")
        if self.tcp is not None and not is_memory(self.tcp):  # mem://: a lockstep run's link
            try:
                _, port = parse_host_port(self.tcp, default_port=1)  # no port: the driver's default
            except ValueError as err:
                raise ConfigError("tcp", str(err)) from None
            if port == 0:
                raise ConfigError("tcp", f"{self.tcp!r}: port 0 is no lidar's port")
