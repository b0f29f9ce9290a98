"""Where the shipped data files (the repository's ``config/``) are, installed or not."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def config_dir() -> Path:
    """The directory holding the shipped configs, scenarios, maps, systemd unit and udev rules."""
    return Path(str(resources.files("racecar_hw.shipped")))


def config_file(*parts: str) -> Path:
    """A shipped data file, e.g. ``config_file("scenarios", "figure8.yaml")``."""
    return config_dir().joinpath(*parts)
