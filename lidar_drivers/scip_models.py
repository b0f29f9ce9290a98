"""Parameter sets of the Hokuyo models the FAKE lidar imitates (``PP``/``VV``/``II`` answers).

The driver never uses these: it reads every number from the device's ``PP`` reply. Values from
/work/shared/reference/lidars.md section 1.8: URG-04LX is documented by Hokuyo; UTM-30LX and
UST-10LX come from third-party code; UST-20LX takes the UST geometry (an assumption), DMIN 20
and DMAX 60000 (unverified: no PP capture is available).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class HokuyoModel:
    """One model's SCIP parameters: distances in mm, angles in steps, ``scan_rpm`` the motor speed.

    ``link`` is how the real device connects (``serial`` USB CDC, ``tcp`` Ethernet); ``no_return``
    the code it sends for a beam with nothing in reach (below DMIN, so an error code).
    """

    name: str
    product: str
    link: str
    dmin: int
    dmax: int
    ares: int
    amin: int
    amax: int
    afrt: int
    scan_rpm: int
    firmware: str
    no_return: int = 1

    @property
    def scan_period_s(self) -> float:
        """Seconds per revolution."""
        return 60.0 / self.scan_rpm

    @property
    def steps(self) -> int:
        """Steps from AMIN to AMAX inclusive."""
        return self.amax - self.amin + 1

    def step_angle(self, step: int | float) -> float:
        """Angle of a step (radians, CCW, 0 straight ahead)."""
        return (step - self.afrt) * 2.0 * math.pi / self.ares

    def pp_fields(self) -> dict[str, str | int]:
        """The ``PP`` reply in device order."""
        return {"MODL": self.product, "DMIN": self.dmin, "DMAX": self.dmax, "ARES": self.ares,
                "AMIN": self.amin, "AMAX": self.amax, "AFRT": self.afrt, "SCAN": self.scan_rpm}


MODELS: dict[str, HokuyoModel] = {
    m.name: m
    for m in (
        HokuyoModel("urg-04lx", "URG-04LX-UG01(Simple-URG)", "serial", 20, 5600, 1024, 44, 725,
                    384, 600, "3.4.03"),
        HokuyoModel("ust-10lx", "UST-10LX", "tcp", 20, 30000, 1440, 0, 1080, 540, 2400, "4.0.3"),
        HokuyoModel("ust-20lx", "UST-20LX", "tcp", 20, 60000, 1440, 0, 1080, 540, 2400, "4.0.3"),
        HokuyoModel("utm-30lx", "UTM-30LX", "tcp", 23, 60000, 1440, 0, 1080, 540, 2400, "1.1.6"),
    )
}


def get_model(name: str) -> HokuyoModel:
    """The model named ``name`` (case-insensitive); KeyError naming the known models."""
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise KeyError(f"unknown Hokuyo model {name!r}; known: {', '.join(MODELS)}") from None
