"""The optional parts of racecar-hw (pip extras) and the one-line error when one is missing.

A car installs ``racecar-hw`` alone: what its shipped configuration (``config/car.yaml``) runs. The
simulator's plots and maps (``[sim]``: matplotlib, Pillow) and the MAVLink ground-station link
(``[mavlink]``: pymavlink) are extras, imported only where their feature is switched on
(docs/install.md, "Extras"). Switching one on without its extra is refused before anything runs,
with one line naming the pip command, as an unknown key is: no traceback.

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
    "sim": Extra("sim", (("matplotlib", "matplotlib"), ("Pillow", "PIL"))),
    "mavlink": Extra("mavlink", (("pymavlink", "pymavlink"),)),
}


class MissingExtra(ConfigError):
    """A feature is switched on whose extra is not installed; the message names the pip command."""


def require_extra(name: str, feature: str, key: str = "") -> None:
    """Raise :class:`MissingExtra` unless extra ``name`` is installed.

    ``feature`` says what needs it ("the MAVLink ground-station link"); ``key`` is the config key
    that switched it on (``mavlink.enabled``), empty for a command.
    """
    extra = EXTRAS[name]
    missing = extra.missing()
    if missing:
        raise MissingExtra(key, f"{feature} needs {' and '.join(missing)}, which the {name} extra "
                                f"installs: {extra.pip}")


__all__ = ["EXTRAS", "Extra", "MissingExtra", "require_extra"]
