"""racecar_hw.bags.follow: reading real and generated bags, clear errors, timing, and the follower on a
real bus."""

from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path

import pytest
from bag_ros1tools import write_real_bag
from fuzzing import write_bag
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from racecar_hw.bags.follow import (
    READY_WAIT_S,
    BagFollower,
    Command,
    CommandSync,
    FollowerParams,
    Hole,
    Step,
    command_from_message,
    fit_speed,
    holes,
    keep_alive,
    load_commands,
    schedule,
    summarize_bag,
)
from racecar_hw.bags.record import Recorder, record_params
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.errors import BagError, ConfigError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, ScanRange, Time
from racecar_hw.base.topics import NAV0_TOPIC, TELEOP_TOPIC
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime import lockstep

T0 = 1_700_000_000 * NS_PER_S


def figure8(n: int = 12, dt_ns: int = 50_000_000) -> list[tuple[int, float, float]]:
    """(t_ns, speed, steering): speed rises, steering swings left then right."""
    return [(T0 + i * dt_ns, 0.5 + 0.1 * i, 0.3 if i < n // 2 else -0.3) for i in range(n)]


def write_ours(path: Path, fmt: str, commands: list[tuple[int, float, float]],
               topic: str = TELEOP_TOPIC, stamped: bool = True) -> Path:
    """An Ackermann bag written with rosbags, unchunked (the recorder's own path is tested elsewhere)."""
    return write_bag(path, fmt, commands, topic, stamped, chunked=False)


# --- reading ----------------------------------------------------------------------------------


def test_follows_a_bag_written_by_the_real_rosbag(tmp_path: Path) -> None:
    cmds = figure8()
    for compression in ("none", "bz2"):
        path = tmp_path / f"real-{compression}.bag"
        md5 = write_real_bag(path, TELEOP_TOPIC, cmds, compression)
        assert md5 == "1fd5d7f58889cefd44d29f6653240d0c"
        got = load_commands(path)
        assert [c.t_ns for c in got] == [t for t, _, _ in cmds]
        assert [c.drive.speed for c in got] == pytest.approx([s for _, s, _ in cmds])
        assert [c.drive.steering_angle for c in got] == pytest.approx([a for _, _, a in cmds])
        back = schedule(got, use_timestamps=True, reverse=True)
        assert [s.offset_ns for s in back] == [T0 + 11 * 50_000_000 - t for t, _, _ in reversed(cmds)]
        assert back[0].drive.speed == pytest.approx(-cmds[-1][1])
        assert back[0].drive.steering_angle == pytest.approx(cmds[-1][2])


@pytest.mark.parametrize("fmt", ["ros1", "mcap", "sqlite3"])
@pytest.mark.parametrize("stamped", [True, False])
def test_reads_each_format(tmp_path: Path, fmt: str, stamped: bool) -> None:
    cmds = figure8()
    path = write_ours(tmp_path / ("b.bag" if fmt == "ros1" else "b"), fmt, cmds, stamped=stamped)
    got = load_commands(path)
    assert [(c.t_ns, c.drive.speed, c.drive.steering_angle) for c in got] == [
        (t, pytest.approx(s), pytest.approx(a)) for t, s, a in cmds]


@pytest.mark.parametrize("name", ["example-lz4.bag", "example-bz2.bag"])
def test_real_ros1_fixtures_read_completely(bag_fixtures: Path, name: str) -> None:
    topics = summarize_bag(bag_fixtures / "ros1" / name)
    assert sum(n for _, n in topics.values()) == 8647
    assert topics["/turtle1/cmd_vel"] == ("geometry_msgs/msg/Twist", 357)
    assert topics["/tf_static"][0] == "tf2_msgs/msg/TFMessage"


def test_unsorted_chunks_fixture(bag_fixtures: Path) -> None:
    assert summarize_bag(bag_fixtures / "ros1" / "example-unsorted-chunks.bag") == {
        "foo": ("std_msgs/msg/String", 3)}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_real_ros2_fixtures(bag_fixtures: Path, storage: str) -> None:
    topics = summarize_bag(bag_fixtures / "ros2" / storage / "cdr_test")
    assert topics == {"/array_topic": ("test_msgs/msg/Arrays", 4),
                      "/test_topic": ("test_msgs/msg/BasicTypes", 3)}


@pytest.mark.parametrize("name", ["example-lz4.bag", "example-bz2.bag"])
def test_missing_topic_lists_topics_and_types(bag_fixtures: Path, name: str) -> None:
    with pytest.raises(BagError) as err:
        load_commands(bag_fixtures / "ros1" / name, TELEOP_TOPIC)
    text = str(err.value)
    assert f"topic {TELEOP_TOPIC} is not in" in text
    assert "/turtle1/cmd_vel (geometry_msgs/msg/Twist, 357 msgs)" in text
    assert "/tf_static (tf2_msgs/msg/TFMessage" in text


def test_a_public_twist_bag_is_followed_and_its_two_turtles_must_be_chosen_from(
        bag_fixtures: Path, caplog) -> None:
    """The turtlesim bag: two geometry_msgs/Twist cmd_vel topics, so no topic is picked alone. The
    turtle drives straight at +-2 m/s or turns in place, which an Ackermann car cannot."""
    bag = bag_fixtures / "ros1" / "example-bz2.bag"
    with pytest.raises(BagError, match=r"2 topics with drive commands: /turtle1/cmd_vel \(357 msgs\), "
                                       r"/turtle2/cmd_vel \(208 msgs\); choose one with --topic"):
        load_commands(bag)
    caplog.set_level(logging.WARNING)
    got = load_commands(bag, "/turtle1/cmd_vel", wheelbase_m=0.33)
    assert len(got) == 357
    assert sorted({(c.drive.speed, c.drive.steering_angle) for c in got}) == [
        (-2.0, 0.0), (0.0, 0.0), (2.0, 0.0)]
    assert sum(c.drive.speed == 0.0 for c in got) == 31
    assert "31 of 357 Twist commands on /turtle1/cmd_vel turn in place" in caplog.text


def test_twist_becomes_the_steering_of_its_yaw_rate() -> None:
    store = ros2_types().store
    vector3 = store.types["geometry_msgs/msg/Vector3"]
    twist = store.types["geometry_msgs/msg/Twist"](vector3(2.0, 0.0, 0.0), vector3(0.0, 0.0, 1.0))
    c = command_from_message("geometry_msgs/msg/Twist", twist, 7, wheelbase_m=0.5)
    assert (c.t_ns, c.drive.speed) == (7, 2.0)
    assert c.drive.steering_angle == pytest.approx(math.atan(0.25))  # tan(d) = L * w / v
    # the bicycle model driven with it turns at the recorded yaw rate
    assert c.drive.speed * math.tan(c.drive.steering_angle) / 0.5 == pytest.approx(1.0)
    backwards = store.types["geometry_msgs/msg/Twist"](vector3(-2.0, 0, 0), vector3(0, 0, 1.0))
    c = command_from_message("geometry_msgs/msg/Twist", backwards, 7, wheelbase_m=0.5)
    assert c.drive.speed * math.tan(c.drive.steering_angle) / 0.5 == pytest.approx(1.0)
    header = store.types["std_msgs/msg/Header"](store.types["builtin_interfaces/msg/Time"](1, 0), "b")
    stamped = store.types["geometry_msgs/msg/TwistStamped"](header, twist)
    assert command_from_message("geometry_msgs/msg/TwistStamped", stamped, 7, 0.5).drive == \
        command_from_message("geometry_msgs/msg/Twist", twist, 7, 0.5).drive


def test_the_only_drive_topic_is_chosen_and_a_mux_input_over_the_output(tmp_path: Path) -> None:
    """A recording of the whole bus (racecar-hw sim --record) holds the input that drove, the mux
    output and other topics: the input is followed."""
    bag = tmp_path / "rec"
    rec = Recorder(Bus(), record_params(tmp_path, name="rec"))
    rec.start()
    for i in range(3):
        drive = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=1.0 + i))
        rec.bus.publish(NAV0_TOPIC, drive)
        rec.bus.publish("/vesc/low_level/ackermann_cmd_mux/output", drive)
        rec.bus.publish("/scan_range", ScanRange())
    rec.stop()
    assert [c.drive.speed for c in load_commands(bag)] == [1.0, 2.0, 3.0]
    one = write_ours(tmp_path / "one", "mcap", figure8(), topic="/drive")
    assert len(load_commands(one)) == 12


