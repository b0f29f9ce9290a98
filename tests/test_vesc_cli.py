"""``racecar-hw fake-vesc`` and ``racecar-hw vesc-info``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from conftest import reaped, wait_for

from racecar_hw.cli import main
from vesc.codec import GetValuesRequest
from vesc.fake import FakeVesc


@pytest.mark.parametrize("command", ["fake-vesc", "vesc-info"])
def test_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert command in capsys.readouterr().out


def test_vesc_info_against_the_fake(tmp_path, device_thread, capsys):
    fake = FakeVesc(str(tmp_path / "vesc"), firmware=(5, 2)).open()
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)
    assert main(["vesc-info", "--port", fake.path]) == 0
    out = capsys.readouterr().out
    assert "firmware: 5.02" in out
    assert "layout V3_60, 73 bytes" in out
    assert "v_in                 16.8" in out


@pytest.mark.parametrize("firmware", [(9, 1), (1, 5), (6, 100)])
def test_vesc_info_reports_an_unknown_firmware_as_unknown_and_decodes_no_telemetry(
        tmp_path, device_thread, capsys, firmware):
    """A firmware outside the layouts the codec knows (2.0 to 7.99): no GET_VALUES is asked, no field
    printed, and the exit status says the driver will not drive it."""
    fake = FakeVesc(str(tmp_path / "vesc"), firmware=firmware).open()
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)
    assert main(["vesc-info", "--port", fake.path]) == 1
    out, err = capsys.readouterr()
    version = f"{firmware[0]}.{firmware[1]:02d}"
    assert f"firmware: {version} (unknown)" in out and "hardware: " in out
    assert "telemetry" not in out and "v_in" not in out
    assert f"firmware {version} is not one racecar-hw knows (it knows 2.x to 7.x)" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not any(isinstance(r.packet, GetValuesRequest) for r in fake.commands)


def test_vesc_info_without_a_device(tmp_path, capsys):
    assert main(["vesc-info", "--port", str(tmp_path / "missing")]) == 1
    assert "no serial device" in capsys.readouterr().err


def test_vesc_info_times_out_on_a_silent_port(tmp_path, capsys):
    from racecar_hw.runtime.fakepty import PtyPort

    with PtyPort(str(tmp_path / "silent")) as port:
        assert main(["vesc-info", "--port", port.path, "--timeout", "0.3"]) == 1
    assert "no FwVersion reply" in capsys.readouterr().err


def ignore_sigint() -> None:
    """What a non-interactive shell does to a background job (``cmd &`` in a script, a CI job):
    SIGINT ignored, inherited by every child. This is how these tests failed on a busy CI machine
    whose test run had been started in the background: the fakes ignored SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_fake_vesc_command_serves_until_ctrl_c(tmp_path, stop):
    link = tmp_path / "vesc"
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "fake-vesc", "--link", str(link),
                             "--firmware", "3.40"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=ignore_sigint)
    with reaped(proc):
        wait_for(lambda: os.path.exists(link) or proc.poll() is not None, timeout=60)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        info = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "vesc-info", "--port", str(link)],
                              capture_output=True, text=True, timeout=60)
        assert info.returncode == 0, info.stderr
        assert "firmware: 3.40" in info.stdout
        proc.send_signal(stop)
        assert proc.wait(30) == 0
        assert not os.path.exists(link)  # cleaned up: the pty's symlink is gone
        assert b"Traceback" not in (proc.stderr.read() if proc.stderr else b"")


def test_vesc_info_into_a_closed_pipe_ends_quietly(tmp_path, device_thread):
    """``racecar-hw vesc-info --port X | head -1``: the reader leaves early; no BrokenPipeError."""
    fake = FakeVesc(str(tmp_path / "vesc"), firmware=(6, 2)).open()
    device_thread.spawn(fake.serve())
    assert fake.ready.wait(10)
    read, write = os.pipe()
    os.close(read)  # the reader is gone before anything is written
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "vesc-info", "--port", fake.path],
                          stdout=write, stderr=subprocess.PIPE, text=True, timeout=60)
    os.close(write)
    assert proc.returncode == 128 + signal.SIGPIPE
    assert proc.stderr == ""
