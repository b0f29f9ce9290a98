"""``racecar-hw sim`` as a user runs it: stopped by a signal, bad arguments, following a bag.

A signal stops a run in real time (a process of its own); the runs whose subject is what the
command does with a bag or its outputs are in lockstep (``--speed max``: the same daemon and fakes
on the simulation's clock, as fast as the machine allows)."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import QUIET_NET, reaped, set_args
from lockstep_sim import OFFLINE

from racecar_hw.bags.record import Recorder, record_params
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time
from racecar_hw.cli import build_parser, main
from racecar_hw.commands.sim import build_scenario
from racecar_hw.sim.trajectory import read_csv

NAV0 = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_stops_the_sim_and_keeps_its_results(tmp_path, stop):
    """Ctrl-C (or systemd's SIGTERM) ends a long run as its duration would: brake, then the report
    (marked interrupted), the trajectory and the plot for the time driven; exit 0."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--duration", "120", "--no-status",
         *set_args(*QUIET_NET), "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # as a background job of a script inherits it: SIGINT ignored
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    with reaped(proc):
        assert proc.stderr is not None
        for line in proc.stderr:  # the daemon runs (its INFO line); the figure-8 starts driving
            if "racecar-hw running" in line:
                break
        proc.send_signal(stop)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "never awaited" not in err
    report = json.loads((tmp_path / "figure8.json").read_text())  # named after the scenario
    assert report["interrupted"] is True and report["stop_reason"] == stop.name
    assert report["sim_time_s"] < 60
    assert read_csv(report["trajectory_csv"])
    assert Path(report["plot_png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"figure8: interrupted by {stop.name} after" in out
    assert "{" not in out  # a short summary after the panel, not the whole JSON


def test_a_second_ctrl_c_still_writes_the_report_without_the_plot(tmp_path, monkeypatch, capsys):
    """Ctrl-C twice while the run stops (here: as the car is left to roll to rest, in lockstep, so
    the two signals land there whatever the machine's pace): the report and the trajectory of the
    time driven are still written, only the roll to rest and the plot are skipped; exit 0. (Before,
    the second Ctrl-C aborted with nothing written.) The signals are real, sent to this process."""
    import asyncio
    import os
    import time

    from racecar_hw.sim.loopback import Loopback

    settle = Loopback._settle

    async def pressed_twice(self: Loopback) -> None:
        for taken in (lambda: self.stop_reason == "SIGINT", lambda: self.hurried):
            os.kill(os.getpid(), signal.SIGINT)
            deadline = time.monotonic() + 30
            while not taken():  # until the event loop has handled this one (then the next)
                assert time.monotonic() < deadline, "the signal was never handled"
                await asyncio.sleep(0.001)
        await settle(self)

    monkeypatch.setattr(Loopback, "_settle", pressed_twice)
    code = main(["sim", "--duration", "2", "--no-status", "--speed", "max", *set_args(*OFFLINE),
                 "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "the report without waiting for the car to stop or drawing the plot" in err
    report = json.loads((tmp_path / "figure8.json").read_text())
    assert report["interrupted"] is True and report["stop_reason"] == "SIGINT"
    assert read_csv(report["trajectory_csv"]) and report["plot_png"] is None
    assert not (tmp_path / "figure8.png").exists()
    assert "plot:       none (Ctrl-C skipped it)" in out


def _plot_worker_of(pid: int) -> int | None:
    """The pid of ``pid``'s plot worker (``python -m racecar_hw.sim.plot_worker``), if it has one."""
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, ValueError):
            continue
        if int(stat.rpartition(")")[2].split()[1]) == pid and b"racecar_hw.sim.plot_worker" in cmdline:
            return int(entry.name)
    return None


def _pipe_holds(path: str) -> int:
    """The bytes waiting in the pipe at ``path`` (a /proc/PID/fd/N), without reading them."""
    import array
    import fcntl
    import termios

    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        count = array.array("i", [0])
        fcntl.ioctl(fd, termios.FIONREAD, count)
        return count[0]
    finally:
        os.close(fd)


def test_ctrl_c_while_the_plot_worker_draws_skips_the_plot_and_keeps_the_results(tmp_path):
    """The run is over and its figure handed to the plot worker, which is stuck (stopped here with
    SIGSTOP, as a stuck or starved child would be): Ctrl-C was not acted upon for up to
    RESULT_TIMEOUT_S (30 s), and then the plot was drawn anyway. Now it gives the plot up at once,
    writes the report and the trajectory, says so in one line and exits 0, as a Ctrl-C that ends a
    run does. (Nothing in the product is made slow for this: the child is frozen from outside.)"""
    from conftest import wait_for

    from racecar_hw.sim.plot_worker import RESULT_TIMEOUT_S

    proc = subprocess.Popen(
        [sys.executable, "-m", "racecar_hw.cli", "sim", "--duration", "1", "--speed", "max",
         "--no-status", "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        wait_for(lambda: _plot_worker_of(proc.pid), timeout=60)  # started with the command
        worker = _plot_worker_of(proc.pid)
        assert worker is not None
        os.kill(worker, signal.SIGSTOP)
        # the run is over and the figure is being handed over: it fills the stopped child's stdin
        wait_for(lambda: _pipe_holds(f"/proc/{worker}/fd/0") > 0, timeout=120)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=RESULT_TIMEOUT_S - 10)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert "racecar-hw sim: stopped while the plot was drawn: no plot (the report and the trajectory " \
           "are written)" in err
    report = json.loads((tmp_path / "figure8.json").read_text())
    assert report["plot_png"] is None and read_csv(report["trajectory_csv"])
    assert not (tmp_path / "figure8.png").exists()
    assert "plot:       none (Ctrl-C skipped it)" in out
    assert not Path(f"/proc/{worker}").exists()  # killed and reaped, not left stopped


@pytest.mark.parametrize("value", ["-5", "0", "nan", "inf", "soon"])
def test_duration_must_be_positive_and_finite(value, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["sim", "--duration", value])
    assert exc.value.code == 2
    assert f"'{value}' is not a positive number of seconds" in capsys.readouterr().err


def test_a_bad_driver_input_or_a_missing_bag_is_one_line_before_anything_runs(tmp_path, capsys):
    assert main(["sim", "--no-status", "--out", str(tmp_path), "--scenario-set",
                 "drivers.0.input=nav_9"]) == 1
    err = capsys.readouterr().err
    assert err == ("racecar-hw sim: scenario.drivers.0.input: 'nav_9' is not a mux input; inputs: "
                   "safety, teleop, nav_0, nav_1, nav_2, nav_3, foxglove, cmd_vel\n")
    assert main(["sim", "--no-status", "--out", str(tmp_path), "--follow", str(tmp_path / "nope")]) == 1
    assert capsys.readouterr().err == f"racecar-hw sim: --follow: bag not found: {tmp_path / 'nope'}\n"
    rec = Recorder(Bus(), record_params(tmp_path, name="other"))
    rec.start()
    rec.bus.publish(NAV0, AckermannDriveStamped())
    rec.stop()
    assert main(["sim", "--no-status", "--out", str(tmp_path), "--follow", str(tmp_path / "other"),
                 "--follow-topic", "/cmd_vel"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("racecar-hw sim: topic /cmd_vel is not in") and err.count("\n") == 1
    assert not list(tmp_path.glob("*.json"))


@pytest.mark.parametrize("lockstep", [[], ["--speed", "max"]], ids=["real time", "lockstep"])
def test_a_scenario_drivers_missing_bag_is_refused_with_the_outputs_naming_its_key(
        tmp_path, capsys, monkeypatch, lockstep):
    """A scenario file whose follow driver (or a car's) names a bag that is not there was refused
    only once the run loaded its bags, with neither the key nor the car, after the plot's process
    had started; now with the output checks, before any of it, naming the key and the path."""
    from racecar_hw.sim import loopback, plot_worker

    def started(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("the run started")

    monkeypatch.setattr(loopback.Loopback, "__init__", started)
    monkeypatch.setattr(plot_worker.PlotWorker, "start", started)
    bag = tmp_path / "drives" / "lap.mcap"
    one = tmp_path / "one.yaml"
    one.write_text(f"map: room\nstart: [2.0, 5.0, 0.0]\ndrivers:\n  - {{type: follow, bag: {bag}}}\n")
    assert main(["sim", "--no-status", "--scenario", str(one), "--out", str(tmp_path), *lockstep]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == f"racecar-hw sim: scenario.drivers.0.bag: bag not found: {bag}", err
    two = tmp_path / "two.yaml"
    two.write_text(f"map: corridor\ncars:\n  - {{name: a, start: [3.0, 0.0, 0.0]}}\n"
                   f"  - {{name: b, drivers: [{{type: follow, bag: {bag}}}]}}\n")
    assert main(["sim", "--scenario", str(two), "--out", str(tmp_path), *lockstep]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == f"racecar-hw sim: scenario.cars.1.drivers.0.bag: bag not found: {bag}", err
    assert not list(tmp_path.glob("*.json")) and not list(tmp_path.glob("*.csv"))


@pytest.mark.parametrize(("option", "words"), [
    ("--report", "a-dir is a directory, not a file"),
    ("--record", "a-file is a file, not a directory"),
    ("--out", "a-file is a file, not a directory"),
])
def test_an_output_that_cannot_be_written_is_one_line_before_anything_runs(tmp_path, capsys, option, words):
    """A report path that is a directory, or a bag or output directory that is a file, is refused
    naming the option before the run (not a traceback at its end, with the report lost)."""
    (tmp_path / "a-dir").mkdir()
    (tmp_path / "a-file").write_text("")
    target = tmp_path / ("a-dir" if option == "--report" else "a-file")
    out = [] if option == "--out" else ["--out", str(tmp_path / "out")]
    code = main(["sim", "--scenario", "wall", "--duration", "0.5", "--speed", "max", "--no-status",
                 *out, option, str(target)])
    err = capsys.readouterr().err.splitlines()
    assert code == 1
    assert err[-1] == f"racecar-hw sim: {option}: {tmp_path}/{words}"
    assert not any("Traceback" in line for line in err)
    assert not (tmp_path / "out").exists()  # nothing ran: no trajectory, no plot


@pytest.mark.parametrize("option", ["--out", "--report", "--record"])
def test_an_output_in_a_place_that_takes_no_file_is_refused_for_root_too(tmp_path, capsys, option):
    """/proc's permission bits let root write (``os.access`` says yes), but it takes no file: the
    run went on and its end raised a traceback, the report lost. A file is now tried there first."""
    target = "/proc/racecar-hw-nope" + (".json" if option == "--report" else "")
    out = [] if option == "--out" else ["--out", str(tmp_path / "out")]
    code = main(["sim", "--scenario", "wall", "--duration", "0.5", "--speed", "max", "--no-status",
                 *out, option, target])
    err = capsys.readouterr().err.splitlines()
    assert code == 1 and not any("Traceback" in line for line in err), err
    assert err[-1].startswith(f"racecar-hw sim: {option}: {target} cannot be written: /proc "), err
    assert not (tmp_path / "out").exists()


def test_follow_options_come_first_and_scenario_sets_apply_to_them(tmp_path):
    args = build_parser().parse_args(["sim", "--follow", str(tmp_path / "b"), "--scenario-set",
                                      "drivers.0.rate_hz=10", "--scenario-set",
                                      "drivers.0.use_timestamps=true"])
    scenario = build_scenario(args)
    (driver,) = scenario.drivers
    assert driver.type == "follow" and driver.rate_hz == 10 and driver.use_timestamps
    assert driver.topic == ""  # the bag's own drive topic, found when it is read
    assert scenario.name == "follow" and "Follow b from the figure8 scenario's start" in scenario.description


def test_a_recording_of_the_whole_bus_is_followed_on_its_mux_input(tmp_path, capsys):
    """What ``sim --record`` writes (the input that drove, the mux output, other topics) is
    followed without --follow-topic, and the report is labelled follow."""
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="drive"))
    rec.start()
    for i in range(20):  # 1 s at 20 Hz: 0.8 m/s straight ahead
        drive = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=0.8))
        bus.publish(NAV0, drive)
        bus.publish("/vesc/low_level/ackermann_cmd_mux/output", drive)
        bus.publish("/odom_placeholder", Header(Time(i, 0), "odom"))
    rec.stop()
    assert main(["sim", "--follow", str(tmp_path / "drive"), "--duration", "2", "--no-status", "--speed",
                 "max", *set_args(*OFFLINE), "--out", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "follow.json").read_text())
    assert report["scenario"] == "follow" and not report["interrupted"]
    assert report["distance_m"] > 0.3  # the car moved
    assert capsys.readouterr().out.startswith("follow: ran ")


def _straight_bag(tmp_path: Path, commands: int) -> Path:
    """A recording of ``commands`` drive commands at 1 m/s straight ahead (20 Hz when followed)."""
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="straight"))
    rec.start()
    for _ in range(commands):
        bus.publish(NAV0, AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=1.0)))
    rec.stop()
    return tmp_path / "straight"


def test_follow_reverse_runs_the_whole_stretched_replay_and_says_when_duration_cuts_it(tmp_path, capsys):
    """Backwards, the reverse cap (0.5 m/s) halves the recorded 1 m/s and doubles the replay's
    length: 2.9 s, longer than the 1.5 s scenario. Without --duration the run lasts as long as the
    replay (and a settle time), so the whole path is driven; a --duration that ends it first is
    named in the summary and the report."""
    bag = _straight_bag(tmp_path, 30)  # 29 gaps of 0.05 s: 1.45 s, 1.45 m
    scenario = tmp_path / "short.yaml"
    scenario.write_text("description: a short scenario in the room\nmap: room\nstart: [0.0, 0.0, 0.0]\n"
                        "duration_s: 1.5\ndrivers: []\n")
    common = ["sim", "--scenario", str(scenario), "--follow", str(bag), "--reverse", "--no-status",
              "--speed", "max", *set_args(*OFFLINE)]
    assert main([*common, "--out", str(tmp_path / "whole")]) == 0
    out = capsys.readouterr().out
    report = json.loads((tmp_path / "whole" / "follow.json").read_text())
    (follow,) = report["follow"]
    assert (follow["replay_s"], follow["speed_scale"]) == (2.9, 0.5)
    assert follow["complete"] and follow["followed"] == 1.0
    assert report["duration_s"] == 3.9  # the replay and 1 s to come to rest, not the scenario's 1.5
    assert not report["interrupted"] and report["max_speed_mps"] <= 0.55
    assert report["distance_m"] > 1.3 and report["final_pose"]["x"] < -1.3  # the whole 1.45 m, backwards
    assert "WARNING" not in out and out.startswith("follow: ran ")

    assert main([*common, "--duration", "1.5", "--out", str(tmp_path / "cut")]) == 0
    out = capsys.readouterr().out
    report = json.loads((tmp_path / "cut" / "follow.json").read_text())
    (follow,) = report["follow"]
    assert not follow["complete"] and 0 < follow["followed"] < 1 and report["duration_s"] == 1.5
    assert not report["interrupted"] and report["distance_m"] < 1.0
    assert (f"WARNING: the replay of straight was cut short: {follow['followed']:.0%} of it followed when "
            "the run's duration (1.5 s) ended; the replay takes 2.9 s") in out


def test_the_panel_shows_sim_time_pose_and_clearance(tmp_path):
    import asyncio

    from racecar_hw.runtime import lockstep
    from racecar_hw.sim.loopback import Loopback
    from racecar_hw.sim.scenario import load_scenario

    seen = []

    def setup(loopback: Loopback) -> None:
        async def look() -> None:  # 1.1 s after the world started (in lockstep: to the step)
            await asyncio.sleep(1.1)
            seen.append(loopback.daemon.snapshot())

        loopback.daemon.add_task(look())

    loopback = Loopback(load_scenario("corridor"), duration_s=1.5, setup=setup, overrides=[*OFFLINE],
                        lockstep=True)
    lockstep.run(loopback.run())
    (snap,) = seen
    assert snap.sim_time_s is not None and snap.sim_time_s > 1.0
    assert snap.sim_pose is not None and snap.sim_pose[0] > 0.5  # driving down the corridor
    assert snap.clearance_m == pytest.approx(0.6, abs=0.05)
    assert snap.vesc_link == "up" and snap.lidar_link == "up"


def test_a_bag_beyond_the_cars_steering_limit_is_driven_clamped_with_one_warning(tmp_path, capsys, caplog):
    """A ROS 1 bag from a car that steers further (0.3 rad; this car's limit is 0.26) drives the
    simulated car in ``sim --follow``, clamped, with one warning that counts the commands. In this
    process (the command, not its process, is the subject): the warnings are the log's records."""
    from racecar_hw.bags.record import BagFile
    from racecar_hw.rosmsg.typestore import types_for

    bag = tmp_path / "f1tenth.bag"
    f = BagFile(bag, "ros1", "none", types_for(1))
    for i in range(40):  # 2 s at 20 Hz: 0.8 m/s, turning left at 0.3 rad
        f.write(NAV0, AckermannDriveStamped(Header(Time(1, i * 50_000_000), "base_link"),
                                            AckermannDrive(speed=0.8, steering_angle=0.3)),
                1_000_000_000 + i * 50_000_000)
    f.close()
    out = tmp_path / "out"
    caplog.set_level(logging.WARNING)
    code = main(["sim", "--follow", str(bag), "--no-status", "--speed", "max", *set_args(*OFFLINE),
                 "--out", str(out)])
    err = capsys.readouterr().err + caplog.text
    assert code == 0, err
    warnings = [r.getMessage() for r in caplog.records if "limits" in r.getMessage()]
    assert len(warnings) == 1, err
    assert "40 of 40 commands" in warnings[0] and "steering up to 0.3 rad (limit 0.26)" in warnings[0]
    assert "clamped" in warnings[0] and "refused" not in err
    report = json.loads(next(out.glob("*.json")).read_text())
    assert report["distance_m"] > 0.8  # the car drove
    assert report["final_pose"]["yaw"] > 0.3  # and turned left, at the clamped angle


def test_at_max_speed_the_command_loads_no_network_library(tmp_path):
    """``racecar-hw sim --speed max`` runs off the network (docs/sim.md, "The network at --speed
    max"), so it never loads aiohttp, cyclonedds or Zenoh: the second of start-up they cost."""
    script = ("import sys\nfrom racecar_hw.cli import main\n"
              "code = main(['sim', '--scenario', 'wall', '--duration', '0.5', '--no-status', "
              f"'--speed', 'max', '--out', {str(tmp_path)!r}])\n"
              "print(code, sorted(m for m in ('aiohttp', 'cyclonedds', 'zenoh') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == "0 []", done.stdout
    assert "--speed max runs off the network" in done.stderr
    assert json.loads((tmp_path / "wall.json").read_text())["live"] == {}


@pytest.mark.parametrize("scenario", ["wall", "two-cars"])
def test_no_plot_writes_the_report_and_trajectory_and_draws_nothing(tmp_path, capsys, monkeypatch, scenario):
    """``--no-plot`` (sweeps, batch runs): the report and every trajectory CSV as without it, no
    PNG, no plot process, and the command says why there is no plot."""
    import racecar_hw.sim.plot_worker as plot_worker

    started = []
    real_start = plot_worker.PlotWorker.start
    monkeypatch.setattr(plot_worker.PlotWorker, "start", lambda: started.append(True) or real_start())
    code = main(["sim", "--scenario", scenario, "--duration", "1", "--no-status", "--speed", "max",
                 "--no-plot", "--out", str(tmp_path)])
    stdout = capsys.readouterr().out
    assert code == 0 and not started
    report = json.loads((tmp_path / f"{scenario}.json").read_text())
    assert report["plot_png"] is None and not list(tmp_path.glob("*.png"))
    assert "plot:       none (--no-plot)" in stdout, stdout
    csvs = [report["trajectory_csv"]] if "cars" not in report else [
        car["trajectory_csv"] for car in report["cars"].values()]
    assert len(csvs) == (2 if scenario == "two-cars" else 1)
    for csv in csvs:
        assert read_csv(csv), csv


def test_sim_says_where_every_output_went_and_bag_info_takes_the_mcap_file(tmp_path, capsys):
    """``sim --record`` prints the bag's path with the report's (named after the scenario), the
    plot's and the trajectory's; ``bag info`` takes the bag's .mcap file as well as its folder."""
    out, record = tmp_path / "out", tmp_path / "bags"
    # the live view and the page turned back on at --speed max, which runs off the network
    code = main(["sim", "--scenario", "wall", "--duration", "1", "--no-status", "--speed", "max",
                 *set_args(*QUIET_NET, "foxglove.enabled=true", "web.enabled=true"), "--out", str(out),
                 "--record", str(record)])
    stdout, stderr = capsys.readouterr()
    assert code == 0, stderr
    assert "--speed max runs off the network" in stderr
    # the summary says where the live view and the page were (free ports here)
    assert re.search(r"live view \(Foxglove\) ws://127\.0\.0\.1:\d+ and status page "
                     r"http://127\.0\.0\.1:\d+/ \(while it ran\)", stdout), stdout
    said = dict(line.split(":", 1) for line in stdout.splitlines()[-4:])
    said = {k.strip(): Path(v.strip()) for k, v in said.items()}
    assert said["report"] == out / "wall.json" and said["report"].is_file()
    assert said["plot"] == out / "wall.png" and said["plot"].is_file()
    assert said["trajectory"] == out / "wall-trajectory.csv" and said["trajectory"].is_file()
    assert said["bag"].parent == record and said["bag"].is_dir()
    assert json.loads(said["report"].read_text())["bags"] == [str(said["bag"])]
    (mcap,) = said["bag"].glob("*.mcap")
    for path in (mcap, said["bag"]):
        assert main(["bag", "info", str(path)]) == 0
        info = capsys.readouterr()
        assert f"path:      {said['bag']}\n" in info.out and "complete:  yes" in info.out, info.err
        assert "//" not in info.out


def test_the_panel_names_the_live_view_the_page_and_with_keyboard_the_keys(monkeypatch, tmp_path):
    """What the status panel shows of the live interfaces (their URLs once listening) and, with
    ``--keyboard``, the keys."""
    import asyncio

    from racecar_hw.config import load_config
    from racecar_hw.daemon import Daemon
    from racecar_hw.teleop.keyboard import KEY_HINTS

    base = ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false", "status.enabled=false",
            "foxglove.enabled=true", *QUIET_NET]  # the live view, off in the car config
    assert Daemon(load_config(None, base)).snapshot().keys is None
    with (tmp_path / "keys").open("w+") as keys:  # the keyboard's stdin (pytest's has no descriptor)
        monkeypatch.setattr("sys.stdin", keys)
        assert Daemon(load_config(None, [*base, "keyboard.enabled=true"])).snapshot().keys == KEY_HINTS
    daemon = Daemon(load_config(None, base))
    assert (daemon.snapshot().live_view, daemon.snapshot().page) == (None, None)  # not yet listening

    async def running() -> tuple[str | None, str | None]:
        stop = asyncio.Event()
        task = asyncio.create_task(daemon.run(stop))
        while not daemon.started_live and not task.done():
            await asyncio.sleep(0.05)
        snap = daemon.snapshot()
        stop.set()
        await task
        return snap.live_view, snap.page

    live_view, page = asyncio.run(running())
    assert live_view is not None and re.fullmatch(r"ws://127\.0\.0\.1:\d+", live_view)
    assert page is not None and re.fullmatch(r"http://127\.0\.0\.1:\d+/", page)