def test_wrong_type(bag_fixtures: Path) -> None:
    with pytest.raises(BagError, match="carries tf2_msgs/msg/TFMessage, expected one of ackermann"):
        load_commands(bag_fixtures / "ros1" / "example-bz2.bag", "/tf_static")


def test_empty_file_and_empty_bag(bag_fixtures: Path, tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"empty \(0 bytes\)"):
        load_commands(bag_fixtures / "ros1" / "empty-file.bag")
    with pytest.raises(BagError, match="holds no messages"):
        load_commands(bag_fixtures / "ros1" / "no-messages.bag")
    with pytest.raises(BagError, match="bag not found"):
        load_commands(tmp_path / "nothing.bag")
    empty = write_ours(tmp_path / "empty", "mcap", [])
    with pytest.raises(BagError, match="holds no messages"):
        load_commands(empty)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_talker_metadata_trap(bag_fixtures: Path, storage: str) -> None:
    path = bag_fixtures / "ros2" / storage / "talker"
    with pytest.raises(BagError, match="metadata says 10 messages on /topic, but reading yielded 0"):
        load_commands(path, "/topic")
    with pytest.raises(BagError, match="metadata says"):
        summarize_bag(path)


def test_unindexed_ros1_bag_hints_at_recovery(tmp_path: Path) -> None:
    path = write_ours(tmp_path / "b.bag", "ros1", figure8())
    assert len(load_commands(path)) == 12
    data = bytearray(path.read_bytes())
    broken = tmp_path / "broken.bag"
    index_field = data.find(b"index_pos=")
    data[index_field + 10:index_field + 18] = bytes(8)
    broken.write_bytes(bytes(data))
    with pytest.raises(BagError, match=f"try: racecar-hw bag recover {broken}"):
        load_commands(broken)


