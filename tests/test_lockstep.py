"""Lockstep: the virtual-time event loop, the in-memory device links, and the real drivers against
the fakes through them (the same codecs, the same bytes), on virtual time."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import pytest

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.params import LidarParams
from lidar_drivers.registry import make_driver, make_fake
from racecar_hw.base import clock
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import DeviceIOError, DeviceNotFound
from racecar_hw.base.link import open_link
from racecar_hw.base.memlink import MemoryLink, MemoryPort
from racecar_hw.base.messages import AckermannDrive, LaserScan
from racecar_hw.runtime import lockstep
from racecar_hw.runtime.lockstep import VirtualTimeLoop
from racecar_hw.runtime.ticker import PeriodicTimer
from vesc.codec import SetRpm, SetServoPosition
from vesc.driver import VescDriver
from vesc.fake import FakeVesc
from vesc.params import VescParams


async def until(predicate, limit_s: float = 30.0, step_s: float = 0.001) -> None:
    """Wait on virtual time until ``predicate()``; fails after ``limit_s`` virtual seconds."""
    end = clock.monotonic() + limit_s
    while not predicate():
        assert clock.monotonic() < end, "condition not met within the virtual time limit"
        await asyncio.sleep(step_s)


# --- the loop -----------------------------------------------------------------------------------


class TimeLimit(BaseException):
    """What a test's time limit raises in whatever runs (pytest-timeout raises pytest's own
    ``BaseException`` from its alarm signal)."""


@pytest.mark.parametrize("where", ["callback", "task"])
def test_a_time_limit_raised_inside_a_run_ends_it(where):
    """asyncio logs and goes on after a ``BaseException`` in a callback, and keeps one in a task
    until awaited: a run whose world or duration timer it ended would never end."""
    ticks: list[float] = []

    async def forever() -> None:  # a world stepping for ever
        while True:
            ticks.append(clock.monotonic())
            await asyncio.sleep(0.01)

    def limit() -> None:
        raise TimeLimit

    async def in_task() -> None:
        await asyncio.sleep(1.0)
        raise TimeLimit

    async def main() -> None:
        loop = asyncio.get_running_loop()
        if where == "callback":
            loop.call_later(1.0, limit)
        else:
            keep = asyncio.create_task(in_task())  # noqa: F841 (held: tasks are weakly referenced)
        await forever()

    with pytest.raises(TimeLimit):
        lockstep.run(main())
    assert 95 <= len(ticks) <= 102  # ended at 1 s of virtual time, not run on


def test_an_ordinary_error_in_a_callback_is_reported_and_the_run_goes_on(caplog):
    async def main() -> float:
        asyncio.get_running_loop().call_later(0.5, lambda: 1 / 0)
        await asyncio.sleep(2.0)
        return clock.monotonic()

    assert lockstep.run(main()) == pytest.approx(3.0)  # the epoch, 1 s, and 2 s run
    assert "ZeroDivisionError" in caplog.text


def test_virtual_time_runs_timers_in_order_without_waiting_and_switches_the_clock_back():
    fired: list[tuple[str, int]] = []

    async def main() -> tuple[int, int, bool]:
        loop = asyncio.get_running_loop()
        start = clock.monotonic_ns()
        for name, delay in (("c", 3600.0), ("a", 0.25), ("b", 1.5)):
            loop.call_later(delay, lambda n=name: fired.append((n, clock.monotonic_ns() - start)))
        await asyncio.sleep(7200)
        return start, clock.wall_ns(), clock.is_virtual()

    real = time.monotonic()
    start, wall, virtual = lockstep.run(main())
    assert time.monotonic() - real < 60  # two hours of sleeping took no real hours
    assert start == clock.SIM_EPOCH_NS and wall == start + 7200 * clock.NS_PER_S and virtual
    assert fired == [("a", 250_000_000), ("b", 1_500_000_000), ("c", 3_600_000_000_000)]
    assert not clock.is_virtual() and abs(clock.wall_ns() - time.time_ns()) < 10 * clock.NS_PER_S


def test_time_stands_still_while_a_thread_works_for_the_loop():
    async def main() -> tuple[int, float]:
        loop = asyncio.get_running_loop()
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                await asyncio.sleep(0.01)
                ticks += 1

        task = asyncio.create_task(ticker())
        before = clock.monotonic_ns()
        await loop.run_in_executor(None, time.sleep, 0.3)  # the ticker cannot run ahead meanwhile
        await asyncio.to_thread(time.sleep, 0.1)
        moved = clock.monotonic_ns() - before
        task.cancel()
        assert isinstance(loop, VirtualTimeLoop)
        return moved, loop.stood_still_s

    moved, stood = lockstep.run(main())
    assert moved == 0
    assert stood > 0.0


def test_a_busy_predicate_holds_time_until_it_clears_and_a_thread_can_hand_work_in():
    async def main() -> list[int]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, VirtualTimeLoop)
        queue = [1, 2, 3]
        remove = loop.add_busy(lambda: bool(queue))
        seen: list[int] = []

        def writer() -> None:  # a writer thread emptying its queue in real time
            while queue:
                time.sleep(0.02)
                loop.call_soon_threadsafe(seen.append, clock.monotonic_ns())
                queue.pop()

        thread = threading.Thread(target=writer)
        thread.start()
        start = clock.monotonic_ns()
        await asyncio.sleep(1.0)  # not before the queue is empty
        thread.join()
        remove()
        return [t - start for t in seen]

    assert lockstep.run(main()) == [0, 0, 0]


def test_as_fast_as_possible_a_busy_loop_still_hears_its_sockets():
    """At ``speed=None`` the loop asks the OS for events at most every EVENTS_EVERY_S of real time
    while it has work: a socket that turns readable while timers keep it busy is still read."""

    async def main() -> bytes:
        loop = asyncio.get_running_loop()
        here, there = socket.socketpair()
        here.setblocking(False)
        got = loop.create_future()
        loop.add_reader(here.fileno(), lambda: got.done() or got.set_result(here.recv(16)))
        ticks = 0

        def tick(_due: int, _periods: int) -> None:
            nonlocal ticks
            ticks += 1

        timer = PeriodicTimer(1000.0, tick)  # a callback every virtual ms: never idle for long
        timer.start()
        try:
            there.send(b"ping")
            return await asyncio.wait_for(got, timeout=3600.0)  # virtual s: an hour of 1 kHz ticks
        finally:
            timer.cancel()
            loop.remove_reader(here.fileno())
            here.close()
            there.close()

    assert lockstep.run(main()) == b"ping"


def test_paced_virtual_time_keeps_at_least_the_real_time_it_stands_for():
    async def main() -> int:
        start = clock.monotonic_ns()
        for _ in range(20):
            await asyncio.sleep(0.05)
        return clock.monotonic_ns() - start

    real = time.monotonic()
    assert lockstep.run(main(), speed=4.0) == 1_000_000_000
    assert time.monotonic() - real >= 1.0 / 4.0  # never faster than asked (slower if loaded)


def test_a_paced_run_held_up_goes_on_from_where_it_was_instead_of_racing():
    """Held up (a callback blocks, as a descheduled process would) for 0.15 s, more than twice
    RESYNC_BEHIND_S, a paced loop does not run the timers it owes back to back: virtual time loses
    the hold. Racing through it would show a 20 Hz stream from another thread with a gap of the
    hold and a period, 0.2 s: a mux input's timeout, and the car would brake."""
    hold_s = 0.15
    assert hold_s > 2 * lockstep.RESYNC_BEHIND_S

    async def main() -> tuple[float, float]:
        start_v, start_r = clock.monotonic(), time.monotonic()
        for i in range(20):
            await asyncio.sleep(0.02)
            if i == 5:
                time.sleep(hold_s)  # held up
        return clock.monotonic() - start_v, time.monotonic() - start_r

    virtual, real = lockstep.run(main(), speed=1.0)
    assert virtual == pytest.approx(0.4)
    # a loaded machine only adds to the real time; racing would have caught up with it
    assert real >= virtual + hold_s - lockstep.RESYNC_BEHIND_S


