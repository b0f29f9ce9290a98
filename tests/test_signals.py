"""racecar_hw.runtime.signals and .interrupts: SIGINT and SIGTERM stop a command whatever it inherited,
from its first moment."""

from __future__ import annotations

import asyncio
import gc
import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from conftest import QUIET_NET, reaped, set_args, wait_for

from racecar_hw.runtime import signals


def test_a_signal_cancels_the_coroutine_and_its_clean_up_runs() -> None:
    ended = []

    async def serve() -> None:
        loop = asyncio.get_running_loop()
        loop.call_later(0.05, os.kill, os.getpid(), signal.SIGTERM)
        try:
            await asyncio.Event().wait()
        finally:
            ended.append(True)

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job inherits it
    try:
        assert signals.run_until_stop_signal(serve) is None
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # left as it was found
    finally:
        signal.signal(signal.SIGINT, previous)
    assert ended == [True]


def test_ctrl_c_before_the_loop_runs_leaves_nothing_never_awaited(monkeypatch) -> None:
    """An early Ctrl-C once printed "coroutine 'FakeVesc.serve' was never awaited"."""
    made = []

    async def serve() -> None:
        made.append(True)

    def interrupted_run(coro: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C while asyncio.run sets up its loop

    monkeypatch.setattr(signals.asyncio, "run", interrupted_run)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert signals.run_until_stop_signal(serve) is None
        gc.collect()
    assert not [w for w in caught if "never awaited" in str(w.message)]
    assert made == []


# --- a real racecar-hw process, stopped while it starts -------------------------------------------


def _catches(pid: int, sig: int) -> bool:
    """Whether the process has a handler of its own for ``sig`` (its SigCgt mask in /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(int(line.split()[1], 16) for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(mask >> (sig - 1) & 1)


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job of a script inherits it


START_UP = {
    "fake-vesc": (["fake-vesc", "--link", "{tmp}/vesc"], "fake VESC"),
    "sim": (["sim", "--duration", "60", "--no-status", *set_args(*QUIET_NET), "--out", "{tmp}/out"],
            "figure8:"),
}


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=["SIGINT", "SIGTERM", "SIGHUP"])
@pytest.mark.parametrize("command", sorted(START_UP))
def test_a_stop_signal_as_the_command_starts_ends_it_quietly(tmp_path, command, stop) -> None:
    """Sent as soon as racecar-hw handles it (its first line; about a second of imports is still
    to come), to a background job that inherited SIGINT ignored: the signal is not lost (a
    fake-vesc once served on for ten minutes) and there is no traceback; exit 130, nothing done."""
    argv, banner = START_UP[command]
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli",
                             *[a.format(tmp=tmp_path) for a in argv]],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_ignore_sigint)
    with reaped(proc):
        wait_for(lambda: _catches(proc.pid, stop) or proc.poll() is not None, timeout=60, interval=0.001)
        proc.send_signal(stop)
        out, err = proc.communicate(timeout=60)
    assert "Traceback" not in err and "Error" not in err, err
    if banner in out:  # a machine so loaded that the start-up was over first: the command's own end
        assert proc.returncode == 0, err
        return
    assert proc.returncode == 130, (out, err)
    assert out == "" and err == ""
    assert not (tmp_path / "vesc").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", sorted(START_UP))
def test_a_sigterm_the_moment_the_process_exists_never_leaves_it_running(tmp_path, command) -> None:
    """Before racecar-hw's first line the inherited default ends the process; after it, exit 130."""
    argv, _banner = START_UP[command]
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli",
                             *[a.format(tmp=tmp_path) for a in argv]],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.send_signal(signal.SIGTERM)
    with reaped(proc):
        out, err = proc.communicate(timeout=60)
    assert proc.returncode in (-signal.SIGTERM, 130), (out, err)
    assert out == "" and err == ""


