"""The control path: the VESC write comes before any bus publication, whoever subscribed first.

Real parts: the daemon with the real VESC driver against the fake VESC over a pty and the real
Hokuyo driver against the fake Hokuyo over TCP.
"""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest
from conftest import QUIET_NET, async_wait_for

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, LaserScan
from racecar_hw.config import load_config
from racecar_hw.daemon import Daemon
from vesc.codec import SetRpm, SetServoPosition
from vesc.fake import CommandRecord, FakeVesc

TELEOP = "/vesc/low_level/ackermann_cmd_mux/input/teleop"
OUTPUT = "/vesc/low_level/ackermann_cmd_mux/output"


def _received(fake: FakeVesc, frames: int, timeout: float = 10.0) -> list[CommandRecord]:
    """The fake VESC's log once it has decoded the first ``frames`` frames the driver wrote.

    Called from a bus observer, which holds the event loop: a frame not yet written when the
    observer was called can never arrive while this waits.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        log = fake.commands
        if log and log[-1].seq >= frames:
            return [r for r in log if r.seq <= frames]
        time.sleep(0.0005)
    raise AssertionError(f"the fake VESC never received frame {frames}")


def test_observers_subscribed_first_see_scans_and_outputs_only_after_the_fake_vesc_got_the_command(
        fakes, tmp_path):
    fake_vesc, fake_lidar = fakes
    host, port = fake_lidar.tcp_address
    config = load_config(None, [f"vesc.port={tmp_path / 'vesc'}", "lidar.model=ust-10lx",
                                f"lidar.tcp={host}:{port}", "gamepad.enabled=false",
                                "status.enabled=false", "arming.start_armed=true",
                                "foxglove.enabled=false", "web.enabled=false", *QUIET_NET])
    assert config.mux.output_topic == OUTPUT
    bus = Bus()
    outputs: list[tuple[int, int, float, float]] = []  # (erpm sent, erpm asked, servo sent, asked)
    scans: list[tuple[int, int]] = []  # (last motor write, the scan's arrival), monotonic ns
    holder: dict[str, Daemon] = {}

    def on_output(msg: AckermannDriveStamped) -> None:
        driver = holder["daemon"].vesc
        if driver is None or driver.firmware is None:  # before the handshake nothing is written
            return
        log = _received(fake_vesc, driver.stats.frames_tx)
        rpm = [r.packet for r in log if isinstance(r.packet, SetRpm)]
        servo = [r.packet for r in log if isinstance(r.packet, SetServoPosition)]
        asked = driver.conversion.to_vesc(msg.drive)
        outputs.append((rpm[-1].erpm, asked.erpm, servo[-1].position, asked.servo))

    def on_scan(scan: LaserScan) -> None:
        daemon = holder["daemon"]
        driver, lidar = daemon.vesc, daemon.lidar
        assert driver is not None and lidar is not None
        if driver.firmware is None or not daemon.control.alive(monotonic_ns()):
            return  # the scan path writes only while the control loop runs
        _received(fake_vesc, driver.stats.frames_tx)
        scans.append((driver.last_motor_write_ns, lidar.frame_arrival_ns))

    # the observers subscribe before the daemon builds anything on the bus
    bus.subscribe("/scan", on_scan)
    bus.subscribe(OUTPUT, on_output)
    daemon = holder["daemon"] = Daemon(config, bus=bus)

    async def drive() -> None:  # 1 m/s and back to 0 every 0.3 s: the limiter ramps each tick
        k = 0
        while True:
            speed = 1.0 if (k // 15) % 2 == 0 else 0.0
            bus.publish(TELEOP, AckermannDriveStamped(drive=AckermannDrive(0.1, 0.0, speed)))
            k += 1
            await asyncio.sleep(0.02)

    async def scenario() -> None:
        stop = asyncio.Event()
        daemon.add_task(drive())
        task = asyncio.create_task(daemon.run(stop))
        try:
            await async_wait_for(lambda: len(scans) >= 20 and len(outputs) >= 100
                                 and len({o[0] for o in outputs}) >= 5, timeout=60)
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)

    asyncio.run(scenario())
    assert bus.callback_errors == 0
    # each output reached the fake VESC as its latest motor and servo command before any observer
    # of the output topic saw it (several different speeds: the previous tick's would differ)
    for sent_erpm, asked_erpm, sent_servo, asked_servo in outputs:
        assert sent_erpm == asked_erpm
        assert sent_servo == pytest.approx(asked_servo, abs=1e-3)
    # each scan's command was written after its frame arrived and before /scan's observers ran
    assert all(written >= arrived > 0 for written, arrived in scans)
    assert len(daemon.stats.scan_to_command_ns) > 0


def test_a_scan_cut_is_written_then_published_and_holds_the_limiter_down():
    """A scan that forbids the current speed: the cut goes to the VESC, then on the bus, and the
    limiter starts the next ticks from the cut speed (RateLimiter.clamp)."""
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "foxglove.enabled=false", "web.enabled=false",
                                "arming.start_armed=true", *QUIET_NET])
    bus = Bus()
    events: list[tuple[str, float]] = []
    bus.subscribe(OUTPUT, lambda msg: events.append(("output", msg.drive.speed)))
    bus.subscribe("/scan", lambda scan: events.append(("scan", 0.0)))
    daemon = Daemon(config, bus=bus)

    class Motor:  # where the control path writes (the VESC driver's command)
        def command(self, drive: AckermannDrive) -> None:
            events.append(("motor", drive.speed))

    def scan(range_m: float) -> LaserScan:
        msg = LaserScan(angle_min=-1.0, angle_increment=0.01, range_min=0.02, range_max=30.0,
                        ranges=np.full(201, range_m, dtype=np.float32))
        msg.header.frame_id = "laser"
        return msg

    control = daemon.control
    control._write = Motor().command
    for _ in range(60):  # open space at 2 m/s (the limiter ramps there at 2.5 m/s^2)
        bus.publish(TELEOP, AckermannDriveStamped(drive=AckermannDrive(speed=2.0)))
        control.take_scan(scan(25.0))
        control.tick(monotonic_ns())
    assert daemon.mux.last_output is not None and daemon.mux.last_output.drive.speed == 2.0
    events.clear()
    control.take_scan(scan(0.6))  # a wall 0.6 m ahead
    assert control.stats.scan_cuts == 1
    (first, cut), *rest = events
    assert first == "motor" and cut < 2.0
    assert rest[:2] == [("scan", 0.0), ("output", cut)]
    assert daemon.mux.limiter.speed == cut  # clamped: the next tick ramps up from here at most


@pytest.mark.parametrize("speed", [1.0, 0.0])  # driving, or standing with the wheels turned
def test_a_blind_lidar_centres_the_steering_through_the_rate_limit_without_a_jump(speed):
    """A scan that blinds the lidar (no return on any beam) stops the car at once and centres its
    steering (safety.centre_when_blind) from the next tick at the mux's steering rate. The scan path
    once wrote a standing car's steering centred at once and the next tick put it back near the
    limiter's angle (0.2, 0.0, 0.136, 0.072, ... on the servo); then, as a cut, it took a limiter
    step of its own between two ticks' steps (5.7 rad/s against the 3.2 allowed)."""
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "foxglove.enabled=false", "web.enabled=false",
                                "arming.start_armed=true", *QUIET_NET])
    daemon = Daemon(config, bus=Bus())
    written: list[tuple[float, float]] = []

    class Motor:  # where the control path writes (the VESC driver's command)
        def command(self, drive: AckermannDrive) -> None:
            written.append((drive.speed, drive.steering_angle))

    def scan(range_m: float) -> LaserScan:
        msg = LaserScan(angle_min=-1.0, angle_increment=0.01, range_min=0.02, range_max=30.0,
                        ranges=np.full(201, range_m, dtype=np.float32))
        msg.header.frame_id = "laser"
        return msg

    def command() -> None:
        drive = AckermannDrive(speed=speed, steering_angle=0.2)
        daemon.bus.publish(TELEOP, AckermannDriveStamped(drive=drive))

    control = daemon.control
    control._write = Motor().command
    for _ in range(60):  # open space, turning left at 0.2 rad
        command()
        control.take_scan(scan(25.0))
        control.tick(monotonic_ns())
    assert written[-1] == (speed, 0.2)
    written.clear()
    control.take_scan(scan(math.inf))  # blinded: every beam no return
    assert written == [(0.0, 0.2)]  # braked at once, the steering left to the ticks
    for k in range(20):
        command()
        if k % 2:  # scans between the ticks, as at 40 Hz
            control.take_scan(scan(math.inf))
        control.tick(monotonic_ns())
    steering = [s for _, s in written]
    assert all(v == 0.0 for v, _ in written) and steering[-1] == 0.0, written
    step = config.mux.max_steering_rate_radps / config.mux.rate_hz  # per tick
    ticks = [s for k, s in enumerate(steering) if k == 0 or s != steering[k - 1]]  # each change
    assert all(0.0 <= a - b <= step + 1e-9 for a, b in zip(ticks, ticks[1:], strict=False)), steering


