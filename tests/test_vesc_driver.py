"""The VESC driver against the fake VESC over real ptys: handshake, commands, telemetry for several
firmware layouts, resync, reconnect after an unplug, the no-command failsafe and shutdown."""

from __future__ import annotations

import asyncio
import math
import time

import pytest
from conftest import async_wait_for

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.messages import AckermannDrive, Float64, Odometry, TFMessage, VescStateStamped
from racecar_hw.runtime import lockstep
from vesc.ackermann import AckermannConversion
from vesc.codec import (
    Alive,
    FwVersion,
    FwVersionRequest,
    RawPacket,
    SetCurrentBrake,
    SetRpm,
    SetServoPosition,
    Values,
    encode_fw_version,
    frame,
    servo_on_wire,
)
from vesc.driver import TOPIC_CORE, TOPIC_ODOM, TOPIC_SERVO, TOPIC_TF, VescDriver
from vesc.fake import CommandRecord, FakeVesc
from vesc.params import VescParams

CONV = AckermannConversion()
CENTRE_WIRE = round(CONV.servo_centre * 1000) / 1000  # the centre as the servo receives it


def start_fake(device_thread, path, firmware=(6, 2), **kw) -> FakeVesc:
    fake = FakeVesc(str(path), firmware, **kw).open()
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)
    return fake


class Recorder:
    """Messages per topic with their monotonic arrival times."""

    def __init__(self, bus: Bus, *topics: str) -> None:
        self.got: dict[str, list[tuple[int, object]]] = {t: [] for t in topics}
        for t in topics:
            bus.subscribe(t, lambda msg, t=t: self.got[t].append((monotonic_ns(), msg)))

    def count(self, topic: str) -> int:
        return len(self.got[topic])

    def last(self, topic: str):
        return self.got[topic][-1][1]


#: the fakes' serving tasks (the loop keeps only weak references to tasks)
SERVING: set[asyncio.Task[None]] = set()


def memory_fake(name: str, **kw) -> FakeVesc:
    """A fake VESC served in the running loop behind the in-memory link ``mem://NAME/vesc`` (for
    a driver and its fake in lockstep, :func:`racecar_hw.runtime.lockstep.run`, which cancels the
    task at its end)."""
    fake = FakeVesc(f"mem://{name}/vesc", **kw).open()
    task = asyncio.ensure_future(fake.serve())
    SERVING.add(task)
    task.add_done_callback(SERVING.discard)
    return fake


async def drive_for(driver: VescDriver, seconds: float, speed: float, steer: float = 0.0,
                    hz: float = 50.0) -> None:
    loop = asyncio.get_running_loop()  # its clock: the monotonic one, or virtual in lockstep
    end = loop.time() + seconds
    while loop.time() < end:
        driver.command(AckermannDrive(speed=speed, steering_angle=steer))
        await asyncio.sleep(1.0 / hz)


def is_brake(p) -> bool:
    return isinstance(p, SetRpm) and p.erpm == 0 or isinstance(p, SetCurrentBrake)


def is_centre(p) -> bool:
    return isinstance(p, SetServoPosition) and p.position == pytest.approx(CENTRE_WIRE)


@pytest.mark.parametrize("firmware", [(2, 18), (3, 40), (5, 2), (6, 2)])
def test_handshake_and_telemetry_per_layout(tmp_path, device_thread, firmware):
    fake = start_fake(device_thread, tmp_path / "vesc", firmware)

    async def scenario() -> None:
        bus = Bus()
        rec = Recorder(bus, TOPIC_CORE, TOPIC_ODOM, TOPIC_TF, TOPIC_SERVO)
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            assert driver.firmware == firmware
            # commands at 50 Hz throughout: a single one is let go by the 50 ms command timeout
            # (brake, centre) before a loaded machine may show its telemetry
            driving = asyncio.create_task(drive_for(driver, 60.0, 1.0, 0.1))
            try:
                await async_wait_for(lambda: rec.count(TOPIC_CORE) >= 10)
                await async_wait_for(lambda: driver.last_state.state.speed == 4614 and rec.count(TOPIC_ODOM)
                                     and rec.last(TOPIC_ODOM).twist.twist.angular.z > 0, timeout=5)
            finally:
                driving.cancel()
                await asyncio.gather(driving, return_exceptions=True)
            state = driver.last_state
            assert isinstance(state, VescStateStamped)
            assert state.state.voltage_input == pytest.approx(16.8, abs=0.5)
            assert state.state.displacement > 0  # tachometer advanced
            mos_temperature_present = firmware >= (3, 48) or firmware < (3, 7)
            assert (state.state.ntc_temp_mos1 == 31.5) is mos_temperature_present
            odom = rec.last(TOPIC_ODOM)
            assert isinstance(odom, Odometry) and odom.pose.pose.position.x > 0
            assert odom.twist.twist.angular.z > 0  # left steering turns left (waited for above)
            assert isinstance(rec.last(TOPIC_TF), TFMessage)
            servo = rec.last(TOPIC_SERVO)
            assert isinstance(servo, Float64)
            assert servo.data == servo_on_wire(CONV.steering_to_servo(0.1))  # as the VESC receives it
            assert not fake.timed_out  # 50 Hz motor commands keep the firmware timeout fed
            assert driver.stats.frames_rx >= 10 and driver.stats.crc_errors == 0

    asyncio.run(scenario())


