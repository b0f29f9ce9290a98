"""Refuse to run when ``vesc``, ``lidar_drivers``, ``mux`` or ``safety`` is someone else's package.

racecar-hw ships five top-level packages. Their names are common: PyPI's ``safety`` (a
vulnerability scanner) installed into the same environment overwrites ``safety/__init__.py``, and a
``safety`` earlier on ``sys.path`` shadows ours. Either way ``import safety`` would no longer load the
safety stop, so every ``racecar-hw`` command checks first, without importing the suspect package
(its code is not run):

* the package must be found where racecar-hw's own ``racecar_hw`` package lives (the same
  site-packages directory, or the same source tree in an editable install);
* where the installed distribution's RECORD lists a hash for its ``__init__.py``, the file must
  still have that hash (another distribution did not overwrite it in place).

The RECORD is read straight from the ``racecar_hw-*.dist-info`` beside our packages (where a wheel
puts it) rather than through :mod:`importlib.metadata`, whose import alone takes about 50 ms of
every command's start; that module is imported only to name the owner of a foreign package.
"""

from __future__ import annotations

import base64
import csv
import hashlib
import importlib.util
from dataclasses import dataclass
from pathlib import Path

#: Our top-level packages besides ``racecar_hw`` itself.
OWN_PACKAGES: tuple[str, ...] = ("vesc", "lidar_drivers", "mux", "safety")
DISTRIBUTION = "racecar-hw"


@dataclass(frozen=True)
class ForeignPackage:
    """A top-level package name of ours that Python would load from elsewhere, or not at all."""

    name: str
    #: The file Python would import (``None``: not found at all).
    found: Path | None
    #: Where racecar-hw's own package is.
    expected: Path
    #: The distribution that owns :attr:`found`, when one claims it (``"safety 3.2.4"``).
    owner: str | None

    def message(self) -> str:
        """One paragraph for the user: which package, where it was loaded from, and the fix."""
        if self.found is None:
            return (f"racecar-hw's package '{self.name}' is missing (expected at {self.expected}); "
                    f"reinstall racecar-hw: pip install --force-reinstall --no-deps racecar-hw")
        owner = f" (installed by the distribution {self.owner})" if self.owner else ""
        if self.owner:
            dist = self.owner.split()[0]
            fix = (f"pip uninstall {dist}, then pip install --force-reinstall --no-deps racecar-hw, "
                   f"or install racecar-hw in a virtual environment of its own")
        else:
            fix = (f"remove that '{self.name}' from the Python path, or install racecar-hw in a "
                   f"virtual environment of its own")
        if self.found == self.expected.resolve():
            where = (f"{self.found}{owner} was overwritten: it no longer has the content racecar-hw "
                     f"installed")
        else:
            where = f"Python loads it from {self.found}{owner}, while racecar-hw's is at {self.expected}"
        return (f"the package '{self.name}' is not racecar-hw's: {where}. Refusing to start a car with "
                f"part of its software replaced. Fix: {fix}.")


def find_foreign_packages(packages: tuple[str, ...] = OWN_PACKAGES) -> list[ForeignPackage]:
    """Every package of ``packages`` that is not racecar-hw's own; empty when all are ours."""
    home = Path(__file__).resolve().parents[2]  # the directory that holds racecar_hw/
    recorded = _recorded_hashes(home)
    foreign = []
    for name in packages:
        expected = home / name / "__init__.py"
        found = _origin(name)
        if found is None:
            foreign.append(ForeignPackage(name, None, expected, None))
        elif found != expected.resolve() or not _hash_matches(found, recorded.get(f"{name}/__init__.py")):
            foreign.append(ForeignPackage(name, found, expected, _owner_of(found)))
    return foreign


def _origin(name: str) -> Path | None:
    """The file ``import name`` would run, found without running it."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or spec.origin in ("built-in", "frozen", "namespace"):
        return None
    return Path(spec.origin).resolve()


def _recorded_hashes(home: Path) -> dict[str, str]:
    """``path -> "sha256=..."`` from the RECORD of the one racecar-hw wheel installed in ``home``.

    Empty for an editable install or a source tree (no dist-info beside the packages; an editable
    install's RECORD lists only its path hook), and when the RECORD cannot be read or is ambiguous
    (two racecar-hw dist-infos): the location check still applies.
    """
    records = list(home.glob("racecar_hw-*.dist-info/RECORD"))
    if len(records) != 1:
        return {}
    try:
        with records[0].open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error):
        return {}
    return {row[0]: row[1] for row in rows if len(row) >= 2 and "=" in row[1]}


def _hash_matches(path: Path, recorded: str | None) -> bool:
    if recorded is None:
        return True
    mode, _, value = recorded.partition("=")
    try:
        digest = hashlib.new(mode, path.read_bytes()).digest()
    except (OSError, ValueError):
        return False
    return base64.urlsafe_b64encode(digest).rstrip(b"=").decode() == value


def _owner_of(path: Path) -> str | None:
    """The installed distribution (other than ours) whose RECORD lists ``path``."""
    import importlib.metadata  # noqa: PLC0415 - only on the way to a refusal

    for dist in importlib.metadata.distributions():
        name = dist.metadata["Name"] or ""
        if name.lower() == DISTRIBUTION:
            continue
        for file in dist.files or []:
            if file.name == path.name and Path(dist.locate_file(file)).resolve() == path:
                return f"{name} {dist.version}"
    return None
