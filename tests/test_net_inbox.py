"""The network inbox: latest value per input, one hand-over per input per period, e-stops first and
never lost, counts; on a loop the test steps (tests/inbox_model.py) and on a real asyncio loop fed
by real threads."""

from __future__ import annotations

import asyncio
import copy
import dataclasses
import math
import threading

import numpy as np
from inbox_model import ESTOP, NAV, RELEASE, TELEOP, make_inbox

from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Bool,
    DiagnosticArray,
    DiagnosticStatus,
    KeyValue,
    Odometry,
    Twist,
    Vector3,
)
from racecar_hw.net.inbox import Inbox, all_finite
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.refusals import Refusals

MS = 1_000_000


def _cmd(speed: float) -> AckermannDriveStamped:
    return AckermannDriveStamped(drive=AckermannDrive(speed=speed))


def test_a_quiet_input_is_handed_over_at_once_and_a_flood_once_per_period():
    inbox, loop, clock, rec = make_inbox(period_s=0.02)
    inbox.offer("zenoh", NAV, _cmd(0.1))
    assert loop.run() == 1 and [i[2].drive.speed for i in rec.items] == [0.1]  # no added latency
    # 1,000 messages within one period: none handed over before the period is up, then the latest
    for k in range(1000):
        clock.ns += 10_000
        inbox.offer("zenoh", NAV, _cmd(k / 1000))
        loop.run()
    assert len(rec.items) == 1
    clock.ns += 20 * MS
    loop.run()
    assert [i[2].drive.speed for i in rec.items] == [0.1, 0.999]
    c = inbox.counts()[NAV]
    assert (c.received, c.handed_over, c.superseded, c.refused) == (1001, 2, 999, 0)
    # the flood woke the loop a few times, not once per message
    assert inbox.wakeups <= 4


def test_inputs_are_coalesced_each_on_its_own():
    inbox, loop, clock, rec = make_inbox()
    for k in range(50):
        inbox.offer("zenoh", NAV, _cmd(k))
        inbox.offer("dds", TELEOP, _cmd(-k))
    loop.run()
    assert [(i[1], i[2].drive.speed, i[3]) for i in rec.items] == [(NAV, 49, "zenoh"), (TELEOP, -49, "dds")]


def test_an_estop_jumps_the_queue_within_the_period_and_before_commands():
    inbox, loop, clock, rec = make_inbox()
    inbox.offer("zenoh", NAV, _cmd(1.0))
    inbox.offer("zenoh", ESTOP, Bool(False))
    loop.run()
    assert len(rec.items) == 2
    clock.ns += 1 * MS
    inbox.offer("zenoh", NAV, _cmd(2.0))      # waits for the period
    inbox.offer("zenoh", RELEASE, Bool(True))  # so does a release (it cannot stop the car)
    loop.run()
    assert len(rec.items) == 2
    clock.ns += 1 * MS
    inbox.offer("dds", ESTOP, Bool(True))      # goes now, with the release queued before it, in order
    loop.run()
    assert [(i[0], i[1]) for i in rec.items[2:]] == [("estop", RELEASE), ("estop", ESTOP)]
    clock.ns += 20 * MS
    inbox.offer("dds", ESTOP, Bool(True))
    inbox.offer("zenoh", TELEOP, _cmd(3.0))
    loop.run()
    kinds = [i[0] for i in rec.items[4:]]
    assert kinds.index("estop") < kinds.index("cmd")  # in one drain: the e-stop first


def test_stops_keep_their_order_and_only_what_cannot_engage_is_dropped():
    inbox, loop, clock, rec = make_inbox()
    inbox.offer("zenoh", ESTOP, Bool(False))
    loop.run()
    clock.ns += 1 * MS
    sent = [(ESTOP, False), (ESTOP, False), (RELEASE, True), (ESTOP, True), (ESTOP, True),
            (ESTOP, False), (RELEASE, True), (RELEASE, True)]
    for topic, value in sent:
        inbox.offer("zenoh", topic, Bool(value))
    clock.ns += 20 * MS
    loop.run()
    got = [(i[1], i[2].data) for i in rec.items[1:]]
    # the repeated false, the second identical e-stop and the repeated release are merged
    assert got == [(ESTOP, False), (RELEASE, True), (ESTOP, True), (ESTOP, False), (RELEASE, True)]
    counts = inbox.counts()
    assert counts[ESTOP].superseded == 2 and counts[RELEASE].superseded == 1