# --- timing -----------------------------------------------------------------------------------


def cmds_from(offsets_ms: list[int]) -> list[Command]:
    return [Command(T0 + ms * 1_000_000, AckermannDrive(steering_angle=0.1 * i, speed=1.0 + i))
            for i, ms in enumerate(offsets_ms)]


def test_schedule_fixed_rate_and_scaling() -> None:
    cmds = cmds_from([0, 10, 500, 510])
    assert [s.offset_ns for s in schedule(cmds, rate_hz=20)] == [0, 50_000_000, 100_000_000,
                                                                 150_000_000]
    assert [s.offset_ns for s in schedule(cmds, rate_hz=20, time_scale=2)] == [
        0, 25_000_000, 50_000_000, 75_000_000]
    assert [s.offset_ns for s in schedule(cmds, use_timestamps=True, time_scale=0.5)] == [
        0, 20_000_000, 1_000_000_000, 1_020_000_000]
    assert schedule([], rate_hz=20) == []


def test_schedule_backwards() -> None:
    cmds = cmds_from([0, 10, 500, 510])
    back = schedule(cmds, use_timestamps=True, reverse=True)
    assert [s.offset_ns for s in back] == [0, 10_000_000, 500_000_000, 510_000_000]
    assert [s.drive.speed for s in back] == [-4.0, -3.0, -2.0, -1.0]
    assert [s.drive.steering_angle for s in back] == pytest.approx([0.3, 0.2, 0.1, 0.0])
    assert cmds[0].drive.speed == 1.0  # the recorded commands are not modified


