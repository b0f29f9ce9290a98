"""The daemon's shutdown is its start-up in reverse (one exit stack), and safe to call twice."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path
from typing import Any

from conftest import QUIET_NET, StuckDisk, async_wait_for

import racecar_hw.bags.record as bag_record
from racecar_hw.base.errors import BagError
from racecar_hw.config import load_config
from racecar_hw.daemon import Daemon


def _spy(events: list[str], obj: Any, method: str, name: str) -> None:
    """Note ``name`` in ``events`` whenever ``obj.method`` is called, then call it."""
    real = getattr(obj, method)

    def call(*args: Any, **kwargs: Any) -> Any:
        events.append(name)
        return real(*args, **kwargs)

    setattr(obj, method, call)


def test_shutdown_undoes_start_up_in_reverse_and_closes_what_was_built(tmp_path):
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "foxglove.enabled=false", "safety.mode=off",
                                "recorder.enabled=true", f"recorder.path={tmp_path / 'bags'}",
                                "scan_summary.enabled=true", *QUIET_NET])
    daemon = Daemon(config)
    events: list[str] = []
    assert daemon.recorder is not None and daemon.scan_summary is not None and daemon.net.web is not None
    for obj, method, name in [
            (daemon.recorder, "open", "start recorder"), (daemon.recorder, "stop", "stop recorder"),
            (daemon.scan_summary, "start", "start scan summary"),
            (daemon.scan_summary, "close", "stop scan summary"),
            (daemon.net.web, "start", "start web"), (daemon.net.web, "stop", "stop web"),
            (daemon.notifier, "ready", "start notifier"), (daemon.notifier, "stopping", "stop notifier")]:
        _spy(events, obj, method, name)

    async def scenario() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(daemon.run(stop))
        while "start notifier" not in events and not task.done():
            await asyncio.sleep(0.01)
        assert not task.done()
        stop.set()
        await asyncio.wait_for(task, 30)
        await daemon.shutdown()  # a second time: nothing left to undo

    asyncio.run(scenario())
    starts = [e.split(" ", 1)[1] for e in events if e.startswith("start ")]
    stops = [e.split(" ", 1)[1] for e in events if e.startswith("stop ")]
    assert starts == ["recorder", "scan summary", "web", "notifier"]
    assert stops == list(reversed(starts))
    # what __init__ built is closed too (its closing was pushed first, so it runs last)
    assert daemon.mux._subs == [] and daemon.safety._subs == []
    assert events.count("stop recorder") == 1  # the second shutdown() undid nothing again


def test_two_components_on_one_topic_with_two_types_name_the_key_that_was_set():
    """The gamepad's drive commands on the e-stop's topic: the daemon is not built, and the error
    names gamepad.topic (set here), not only the topic."""
    import pytest

    from racecar_hw.base.errors import ConfigError

    config = load_config(None, ["gamepad.enabled=true", "gamepad.topic=/estop", *QUIET_NET])
    with pytest.raises(ConfigError) as err:
        Daemon(config)
    assert err.value.key == "gamepad.topic"
    assert "/estop carries std_msgs/msg/Bool, not ackermann_msgs/msg/AckermannDriveStamped" in str(err.value)
    assert "mux.estop_topic, gamepad.topic" in str(err.value)


def test_the_safety_controller_sweeps_the_steering_the_vesc_conversion_lets_the_car_drive():
    """A calibrated servo offset clips full right to -0.222 rad: the daemon's safety controller
    sweeps that, not the configured -0.26 (tests/test_safety_controller.py shows the difference)."""
    import pytest

    config = load_config(None, ["vesc.steering_angle_to_servo_offset=0.5804", *QUIET_NET])
    right, left = Daemon(config).safety.controller.steering_range
    assert right == pytest.approx((0.85 - 0.5804) / -1.2135) and left == pytest.approx(0.26)


def _recording_daemon(tmp_path: Path) -> Daemon:
    return Daemon(load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                     "status.enabled=false", "foxglove.enabled=false", "safety.mode=off",
                                     "recorder.enabled=true", f"recorder.path={tmp_path / 'bags'}",
                                     *QUIET_NET]))


def _start_on_a_stuck_disk(daemon: Daemon, disk: StuckDisk, stop_when_blocked: bool) -> BaseException:
    """Run ``daemon`` on a disk stuck from the start; what its run raised."""
    disk.stick()
    watchdog = threading.Timer(30, disk.released.set)  # a start that holds the loop ends, and fails
    watchdog.start()

    async def scenario() -> BaseException:
        stop = asyncio.Event()
        task = asyncio.create_task(daemon.run(stop))
        await async_wait_for(disk.blocked.is_set, 60)
        if stop_when_blocked:
            stop.set()
        try:
            await asyncio.wait_for(task, 90)
        except BagError as err:
            return err
        finally:
            await daemon.shutdown()
        raise AssertionError("the daemon started on a stuck disk")

    try:
        return asyncio.run(scenario())
    finally:
        watchdog.cancel()


def test_a_stop_during_a_start_held_by_a_stuck_disk_ends_it_at_once(tmp_path, stuck_disk):
    """The first bag opened on the event loop: a disk whose fsync hung froze the daemon's start and
    held Ctrl-C for as long as the disk did (90 s in the reviewer's run)."""
    err = _start_on_a_stuck_disk(_recording_daemon(tmp_path), stuck_disk, stop_when_blocked=True)
    assert str(err) == (f"cannot start recording into {tmp_path / 'bags'} (recorder.path): stopped while "
                        "its disk did not answer")


def test_a_start_held_by_a_stuck_disk_gives_up_naming_recorder_path(tmp_path, stuck_disk, monkeypatch):
    monkeypatch.setattr(bag_record, "WRITER_STALL_S", 0.5)  # 15 s on a car
    daemon = _recording_daemon(tmp_path)
    err = _start_on_a_stuck_disk(daemon, stuck_disk, stop_when_blocked=False)
    assert str(err) == (f"cannot start recording into {tmp_path / 'bags'} (recorder.path): the disk did "
                        "not answer for 0.5 s")
    assert daemon.recorder is not None and daemon.recorder.stats.error == str(err)