def test_a_flood_of_releases_cannot_push_an_estop_out():
    inbox, loop, clock, rec = make_inbox()
    inbox.offer("zenoh", ESTOP, Bool(False))
    loop.run()
    inbox.offer("a", ESTOP, Bool(True))
    for _ in range(500):  # the loop does not run: the FIFO fills with releases and falses
        inbox.offer("b", RELEASE, Bool(True))
        inbox.offer("b", ESTOP, Bool(False))
    loop.run()
    got = [(i[1], i[2].data) for i in rec.items[1:]]
    assert got[0] == (ESTOP, True) and len(got) <= 32


def test_malformed_and_non_finite_messages_are_refused_and_counted():
    refusals = Refusals()
    inbox, loop, clock, rec = make_inbox()
    inbox.refusals = refusals
    types = ros2_types()
    good = types.serialize(_cmd(0.5))
    assert inbox.offer_cdr("zenoh", NAV, AckermannDriveStamped, good[:7]) == "malformed"
    nan = types.serialize(_cmd(math.nan))
    assert inbox.offer_cdr("zenoh", NAV, AckermannDriveStamped, nan) == "non-finite"
    assert inbox.offer("zenoh", ESTOP, Bool(True)) is None
    inbox.refuse("zenoh", NAV, "no attachment")
    assert inbox.offer_cdr("zenoh", NAV, AckermannDriveStamped, good) is None
    loop.run()
    assert [i[1] for i in rec.items] == [ESTOP, NAV]
    c = inbox.counts()[NAV]
    assert (c.received, c.refused) == (1, 3)
    assert c.reasons == {"malformed": 1, "non-finite": 1, "no attachment": 1}
    assert refusals.counts() == {("zenoh", "malformed"): 1, ("zenoh", "no attachment"): 1,
                                 ("zenoh", "non-finite"): 1}
    status = inbox.diagnostics()
    assert status.level == DiagnosticStatus.WARN and status.name == "racecar_hw: network inbox"
    values = {kv.key: kv.value for kv in status.values}
    assert values[NAV].startswith("received 1, superseded 0, refused 3, handed over 1")
    assert status.message == "2 received, 0 superseded, 3 refused"


def test_a_flood_is_noted_in_the_refusals_a_line_per_interval():
    refusals = Refusals()
    inbox, loop, clock, rec = make_inbox()
    inbox.refusals = refusals
    for k in range(1000):
        inbox.offer("zenoh", NAV, _cmd(k))
    inbox.flush_floods()
    assert refusals.total("zenoh") == 999


def test_a_client_at_the_tick_rate_is_not_called_a_flood_however_long_it_runs():
    """A 50 Hz client whose messages sometimes meet in one period (jitter: one in twenty here) was
    logged as a flood after 10-20 s, superseded messages being counted over all time. A flood is
    FLOOD_NOTE superseded within FLOOD_WINDOW_NS; a real one is still noted."""
    refusals = Refusals()
    inbox, loop, clock, rec = make_inbox(period_s=0.02)
    inbox.refusals = refusals
    for k in range(3000):  # a minute at 50 Hz
        clock.ns += 1 * MS if k % 20 == 1 else 20 * MS  # every twentieth right after the one before
        inbox.offer("dds", NAV, _cmd(0.5))
        loop.run()
    inbox.flush_floods()
    assert inbox.counts()[NAV].superseded >= 100  # what the old count called a flood
    assert refusals.total("dds") == 0
    for _ in range(300):  # then 300 within a period
        clock.ns += 10_000
        inbox.offer("dds", NAV, _cmd(0.5))
        loop.run()
    inbox.flush_floods()
    assert refusals.total("dds") >= 299


def test_nothing_is_handed_over_after_close():
    inbox, loop, clock, rec = make_inbox()
    inbox.offer("zenoh", NAV, _cmd(1.0))
    inbox.close()
    inbox.offer("zenoh", ESTOP, Bool(True))
    loop.run()
    assert rec.items == []