def test_backwards_over_the_reverse_cap_is_slowed_and_stretched_to_the_same_path() -> None:
    cmds = cmds_from([0, 100, 200, 300])  # 1, 2, 3, 4 m/s forwards
    assert fit_speed(cmds, 0.5, reverse=True) == pytest.approx(0.125)  # 4 m/s backwards -> 0.5
    assert fit_speed(cmds, 0.45, reverse=True) == pytest.approx(1 / 9)  # a whole number of times slower
    assert fit_speed(cmds, 0.5, reverse=False) == 1.0  # forwards: nothing reverses
    assert fit_speed(cmds, 5.0, reverse=True) == 1.0 and fit_speed(cmds, None, reverse=True) == 1.0
    for timestamps in (True, False):
        plain = schedule(cmds, use_timestamps=timestamps, rate_hz=10.0, reverse=True)
        slow = schedule(cmds, use_timestamps=timestamps, rate_hz=10.0, reverse=True, speed_scale=0.125)
        assert [s.drive.speed for s in slow] == [-0.5, -0.375, -0.25, -0.125]
        assert [s.offset_ns for s in slow] == [8 * s.offset_ns for s in plain]
        # distance = speed x time of each step: the same path
        for a, b, pa, pb in zip(slow, slow[1:], plain, plain[1:], strict=False):
            assert a.drive.speed * (b.offset_ns - a.offset_ns) == pytest.approx(
                pa.drive.speed * (pb.offset_ns - pa.offset_ns))
    with pytest.raises(ValueError):
        schedule(cmds, speed_scale=0.0)


def _driven_m(steps: list[Step], timeout_s: float) -> float:
    """How far the commands drive a car through a mux input with ``timeout_s``: each one holds
    until the next arrives or the input times out (the physical world, reduced to distance)."""
    timeout_ns = round(timeout_s * NS_PER_S)
    return sum(abs(a.drive.speed) * min(b.offset_ns - a.offset_ns, timeout_ns) / NS_PER_S
               for a, b in zip(steps, steps[1:], strict=False))


@pytest.mark.parametrize("speed_scale", [1 / 2, 1 / 3, 1 / 8])
@pytest.mark.parametrize("timestamps", [True, False], ids=["timestamps", "fixed-rate"])
def test_a_slowed_replay_keeps_the_mux_input_alive_where_the_recording_did(speed_scale, timestamps) -> None:
    """A 20 Hz recording with the holes a held-up recorder leaves: 0.15 s (which the 0.2 s mux
    timeout bridged, the car drove on) and 0.5 s (it did not: the car stopped after 0.2 s).
    Slowed down for the reverse cap, the replay must drive exactly as far."""
    ms = [0, 50, 100, 250, 300, 350, 850, 900, 950, 1000]
    cmds = [Command(T0 + t * 1_000_000, AckermannDrive(speed=1.0)) for t in ms]
    recorded = schedule(cmds, use_timestamps=timestamps)
    slow = schedule(cmds, use_timestamps=timestamps, reverse=True, speed_scale=speed_scale)
    kept = keep_alive(slow, speed_scale)
    assert _driven_m(kept, 0.2) == pytest.approx(_driven_m(recorded, 0.2))
    if max(b.offset_ns - a.offset_ns for a, b in zip(slow, slow[1:], strict=False)) > 0.3 * NS_PER_S:
        assert _driven_m(slow, 0.2) < _driven_m(recorded, 0.2) - 0.05  # what the stretch did alone
    assert [s.offset_ns for s in kept] == sorted(s.offset_ns for s in kept)
    assert kept[-1] == slow[-1] and {s.offset_ns for s in slow} <= {s.offset_ns for s in kept}
    assert max(b.offset_ns - a.offset_ns for a, b in zip(kept, kept[1:], strict=False)) <= max(
        b.offset_ns - a.offset_ns for a, b in zip(recorded, recorded[1:], strict=False))
    assert keep_alive(recorded, 1.0) == recorded


