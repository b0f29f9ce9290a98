"""Parameter sets of the Hokuyo models the FAKE lidar imitates (``PP``/``VV``/``II`` answers).

The driver never uses these: it reads every number from the device's ``PP`` reply. Values from
/work/shared/reference/lidars.md section 1.8: URG-04LX is documented by Hokuyo; UTM-30LX and
UST-10LX come from third-party code; UST-20LX takes the UST geometry (an assumption), DMIN 20
and DMAX 60000 (unverified: no PP capture is available). The UTM-30LX is a USB unit; its
Ethernet sibling, the UTM-30LX-EW, has the same scan geometry.

What the devices do besides (Hokuyo's SCIP 2.0 specification C-42-03320B): the URG-04LX has no
intensity commands (``ME``/``GE`` are undefined commands to it), its steps outside AMIN..AMAX
(0-43 and 726-768 of its 769) read error code 19, "non-measurable step"; the classic URG-04LX
boots speaking SCIP 1.1 and answers ``E`` to a SCIP 2.0 command until told ``SCIP2.0``.
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
    DMIN, so an error code); ``last_step`` the last step a scan command may ask for (steps outside
    AMIN..AMAX read ``unmeasurable``); ``intensities`` whether ``ME``/``GE`` exist.
    """

    name: str
    link: str
    firmware: str
    no_return: int = 1
    last_step: int | None = None  # None: AMAX
    unmeasurable: int = 19
    intensities: bool = True

    @property
    def max_step(self) -> int:
        """The last step a scan command may ask for."""
        return self.amax if self.last_step is None else self.last_step


MODELS: dict[str, HokuyoModel] = {
    m.name: m
    for m in (
        HokuyoModel("URG-04LX-UG01(Simple-URG)", 20, 5600, 1024, 44, 725, 384, 600,
                    name="urg-04lx", link="serial", firmware="3.4.03", last_step=768,
                    intensities=False),
        HokuyoModel("UST-10LX", 20, 30000, 1440, 0, 1080, 540, 2400,
                    name="ust-10lx", link="tcp", firmware="4.0.3"),
        HokuyoModel("UST-20LX", 20, 60000, 1440, 0, 1080, 540, 2400,
                    name="ust-20lx", link="tcp", firmware="4.0.3"),
        HokuyoModel("UTM-30LX", 23, 60000, 1440, 0, 1080, 540, 2400,
                    name="utm-30lx", link="serial", firmware="1.1.6"),
        HokuyoModel("UTM-30LX-EW", 23, 60000, 1440, 0, 1080, 540, 2400,
                    name="utm-30lx-ew", link="tcp", firmware="1.1.6"),
    )
}


def get_model(name: str) -> HokuyoModel:
    """The model named ``name`` (case-insensitive); KeyError naming the known models."""
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise KeyError(f"unknown Hokuyo model {name!r}; known: {', '.join(MODELS)}") from None