@pytest.mark.parametrize("speed", [0.0, -1.0, float("nan"), float("inf")])
def test_a_speed_must_be_positive_and_finite(speed):
    with pytest.raises(ValueError, match="speed"):
        VirtualTimeLoop(speed)


def test_one_virtual_clock_per_process():
    async def main() -> None:
        with clock.use_virtual_time(lambda: 0):
            pass

    with pytest.raises(RuntimeError, match="one per process"):
        lockstep.run(main())
    assert not clock.is_virtual()


# --- in-memory links ----------------------------------------------------------------------------


def test_a_memory_link_carries_bytes_both_ways_and_sees_an_unplug_as_a_lost_device():
    async def main() -> None:
        loop = asyncio.get_running_loop()
        link = open_link("mem://t/dev")
        assert isinstance(link, MemoryLink) and link.is_serial
        with pytest.raises(DeviceNotFound, match="mem://t/dev"):
            await link.open()
        port = MemoryPort("mem://t/dev").open()
        heard: list[bytes] = []
        port.watch(loop, lambda: heard.append(port.read()))
        assert port.write(b"lost") == 0 and port.dropped_bytes == 4  # nobody has it open
        await link.open()
        link.write(b"ping")
        port.write(b"pong")
        assert await link.read() == b"pong"
        await until(lambda: heard)
        assert heard == [b"ping"]
        port.unplug()
        with pytest.raises(DeviceIOError, match="unplugged"):
            await link.read()
        with pytest.raises(DeviceIOError):
            link.write(b"x")
        link.close()
        with pytest.raises(DeviceNotFound):
            await MemoryLink("mem://t/dev").open()
        port.replug()
        again = MemoryLink("mem://t/dev")
        await again.open()
        port.write(b"back")
        assert await again.read() == b"back"
        again.close()
        port.close()

    lockstep.run(main())


