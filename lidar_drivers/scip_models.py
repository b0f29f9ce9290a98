"""Parameter sets of the Hokuyo models the FAKE lidar imitates (``PP``/``VV``/``II`` answers).

The driver never uses these: it reads every number from the device's ``PP`` reply. Values from
/work/shared/reference/lidars.md section 1.8: URG-04LX is documented by Hokuyo; UTM-30LX and
UST-10LX come from third-party code; UST-20LX takes the UST geometry (an assumption), DMIN 20
and DMAX 60000 (unverified: no PP capture is available).
"""

from __future__ import annotations

from dataclasses import dataclass

from lidar_drivers.scip import SensorParams


@dataclass(frozen=True, kw_only=True)
class HokuyoModel(SensorParams):
    """One model: its ``PP`` reply (the :class:`SensorParams` fields, ``model`` the MODL string) and
    what the fake needs besides.

    ``name`` is the config's model key; ``link`` how the real device connects (``serial`` USB CDC,
    ``tcp`` Ethernet); ``no_return`` the code it sends for a beam with nothing in reach (below
    DMIN, so an error code).
    """

    name: str
    link: str
    firmware: str
    no_return: int = 1


MODELS: dict[str, HokuyoModel] = {
    m.name: m
    for m in (
        HokuyoModel("URG-04LX-UG01(Simple-URG)", 20, 5600, 1024, 44, 725, 384, 600,
                    name="urg-04lx", link="serial", firmware="3.4.03"),
        HokuyoModel("UST-10LX", 20, 30000, 1440, 0, 1080, 540, 2400,
                    name="ust-10lx", link="tcp", firmware="4.0.3"),
        HokuyoModel("UST-20LX", 20, 60000, 1440, 0, 1080, 540, 2400,
                    name="ust-20lx", link="tcp", firmware="4.0.3"),
        HokuyoModel("UTM-30LX", 23, 60000, 1440, 0, 1080, 540, 2400,
                    name="utm-30lx", link="tcp", firmware="1.1.6"),
    )
}


def get_model(name: str) -> HokuyoModel:
    """The model named ``name`` (case-insensitive); KeyError naming the known models."""
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise KeyError(f"unknown Hokuyo model {name!r}; known: {', '.join(MODELS)}") from None
