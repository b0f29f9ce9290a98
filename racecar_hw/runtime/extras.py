"""The optional parts of racecar-hw (pip extras) and the one-line error when one is missing.

A car installs ``racecar-hw`` alone: what its shipped configuration (``config/car.yaml``) runs. The
Foxglove live view (``[foxglove]``: foxglove-sdk, cryptography), the simulator's plots and maps
(``[sim]``: matplotlib, Pillow, and the live view) and the MAVLink ground-station link
(``[mavlink]``: pymavlink) are extras, imported only where their feature is switched on
(docs/install.md, "Extras"). A command or a feature that is off by default (``racecar-hw sim``,
``mavlink.enabled``) is refused without its extra before anything runs, with one line naming the
pip command, as an unknown key is: no traceback. The live view, on by default, is left off with
one warning line instead, as the DDS interface is without cyclonedds: a car whose configuration
predates the extra still drives.

The check looks the modules up without importing them (:func:`importlib.util.find_spec`), so it
costs nothing when the extra is there.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

from racecar_hw.base.errors import ConfigError


@dataclass(frozen=True)
class Extra:
    """One pip extra: the distributions it installs, each with the module it is imported as."""

    name: str
    #: (distribution, top-level module) of each
    modules: tuple[tuple[str, str], ...]

    def missing(self) -> list[str]:
        """The distributions of this extra whose module is not installed."""
        return [dist for dist, module in self.modules if importlib.util.find_spec(module) is None]

    @property
    def pip(self) -> str:
        """The command that installs it."""
        return f"pip install 'racecar-hw[{self.name}]'"


#: Every extra a feature of the program needs (``[test]`` is for the test suite only).
EXTRAS: dict[str, Extra] = {
    "foxglove": Extra("foxglove", (("foxglove-sdk", "foxglove"), ("cryptography", "cryptography"))),
    # MCAP bags (the recorder's default format, off in the car's config), with zstandard and lz4
    "mcap": Extra("mcap", (("mcap", "mcap"),)),
    # the simulator shows its run in the Foxglove live view and records MCAP (--record)
    "sim": Extra("sim", (("matplotlib", "matplotlib"), ("Pillow", "PIL"), ("foxglove-sdk", "foxglove"),
                         ("cryptography", "cryptography"), ("mcap", "mcap"))),
    "mavlink": Extra("mavlink", (("pymavlink", "pymavlink"),)),
}


class MissingExtra(ConfigError):
    """A feature is switched on whose extra is not installed; the message names the pip command."""


def missing_extra(name: str, feature: str) -> str | None:
    """None when extra ``name`` is installed; else what is missing, and the pip command, in words.

    ``feature`` says what needs it ("the MAVLink ground-station link").
    """
    extra = EXTRAS[name]
    missing = extra.missing()
    if not missing:
        return None
    names = missing[0] if len(missing) == 1 else f"{', '.join(missing[:-1])} and {missing[-1]}"
    return f"{feature} needs {names}, which the {name} extra installs: {extra.pip}"


def require_extra(name: str, feature: str, key: str = "") -> None:
    """Raise :class:`MissingExtra` unless extra ``name`` is installed.

    ``feature`` says what needs it; ``key`` is the config key that switched it on
    (``mavlink.enabled``), empty for a command.
    """
    message = missing_extra(name, feature)
    if message is not None:
        raise MissingExtra(key, message)


__all__ = ["EXTRAS", "Extra", "MissingExtra", "missing_extra", "require_extra"]
