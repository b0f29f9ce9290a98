"""Every parser under the fuzz harness for many frames: ``python benchmarks/fuzz.py``.

The harness and its targets are tests/fuzzing.py (tests/test_fuzz.py runs them for a few thousand
frames in CI). By default each wire parser gets 10^6 frames and bag loading 10^5 damaged bags
(about 250 a second: 10^6 would take over an hour; ``--bag-frames`` sets it). The table: frames,
escaped exceptions, recovery rate (valid frames after damage that came out, of those the protocol
can deliver), invented (decoded keys no frame had: frames, or samples for the RPLIDAR streams; for
bags, loads that returned a command out of limits) and throughput. Results: docs/fuzz.md.

``run()`` (for run_all.py) is a shorter pass: 10^5 frames per parser, 3,000 bags.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

import fuzzing  # noqa: E402
from fuzzing import FuzzResult, format_table, fuzz_bags, wire_targets  # noqa: E402
from table import print_rows  # noqa: E402

#: Recovery each protocol should reach (tests/test_fuzz.py asserts the same).
RECOVERY_TARGET = {
    "VESC replies": 1.0, "VESC requests": 1.0, "SCIP replies": 0.99, "SCIP commands": 1.0,
    "RPLIDAR responses": 0.9, "RPLIDAR nodes": 0.9, "RPLIDAR capsules": 0.99, "RPLIDAR requests": 0.99,
    "MAVLink inbound": 1.0, "MAVLink inbound, signed": 1.0,
}


def results(frames: int, bag_frames: int, names: list[str] | None = None, seed: int = 2024,
            progress: bool = False) -> list[FuzzResult]:
    """Fuzz the wire parsers (``frames`` each) and bag loading (``bag_frames``)."""
    out = []
    for target in wire_targets():
        if names and target.name not in names:
            continue
        out.append(fuzzing.run(target, frames, seed))
        if progress:
            print(format_table([out[-1].row()]).splitlines()[1], file=sys.stderr, flush=True)
    if bag_frames and (not names or "bag loading" in names):
        with tempfile.TemporaryDirectory(prefix="racecar-hw-fuzz-") as tmp:
            bags = fuzz_bags(Path(tmp), bag_frames, seed)
        out.append(bags.result)
        if progress:
            print(format_table([bags.result.row()]).splitlines()[1], f"(loaded {bags.loaded}, refused "
                  f"{bags.refused}, absurd {bags.absurd})", file=sys.stderr, flush=True)
    return out


def run(frames: int = 100_000, bag_frames: int = 3_000) -> list[dict]:
    """Rows for run_all.py: escaped (target 0), recovery and throughput per parser."""
    rows: list[dict] = []
    for r in results(frames, bag_frames):
        rows.append({"name": f"fuzz {r.parser}: escaped", "value": sum(r.escaped.values()), "unit": "",
                     "target": 0})
        if r.recoverable:
            rows.append({"name": f"fuzz {r.parser}: recovery", "value": r.recovery_rate, "unit": "",
                         "target": RECOVERY_TARGET.get(r.parser), "higher_is_better": True})
        rows.append({"name": f"fuzz {r.parser}: throughput", "value": r.throughput, "unit": "frames/s",
                     "target": None})
    return rows


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="parsers to run (default: all), e.g. 'VESC replies'")
    parser.add_argument("--frames", type=int, default=1_000_000, help="frames per wire parser")
    parser.add_argument("--bag-frames", type=int, default=100_000, help="damaged bags to load")
    parser.add_argument("--seed", type=int, default=2024)
    args = parser.parse_args(argv)
    found = results(args.frames, args.bag_frames, args.names or None, args.seed, progress=True)
    print(format_table([r.row() for r in found]))
    for r in found:
        if r.invented_kinds:
            kinds = ", ".join(f"{kind} {n}" for kind, n in r.invented_kinds.most_common())
            print(f"invented, {r.parser}: {kinds}")
    for r in found:
        if r.escaped:
            print(f"\n{r.parser}: {dict(r.escaped)}\n{r.examples[0]}")
    if found and not any(r.escaped for r in found):
        print_rows([{"name": "escaped exceptions, all parsers", "value": 0, "unit": "", "target": 0}])
    return 1 if any(r.escaped for r in found) else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
