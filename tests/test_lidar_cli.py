"""``racecar-hw fake-lidar`` and ``racecar-hw lidar-info`` against real ptys, TCP and a subprocess."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import socket
import subprocess
import sys

import pytest
from conftest import reaped, wait_for

from lidar_drivers.base import RoomRangeSource
from lidar_drivers.rplidar_fake import FakeRplidar
from lidar_drivers.scip_fake import FakeHokuyo
from racecar_hw.cli import main


@pytest.mark.parametrize("command", ["fake-lidar", "lidar-info"])
def test_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert "--model" in capsys.readouterr().out


def test_bad_arguments_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["fake-lidar", "--model", "ust-10lx", "--tcp", "127.0.0.1:0", "--room", "0x3"])
    assert exc.value.code == 2
    assert main(["fake-lidar", "--model", "ust-10lx"]) == 2


@pytest.mark.parametrize("model", ["urg-04lx", "utm-30lx"])
def test_a_usb_hokuyo_is_not_served_over_tcp(model, capsys):
    """The URG-04LX and UTM-30LX have no Ethernet port, so the fake does not pretend they do."""
    assert main(["fake-lidar", "--model", model, "--tcp", "127.0.0.1:0"]) == 2
    out = capsys.readouterr().out
    assert f"the {model} is a USB lidar with no Ethernet port; serve it on a pty with --link PATH" in out


@pytest.mark.parametrize(("model", "kind"), [("urg-04lx", "a USB lidar"), ("a1", "a serial lidar")])
def test_lidar_info_refuses_tcp_for_a_lidar_without_ethernet(model, kind, capsys):
    assert main(["lidar-info", "--tcp", "127.0.0.1:1", "--model", model]) == 2
    out = capsys.readouterr().out
    assert out == f"racecar-hw lidar-info: the {model} is {kind} with no Ethernet port; use --port\n"


@pytest.mark.parametrize("transport", ["tcp", "pty"])
def test_lidar_info_against_the_fake(device_thread, tmp_path, capsys, transport):
    fake = FakeHokuyo("urg-04lx" if transport == "pty" else "ust-10lx", RoomRangeSource(8, 6),
                      link=str(tmp_path / "urg") if transport == "pty" else None,
                      tcp=("127.0.0.1", 0) if transport == "tcp" else None)
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)
    where = (["--tcp", "{}:{}".format(*fake.tcp_address)] if transport == "tcp"
             else ["--port", fake.path])
    assert main(["lidar-info", *where, "--model", fake.model.name, "--timeout", "15"]) == 0
    out = capsys.readouterr().out
    assert fake.model.model in out and f"firmware:   {fake.model.firmware}" in out
    assert f"{fake.model.steps} beams" in out
    # in the middle of an 8 x 6 m room the nearest wall is 3 m away at +-90 deg
    closest = re.search(r"closest:\s+([\d.]+) m at (-?[\d.]+) deg", out)
    assert closest and float(closest[1]) == pytest.approx(3.0, abs=0.002)
    assert abs(float(closest[2])) == pytest.approx(90, abs=2)
    assert re.search(r"farthest:\s+([\d.]+) m", out)


def test_lidar_info_without_a_device_fails_cleanly(tmp_path, capsys):
    assert main(["lidar-info", "--port", str(tmp_path / "none"), "--model", "urg-04lx",
                 "--timeout", "0.5"]) == 1
    assert "no scan" in capsys.readouterr().out


def test_lidar_info_where_nothing_listens_says_so_and_not_give_model(capsys):
    """Nothing at the address: the advice was "give --model", which no model would have helped."""
    with socket.socket() as bound:  # bound, not listening: a connection is refused
        bound.bind(("127.0.0.1", 0))
        address = "{}:{}".format(*bound.getsockname())
        assert main(["lidar-info", "--tcp", address, "--timeout", "0.3"]) == 1
    out = capsys.readouterr().out
    assert out == (f"racecar-hw lidar-info: nothing listens at {address}; check the address (lidar.tcp), "
                   "the cable and the lidar's power\n")


def test_lidar_info_where_something_answers_but_no_lidar_gives_model(device_thread, capsys):
    """Something answers at the address, but not as a UST-10LX names itself: then --model helps."""
    async def chatter(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError):
            while await reader.read(100):
                writer.write(b"no SCIP here\n\n")
        writer.close()

    server = device_thread.call(asyncio.start_server, chatter, "127.0.0.1", 0)
    try:
        address = "{}:{}".format(*server.sockets[0].getsockname())
        assert main(["lidar-info", "--tcp", address, "--timeout", "0.5"]) == 1
    finally:
        device_thread.call(server.close)
    out = capsys.readouterr().out
    assert out.startswith("racecar-hw lidar-info: something answered but no lidar named itself within 0.5 s, "
                          "tried as ust-10lx") and out.endswith("; give --model\n"), out


def test_fake_lidar_process_serves_until_ctrl_c(capsys):
    # started as a background job of a script or CI job is: SIGINT ignored (see test_vesc_cli.py)
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "fake-lidar", "--model",
                             "ust-10lx", "--tcp", "127.0.0.1:0", "--room", "10x4"],
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    with reaped(proc):
        assert proc.stdout is not None
        line = proc.stdout.readline()
        port = re.search(r"tcp 127\.0\.0\.1:(\d+)", line)
        assert port, line
        assert main(["lidar-info", "--tcp", f"127.0.0.1:{port[1]}", "--model", "ust-10lx",
                     "--timeout", "15"]) == 0
        assert "closest:    2.000 m" in capsys.readouterr().out  # 10 x 4 room: 2 m to the side
        proc.send_signal(signal.SIGINT)
        assert proc.wait(20) == 0


def test_lidar_info_names_the_model_the_device_reports(device_thread, tmp_path, capsys):
    fake = FakeRplidar("c1", RoomRangeSource(8, 6), str(tmp_path / "rplidar"))
    device_thread.spawn(fake.serve())
    wait_for(lambda: fake.port.plugged)
    assert main(["lidar-info", "--port", fake.link, "--model", "a1", "--timeout", "15"]) == 0
    out = capsys.readouterr().out
    assert "model:      a1 (device reports C1M1)" in out
    assert "the device reports C1M1, not A1M8 (a1); use --model c1" in out
    assert "scan_mode:  DenseBoost" in out


def test_fake_rplidar_process_old_firmware_and_sigterm(tmp_path, capsys):
    """``--firmware 1.20``: the legacy scan commands; SIGTERM removes the link like Ctrl-C."""
    link = tmp_path / "rplidar"
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "fake-lidar", "--model", "a2m8",
                             "--link", str(link), "--firmware", "1.20"],
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    with reaped(proc):
        assert proc.stdout is not None
        assert "fake a2m8 at pty" in proc.stdout.readline()
        assert main(["lidar-info", "--port", str(link), "--model", "a2m8", "--timeout", "15"]) == 0
        out = capsys.readouterr().out
        assert "firmware:   1.20" in out and "scan_mode:  Express" in out
        assert "scan_modes: Standard, Express* (* typical)" in out
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
        assert not link.exists()


@pytest.mark.parametrize("kind", ["ust-20lx tcp", "urg-04lx pty", "c1 pty"])
def test_lidar_info_takes_the_model_the_device_reports_without_model(device_thread, tmp_path, capsys, kind):
    """No --model: the device's own name picks it (Ethernet: SCIP; serial: SCIP, then RPLIDAR)."""
    model, transport = kind.split()
    if model == "c1":
        fake = FakeRplidar("c1", RoomRangeSource(8, 6), str(tmp_path / "rplidar"))
        device_thread.spawn(fake.serve())
        wait_for(lambda: fake.port.plugged)
        where = ["--port", fake.link]
    else:
        fake = FakeHokuyo(model, RoomRangeSource(8, 6), link=str(tmp_path / "urg") if transport == "pty"
                          else None, tcp=("127.0.0.1", 0) if transport == "tcp" else None)
        device_thread.spawn(fake.serve())
        assert fake.ready.wait(10)
        where = (["--tcp", "{}:{}".format(*fake.tcp_address)] if transport == "tcp"
                 else ["--port", fake.path])
    assert main(["lidar-info", *where, "--timeout", "10"]) == 0
    out = capsys.readouterr().out
    assert re.search(rf"^model:      {model} \(device reports \S+\), detected$", out, re.M), out
    assert "warning" not in out and re.search(r"closest:\s+[\d.]+ m", out)