def test_follower_warns_of_the_reverse_cap_and_slows_down(tmp_path: Path, caplog) -> None:
    bag = write_ours(tmp_path / "r.bag", "ros1", [(T0, 1.0, 0.2), (T0 + 10**7, 1.0, 0.2)])
    caplog.set_level(logging.WARNING)

    async def main() -> BagFollower:
        follower = BagFollower(Bus(), FollowerParams(bag=str(bag), reverse=True, rate_hz=100.0),
                               reverse_speed_cap_mps=0.5)
        await follower.run()
        return follower

    follower = asyncio.run(main())
    assert follower.speed_scale == 0.5
    assert "reverses at up to 1.00 m/s, over the safety controller's reverse cap of 0.50 m/s" in caplog.text
    assert "retraced 2.0 times slower" in caplog.text


def test_command_sync_loops_and_plays() -> None:
    steps = schedule(cmds_from([0, 100]), use_timestamps=True)
    sync = CommandSync(steps, loop=True, gap_ns=50_000_000)
    it = iter(sync)
    got = [next(it)[0] for _ in range(5)]
    assert got == [0, 100_000_000, 150_000_000, 250_000_000, 300_000_000]
    clock = [0]
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        clock[0] += round(s * NS_PER_S)

    played = list(CommandSync(steps).play(sleep=sleep, now_ns=lambda: clock[0]))
    assert [p.drive.speed for p in played] == [1.0, 2.0]
    assert slept == [pytest.approx(0.1)]


def test_holes_are_gaps_far_over_the_usual_spacing() -> None:
    steady = [i * 50 for i in range(20)]  # 20 Hz
    assert holes(cmds_from(steady)) == []
    assert holes(cmds_from([0, 50, 100, 260, 310, 360, 410, 700, 750])) == [
        Hole(0.1, 0.16), Hole(0.41, 0.29)]
    assert holes(cmds_from([0, 500])) == []  # too few to know the usual spacing
    assert holes(cmds_from([0, 0, 0, 0])) == []


def test_fixed_rate_replay_warns_of_holes_and_timestamps_do_not(tmp_path: Path, caplog) -> None:
    commands = figure8(12)
    commands = commands[:5] + [(t + 400_000_000, v, s) for t, v, s in commands[5:]]
    bag = write_ours(tmp_path / "holes.bag", "ros1", commands)
    caplog.set_level(logging.WARNING, "racecar_hw.bags.follow")
    BagFollower(Bus(), FollowerParams(bag=str(bag), use_timestamps=True)).load()
    assert not caplog.records
    BagFollower(Bus(), FollowerParams(bag=str(bag))).load()
    (record,) = caplog.records
    assert "1 gap(s)" in record.message and "longest 450 ms, 0.2 s in" in record.message
    assert "use_timestamps" in record.message


def test_params_validate() -> None:
    with pytest.raises(ConfigError, match="input_topic"):
        FollowerParams(input_topic="nav_0")


# --- the follower on a real bus ---------------------------------------------------------------


def run_follower(bag: Path, **kw: object) -> tuple[list[tuple[int, AckermannDriveStamped]],
                                                   BagFollower, list[tuple[float, float]]]:
    async def main() -> tuple[list[tuple[int, AckermannDriveStamped]], BagFollower,
                              list[tuple[float, float]]]:
        bus = Bus()
        got: list[tuple[int, AckermannDriveStamped]] = []
        bus.subscribe(NAV0_TOPIC, lambda m: got.append((monotonic_ns(), m)))
        progress: list[tuple[float, float]] = []
        follower = BagFollower(bus, FollowerParams(bag=str(bag), **kw),
                               progress=lambda f, eta: progress.append((f, eta)))
        task = asyncio.create_task(follower.run())
        if kw.get("loop"):
            deadline = monotonic_ns() + 30 * NS_PER_S
            while len(got) < 30 and monotonic_ns() < deadline:
                await asyncio.sleep(0.01)
            follower.stop()
        await asyncio.wait_for(task, 30)
        return got, follower, progress

    return asyncio.run(main())


