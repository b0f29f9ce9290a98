"""``racecar-hw run`` as systemd runs it: fake devices, a real NOTIFY_SOCKET, SIGTERM at the end."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from conftest import QUIET_NET, wait_for

from racecar_hw.base.errors import ConfigError
from racecar_hw.cli import main
from racecar_hw.config import load_config
from racecar_hw.control.stats import ControlStats
from vesc.codec import SetCurrentBrake, SetRpm, SetServoPosition


def _notifications(sock: socket.socket, until: float, last: str = "STOPPING=1") -> list[str]:
    """The notifications that arrive before ``until`` (monotonic s), or up to ``last``."""
    got: list[str] = []
    sock.settimeout(0.2)
    while time.monotonic() < until:
        try:
            got.extend(sock.recv(4096).decode().split("\n"))
        except TimeoutError:
            continue
        if any(line == last for line in got):
            break
    return got


def _recording_config(tmp_path: Path, lidar: Any, **recorder: Any) -> Path:
    """A car config for ``run`` on the fakes (the lidar over TCP), no network interface but the live
    view and the page on free ports, recording to ``tmp_path/bags`` with ``recorder``'s settings."""
    host, port = lidar.tcp_address
    config = {
        "vesc": {"port": str(tmp_path / "vesc")},
        "lidar": {"model": "ust-10lx", "tcp": f"{host}:{port}"},
        "status": {"enabled": False}, "zenoh": {"enabled": False}, "dds": {"enabled": False},
        "foxglove": {"port": 0}, "web": {"port": 0},
        "recorder": {"enabled": True, "path": str(tmp_path / "bags"), **recorder},
    }
    cfg = tmp_path / "car.yaml"
    cfg.write_text(yaml.safe_dump(config))
    return cfg


def test_run_notifies_systemd_records_and_stops_safely_on_sigterm(fakes, tmp_path):
    vesc, lidar = fakes
    cfg = _recording_config(tmp_path, lidar, name="drive", format="mcap")
    notify = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(notify))
    env = dict(os.environ, NOTIFY_SOCKET=str(notify), WATCHDOG_USEC="400000")
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "-v", "run", "--config", str(cfg)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        got = _notifications(sock, time.monotonic() + 20, last="READY=1")
        assert "READY=1" in got
        wait_for(lambda: vesc.timed_out is False and len(vesc.commands) > 20, timeout=20)
        got = _notifications(sock, time.monotonic() + 1.0)
        assert got.count("WATCHDOG=1") >= 2  # pinged at half of 0.4 s while the loop runs
        vesc.clear_commands()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    assert proc.returncode == 0, err
    commands = [c.packet for c in vesc.commands]
    motor = [p for p in commands if isinstance(p, (SetRpm, SetCurrentBrake))]
    servo = [p for p in commands if isinstance(p, SetServoPosition)]
    assert motor and (isinstance(motor[-1], SetCurrentBrake) or motor[-1].erpm == 0)
    assert servo and servo[-1].position == pytest.approx(0.5304, abs=1e-3)
    # every scan re-sent the (idle) command at once; the shutdown summary times those writes
    summary = re.search(r"scan-to-command latency p50=([\d.]+) ms p99=([\d.]+) ms max=([\d.]+) ms "
                        r"over (\d+) scans; on the CPU p50=([\d.]+) ms p99=([\d.]+) ms; "
                        r"off it p99=([\d.]+) ms", err)
    assert summary, err[-2000:]
    p50, p99, worst, scans, cpu_p50, cpu_p99, off_p99 = map(float, summary.groups())
    assert scans > 0 and 0.0 < p50 <= p99 <= worst
    # each scan's CPU time is part of its latency, so its percentiles are too
    assert 0.0 < cpu_p50 <= p50 and cpu_p50 <= cpu_p99 <= p99 and 0.0 <= off_p99 <= worst
    bags = list((tmp_path / "bags").rglob("*.mcap"))
    assert bags, "the recorder left no bag"
    from rosbags.highlevel import AnyReader

    with AnyReader([bags[0].parent]) as reader:
        topics = {c.topic for c in reader.connections}
    assert {"/scan", "/odom", "/vesc/sensors/core", "/tf_static"} <= topics