def test_commands_arrive_with_exact_values():
    """In lockstep (the driver and the fake VESC on virtual time behind an in-memory link): the
    same run on an idle or a loaded machine (over a pty, a loaded one once showed the fake a brake
    of SetRpm(0) before the first command)."""
    async def scenario() -> None:
        fake = memory_fake("exact")
        async with VescDriver(Bus(), VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            fake.clear_commands()
            before, before_cpu = monotonic_ns(), time.thread_time_ns()
            driver.command(AckermannDrive(speed=1.5, steering_angle=-0.1))
            # written before command() returns, stamped on both of this thread's clocks
            assert before == driver.last_motor_write_ns == monotonic_ns()  # no virtual time passed
            assert before_cpu <= driver.last_motor_write_cpu_ns <= time.thread_time_ns()
            driver.command(AckermannDrive(speed=-0.5, steering_angle=0.3))
            await async_wait_for(lambda: sum(isinstance(r.packet, SetServoPosition)
                                             for r in fake.commands) >= 2)
            sent = [r.packet for r in fake.commands if isinstance(r.packet, (SetRpm, SetServoPosition))]
            assert sent[:4] == [SetRpm(6921), SetServoPosition(0.652),  # 0.5304 + 0.12135 -> 652
                                SetRpm(-2307), SetServoPosition(0.215)]  # 0.3 clamps to 0.26 rad
            keep_driving = asyncio.create_task(drive_for(driver, 10.0, -0.5, 0.3))
            await async_wait_for(lambda: fake.erpm == -2307 and fake.servo == 0.215, timeout=5)
            keep_driving.cancel()

    lockstep.run(scenario())


def test_the_servo_topic_says_what_the_vesc_received():
    """``servo_position_command`` carries the position in the thousandths the VESC receives, not the
    unrounded one: calibration fits the servo offset against it (the unrounded 0.65175 put the
    fitted offset 0.0005 from the car's, outside its error bar). Odometry steers by the same."""
    async def scenario() -> None:
        fake = memory_fake("servo-topic")
        bus = Bus()
        rec = Recorder(bus, TOPIC_SERVO)
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            raw = CONV.steering_to_servo(-0.1)
            assert raw != round(raw, 3)  # 0.5304 + 0.12135: a position between two thousandths
            fake.clear_commands()
            driver.command(AckermannDrive(speed=1.0, steering_angle=-0.1))
            await async_wait_for(lambda: any(isinstance(r.packet, SetServoPosition) for r in fake.commands))
            servo = next(r.packet for r in fake.commands if isinstance(r.packet, SetServoPosition))
            assert rec.last(TOPIC_SERVO).data == servo.position == driver.servo_sent == 0.652

    lockstep.run(scenario())


def test_the_estopped_mux_output_stops_the_motor_whatever_the_erpm_offset():
    """The mux's e-stop output (speed 0) through the driver with ``speed_to_erpm_offset`` 2000 (0.43
    m/s at the default gain): SET_RPM 0 reaches the fake VESC, not the offset; driving keeps it."""
    from mux.node import CommandMux

    async def scenario() -> None:
        fake = memory_fake("offset")
        bus = Bus()
        mux = CommandMux(bus)
        async with VescDriver(bus, VescParams(port=fake.path, speed_to_erpm_offset=2000.0)) as driver:
            await async_wait_for(lambda: driver.connected)
            driver.command(AckermannDrive(speed=1.0, steering_angle=0.0))
            await async_wait_for(lambda: any(r.packet == SetRpm(4614 + 2000) for r in fake.commands))
            mux.engage_estop("operator pressed E-STOP")
            fake.clear_commands()
            for _ in range(5):  # what the control path does each period
                out = mux.decide()
                assert out.drive.speed == 0.0
                driver.command(out.drive)
                await asyncio.sleep(0.02)
            await async_wait_for(lambda: sum(isinstance(r.packet, SetRpm) for r in fake.commands) >= 5)
            assert {r.packet.erpm for r in fake.commands if isinstance(r.packet, SetRpm)} == {0}

    lockstep.run(scenario())


def test_failsafe_brakes_and_centres_within_100ms():
    """In lockstep (the driver and the fake VESC on virtual time behind an in-memory link): the
    brake and the centring come exactly the 50 ms command timeout after the last command."""
    async def scenario() -> None:
        fake = memory_fake("failsafe")
        async with VescDriver(Bus(), VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            await drive_for(driver, 0.4, 2.0, 0.2)
            # the control loop stops here: command loss
            await async_wait_for(lambda: not driver.moving, timeout=5)
            await async_wait_for(lambda: sum(is_brake(r.packet) for r in _after_last_motion(fake)) >= 5,
                                 timeout=5)
            log = fake.commands
            last_motion = max(r.t_ns for r in log if isinstance(r.packet, SetRpm) and r.packet.erpm != 0)
            after = [r for r in log if r.t_ns > last_motion or (r.t_ns == last_motion and is_brake(r.packet))]
            first_brake = next(r.t_ns for r in after if is_brake(r.packet))
            first_centre = next(r.t_ns for r in after if is_centre(r.packet))
            assert first_brake - last_motion == 50_000_000, (first_brake - last_motion) / 1e6
            assert first_centre - last_motion == 50_000_000, (first_centre - last_motion) / 1e6
            assert driver.stats.failsafes == 1
            await async_wait_for(lambda: fake.erpm == 0 and fake.servo == CENTRE_WIRE, timeout=5)

    lockstep.run(scenario())


def test_a_command_stream_leaves_the_failsafe_timer_until_it_is_half_due(tmp_path):
    """On virtual time (lockstep), so that 30 ms is exactly past half of the 50 ms timeout and
    never past all of it."""
    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        driver = VescDriver(Bus(), VescParams(port=str(tmp_path / "absent")))
        driver.command(AckermannDrive(speed=1.0))
        timer = driver._failsafe_timer  # noqa: SLF001
        assert timer is not None and timer.when() == pytest.approx(loop.time() + 0.05, abs=1e-9)
        for _ in range(100):  # back to back: the timer is still due a whole timeout from now
            driver.command(AckermannDrive(speed=1.0))
        assert driver._failsafe_timer is timer  # noqa: SLF001
        await asyncio.sleep(0.03)  # past half of the 50 ms timeout
        assert driver.moving and driver.stats.failsafes == 0
        before = loop.time()
        driver.command(AckermannDrive(speed=1.0))
        moved = driver._failsafe_timer  # noqa: SLF001
        assert moved is not timer and timer.cancelled()  # moved: a whole timeout from this command
        assert moved.when() == pytest.approx(before + 0.05, abs=1e-9)
        await async_wait_for(lambda: not driver.moving, timeout=5)  # commands stop: it brakes
        assert driver.stats.failsafes == 1

    lockstep.run(scenario())


def test_a_held_up_process_brakes_only_if_the_next_command_was_not_due_first():
    """The whole process stalls past the failsafe deadline with a command due before it.

    Every overdue timer then runs in one pass, in deadline order: a poll tick (due first), the
    control tick's command, the failsafe timer. The car was never without a fresh command in that
    order, so it must not brake; once commands really stop, it brakes, a timeout after the last.
    The driver and the fake VESC run in lockstep behind an in-memory link, the hold-up is a stall
    of the virtual clock, and every time is exact.
    """
    async def scenario() -> None:
        fake = memory_fake("held-up")
        params = VescParams(port=fake.path, poll_rate_hz=100.0)  # a poll tick every 10 ms
        async with VescDriver(Bus(), params) as driver:
            await async_wait_for(lambda: driver.connected)
            await async_wait_for(lambda: driver.last_state is not None)  # the poll ticks run
            loop = asyncio.get_running_loop()
            assert isinstance(loop, lockstep.VirtualTimeLoop)
            driver.command(AckermannDrive(speed=1.0))
            commanded_ns = loop.now_ns()
            loop.call_at(commanded_ns / NS_PER_S + 0.03, driver.command, AckermannDrive(speed=1.0))
            loop.stall(0.09)  # the process held up: the 50 ms deadline passes with nothing running
            await asyncio.sleep(0.005)
            assert driver.stats.failsafes == 0 and driver.moving
            await async_wait_for(lambda: not driver.moving, timeout=5)
            assert driver.stats.failsafes == 1
            # the command due at 30 ms ran at the end of the 90 ms hold-up: the brake came 50 ms later

            def brakes() -> list[CommandRecord]:
                return [r for r in fake.commands if r.t_ns > commanded_ns and is_brake(r.packet)]

            await async_wait_for(brakes)  # read by the fake
            assert brakes()[0].t_ns == commanded_ns + 90_000_000 + 50_000_000

    lockstep.run(scenario())


def _after_last_motion(fake: FakeVesc) -> list[CommandRecord]:
    log = fake.commands
    motion = [i for i, r in enumerate(log) if isinstance(r.packet, SetRpm) and r.packet.erpm != 0]
    idx = motion[-1] if motion else -1
    return log[idx + 1:]


def test_nan_command_brakes_at_once_and_brake_current_mode(tmp_path, device_thread):
    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        params = VescParams(port=fake.path, brake_mode="current", brake_current_a=15.0)
        async with VescDriver(Bus(), params) as driver:
            await async_wait_for(lambda: driver.connected)
            await drive_for(driver, 0.2, 1.0)
            fake.clear_commands()
            driver.command(AckermannDrive(speed=math.nan))
            assert driver.stats.refused_commands == 1 and not driver.moving
            await async_wait_for(lambda: any(isinstance(r.packet, SetCurrentBrake) for r in fake.commands))
            motor = [r.packet for r in fake.commands if isinstance(r.packet, (SetRpm, SetCurrentBrake))]
            assert motor[0] == SetCurrentBrake(15.0)
            assert not any(isinstance(p, SetRpm) for p in motor)
            await async_wait_for(lambda: fake.mode == "brake" and fake.erpm == 0, timeout=5)

    asyncio.run(scenario())


def test_a_numpy_float32_command_drives_and_a_non_number_brakes(tmp_path, device_thread):
    """``command()`` never raises: numpy scalars drive, a value that is no number brakes."""
    import numpy as np

    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        async with VescDriver(Bus(), VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            driver.command(AckermannDrive(speed=np.float32(1.0), steering_angle=np.float32(0.1)))
            assert driver.moving and driver.stats.refused_commands == 0
            await async_wait_for(lambda: fake.erpm != 0)
            driver.command(AckermannDrive(speed="fast"))  # type: ignore[arg-type]
            assert driver.stats.refused_commands == 1 and not driver.moving
            await async_wait_for(lambda: fake.erpm == 0, timeout=5)

    asyncio.run(scenario())


def test_a_vesc_that_stops_answering_is_a_lost_link_and_is_reopened(tmp_path, device_thread, caplog):
    """A VESC whose firmware hangs with its port still there: after reply_timeout_s with polls
    unanswered the driver says so, reopens the port and, once it answers again, drives on."""
    import logging

    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        async with VescDriver(Bus(), VescParams(port=fake.path, reply_timeout_s=0.3)) as driver:
            await async_wait_for(lambda: driver.connected and driver.last_state is not None)
            fake.mute(True)
            await async_wait_for(lambda: driver.stats.reconnects >= 1, timeout=15)
            assert not driver.connected  # no handshake answer yet
            fake.mute(False)
            await async_wait_for(lambda: driver.connected, timeout=15)
            await drive_for(driver, 0.2, 1.0)
            await async_wait_for(lambda: fake.erpm != 0)

    with caplog.at_level(logging.WARNING, logger="vesc.driver"):
        asyncio.run(scenario())
    lost = [r.getMessage() for r in caplog.records if "link lost" in r.getMessage()]
    assert lost and "sent no valid frame for" in lost[0], [r.getMessage() for r in caplog.records]
    assert not [r for r in caplog.records if r.exc_info]


def test_a_vesc_that_stops_reading_never_gets_an_unbounded_backlog(tmp_path, device_thread):
    """The device stops reading its port: the driver's queued bytes stay bounded (the link fails
    and is reopened), and once it reads again the car is driven afresh."""
    from racecar_hw.base.link import MAX_TX_PENDING

    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        async with VescDriver(Bus(), VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            fake.stop_reading(True)
            most = 0

            def lost() -> bool:
                nonlocal most
                link = driver._link
                most = max(most, link.tx_pending if link is not None and link.is_open else 0)
                driver.command(AckermannDrive(speed=1.0))
                return driver.stats.reconnects >= 1

            await async_wait_for(lost, timeout=20)
            assert most <= MAX_TX_PENDING
            fake.stop_reading(False)
            await async_wait_for(lambda: driver.connected, timeout=15)
            await drive_for(driver, 0.2, 1.0)
            await async_wait_for(lambda: fake.erpm != 0)

    asyncio.run(scenario())


def test_alive_keeps_the_firmware_fed_between_sparse_commands(tmp_path, device_thread):
    fake = start_fake(device_thread, tmp_path / "vesc", timeout_s=0.3)

    async def scenario() -> None:
        params = VescParams(port=fake.path, command_timeout_s=0.09, alive_interval_s=0.02, poll_rate_hz=100)
        async with VescDriver(Bus(), params) as driver:
            await async_wait_for(lambda: driver.connected)
            fake.clear_commands()
            await drive_for(driver, 1.0, 1.0, hz=16)  # 62 ms apart: fresh, but sparse
            assert any(isinstance(r.packet, Alive) for r in fake.commands)
            assert not fake.timed_out

    asyncio.run(scenario())


def test_resync_after_garbage_bad_crc_and_split_replies(tmp_path, device_thread):
    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        bus = Bus()
        rec = Recorder(bus, TOPIC_CORE)
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: rec.count(TOPIC_CORE) >= 3)
            fake.split_replies(True)
            fake.inject_garbage(300)
            fake.corrupt_next_crc()
            before = rec.count(TOPIC_CORE)
            await async_wait_for(lambda: driver.stats.crc_errors >= 1 and driver.stats.resyncs >= 1)
            await async_wait_for(lambda: rec.count(TOPIC_CORE) >= before + 20)
            fake.split_replies(False)
            assert driver.connected and driver.stats.reconnects == 0
            assert driver.stats.dropped_bytes >= 300

    asyncio.run(scenario())


def test_a_fw_version_frame_mid_session_changes_nothing(tmp_path, device_thread):
    """Line noise (FW_VERSION 0.0, an all-zero payload with CRC 0) and a real-looking 2.18 reply,
    both unasked mid-session, leave the 6.2 layout: telemetry keeps decoding true speeds."""
    fake = start_fake(device_thread, tmp_path / "vesc", (6, 2))

    async def scenario() -> None:
        bus = Bus()
        rec = Recorder(bus, TOPIC_CORE)
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            driving = asyncio.create_task(drive_for(driver, 30.0, 1.0))
            await async_wait_for(lambda: driver.last_state is not None
                                 and driver.last_state.state.speed == 4614, timeout=5)
            crc_errors = driver.stats.crc_errors
            fake.inject_reply(RawPacket(bytes(3)))  # noise: dropped by the codec (its CRC is 0)
            fake.inject_reply(FwVersion(2, 18))
            fake.inject_reply(FwVersion(0, 1))
            await async_wait_for(lambda: driver.stats.ignored_fw_versions == 2
                                 and driver.stats.crc_errors == crc_errors + 1)
            before = rec.count(TOPIC_CORE)
            await async_wait_for(lambda: rec.count(TOPIC_CORE) >= before + 10)
            driving.cancel()
            assert driver.firmware == (6, 2)
            speeds = [msg.state.speed for _, msg in rec.got[TOPIC_CORE][before:]]
            assert all(abs(v) <= 4614 for v in speeds), speeds  # ERPM of 1 m/s, never ~7,500 m/s
            assert driver.stats.reconnects == 0 and driver.stats.implausible_telemetry == 0

    asyncio.run(scenario())


def test_impossible_telemetry_is_dropped_and_counted(tmp_path, device_thread):
    fake = start_fake(device_thread, tmp_path / "vesc", (6, 2))

    async def scenario() -> None:
        bus = Bus()
        rec = Recorder(bus, TOPIC_CORE, TOPIC_ODOM)
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: rec.count(TOPIC_CORE) >= 3)
            for bad in (Values(erpm=10**7, v_in=16.0), Values(erpm=0, v_in=480.0), Values(v_in=-3.0),
                        Values(duty=7.5, v_in=16.0)):
                fake.inject_reply(bad)
            await async_wait_for(lambda: driver.stats.implausible_telemetry == 4)
            before = rec.count(TOPIC_CORE)
            await async_wait_for(lambda: rec.count(TOPIC_CORE) >= before + 5)  # polls go on
            assert all(m.state.speed == 0 and 16 < m.state.voltage_input < 17 and m.state.duty_cycle == 0
                       for _, m in rec.got[TOPIC_CORE])  # the car stands; nothing impossible got out
            assert all(m.twist.twist.linear.x == 0 for _, m in rec.got[TOPIC_ODOM])

    asyncio.run(scenario())


def test_a_fw_version_nobody_asked_for_is_not_a_handshake():
    driver = VescDriver(Bus(), VescParams(port="/nonexistent"))
    driver._on_bytes(frame(bytes(3)))  # noqa: SLF001 - line noise: the codec drops it
    assert driver.stats.crc_errors == 1 and driver.stats.ignored_fw_versions == 0
    driver._on_bytes(frame(encode_fw_version(FwVersion(6, 2))))  # noqa: SLF001 - before any request
    assert driver.firmware is None and driver.stats.ignored_fw_versions == 1
    driver._fw_asked = True  # noqa: SLF001 - as after the handshake's request
    driver._on_bytes(frame(encode_fw_version(FwVersion(0, 1))))  # noqa: SLF001 - no such firmware
    assert driver.firmware is None and driver.stats.ignored_fw_versions == 2
    driver._on_bytes(frame(encode_fw_version(FwVersion(6, 2))))  # noqa: SLF001
    assert driver.firmware == (6, 2)


def test_reconnects_within_1s_of_replug_brake_and_centre_first(tmp_path, device_thread):
    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        bus = Bus()
        rec = Recorder(bus, TOPIC_CORE)
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected)
            await drive_for(driver, 0.2, 1.0)
            await asyncio.to_thread(fake.unplug)
            await async_wait_for(lambda: not driver.connected)
            # stay unplugged long enough for the reconnect backoff to reach its cap
            await asyncio.sleep(1.5)
            assert not driver.connected
            fake.clear_commands()
            before = rec.count(TOPIC_CORE)
            replug_ns = monotonic_ns()
            await asyncio.to_thread(fake.replug)
            await async_wait_for(lambda: rec.count(TOPIC_CORE) > before, timeout=10)
            first_telemetry_ns = rec.got[TOPIC_CORE][before][0]
            assert first_telemetry_ns - replug_ns < NS_PER_S, (first_telemetry_ns - replug_ns) / 1e6
            first = [r.packet for r in fake.commands[:3]]
            assert is_brake(first[0]) and is_centre(first[1]) and isinstance(first[2], FwVersionRequest)
            assert driver.stats.reconnects == 1
            await drive_for(driver, 0.2, 1.0)
            await async_wait_for(lambda: fake.erpm > 0)

    asyncio.run(scenario())


def test_shutdown_brakes_centres_and_closes(tmp_path, device_thread):
    fake = start_fake(device_thread, tmp_path / "vesc")

    async def scenario() -> None:
        driver = VescDriver(Bus(), VescParams(port=fake.path))
        task = asyncio.create_task(driver.run())
        await async_wait_for(lambda: driver.connected)
        await drive_for(driver, 0.1, 1.0, 0.2)
        driver.command(AckermannDrive(speed=1.0, steering_angle=0.2))
        await driver.shutdown()
        await driver.shutdown()
        assert task.done() and task.exception() is None
        assert not driver.connected

        def last_two():
            return [r.packet for r in fake.commands[-2:]]

        # the final frames on the wire are brake and centre, right after the moving command
        await async_wait_for(lambda: is_brake(last_two()[0]) and is_centre(last_two()[1]))
        motion = [r for r in fake.commands if isinstance(r.packet, SetRpm) and r.packet.erpm == 4614]
        assert motion and fake.commands.index(motion[-1]) < len(fake.commands) - 2
        driver.command(AckermannDrive(speed=1.0))  # after shutdown: ignored, never raises

    asyncio.run(scenario())


def test_run_survives_a_missing_device(tmp_path):
    async def scenario() -> None:
        for port in (str(tmp_path / "nothing"), "auto"):
            params = VescParams(port=port, usb_vid_pid="ffff:fffe")
            driver = VescDriver(Bus(), params)
            task = asyncio.create_task(driver.run())
            driver.command(AckermannDrive(speed=1.0))  # no device: ignored
            await asyncio.sleep(0.3)
            assert not task.done() and not driver.connected
            await asyncio.wait_for(driver.shutdown(), 5)
            assert task.done() and task.exception() is None

    asyncio.run(scenario())