def test_follower_forwards_fixed_rate(tmp_path: Path) -> None:
    bag = write_ours(tmp_path / "f.bag", "ros1", figure8())
    got, follower, progress = run_follower(bag, rate_hz=100.0)
    assert follower.done
    drives = [m.drive for _, m in got]
    assert [d.speed for d in drives[:-1]] == pytest.approx([s for _, s, _ in figure8()])
    assert drives[-1] == AckermannDrive()  # stop_at_end
    assert all(m.header.frame_id == "base_link" and m.header.stamp.sec > 1 for _, m in got)
    # absolute deadlines: 11 periods of 10 ms at least between the first and last command
    assert got[11][0] - got[0][0] >= 11 * 10_000_000 - 1_000_000
    assert progress[-1] == (1.0, 0.0)
    assert [f for f, _ in progress] == sorted(f for f, _ in progress)


def follow_in_lockstep(bag: Path, ready_at_s: float | None) -> tuple[list[int], int]:
    """Replay ``bag`` at 100 Hz on virtual time with the car ready ``ready_at_s`` seconds in (None:
    never): the sim-time instants (ns) of the commands, and the instant the replay was started."""

    async def main() -> tuple[list[int], int]:
        bus, at = Bus(), []
        bus.subscribe(NAV0_TOPIC, lambda _m: at.append(monotonic_ns()))
        follower = BagFollower(bus, FollowerParams(bag=str(bag), rate_hz=100.0))
        follower.load()
        began = monotonic_ns()
        if ready_at_s is not None:
            follower.ready = lambda: monotonic_ns() - began >= ready_at_s * NS_PER_S
        else:
            follower.ready = lambda: False
        await follower.run()
        return at, began

    return lockstep.run(main())


def test_the_replay_waits_until_the_car_is_ready(tmp_path: Path) -> None:
    """Commands played while the VESC or the lidar is still connecting would be lost: the replay
    starts when the daemon says the car is ready (here 2.5 s in), not when the daemon starts."""
    bag = write_ours(tmp_path / "f.bag", "ros1", figure8())
    at, began = follow_in_lockstep(bag, 2.5)
    assert len(at) == len(figure8()) + 1  # every command, then the stop
    assert 2.5 * NS_PER_S <= at[0] - began <= 2.6 * NS_PER_S  # polled every 20 ms
    assert at[11] - at[0] == 11 * 10_000_000  # the bag's own pacing from there


def test_a_car_that_never_gets_ready_is_replayed_to_after_ten_seconds(tmp_path: Path, caplog) -> None:
    bag = write_ours(tmp_path / "f.bag", "ros1", figure8())
    caplog.set_level(logging.INFO, "racecar_hw.bags.follow")
    at, began = follow_in_lockstep(bag, None)
    assert len(at) == len(figure8()) + 1
    assert READY_WAIT_S * NS_PER_S <= at[0] - began <= (READY_WAIT_S + 0.1) * NS_PER_S
    assert "waiting for the car (VESC and lidar) before replaying" in caplog.text
    assert "the car is not ready after 10 s; replaying anyway" in caplog.text


