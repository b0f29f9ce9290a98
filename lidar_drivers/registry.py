"""Lidar drivers and fake lidars chosen by model name.

``make_driver`` and ``make_fake`` pick the family (Hokuyo SCIP 2.0 or Slamtec RPLIDAR) from
``params.model``; the RPLIDAR classes are imported only when asked for.
"""

from __future__ import annotations

from typing import Any

from lidar_drivers.base import LidarDriver, RangeSource
from lidar_drivers.params import HOKUYO_MODELS, MODELS, RPLIDAR_MODELS, LidarParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError

#: Serial baud rate by model (reference lidars.md 2.8; Hokuyo USB is nominally 115200).
DEFAULT_BAUD: dict[str, int] = {
    "a1": 115200, "a2m8": 115200, "a2m7": 256000, "a2m12": 256000, "a3": 256000, "s1": 256000,
    "c1": 460800,
    "urg-04lx": 115200, "ust-10lx": 115200, "ust-20lx": 115200, "utm-30lx": 115200,
    "utm-30lx-ew": 115200,
}


def family(model: str) -> str:
    """``"hokuyo"`` or ``"rplidar"``; ConfigError for an unknown model."""
    m = model.lower()
    if m in HOKUYO_MODELS:
        return "hokuyo"
    if m in RPLIDAR_MODELS:
        return "rplidar"
    raise ConfigError("lidar.model", f"unknown lidar model {model!r}; known: {', '.join(MODELS)}")


def make_driver(bus: Bus, params: LidarParams) -> LidarDriver:
    """The driver for ``params.model``."""
    if family(params.model) == "hokuyo":
        from lidar_drivers.scip_driver import HokuyoDriver

        return HokuyoDriver(bus, params)
    from lidar_drivers.rplidar_driver import RplidarDriver

    return RplidarDriver(bus, params)  # type: ignore[abstract,unused-ignore]


def make_fake(model: str, range_source: RangeSource, link: str | None = None,
              tcp: tuple[str, int] | None = None, firmware: tuple[int, int] | None = None) -> Any:
    """A fake lidar of ``model`` on a pty at ``link`` and/or (Hokuyo only) a TCP server;
    ``firmware`` (RPLIDAR only) is the version it reports.

    The result has ``async serve()``; run it in a DeviceThread or an event loop.
    """
    if family(model) == "hokuyo":
        from lidar_drivers.scip_fake import FakeHokuyo

        return FakeHokuyo(model.lower(), range_source, link=link, tcp=tcp)
    if tcp is not None:
        raise ConfigError("lidar.tcp", f"{model} is a serial lidar: it has no TCP port")
    from lidar_drivers.rplidar_fake import FakeRplidar

    return FakeRplidar(model.lower(), range_source, link, firmware=firmware)


def model_name(model: str) -> str:
    """The name a device of config model ``model`` reports (RPLIDAR GET_INFO, Hokuyo PP MODL)."""
    if family(model) == "hokuyo":
        from lidar_drivers.scip_models import get_model

        return get_model(model).model
    from lidar_drivers.rplidar_models import model as rplidar_model

    return rplidar_model(model).name


def model_for_reported(reported: str) -> str | None:
    """The config model whose devices report ``reported`` as their name, if racecar-hw knows it."""
    for key in MODELS:
        if model_name(key).lower() == reported.strip().lower():
            return key
    return None
