"""Every parser under the fuzz harness (tests/fuzzing.py), a few thousand frames each.

benchmarks/fuzz.py runs the same targets for 10^6 frames each; docs/fuzz.md has its table. Here:
nothing escapes but the documented error; valid frames after damage come out wherever the
protocol can deliver them; a checksum strong enough to promise it lets no invented frame through.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from fuzzing import MUTATIONS, Target, fuzz_bags, run, wire_targets

FRAMES = 4000

#: The recovery each protocol allows, measured with the seeds below and rounded down (docs/fuzz.md
#: explains the ones under 1: descriptor-framed RPLIDAR answers and check-bit-only nodes can be
#: swallowed or mistaken by damage before them; a SCIP tag can absorb garbage glued to its echo).
RECOVERY = {
    "VESC replies": 1.0, "VESC requests": 1.0, "SCIP replies": 0.99, "SCIP commands": 1.0,
    "RPLIDAR responses": 0.9, "RPLIDAR nodes": 0.9, "RPLIDAR capsules": 0.99, "RPLIDAR requests": 0.99,
    "MAVLink inbound": 1.0, "MAVLink inbound, signed": 1.0,
}
#: Parsers whose check lets no damaged frame through here: a CRC-16 (and SHA-256 when signed).
#: (Unsigned MAVLink lets about 3 in 10^6 through at length, by CRC_EXTRA: docs/fuzz.md.)
NO_INVENTION = {"VESC replies", "VESC requests", "MAVLink inbound", "MAVLink inbound, signed"}


@pytest.mark.parametrize("target", wire_targets(), ids=lambda t: t.name)
def test_a_wire_parser_survives_damage_and_recovers_what_follows(target: Target) -> None:
    result = run(target, FRAMES, seed=16)
    assert not result.escaped, result.examples[0]
    assert result.recoverable > FRAMES // 10  # the mutations did damage frames before valid ones
    assert result.recovery_rate >= RECOVERY[target.name], result.row()
    if target.name in NO_INVENTION:
        assert result.invented == 0, result.row()


def test_damaged_scans_that_pass_the_scip_checksums_are_rare() -> None:
    """SCIP has a 6-bit checksum per line and none on the echo or on the number of lines: a reply
    cut at a line end (an info reply with fewer fields) or a damaged echo passes, and so do two bit
    flips in one line that change its sum by a multiple of 64. Scans with damaged data come out
    for under one frame in a thousand (the 10^6 run in docs/fuzz.md gives the rate)."""
    result = run(next(t for t in wire_targets() if t.name == "SCIP replies"), FRAMES, seed=16)
    assert not result.escaped
    assert result.invented_kinds["scan"] <= FRAMES / 1000, result.invented_kinds


def test_capsules_that_pass_their_xor_checksum_and_angle_check_are_rare() -> None:
    """Two bit flips in the same bit of an express capsule keep its XOR checksum: the distances
    can change. Under one sample in a thousand comes out invented."""
    result = run(next(t for t in wire_targets() if t.name == "RPLIDAR capsules"), FRAMES, seed=16)
    assert result.invented <= FRAMES * 32 / 1000


def test_the_harness_uses_every_mutation() -> None:
    assert MUTATIONS == ("random_bytes", "bit_flips", "truncation", "duplication", "garbage_between",
                         "split_points")


def test_damaged_bags_give_bag_error_or_sane_commands(tmp_path: Path) -> None:
    """ROS 1, MCAP and sqlite3 bags with random bytes, bit flips, truncations, duplicated ranges
    and inserted garbage: BagError or commands within the car's limits, nothing else."""
    fuzz = fuzz_bags(tmp_path, 450, seed=16)
    assert not fuzz.result.escaped, fuzz.result.examples[0]
    assert fuzz.absurd == 0
    assert fuzz.refused > 100 and fuzz.loaded > 10  # both outcomes were exercised
    assert set(fuzz.mutations) == {"random_bytes", "bit_flips", "truncation", "duplication",
                                   "garbage_between"}
    assert math.isnan(fuzz.result.recovery_rate)  # a bag has no frames to recover
    # MCAP chunks carry their CRC-32: no damaged MCAP bag loads with altered commands (before the
    # CRCs, 120 of these loads silently differed); sqlite3 has no checksum to catch a flipped bit
    assert not [key for key in fuzz.differed if key[0] == "mcap"], fuzz.differed