def test_a_car_that_cannot_get_ready_is_not_replayed_to(tmp_path: Path, caplog) -> None:
    """``racecar-hw follow`` against a VESC port that does not exist: the replay ends as soon as
    that is known (here 0.5 s in), with only the final stop published, not after ten seconds."""
    bag = write_ours(tmp_path / "f.bag", "ros1", figure8())
    caplog.set_level(logging.INFO, "racecar_hw.bags.follow")

    async def main() -> tuple[list[int], int, BagFollower]:
        bus, at = Bus(), []
        bus.subscribe(NAV0_TOPIC, lambda m: at.append((monotonic_ns(), m.drive.speed)))
        follower = BagFollower(bus, FollowerParams(bag=str(bag), rate_hz=100.0))
        began = monotonic_ns()
        follower.ready = lambda: False
        follower.hopeless = lambda: ("the VESC's port /dev/nope does not exist"
                                     if monotonic_ns() - began >= NS_PER_S // 2 else None)
        await follower.run()
        return at, began, follower

    at, began, follower = lockstep.run(main())
    assert [speed for _, speed in at] == [0.0] and follower.done  # the stop, nothing of the bag
    assert NS_PER_S // 2 <= at[0][0] - began <= NS_PER_S // 2 + 30_000_000  # polled every 20 ms
    assert f"not replaying {bag}: the VESC's port /dev/nope does not exist" in caplog.text
    assert "replaying anyway" not in caplog.text


def test_follower_backwards_with_timestamps(tmp_path: Path) -> None:
    cmds = [(T0, 1.0, 0.2), (T0 + 20_000_000, 2.0, 0.3), (T0 + 320_000_000, 3.0, -0.1)]
    bag = write_ours(tmp_path / "b", "mcap", cmds)
    got, follower, _ = run_follower(bag, use_timestamps=True, reverse=True, time_scale=2.0,
                                    stop_at_end=False)
    assert [m.drive.speed for _, m in got] == pytest.approx([-3.0, -2.0, -1.0])
    assert [m.drive.steering_angle for _, m in got] == pytest.approx([-0.1, 0.3, 0.2])
    # reversed gaps, halved: 150 ms then 10 ms
    assert got[1][0] - got[0][0] >= 150_000_000 - 2_000_000
    assert follower.published == 3


def test_follower_loops_until_stopped(tmp_path: Path) -> None:
    bag = write_ours(tmp_path / "l", "sqlite3", figure8(4))
    got, follower, _ = run_follower(bag, rate_hz=200.0, loop=True)
    speeds = [m.drive.speed for _, m in got]
    assert len(speeds) >= 30
    assert speeds[:8] == pytest.approx([0.5, 0.6, 0.7, 0.8] * 2)
    assert speeds[-1] == 0.0 and follower.done


def test_follower_reports_bag_errors(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="bag not found"):
        run_follower(tmp_path / "missing.bag")


def test_a_twist_sharper_than_the_car_can_steer_is_clamped_not_refused(tmp_path: Path) -> None:
    """A Twist names a yaw rate, not a steering angle: one the car cannot follow is driven at the
    steering limit (as /cmd_vel is), and so is an Ackermann command beyond the limit; only a
    physically absurd angle refuses the bag."""
    from racecar_hw.bags.validate import CommandLimits

    store = ros2_types().store
    Twist, Vector3 = store.types["geometry_msgs/msg/Twist"], store.types["geometry_msgs/msg/Vector3"]
    path = tmp_path / "cmd_vel"
    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as w2:
        conn = w2.add_connection("/cmd_vel", "geometry_msgs/msg/Twist", typestore=store)
        for i, yaw_rate in enumerate((2.0, -2.0, 0.1)):
            twist = Twist(Vector3(0.5, 0.0, 0.0), Vector3(0.0, 0.0, yaw_rate))
            w2.write(conn, (i + 1) * NS_PER_S // 10, store.serialize_cdr(twist, "geometry_msgs/msg/Twist"))
    limits = CommandLimits(max_speed_mps=5.0, max_steering_rad=0.26)
    got = load_commands(path, wheelbase_m=0.33, limits=limits)
    assert [c.drive.steering_angle for c in got] == pytest.approx([0.26, -0.26, math.atan(0.33 * 0.1 / 0.5)])
    assert all(c.drive.speed == pytest.approx(0.5) for c in got)
    sharp = write_ours(tmp_path / "sharp", "mcap", [(NS_PER_S, 0.5, 0.9)])  # beyond 0.26: clamped
    assert load_commands(sharp, TELEOP_TOPIC, limits=limits)[0].drive.steering_angle == pytest.approx(0.26)
    absurd = write_ours(tmp_path / "absurd", "mcap", [(NS_PER_S, 0.5, 1.7)])  # no wheel turns 1.7 rad
    with pytest.raises(BagError, match="steering"):
        load_commands(absurd, TELEOP_TOPIC, limits=limits)