def test_a_non_finite_command_stops_at_the_mux_edge_and_only_finite_commands_are_written():
    """The one finiteness check for bus sources is where a command enters the mux: NaN or inf
    there becomes a stop from that source (counted), so the filters, the limiter and the VESC
    write downstream only see finite numbers. (The network inbox refuses such messages before the
    bus, tests/test_net_inbox.py; the VESC driver still refuses NaN/inf, tests/test_vesc_driver.py.)"""
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "foxglove.enabled=false", "web.enabled=false",
                                "arming.start_armed=true", "safety.mode=off", *QUIET_NET])
    daemon = Daemon(config)
    written: list[AckermannDrive] = []
    daemon.control._write = written.append
    for speed, steering in ((1.0, 0.1), (math.nan, 0.1), (1.0, math.inf), (-math.inf, math.nan), (1.0, 0.1)):
        daemon.bus.publish(TELEOP, AckermannDriveStamped(drive=AckermannDrive(steering, 0.0, speed)))
        daemon.control.tick(monotonic_ns())
    assert len(written) == 5
    assert all(math.isfinite(d.speed) and math.isfinite(d.steering_angle) for d in written)
    assert written[0].speed > 0.0 and written[-1].speed > 0.0
    assert daemon.mux.rejected["teleop"] == 3