def test_a_stop_signal_after_the_banner_ends_fake_vesc_as_documented(tmp_path) -> None:
    """Once it serves, a stop signal is its normal end: exit 0, the link removed, no traceback."""
    link = tmp_path / "vesc"
    proc = subprocess.Popen([sys.executable, "-m", "racecar_hw.cli", "fake-vesc", "--link", str(link)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_ignore_sigint)
    with reaped(proc):
        assert proc.stdout is not None
        assert "fake VESC" in proc.stdout.readline()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "Traceback" not in err, err
    assert not link.exists()


def test_ctrl_c_held_down_through_the_end_of_run_still_exits_0(tmp_path) -> None:
    """SIGINT after SIGINT (every 3 ms) from the first until the process is gone: ``run`` stops
    once, closes its ROS 1 bag and exits 0. The signals that came while the interpreter exited met
    Python's own handler again and ended the process as killed by SIGINT (-2)."""
    import time

    cmd = [sys.executable, "-m", "racecar_hw.cli", "-v", "run", "--no-status",
           *set_args(*QUIET_NET, "vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                     "recorder.enabled=true", f"recorder.path={tmp_path / 'rec'}", "recorder.format=ros1")]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        assert proc.stderr is not None
        for line in proc.stderr:
            if "racecar-hw running" in line:
                break
        while proc.poll() is None:
            try:
                proc.send_signal(signal.SIGINT)
            except ProcessLookupError:
                break
            time.sleep(0.003)
        proc.wait(timeout=60)
    assert proc.returncode == 0
    assert list((tmp_path / "rec").glob("*.bag"))  # the recording, closed


def test_a_ctrl_c_while_the_loops_handlers_are_removed_is_noted_not_raised(monkeypatch) -> None:
    """Between asyncio taking its handlers away (putting Python's default back) and the noting one
    taking over, a Ctrl-C once raised KeyboardInterrupt: exit 130 after a finished run (3 in 30
    runs under a burst of Ctrl-Cs). One sent exactly there is noted now."""
    from racecar_hw.runtime.interrupts import StopSignals

    with StopSignals(keep=False) as stops:
        loop = asyncio.new_event_loop()
        try:
            remove = signals.add_stop_handlers(loop, lambda _sig: None, noted=stops)
            real = loop.remove_signal_handler

            def remove_then_ctrl_c(sig: int) -> bool:
                removed = real(sig)
                if sig == signal.SIGINT:
                    os.kill(os.getpid(), signal.SIGINT)  # with Python's default handler in place
                return removed

            monkeypatch.setattr(loop, "remove_signal_handler", remove_then_ctrl_c)
            remove()  # raised KeyboardInterrupt here
            wait_for(lambda: stops.noted == signal.SIGINT, timeout=10)
        finally:
            loop.close()


def _run_recording(tmp_path: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "racecar_hw.cli", "-v", "run", "--no-status",
           *set_args(*QUIET_NET, "vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                     "recorder.enabled=true", f"recorder.path={tmp_path / 'rec'}", "recorder.format=mcap")]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _until_running(proc: subprocess.Popen) -> None:
    assert proc.stderr is not None
    for line in proc.stderr:
        if "racecar-hw running" in line:
            return
    raise AssertionError("the daemon ended before it ran")


def test_a_hangup_ends_run_as_a_stop_does(tmp_path) -> None:
    """``racecar-hw run`` started by hand over SSH, and the session drops: SIGHUP killed it on the
    spot (exit 129), the motor left running until the VESC's own timeout and the bag open. It is
    a stop signal now: exit 0 and the bag closed."""
    from racecar_hw.bags.info import bag_info

    proc = _run_recording(tmp_path)
    with reaped(proc):
        _until_running(proc)
        proc.send_signal(signal.SIGHUP)
        _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    (bag,) = (tmp_path / "rec").iterdir()
    assert bag_info(bag).state.complete


def test_a_reload_signal_during_start_up_does_nothing(tmp_path) -> None:
    """SIGUSR1 (``systemctl reload``: restart the MAVLink signing state) sent as the command starts,
    before the daemon takes it, killed the process (exit 138); now it does nothing until then."""
    proc = _run_recording(tmp_path)
    with reaped(proc):
        wait_for(lambda: _catches(proc.pid, signal.SIGTERM) or proc.poll() is not None, timeout=60,
                 interval=0.001)
        proc.send_signal(signal.SIGUSR1)
        _until_running(proc)
        proc.send_signal(signal.SIGUSR1)  # the daemon's: said in the log, the car runs on
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "SIGUSR1: the MAVLink link is off" in err
