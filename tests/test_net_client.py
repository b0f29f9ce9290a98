"""racecar_hw.client against ``racecar-hw sim`` in processes of their own: the wall-follower example
drives a lap of the track; two cars with namespaces behind one of them acting as the Zenoh router,
driven independently through one client session; user/password keeps out a session without it;
safety states, callbacks, the daemon's remaps, and the stop sent when a ``with`` block ends."""

from __future__ import annotations

import asyncio
import math
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import ahead_of_ordinary_load, wait_for
from zenoh_util import ROOT, endpoint, free_port, start_sim, switches, wait_standing, wait_until_stopped

from racecar_hw.client import AsyncCar, Car, ClientError
from racecar_hw.sim.trajectory import read_csv
from safety.controller import REASONS


def _wait_listening(port: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise AssertionError(f"nothing listens on port {port} after {timeout} s") from None
            time.sleep(0.1)


def _connected(connect: str, timeout: float = 60.0, **car: object) -> Car:
    """A :class:`Car` connected to ``connect``, trying again while the daemon's Zenoh session does not
    answer yet: its port listens before the session accepts, and on a loaded machine one try (the
    client's 3 s) can end first."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return Car(connect, **car)
        except ClientError:
            if time.monotonic() > deadline:
                raise


#: The wall-follower's lap runs the sim at this many times real time (lockstep, ``--speed``).
LAP_SPEED = 3.0


@pytest.mark.slow
def test_the_wall_follower_example_drives_a_lap_of_the_track(tmp_path):
    port = free_port()
    # The sim runs in lockstep paced at LAP_SPEED times real time, every interface on as in real
    # time: the lap is on the sim's clock (scans, odometry and the mux's timeout), and the example
    # steers from the newest scan each time (the client hands a slow reader the newest), as it does
    # on a car. A lap then takes about 25 s instead of 45 s (at load 6-8, with no intervention of
    # the safety stop); a loaded machine runs the sim slower than LAP_SPEED (its clock waits for
    # the run, never the other way), so the deadlines are generous: they bound a
    # stuck run, the lap itself is what is checked. The example runs ahead of the other test
    # workers' load where allowed (conftest.ahead_of_ordinary_load): what is checked is its driving,
    # not the machine's scheduling. The sim does not: in lockstep its pace is not what is checked,
    # and it takes all the CPU it is given (at three times real time on a loaded machine), which at
    # FIFO priority would hold up the real-time sims of the other workers' tests.
    sim = start_sim(tmp_path, port, scenario_sets=("map=track", "drivers=[]"), duration=600.0,
                    speed=LAP_SPEED)
    try:
        _wait_listening(port)  # the example connects once (client mode) and gives up after 3 s
        example = subprocess.run([sys.executable, str(ROOT / "examples" / "wall_follower.py"),
                                  "--connect", endpoint(port), "--laps", "1", "--timeout", "480"],
                                 capture_output=True, text=True, timeout=560, cwd=ROOT,
                                 preexec_fn=ahead_of_ordinary_load)
        sim.proc.send_signal(signal.SIGINT)  # the sim ends early and still writes its report
        report = sim.report()
    finally:
        sim.kill()
    assert example.returncode == 0, example.stdout + example.stderr
    assert "1 lap(s)" in example.stdout
    assert not report["collided"], report["collisions"]
    # ground truth from the world: the car went round all four corridors and back past its start
    samples = read_csv(report["trajectory_csv"])
    xs, ys = [s.x for s in samples], [s.y for s in samples]
    assert max(xs) > 13.0 and max(ys) > 10.5 and min(xs) < -2.0, (min(xs), max(xs), max(ys))
    left_corridor = next(i for i, s in enumerate(samples) if s.x < -2.0)
    assert any(s.x > 0.0 and s.y < 1.0 for s in samples[left_corridor:])
    assert report["distance_m"] > 50.0
    # The example steers by itself; on a loaded machine its process may answer a scan late and the
    # safety stop step in near a wall now and then (its job), but not keep doing so.
    by_reason = report["safety_interventions_by_reason"]
    assert set(by_reason) <= {"stale_scan", "obstacle"} and by_reason.get("obstacle", 0) <= 2, by_reason


def _drive_at_20_hz(stop: threading.Event, *commands: tuple[Car, float, float]) -> None:
    """Send each (car, speed m/s, steering rad) every 50 ms until ``stop`` is set."""
    while not stop.is_set():
        for car, speed, steering in commands:
            car.drive(speed, steering)
        stop.wait(0.05)


@pytest.mark.slow
def test_two_cars_behind_one_as_router_are_driven_independently(tmp_path):
    router_port = free_port()
    # both sims are ended (SIGINT) once the cars stand still again, not after a fixed duration
    car1 = start_sim(tmp_path / "car1", router_port, "zenoh.mode=router", "zenoh.namespace=/car1",
                     duration=180.0)
    car2 = None
    try:
        _wait_listening(router_port)
        car2 = start_sim(tmp_path / "car2", None, "zenoh.mode=client", "zenoh.listen=[]",
                         f'zenoh.connect=["{endpoint(router_port)}"]', "zenoh.namespace=/car2",
                         duration=180.0)
        with _connected(endpoint(router_port), namespace="/car1") as one:
            two = Car(namespace="/car2", session=one.session)  # one client session, both cars
            assert one.next_scan(timeout=30).ranges.size == 1081
            assert two.next_scan(timeout=30).ranges.size == 1081
            # 1.5 s at 20 Hz, and on while the odometry is read: read after the last command, a
            # late read on a loaded machine saw the car braking (the commands' timeout). A loaded
            # machine may also hold the driving thread up past the mux's 0.2 s timeout, and a car
            # brakes until the next command: the odometry is read until it shows both cars driving.
            stop_driving = threading.Event()
            driver = threading.Thread(target=_drive_at_20_hz, daemon=True,
                                      args=(stop_driving, (one, 0.5, 0.0), (two, 1.0, 0.2)))
            driver.start()
            try:
                driven = time.monotonic() + 1.5
                deadline = driven + 30
                while True:
                    odom1, odom2 = one.next_odom(), two.next_odom()
                    if time.monotonic() > driven and 0.3 < odom1.speed < 0.6 and 0.7 < odom2.speed < 1.1:
                        break
                    assert time.monotonic() < deadline, (odom1, odom2)
            finally:
                stop_driving.set()
                driver.join(timeout=30)
            for car in (one, two):  # the mux's timeout, then the brakes
                wait_standing(car)
            two.close()
        r2 = car2.interrupt()  # the client first: it would lose its router
        r1 = car1.interrupt()
    finally:
        car1.kill()
        if car2 is not None:
            car2.kill()
    assert "nav_0" in switches(r1) and "nav_0" in switches(r2)
    assert r1["max_speed_mps"] == pytest.approx(0.5, abs=0.05)
    assert r2["max_speed_mps"] == pytest.approx(1.0, abs=0.08)
    assert abs(r1["final_pose"]["yaw"]) < 0.05 < r2["final_pose"]["yaw"]
    assert 0.3 < odom1.speed < 0.6 and 0.7 < odom2.speed < 1.1
    assert r1["final_speed_mps"] == pytest.approx(0.0, abs=0.02)
    assert r2["final_speed_mps"] == pytest.approx(0.0, abs=0.02)


@pytest.mark.slow
def test_with_user_password_a_session_without_it_gets_nothing_and_cannot_drive(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("driver:s3cret\n")
    port = free_port()
    # ended (SIGINT) once the sessions are done, not after a fixed duration
    sim = start_sim(tmp_path / "sim", port, f"zenoh.auth.dictionary_file={users}", duration=180.0)
    try:
        _wait_listening(port)
        with pytest.raises(ClientError, match="cannot connect"):
            Car(endpoint(port))  # client mode: the daemon refuses the link
        with pytest.raises(ClientError, match="cannot connect"):
            Car(endpoint(port), user="driver", password="wrong")
        # a peer without credentials opens (it keeps retrying) but nothing flows either way
        intruder = Car(endpoint(port), mode="peer")
        with _connected(endpoint(port), user="driver", password="s3cret") as good:
            assert good.next_scan(timeout=30).ranges.size == 1081
            for _ in range(20):
                intruder.drive(2.0, 0.2)
                time.sleep(0.05)
            assert intruder.scan is None and intruder.odom is None
            with pytest.raises(ClientError):
                intruder.next_scan(timeout=0.5)
        intruder.close()
        report = sim.interrupt()
    finally:
        sim.kill()
    assert "nav_0" not in switches(report)
    assert report["distance_m"] < 0.05


@pytest.mark.slow
def test_the_asyncio_client_iterates_scans_and_odometry(tmp_path):
    port = free_port()
    # ended (SIGINT) once the car stands still after the client's stop: a fixed duration could
    # also end the run before a client held up on a loaded machine had its 30 scans
    sim = start_sim(tmp_path, port, duration=180.0)

    async def use() -> tuple[int, float]:
        async with AsyncCar(endpoint(port)) as car:
            n = 0
            async for scan in car.scans(timeout=30):
                assert scan.ranges.size == scan.angles.size == 1081
                n += 1
                car.drive(0.3, 0.0)
                # at least 30 scans, and on until the car moves: on a loaded machine the first
                # commands can go out before the daemon has matched the client's publisher
                latest = car.odom
                if n >= 30 and (n >= 400 or (latest is not None and latest.speed > 0.05)):
                    break
            async for odom in car.odometry(timeout=5):
                return n, odom.speed
        raise AssertionError("no odometry")

    try:
        _wait_listening(port)
        n, speed = asyncio.run(use())
        wait_until_stopped(port)
        report = sim.interrupt()
    finally:
        sim.kill()
    assert 30 <= n < 400 and 0.05 < speed < 0.4
    assert "nav_0" in switches(report)
    assert math.isclose(report["final_speed_mps"], 0.0, abs_tol=0.02)


@pytest.mark.slow
def test_safety_states_callbacks_remaps_and_leaving_the_block_stops_the_car_at_once(tmp_path):
    """The daemon uses F1TENTH names with /odom renamed, and its nav_0 input times out only after
    5 s (the longest an input may hold): a car that stops after the ``with`` block, with nav_0
    still the mux's source commanding zero and no safety intervention, was stopped by the client's
    stop command, not by a timeout."""
    port = free_port()
    remap = {"/odom": "/wheel/odom"}
    sim = start_sim(tmp_path, port, "mux.inputs.2.timeout_s=5", "zenoh.profile=f1tenth",
                    "zenoh.remap={/odom: /wheel/odom}", duration=120.0)
    try:
        _wait_listening(port)
        with _connected(endpoint(port), profile="f1tenth", remap=remap) as watcher:
            scans: list = []
            odoms: list = []
            states: list = []
            watcher.on_scan(scans.append)
            watcher.on_odom(odoms.append)
            watcher.on_safety(states.append)
            state = next(watcher.safety_states(timeout=30))
            assert state.reason in REASONS and isinstance(state.intervening, bool)
            assert math.isfinite(state.allowed_speed) and state.allowed_speed >= 0.0
            assert state.values["mode"] and state.msg.status[0].name == "safety"
            wait_for(lambda: len(scans) >= 3 and len(odoms) >= 3 and len(states) >= 2, timeout=30)
            assert all(s.ranges.size == 1081 for s in scans[:3])
            assert all(isinstance(o.speed, float) for o in odoms[:3])
            with Car(endpoint(port), profile="f1tenth") as unmapped, pytest.raises(ClientError):
                unmapped.wait_ready(timeout=2.0)  # the daemon's odometry is not on /odom
            with Car(endpoint(port), profile="f1tenth", remap=remap) as fresh:
                assert fresh.odom is None  # nothing has arrived the instant it connects
                fresh.wait_ready(timeout=30)
                assert fresh.scan is not None and fresh.odom is not None

            with Car(endpoint(port), profile="f1tenth", remap=remap) as driver:
                deadline = time.monotonic() + 30
                while watcher.odom is None or watcher.odom.speed < 0.4:
                    assert time.monotonic() < deadline, "the car never reached 0.4 m/s"
                    driver.drive(0.5, 0.0)  # /drive: nav_0 under the f1tenth profile
                    time.sleep(0.05)

            def stopped_by_nav_0() -> bool:
                values = watcher.safety.values  # the mux's command, before the safety limit
                assert values["interventions"] == 0, values  # not stopped by the wall ahead (typed)
                return (values["source"] == "nav_0" and values["commanded_speed"] == 0.0
                        and abs(watcher.odom.speed) < 0.02)

            # without the stop, nav_0 would hold 0.5 m/s for 5 s, until the safety controller
            # stopped the car at the wall ahead (and counted an intervention)
            wait_for(stopped_by_nav_0, timeout=20)
        sim.proc.send_signal(signal.SIGINT)
        report = sim.report()
    finally:
        sim.kill()
    assert report["max_speed_mps"] >= 0.4
    # nav_0 stayed the active source to the end: its zero command stopped the car, no timeout did
    assert switches(report)[-1] == "nav_0", report["mux_switches"]
    assert report["final_speed_mps"] == pytest.approx(0.0, abs=0.02)


def test_samples_are_decoded_when_read_and_only_the_newest():
    """The client's stream keeps a sample's bytes until somebody reads it: a reader gets the newest
    value, decoded once; a sample that does not decode is skipped (the last good value stays, a
    waiting reader waits on); with a callback every sample is decoded as it arrives."""
    from racecar_hw.base.messages import Header, LaserScan, Time  # noqa: PLC0415
    from racecar_hw.client import Scan, _scan, _Stream  # noqa: PLC0415
    from racecar_hw.rosmsg.typestore import ros2_types  # noqa: PLC0415

    decoded = []

    def decode(raw: bytes) -> Scan:
        decoded.append(raw)
        return _scan(ros2_types().deserialize(raw, LaserScan))

    def scan_bytes(sec: int) -> bytes:
        return ros2_types().serialize(LaserScan(Header(Time(sec, 0), "laser"), angle_increment=0.5,
                                                ranges=np.full(5, float(sec), dtype=np.float32)))

    stream = _Stream(decode)
    assert stream.latest is None
    for sec in (1, 2, 3):
        stream.push_raw(scan_bytes(sec))
    assert decoded == []  # nobody read yet
    value, seen = stream.wait_newer(0, timeout=1.0)
    assert value.stamp_s == 3.0 and seen == 3 and len(decoded) == 1
    assert np.array_equal(value.angles, 0.5 * np.arange(5)) and value.ranges.dtype == np.float64
    stream.push_raw(b"\x00\x01\x00\x00broken")
    assert stream.latest.stamp_s == 3.0  # the last good value
    with pytest.raises(ClientError):
        stream.wait_newer(seen, timeout=0.2)  # only a broken sample came since
    stream.push_raw(scan_bytes(4))
    assert stream.wait_newer(seen, timeout=1.0)[0].stamp_s == 4.0
    got = []
    stream.callbacks.append(got.append)
    stream.push_raw(scan_bytes(5))
    assert [s.stamp_s for s in got] == [5.0] and stream.latest.stamp_s == 5.0


def test_safety_values_are_typed_and_the_laser_pose_is_the_shipped_one():
    """``SafetyState.values`` as the safety node publishes them: numbers as numbers, true/false as
    bools, text as text; the documented laser pose is the shipped configs' base_link -> laser."""
    from racecar_hw.base.bus import Bus
    from racecar_hw.client import LASER_IN_BASE_LINK, _safety, typed_value
    from racecar_hw.config import load_config, shipped_config
    from safety.node import SafetyNode

    assert [typed_value(t) for t in ("3", "0.500", "-1.25", "inf", "true", "false", "", "nav_0")] == [
        3, 0.5, -1.25, math.inf, True, False, "", "nav_0"]
    config = load_config(None)
    node = SafetyNode(Bus(), config.safety, None)
    state = _safety(node.state_message())
    assert isinstance(state.values["allowed_speed"], float) and isinstance(state.values["intervening"], bool)
    assert isinstance(state.values["commanded_speed"], float) and isinstance(state.values["mode"], str)
    assert isinstance(state.values["memory_points"], int)
    assert state.intervening is state.values["intervening"] and state.reason == state.values["reason"]
    for name in ("car", "sim"):
        laser = next(t for t in load_config(shipped_config(name)).static_transforms
                     if t.child_frame_id == "laser")
        assert (*laser.xyz, 0.0) == pytest.approx(LASER_IN_BASE_LINK)


def test_the_mux_status_is_not_hidden_by_other_components_diagnostics():
    """``/diagnostics`` carries one array per component; a reader waiting for the mux's status gets
    it even when another component's array arrives right after it (the race that failed CI's
    e-stop test on a loaded machine: the newest sample was never the mux's when the reader woke)."""
    from racecar_hw.base.messages import DiagnosticArray, DiagnosticStatus, Header, KeyValue, Time  # noqa: PLC0415
    from racecar_hw.client import MUX_STATUS_NAME, _mux_status, _Stream  # noqa: PLC0415
    from racecar_hw.rosmsg.typestore import ros2_types  # noqa: PLC0415

    def array(name: str, state: str) -> bytes:
        status = DiagnosticStatus(DiagnosticStatus.OK, name, "", "", [KeyValue("state", state)])
        return ros2_types().serialize(DiagnosticArray(Header(Time(1, 0), ""), [status]))

    def decode(raw: bytes):
        return _mux_status(ros2_types().deserialize(raw, DiagnosticArray))

    stream = _Stream(decode, shared=True)
    stream.push_raw(array(MUX_STATUS_NAME, "estop"))
    stream.push_raw(array("racecar_hw: control loop", "whatever"))
    stream.push_raw(array("racecar_hw: network security", "whatever"))
    value, seen = stream.wait_newer(0, timeout=1.0)
    assert value.state == "estop" and seen == 1  # the other arrays were not counted
    with pytest.raises(ClientError, match="nothing received for 0.2 s"):
        stream.wait_newer(seen, timeout=0.2)
    stream.push_raw(array(MUX_STATUS_NAME, "running"))
    stream.push_raw(array("racecar_hw: control loop", "whatever"))
    assert stream.wait_newer(seen, timeout=1.0)[0].state == "running"


def test_closing_the_client_wakes_every_reader_with_a_clear_error():
    """A thread waiting for a scan with no timeout, and an async reader, when another thread closes
    the car: both get ClientError("the client is closed") instead of waiting forever; a read after
    close gets it at once. The car's peer is a bare Zenoh session: no daemon needed."""
    import zenoh

    from racecar_hw.net.zenoh_config import session_config

    port = free_port()
    peer = zenoh.open(session_config("peer", [f"tcp/127.0.0.1:{port}"], []))
    errors: list[BaseException] = []

    async def main() -> str:
        car = AsyncCar(f"tcp/127.0.0.1:{port}", mode="peer")

        def wait_forever() -> None:
            try:
                car.next_scan(timeout=None)  # the blocking Car method, in a thread
            except ClientError as err:
                errors.append(err)

        reader = threading.Thread(target=wait_forever, daemon=True)
        reader.start()
        threading.Timer(0.3, car.car.close).start()  # another thread closes the car
        try:
            async for _ in car.scans(timeout=None):
                pass
        except ClientError as err:
            reader.join(30)
            assert not reader.is_alive()
            with pytest.raises(ClientError, match="the client is closed"):
                car.next_scan(timeout=None)
            with pytest.raises(ValueError, match="must be finite"):  # checked before anything is sent
                car.twist(math.nan, 0.0)
            return str(err)
        return "ended without an error"

    try:
        assert asyncio.run(asyncio.wait_for(main(), 30)) == "the client is closed"
    finally:
        peer.close()
    assert [str(e) for e in errors] == ["the client is closed"]


def test_after_close_the_latest_values_and_wait_ready_raise_instead_of_answering_stale():
    """``car.scan``, ``car.odom``, ``car.safety``, ``now()`` on sim time and ``wait_ready()`` after
    close: ClientError("the client is closed"), as docs/interop.md says of a read after close (they
    gave the last values, and wait_ready returned, once a scan and odometry had come). The car's
    peer is a bare Zenoh session: the values are put in the client's streams by hand."""
    import zenoh

    from racecar_hw.net.zenoh_config import session_config

    port = free_port()
    peer = zenoh.open(session_config("peer", [f"tcp/127.0.0.1:{port}"], []))
    try:
        car = Car(f"tcp/127.0.0.1:{port}", mode="peer", use_sim_time=True)
        for stream in (car.scan_stream, car.odom_stream, car.safety_stream, car.clock_stream):
            stream.push(7)  # any value: what is read back is all that matters
        car.wait_ready(timeout=0)
        assert (car.scan, car.odom, car.safety, car.now_ns()) == (7, 7, 7, 7)
        car.close()
        for read in (lambda: car.scan, lambda: car.odom, lambda: car.safety, car.now, car.wait_ready):
            with pytest.raises(ClientError, match="^the client is closed$"):
                read()
    finally:
        peer.close()


@pytest.mark.parametrize(("connect", "words"), [
    ("localhost:7447", "connect: 'localhost:7447' is not a Zenoh endpoint (like tcp/127.0.0.1:7447); "
                       "protocols: tcp, udp, tls, quic, ws, unixsock-stream; "
                       "did you mean 'tcp/localhost:7447'?"),
    (["tcp/127.0.0.1:7447", "10.0.0.2:7447"], "'10.0.0.2:7447' is not a Zenoh endpoint"),
    ("tcp/localhost", "connect: 'tcp/localhost': expected host:port"),
    ("TCP/127.0.0.1:7447", "'TCP/127.0.0.1:7447' is not a Zenoh endpoint (like tcp/127.0.0.1:7447)"),
    ([7447], "7447 is not a Zenoh endpoint (like tcp/127.0.0.1:7447)"),
])
def test_an_endpoint_not_in_zenohs_form_is_refused_before_zenoh_reads_it(connect, words):
    """``Car("localhost:7447")`` said "is the daemon running, and does it want a user and password?
    (Zenoh: Json5Err(...))": now one line naming the endpoint and the form it wants."""
    with pytest.raises(ClientError) as err:
        Car(connect)
    assert words in str(err.value) and "\n" not in str(err.value)
    assert "Zenoh:" not in str(err.value) and "user and password" not in str(err.value)