def test_the_outboxes_wait_for_a_remote_answer_while_remote_code_answers_scans():
    """The idle hooks (the outboxes' batches: the bag writer, the senders) run after a scan's
    bookkeeping; while remote navigation code answers scans (a remote command written within
    REMOTE_ANSWER_NS), after that command's write instead, so a batch never lands between a scan
    and its answer."""
    from racecar_hw.control.path import REMOTE_ANSWER_NS

    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "foxglove.enabled=false", "web.enabled=false",
                                "arming.start_armed=true", "safety.mode=off", *QUIET_NET])
    daemon = Daemon(config)
    control = daemon.control
    nav = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"
    control.remote_inputs[nav] = "nav_0"
    events: list[str] = []
    control._write = lambda drive: events.append("motor")
    control.idle.append(lambda: events.append("idle"))

    def scan() -> LaserScan:
        msg = LaserScan(angle_min=-1.0, angle_increment=0.01, range_min=0.02, range_max=30.0,
                        ranges=np.full(201, 25.0, dtype=np.float32))
        msg.header.frame_id = "laser"
        return msg

    control.tick(monotonic_ns())  # the loop runs: the scan path and the early step may write
    events.clear()
    control.take_scan(scan())  # nobody remote yet
    assert events[-1] == "idle"
    events.clear()
    control.take_input(nav, AckermannDriveStamped(drive=AckermannDrive(speed=0.5)), "zenoh")
    assert events == ["motor", "idle"]  # the answer's write, then the batches
    events.clear()
    control.take_scan(scan())  # the next answer is on its way: no batch now
    assert "idle" not in events
    control._remote_write_ns -= REMOTE_ANSWER_NS + 1  # the remote code went quiet
    events.clear()
    control.take_scan(scan())
    assert events[-1] == "idle"


def test_a_disarm_is_written_at_once_and_a_scan_before_the_next_tick_does_not_resend_the_drive():
    """Disarming (the page, the gamepad, MAVLink) wrote the stop only at the next control tick; a
    scan in between re-sent the mux's last output, the drive from before the disarm, past the
    arming filter (a review found it in the code). The stop now goes out with the disarm."""
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "foxglove.enabled=false", "web.enabled=false",
                                "arming.start_armed=true", *QUIET_NET])
    daemon = Daemon(config)
    written: list[float] = []
    daemon.control._write = lambda drive: written.append(drive.speed)
    open_space = LaserScan(angle_min=-1.0, angle_increment=0.01, range_min=0.02, range_max=30.0,
                           ranges=np.full(201, 25.0, dtype=np.float32))
    open_space.header.frame_id = "laser"
    for _ in range(60):  # driving at 2 m/s
        daemon.bus.publish(TELEOP, AckermannDriveStamped(drive=AckermannDrive(speed=2.0)))
        daemon.control.take_scan(open_space)
        daemon.control.tick(monotonic_ns())
    assert written[-1] == 2.0
    written.clear()
    daemon.disarm("test")
    daemon.control.take_scan(open_space)  # before the next tick
    assert written and all(speed < 2.0 for speed in written), written
    assert written[-1] == written[0] and daemon.mux.last_output.drive.speed == written[0]