def test_real_threads_flooding_a_real_loop_never_lose_an_estop():
    """Four threads flood commands and e-stop noise into a running asyncio loop while a fifth sends
    e-stops: every e-stop is handed over, before the commands of its drain, and the loop is woken
    far less often than once per message."""
    got: list[tuple[str, str, object]] = []

    async def run() -> Inbox:
        inbox = Inbox([NAV, TELEOP], lambda t, m, o: got.append(("cmd", t, m)), period_s=0.02,
                      estop_topic=ESTOP, release_topic=RELEASE,
                      on_estop=lambda t, m, o: got.append(("estop", t, m)))
        inbox.bind(asyncio.get_running_loop())
        stop = threading.Event()

        def flood(topic: str) -> None:
            k = 0
            while not stop.is_set():
                k += 1
                inbox.offer("zenoh", topic, _cmd(k))
                if k % 50 == 0:
                    inbox.offer("zenoh", RELEASE, Bool(True))
                    inbox.offer("zenoh", ESTOP, Bool(False))

        estops = [Bool(True) for _ in range(20)]

        def stopper() -> None:
            for msg in estops:
                inbox.offer("dds", ESTOP, msg)
                stop.wait(0.01)

        threads = [threading.Thread(target=flood, args=(t,)) for t in (NAV, TELEOP, NAV, TELEOP)]
        threads.append(threading.Thread(target=stopper))
        for t in threads:
            t.start()
        await asyncio.to_thread(threads[-1].join)
        stop.set()
        for t in threads[:-1]:
            await asyncio.to_thread(t.join)
        await asyncio.sleep(0.1)  # the last timer hands over what is left
        inbox.close()
        handed = {id(m) for kind, _, m in got if kind == "estop"}
        # an e-stop may be merged only into an identical one from the same surface just before it
        lost = [i for i, m in enumerate(estops) if id(m) not in handed
                and not (i and id(estops[i - 1]) in handed)]
        assert not lost, lost
        return inbox

    inbox = asyncio.run(run())
    c = inbox.counts()
    received = c[NAV].received + c[TELEOP].received
    assert received > 1000
    assert c[NAV].handed_over + c[NAV].superseded == c[NAV].received
    assert inbox.wakeups < received / 5


def _float_paths(msg: object, path: tuple = ()) -> list[tuple]:
    """Every float field's path in a message (attribute names, list indices)."""
    if isinstance(msg, float):
        return [path]
    if isinstance(msg, list):
        return [p for i, item in enumerate(msg) for p in _float_paths(item, (*path, i))]
    if dataclasses.is_dataclass(msg):
        return [p for f in dataclasses.fields(msg)
                for p in _float_paths(getattr(msg, f.name), (*path, f.name))]
    return []


def _with(msg: object, path: tuple, value: float) -> object:
    out = copy.deepcopy(msg)
    target = out
    for step in path[:-1]:
        target = target[step] if isinstance(step, int) else getattr(target, step)
    if isinstance(path[-1], int):
        target[path[-1]] = value
    else:
        setattr(target, path[-1], value)
    return out


def test_the_finiteness_check_finds_a_nan_or_inf_in_any_float_field_first_time_and_after() -> None:
    """all_finite keeps each class's field names after its first message: the answer is the same
    for every float field of nested messages and lists, before and after the class is known."""
    samples = [AckermannDriveStamped(drive=AckermannDrive(0.5, 0.1, 1.0)), Twist(Vector3(1.0, 0.0, 0.0)),
               Odometry(), DiagnosticArray(status=[DiagnosticStatus(0, "a", "b", "", [KeyValue("k", "v")])])]
    for msg in samples:
        paths = _float_paths(msg)
        assert all_finite(msg) and all_finite(msg)  # the class unknown, then known
        for path in paths:
            for bad in (math.nan, math.inf, -math.inf):
                assert not all_finite(_with(msg, path, bad)), (type(msg).__name__, path, bad)
            assert not all_finite(_with(msg, path, np.float64("nan")))  # a float subclass
    assert _float_paths(samples[0]) and _float_paths(samples[2])
    odom = Odometry()
    odom.pose.covariance = np.array(odom.pose.covariance, dtype=np.float64)
    assert all_finite(odom)
    odom.pose.covariance[7] = math.nan
    assert not all_finite(odom)  # a float array inside a known class
