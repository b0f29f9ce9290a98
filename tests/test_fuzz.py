"""Every parser under the fuzz harness (tests/fuzzing.py), a few thousand frames each.

benchmarks/fuzz.py runs the same targets for 10^6 frames each; docs/fuzz.md has its table. Here:
nothing escapes but the documented error; valid frames after damage come out wherever the
protocol can deliver them; a checksum strong enough to promise it lets no invented frame through.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from fuzzing import MUTATIONS, Target, fuzz_bags, run, wire_targets
from hypothesis import example, given, settings
from hypothesis import strategies as st
from inbox_model import ESTOP, NAV, RELEASE, TELEOP, make_inbox

from racecar_hw.base.messages import AckermannDrive, Bool
from racecar_hw.base.messages import AckermannDriveStamped as _Cmd

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

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


# --- the network inbox's hand-over (racecar_hw/net/inbox.py) ---------------------------------------
#
# Hypothesis plays random interleavings of several receiving threads (surfaces ``a``, ``b``, ``c``)
# offering commands and e-stop messages, the clock moving and the event loop running, on the
# stepped loop of tests/inbox_model.py. Whatever the interleaving: no e-stop is lost (each one is
# handed over, or merged into an identical one from the same surface with nothing handed over in
# between), each goes at the loop's next run and before any command of its drain, e-stop messages
# keep their order, no input is handed over twice within a period, every command handed over is its
# input's newest, and the car is never less stopped than if every message had been applied.

_TOPICS = (ESTOP, RELEASE, NAV, TELEOP)
_OP = st.one_of(
    st.tuples(st.just("offer"), st.sampled_from("abc"), st.sampled_from(_TOPICS), st.booleans()),
    st.tuples(st.just("advance"), st.integers(0, 30)),
    st.tuples(st.just("run")),
)


def _latched(messages: list[tuple[str, bool]]) -> bool:
    """The mux's e-stop after ``messages`` (topic, data): true latches; a release needs the e-stop
    topic's last word to be false."""
    latched = asserted = False
    for topic, data in messages:
        if topic == ESTOP:
            asserted = data
            latched = latched or data
        elif data and not asserted:
            latched = False
    return latched


@given(st.lists(_OP, max_size=300))
@example(ops=[("offer", "a", "/estop", True), ("offer", "b", "/estop", True), ("offer", "a", "/estop", True)])
@settings(max_examples=400, deadline=None)
def test_the_inbox_hand_over_never_loses_an_estop(ops) -> None:
    inbox, loop, clock, rec = make_inbox(period_s=0.02)
    offers: list[tuple[int, str, str, Bool | _Cmd, int]] = []  # (index, origin, topic, msg, run index)
    runs = 0
    handed_at: dict[int, tuple[int, int]] = {}  # id(msg) -> (run index, clock ns)
    latest: dict[str, object] = {}

    def run_loop() -> None:
        nonlocal runs
        runs += 1
        before = len(rec.items)
        loop.run()
        for item in rec.items[before:]:
            handed_at[id(item[2])] = (runs, clock.ns)
            if item[0] == "cmd":
                assert item[2] is latest[item[1]]  # the newest of its input
        drained = rec.items[before:]
        for drain in {d for *_, d in drained}:
            kinds = [k for k, *_, d in drained if d == drain]
            assert kinds == sorted(kinds, key=lambda k: k != "estop")  # e-stops first

    for op in ops:
        if op[0] == "offer":
            _, origin, topic, value = op
            msg = Bool(value) if topic in (ESTOP, RELEASE) else _Cmd(drive=AckermannDrive(speed=float(value)))
            offers.append((len(offers), origin, topic, msg, runs))
            latest[topic] = msg
            inbox.offer(origin, topic, msg)
        elif op[0] == "advance":
            clock.ns += op[1] * 1_000_000
        else:
            run_loop()
    for _ in range(3):  # everything left goes within a period
        clock.ns += 25_000_000
        run_loop()

    stops = [o for o in offers if o[2] in (ESTOP, RELEASE)]
    handed = [o for o in stops if id(o[3]) in handed_at]
    # order kept: the e-stop messages handed over are a subsequence of those offered, in order
    got = [id(item[2]) for item in rec.items if item[0] == "estop"]
    assert got == [id(o[3]) for o in handed]
    for i, (k, origin, topic, msg, at_run) in enumerate(stops):
        if topic != ESTOP or not msg.data:
            continue
        if id(msg) in handed_at:
            assert handed_at[id(msg)][0] == at_run + 1  # at the loop's next run
            continue
        # merged: an e-stop from the same surface went at that run, with only e-stops (engaging
        # messages, from any surface) between the two: nothing that could release in between
        earlier = [o for o in stops[:i] if id(o[3]) in handed_at]
        assert earlier, f"e-stop {k} lost"
        run_of_stops = []
        for o in reversed(earlier):
            if not (o[2] == ESTOP and o[3].data):
                break
            run_of_stops.append(o)
        target = next((o for o in run_of_stops if o[1] == origin), None)
        assert target is not None, f"e-stop {k} lost"
        assert handed_at[id(target[3])][0] == at_run + 1
    # never less stopped than the messages say
    if _latched([(o[2], o[3].data) for o in stops]):
        assert _latched([(o[2], o[3].data) for o in handed])
    # one hand-over per input per period, and the newest of each input got through in the end
    for topic in (NAV, TELEOP):
        times = [handed_at[id(item[2])][1] for item in rec.items if item[1] == topic]
        assert all(b - a >= 20_000_000 for a, b in itertools.pairwise(times))
        if topic in latest:
            assert id(latest[topic]) in handed_at