def test_run_exits_1_and_says_so_when_the_recording_failed(fakes, tmp_path):
    """The recorder's disk stops taking bytes while the daemon runs (a real write error: a file-size
    limit the bag soon passes): the car drives on, as before, but at SIGTERM ``run`` exited 0 with
    the lost recording only in the log; now 1, with one line saying why, as ``sim``."""
    import resource
    import threading

    _vesc, lidar = fakes
    cfg = _recording_config(tmp_path, lidar, flush_interval_s=0.2)
    limit = 100_000  # bytes: a second or two of scans
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "run", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    watchdog = threading.Timer(120, proc.kill)  # a run that never fails its recording ends the test
    watchdog.start()
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if "bag writing failed" in line:
                break
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, err
    # said by the command at its end, not a crash; the cut bag's abort is one log line too (its
    # file's close, writing the buffered bytes again, showed a traceback in 4 of 6 runs)
    assert "Traceback" not in err, err
    assert re.search(r"^racecar-hw run: the recording failed: OSError: \[Errno 27\] File too large "
                     r"\(\d+ messages on disk, \d+ dropped; ", err, re.MULTILINE), err


def test_latency_summary_splits_time_on_and_off_the_cpu():
    stats = ControlStats()
    for k in range(1, 101):  # 1..100 ms, of which k / 2 ms on the CPU and one slow scan off it
        stats.scan_to_command_ns.append(k * 1_000_000)
        stats.scan_to_command_cpu_ns.append(k * 500_000 if k < 100 else 1_000_000)
    got = stats.latency_ms()
    assert got == {"p50": 51.0, "p99": 100.0, "max": 100.0, "count": 100.0,
                   "cpu_p50": 25.0, "cpu_p99": 49.5, "off_cpu_p99": 99.0}
    assert ControlStats().latency_ms() == {}
    assert "p50=51.000 ms p99=100.000 ms max=100.000 ms over 100 scans" in stats.summary()
    empty = ControlStats().summary()  # no VESC, no lidar: nothing was timed, and it says so
    assert "nan" not in empty and "no scan-to-command latency measured" in empty


def test_a_missing_vesc_shows_as_connecting_on_the_panel(tmp_path):
    """racecar-hw run without its VESC: the panel says 'connecting N s' (and the log reminds, see
    test_links.py) instead of one warning and silence."""
    import asyncio

    from racecar_hw.daemon import Daemon

    config = load_config(None, [f"vesc.port={tmp_path / 'no-vesc'}", "lidar.enabled=false",
                                "gamepad.enabled=false", "status.enabled=false",
                                "safety.mode=off", *QUIET_NET])

    async def scenario() -> tuple[str | None, str | None]:
        daemon = Daemon(config)
        stop = asyncio.Event()
        task = asyncio.create_task(daemon.run(stop))
        assert daemon.vesc is not None
        deadline = time.monotonic() + 20
        while daemon.vesc.last_error is None and time.monotonic() < deadline:
            await asyncio.sleep(0.05)  # until the driver tried the port and failed
        assert daemon.vesc.last_error is not None
        snap = daemon.snapshot()
        stop.set()
        await asyncio.wait_for(task, 20)
        return snap.vesc_link, snap.lidar_link

    vesc_link, lidar_link = asyncio.run(scenario())
    assert vesc_link is not None and vesc_link.startswith("connecting ")
    assert lidar_link is None  # no lidar configured: no lidar link shown


