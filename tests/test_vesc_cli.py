"""``racecar-hw fake-vesc`` and ``racecar-hw vesc-info``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from conftest import wait_for

from racecar_hw.cli import main
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
    assert main(["vesc-info", "--port", fake.path]) == 0
    out = capsys.readouterr().out
    assert "firmware: 5.02" in out
    assert "layout V3_60, 73 bytes" in out
    assert "v_in                 16.8" in out


def test_vesc_info_without_a_device(tmp_path, capsys):
    assert main(["vesc-info", "--port", str(tmp_path / "missing")]) == 1
    assert "no serial device" in capsys.readouterr().err


def test_vesc_info_times_out_on_a_silent_port(tmp_path, capsys):
    from racecar_hw.runtime.fakepty import PtyPort

    with PtyPort(str(tmp_path / "silent")) as port:
        assert main(["vesc-info", "--port", port.path, "--timeout", "0.3"]) == 1
    assert "no FwVersion reply" in capsys.readouterr().err


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_fake_vesc_command_serves_until_ctrl_c(tmp_path, stop):
    link = tmp_path / "vesc"
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "fake-vesc", "--link", str(link),
                             "--firmware", "3.40"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_for(lambda: os.path.exists(link) or proc.poll() is not None)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        info = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "vesc-info", "--port", str(link)],
                              capture_output=True, text=True, timeout=60)
        assert info.returncode == 0, info.stderr
        assert "firmware: 3.40" in info.stdout
        proc.send_signal(stop)
        assert proc.wait(30) == 0
        assert not os.path.exists(link)  # the symlink goes with the fake, however it is stopped
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
