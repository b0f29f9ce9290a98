"""The size of the car's install: ``pip install .`` (no extras) into a fresh virtual environment.

Two fresh venvs in a temporary directory, one bare and one with this checkout installed as a car
installs it (no extras, not editable); the size is ``du`` of the second's site-packages minus the
first's (pip and setuptools), in MB (2^20 bytes). Each distribution's size is the sum of the files
its RECORD lists. The extras (docs/install.md, "Extras") are not installed: whatever pulls them in
by accident shows here. pip's cache and index are whatever this machine's pip uses.

Run ``python benchmarks/bench_install.py [EXTRAS]`` (``EXTRAS``: e.g. ``foxglove`` to size the car
with the live view). Not in run_all.py: it takes minutes and needs the package index (or pip's
cache).
"""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
import tempfile
import venv
from pathlib import Path

from table import print_rows

ROOT = Path(__file__).resolve().parents[1]
SIZE_TARGET = 200.0  # MB, the car install (issue 26)


def _site_packages(env: Path) -> Path:
    (found,) = env.glob("lib/python3*/site-packages")
    return found


def _du_mb(path: Path) -> float:
    out = subprocess.run(["du", "-sk", str(path)], capture_output=True, text=True, check=True).stdout
    return int(out.split()[0]) / 1024.0


def distributions(site: Path) -> list[tuple[str, float]]:
    """(name version, MB) of every distribution installed in ``site``, largest first."""
    rows = []
    for dist in importlib.metadata.distributions(path=[str(site)]):
        size = sum((site / f).stat().st_size for f in dist.files or () if (site / f).is_file())
        rows.append((f"{dist.metadata['Name']} {dist.version}", size / 2**20))
    return sorted(rows, key=lambda r: -r[1])


def run(extras: str = "") -> list[dict]:
    target = f"{ROOT}[{extras}]" if extras else str(ROOT)
    with tempfile.TemporaryDirectory() as tmp:
        bare, car = Path(tmp) / "bare", Path(tmp) / "car"
        for env in (bare, car):
            venv.create(env, with_pip=True)
        subprocess.run([str(car / "bin" / "python"), "-m", "pip", "install", "-q", target], check=True)
        base = _du_mb(_site_packages(bare))
        size = _du_mb(_site_packages(car)) - base
        bare_names = {n for n, _ in distributions(_site_packages(bare))}
        dists = [(n, mb) for n, mb in distributions(_site_packages(car)) if n not in bare_names]
    label = f"racecar-hw[{extras}]" if extras else "racecar-hw"
    rows = [{"name": f"pip install {label}: site-packages minus a bare venv's ({base:.0f} MB)",
             "value": size, "unit": "MB", "target": SIZE_TARGET if not extras else None},
            {"name": "  distributions", "value": len(dists), "unit": "", "target": None}]
    rows += [{"name": f"  {name}", "value": mb, "unit": "MB", "target": None}
             for name, mb in dists if mb >= 0.5]
    return rows


if __name__ == "__main__":
    print_rows(run(sys.argv[1] if len(sys.argv) > 1 else ""))