def test_config_errors_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="^vesc.speed_to_erpm_gian: unknown key"):
        load_config(None, ["vesc.speed_to_erpm_gian=1"])
    allowed = r"^lidar.model: 'hokuyo' \(str\) is not allowed; allowed values: urg-04lx"
    with pytest.raises(ConfigError, match=allowed):
        load_config(None, ["lidar.model=hokuyo"])
    with pytest.raises(ConfigError, match="^telemetry: unknown section"):
        load_config(None, ["telemetry.rate=1"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("vesc: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)


def test_rplidar_needs_safety_timing_for_its_sweep_rate():
    with pytest.raises(ConfigError, match="^safety.scan_timeout_s: 0.1 s is shorter than two sweeps"):
        load_config(None, ["lidar.model=a1", "lidar.port=/dev/sensors/rplidar", "lidar.tcp=null"])
    config = load_config(None, ["lidar.model=a1", "lidar.port=/dev/sensors/rplidar", "lidar.tcp=null",
                                "safety.scan_timeout_s=0.3", "safety.scan_period_s=0.1"])
    assert config.safety.scan_timeout_s == 0.3


def test_check_config_prints_the_effective_config(capsys):
    # in this process: what the command prints is the subject, not its process
    assert main(["check-config", "--set", "mux.rate_hz=40"]) == 0
    data = yaml.safe_load(capsys.readouterr().out)
    assert data["mux"]["rate_hz"] == 40.0
    assert data["vesc"]["speed_to_erpm_gain"] == 4614.0
    assert data["static_transforms"][0]["child_frame_id"] == "laser"
    assert main(["check-config", "--set", "safety.margin_m=-1"]) == 1
    err = capsys.readouterr().err
    assert "safety.margin_m" in err and "out of range" in err


@pytest.mark.slow
def test_follow_command_refuses_a_disarmed_car_then_drives_a_twist_bag_with_arm(fakes, tmp_path, capsys,
                                                                                caplog):
    """A cmd_vel bag (geometry_msgs/Twist, as most public bags carry) on the car config, which
    starts disarmed: refused in one line (the command in this process: its line and its log's
    warnings), then followed with --arm (a process, as a user runs it); the topic is found alone."""
    import math

    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    vesc, lidar = fakes
    store = get_typestore(Stores.ROS2_HUMBLE)
    twist, vector3 = store.types["geometry_msgs/msg/Twist"], store.types["geometry_msgs/msg/Vector3"]
    bag = tmp_path / "drive"
    with Writer2(bag, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/cmd_vel", "geometry_msgs/msg/Twist", typestore=store)
        for i in range(30):  # 1.5 s at 20 Hz: 0.5 m/s turning left at 0.2 rad/s
            msg = twist(vector3(0.5, 0.0, 0.0), vector3(0.0, 0.0, 0.2))
            writer.write(conn, 1_700_000_000_000_000_000 + i * 50_000_000,
                         store.serialize_cdr(msg, "geometry_msgs/msg/Twist"))
    host, port = lidar.tcp_address
    cfg = tmp_path / "car.yaml"
    cfg.write_text(yaml.safe_dump({
        "vesc": {"port": str(tmp_path / "vesc")},
        "lidar": {"model": "ust-10lx", "tcp": f"{host}:{port}"},
        "gamepad": {"enabled": False}, "status": {"enabled": False},
        "zenoh": {"enabled": False}, "dds": {"enabled": False}, "foxglove": {"port": 0}, "web": {"port": 0},
    }))
    caplog.set_level("WARNING")
    assert main(["follow", str(bag), "--config", str(cfg)]) == 1
    refused = capsys.readouterr().err + "".join(f"{r.getMessage()}\n" for r in caplog.records)
    assert refused.count("\n") == 1 and "starts disarmed" in refused
    assert "--arm" in refused
    assert not any(isinstance(c.packet, SetRpm) for c in vesc.commands)  # never connected
    command = [sys.executable, "-m", "racecar_hw.cli", "follow", str(bag), "--config", str(cfg)]
    proc = subprocess.run([*command, "--arm"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr

    def erpms() -> list[float]:
        return [c.packet.erpm for c in vesc.commands if isinstance(c.packet, SetRpm)]

    # the replay's last frames, its shutdown's brake, may still wait in the pty for the fake's
    # thread in this (loaded) process when the replay's process has ended
    wait_for(lambda: erpms() and erpms()[-1] == 0, timeout=10)
    # 0.5 m/s x 4614 ERPM per m/s, reached through the rate limiter; then brake at the end
    assert max(erpms()) == pytest.approx(0.5 * 4614, abs=2)
    servo = [c.packet.position for c in vesc.commands if isinstance(c.packet, SetServoPosition)]
    steering = math.atan(0.25 * 0.2 / 0.5)  # the yaw rate's steering on a 0.25 m wheelbase
    assert min(servo) == pytest.approx(0.5304 - 1.2135 * steering, abs=2e-3)


def test_follow_fails_in_one_line_for_a_missing_bag_or_topic(tmp_path, capsys):
    assert main(["follow", str(tmp_path / "nope"), "--arm"]) == 1
    assert capsys.readouterr().err == f"racecar-hw follow: bag not found: {tmp_path / 'nope'}\n"
    bag = tmp_path / "b.bag"
    from racecar_hw.bags.record import BagFile
    from racecar_hw.base.messages import AckermannDriveStamped
    from racecar_hw.rosmsg.typestore import types_for

    f = BagFile(bag, "ros1", "none", types_for(1))
    f.write("/a", AckermannDriveStamped(), 1)
    f.close()
    assert main(["follow", str(bag), "--arm", "--topic", "/b"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("racecar-hw follow: topic /b is not in") and err.count("\n") == 1


def _short_drive_bag(path) -> None:
    """A ROS 1 bag of 10 AckermannDriveStamped commands at 0.5 m/s."""
    from racecar_hw.bags.record import BagFile
    from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped
    from racecar_hw.rosmsg.typestore import types_for

    f = BagFile(path, "ros1", "none", types_for(1))
    for i in range(10):
        f.write("/nav", AckermannDriveStamped(drive=AckermannDrive(speed=0.5)), 1 + i * 50_000_000)
    f.close()


def _no_network(tmp_path) -> dict:
    return {"gamepad": {"enabled": False}, "status": {"enabled": False},
            "zenoh": {"enabled": False}, "foxglove": {"enabled": False}, "web": {"enabled": False},
            "lidar": {"enabled": False}}


def test_follow_arm_against_a_missing_vesc_port_exits_1_saying_why(tmp_path):
    """A replay that never reached a VESC did not drive the car: exit 1 and say why, not 100 % and 0."""
    bag = tmp_path / "drive.bag"
    _short_drive_bag(bag)
    cfg = tmp_path / "car.yaml"
    cfg.write_text(yaml.safe_dump({**_no_network(tmp_path), "vesc": {"port": str(tmp_path / "nope")}}))
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "follow", str(bag), "--arm",
                           "--config", str(cfg)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("racecar-hw follow: no motor command reached the VESC: it never connected")
    assert str(tmp_path / "nope") in last and "Traceback" not in proc.stderr
    # a port that does not exist is not waited for (docs/bags.md): the bag is not played into nothing
    assert f"the VESC's port {tmp_path / 'nope'} does not exist" in proc.stderr
    assert "replaying anyway" not in proc.stderr


def test_run_with_a_bag_follower_against_a_missing_vesc_exits_1_saying_why(tmp_path):
    bag = tmp_path / "drive.bag"
    _short_drive_bag(bag)
    cfg = tmp_path / "car.yaml"
    cfg.write_text(yaml.safe_dump({
        **_no_network(tmp_path), "vesc": {"port": str(tmp_path / "nope")},
        "arming": {"start_armed": True},
        "follower": {"enabled": True, "bag": str(bag),
                     "input_topic": "/vesc/high_level/ackermann_cmd_mux/input/nav_0"}}))
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "-v", "run", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        lines: list[str] = []
        while time.monotonic() < deadline:  # wait for the daemon to run before stopping it
            line = proc.stderr.readline()
            lines.append(line)
            if "racecar-hw running" in line or not line:
                break
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, "".join(lines) + err
    assert "racecar-hw run: no motor command reached the VESC: it never connected" in err


def test_follow_arm_with_the_vesc_connected_exits_0(fakes, tmp_path):
    vesc, lidar = fakes
    host, port = lidar.tcp_address
    bag = tmp_path / "drive.bag"
    _short_drive_bag(bag)
    cfg = tmp_path / "car.yaml"
    cfg.write_text(yaml.safe_dump({**_no_network(tmp_path), "vesc": {"port": str(tmp_path / "vesc")},
                                   "lidar": {"model": "ust-10lx", "tcp": f"{host}:{port}"}}))
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "follow", str(bag), "--arm",
                           "--config", str(cfg)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert any(isinstance(c.packet, SetRpm) and c.packet.erpm > 0 for c in vesc.commands)


@pytest.mark.parametrize("where", ["exists", "file"])
def test_a_bag_that_cannot_be_created_ends_run_in_one_line_with_zenoh_closed(tmp_path, where):
    """A recorder that cannot open its bag (a fixed recorder.name after a restart, a file where the
    folder should be) refuses in one line, and the process ends: the Zenoh session opened before
    it was left open, and its threads kept the process alive through SIGTERM and SIGINT."""
    from zenoh_util import endpoint, free_port

    bags = tmp_path / "bags"
    if where == "exists":
        (bags / "drive").mkdir(parents=True)
    else:
        bags.write_text("not a folder")
    cfg = tmp_path / "car.yaml"
    cfg.write_text(yaml.safe_dump({
        **_no_network(tmp_path), "vesc": {"port": str(tmp_path / "nope")},
        "zenoh": {"enabled": True, "listen": [endpoint(free_port())]},
        "recorder": {"enabled": True, "path": str(bags), "name": "drive"}}))
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "run", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    why = "it exists already, not overwriting" if where == "exists" else "cannot create the bag folder"
    assert proc.stderr.startswith("racecar-hw run: ") and why in proc.stderr, proc.stderr