def test_a_memory_port_name_is_checked_and_plugs_in_once():
    with pytest.raises(ValueError, match="mem://"):
        MemoryPort("/dev/ttyACM0")
    port = MemoryPort("mem://t/once").open()
    try:
        with pytest.raises(RuntimeError, match="plugged in already"):
            MemoryPort("mem://t/once").open()
    finally:
        port.close()


# --- the real drivers against the fakes, in lockstep --------------------------------------------


def test_the_vesc_driver_drives_the_fake_over_a_memory_link_and_comes_back_after_an_unplug():
    async def main() -> None:
        bus = Bus()
        fake = FakeVesc("mem://t/vesc").open()
        served = asyncio.create_task(fake.serve())
        driver = VescDriver(bus, VescParams(port="mem://t/vesc"))
        task = asyncio.create_task(driver.run())
        try:
            await until(lambda: driver.connected)
            assert driver.firmware == (6, 2)
            started = clock.monotonic_ns()
            driver.command(AckermannDrive(speed=1.0, steering_angle=0.1))
            await until(lambda: any(isinstance(c.packet, SetRpm) and c.packet.erpm > 0
                                    for c in fake.commands))
            got = next(c for c in fake.commands if isinstance(c.packet, SetRpm) and c.packet.erpm > 0)
            assert got.t_ns == started  # no virtual time passes on the way: lockstep
            assert any(isinstance(c.packet, SetServoPosition) for c in fake.commands)
            fake.unplug()
            await until(lambda: not driver.connected)
            fake.replug()
            await until(lambda: driver.connected)
            assert driver.stats.reconnects >= 1
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            served.cancel()
            await asyncio.gather(served, return_exceptions=True)

    lockstep.run(main())


@pytest.mark.parametrize(("model", "tcp"), [("ust-10lx", True), ("urg-04lx", False), ("a2m8", False)])
def test_the_lidar_drivers_stream_scans_from_the_fakes_over_memory_links(model, tcp):
    async def main() -> list[float]:
        bus = Bus()
        scans: list[float] = []
        bus.subscribe("/scan", lambda m: scans.append(clock.monotonic()))
        fake = make_fake(model, RoomRangeSource(), link=f"mem://t/{model}")
        served = asyncio.create_task(fake.serve())
        where = {"tcp": f"mem://t/{model}"} if tcp else {"port": f"mem://t/{model}"}
        driver = make_driver(bus, LidarParams(model=model, **where))
        task = asyncio.create_task(driver.run())
        try:
            await until(lambda: len(scans) >= 5)
            assert driver.connected and isinstance(bus.latest("/scan"), LaserScan)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            served.cancel()
            await asyncio.gather(served, return_exceptions=True)
        return scans

    first = lockstep.run(main())
    assert first == lockstep.run(main())  # the same arrival times, to the nanosecond


def test_timers_due_at_the_same_time_run_in_the_order_they_were_set():
    # asyncio's heap orders timers of equal time by its shape; the virtual loop by when they were
    # set, so a timer added or removed elsewhere does not reorder the others' shared instants
    # (a run's outcome depends on that order: which of the world's step and a scan comes first)
    ran: list[tuple[float, int]] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        start = loop.time()
        handles = [loop.call_at(start + (0.010 if i % 3 else 0.005), ran.append, (i % 3 != 0, i))
                   for i in range(40)]
        for handle in handles[1::7]:
            handle.cancel()
        await asyncio.sleep(0.02)

    lockstep.run(main())
    kept = [(later, i) for later, i in [(i % 3 != 0, i) for i in range(40)] if i % 7 != 1]
    assert ran == sorted(kept)  # the 5 ms ones first, each group in the order set


def test_a_fake_vesc_stepped_from_outside_moves_as_on_its_own_timer():
    """The lockstep sim steps the fake VESC's motor from the world's timer (one timer for both):
    the same commands give the same motor, step by step, as the fake's own timer."""

    async def drive(own_timer: bool) -> list[tuple[int, float, float]]:
        name = f"mem://t/vesc-{own_timer}"
        bus = Bus()
        fake = FakeVesc(name).open()
        served = asyncio.create_task(fake.serve(motor_timer=own_timer))
        outside = PeriodicTimer(1.0 / fake.tick_s, lambda _due, _n: fake.step_motor(clock.monotonic_ns()))
        if not own_timer:
            outside.start()
        driver = VescDriver(bus, VescParams(port=name))
        task = asyncio.create_task(driver.run())
        seen: list[tuple[int, float, float]] = []
        try:
            await until(lambda: driver.connected)
            start = clock.monotonic_ns()
            for speed in (1.0, 2.5, -0.5, 0.0):
                driver.command(AckermannDrive(speed=speed, steering_angle=0.0))
                for _ in range(40):
                    await asyncio.sleep(0.0125)
                    seen.append((clock.monotonic_ns() - start, fake.erpm, fake.status))
        finally:
            outside.cancel()
            task.cancel()
            served.cancel()
            await asyncio.gather(task, served, return_exceptions=True)
        return seen

    own = lockstep.run(drive(True))
    stepped = lockstep.run(drive(False))
    assert max(abs(erpm) for _, erpm, _ in own) > 1000  # it moved
    assert stepped == own
