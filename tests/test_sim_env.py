"""The step API (racecar_hw.sim.env): the real daemon on the fakes in lockstep, one control period a
step, the same run for the same seed; and the loop's stepping and rewinding underneath it."""

from __future__ import annotations

import asyncio
import dataclasses
import math

import numpy as np
import pytest

from racecar_hw.base import clock
from racecar_hw.base.clock import NS_PER_S, SIM_EPOCH_NS
from racecar_hw.base.errors import ConfigError
from racecar_hw.runtime.lockstep import VirtualTimeLoop, close
from racecar_hw.sim.env import RaceEnv
from racecar_hw.sim.laps import LapProgress, infield_centre
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.policies import STEERING_MAX_RAD, follow_right_wall
from racecar_hw.sim.scenario import load_scenario

#: lockstep in this process, interfaces off, or pure computation: may run beside an alone test
pytestmark = pytest.mark.quiet


def drive_track(env: RaceEnv, seed: int, steps: int) -> dict:
    """One episode of the track scenario under :func:`follow_right_wall`: its final state."""
    obs, info = env.reset("track", seed=seed)
    angles = env.scan_angles
    rewards, ends = [], []
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(follow_right_wall(obs["scan"], angles))
        rewards.append(reward)
        ends.append((terminated, truncated))
    return {"obs": obs, "info": info, "rewards": rewards, "ends": ends,
            "interventions": env.daemon.safety.interventions, "time_ns": env.loop.now_ns()}


def assert_same_state(a: dict, b: dict) -> None:
    """Exactly the same: pose, odometry, scan, safety, step count, time and every reward."""
    assert np.array_equal(a["info"]["pose"], b["info"]["pose"])
    assert np.array_equal(a["obs"]["odom"], b["obs"]["odom"])
    assert np.array_equal(a["obs"]["scan"], b["obs"]["scan"])
    assert a["obs"]["safety"] == b["obs"]["safety"]
    assert a["info"]["steps"] == b["info"]["steps"]
    assert a["info"]["time_s"] == b["info"]["time_s"] and a["time_ns"] == b["time_ns"]
    assert a["info"]["speed_mps"] == b["info"]["speed_mps"]
    assert a["info"]["distance_m"] == b["info"]["distance_m"]
    assert a["rewards"] == b["rewards"] and a["ends"] == b["ends"]


def test_a_thousand_track_steps_reach_the_same_state_for_the_same_seed_twice():
    with RaceEnv("track") as env:
        first = drive_track(env, seed=7, steps=1000)
        assert env.period_s == 0.02  # the daemon's control period: mux.rate_hz 50
        second = drive_track(env, seed=7, steps=1000)  # reset: a new daemon, new fakes, same loop
    assert_same_state(first, second)
    info = first["info"]
    assert info["steps"] == 1000 and info["time_s"] == pytest.approx(20.0)
    # the policy drove the car round the first two corners without touching a wall
    assert not info["collided"] and first["ends"][-1] == (False, False)
    assert 0.4 < info["lap_progress"] < 1.0 and info["laps"] == 0
    assert sum(first["rewards"]) == pytest.approx(info["lap_progress"])
    assert info["mux_source"] == "nav_0"
    assert 25.0 < info["distance_m"] < 40.0
    # odometry (odom frame, from the start) follows the true pose (map frame, start at the origin)
    assert math.hypot(*(first["obs"]["odom"][:2] - info["pose"][:2])) < 2.0


def test_reset_starts_the_same_episode_again_and_a_fresh_env_runs_it_the_same():
    with RaceEnv() as env:
        obs1, info1 = env.reset(seed=5)
        tasks_of_first = set(asyncio.all_tasks(env.loop))
        for _ in range(50):
            env.step((1.0, 0.1))
        obs2, info2 = env.reset(seed=5)
        assert not tasks_of_first & asyncio.all_tasks(env.loop)  # the first episode is gone
        short = [env.step((1.0, 0.1)) for _ in range(100)]
        obs3, _ = env.reset(seed=6, options={"scenario": "track"})  # Gymnasium's way to say it
    assert obs1["scan"].shape == (1081,) and np.array_equal(obs1["scan"], obs2["scan"])
    assert np.array_equal(obs1["odom"], obs2["odom"]) and obs1["safety"] == obs2["safety"]
    assert info1["steps"] == info2["steps"] == 0 and info1["time_s"] == info2["time_s"] == 0.0
    assert np.array_equal(info1["pose"], np.zeros(3))
    assert not np.array_equal(obs1["scan"], obs3["scan"])  # another seed: other lidar noise
    with RaceEnv() as fresh:
        obs4, _ = fresh.reset(seed=5)
        again = [fresh.step((1.0, 0.1)) for _ in range(100)]
    assert np.array_equal(obs1["scan"], obs4["scan"])
    assert np.array_equal(short[-1][0]["odom"], again[-1][0]["odom"])
    assert np.array_equal(short[-1][4]["pose"], again[-1][4]["pose"])
    assert short[-1][4]["distance_m"] > 1.0


def test_a_step_ends_with_everything_the_fakes_sent_consumed():
    """Lockstep's guarantee at every step's end: each scan the fake lidar sent was decoded and is
    the observation's, each VESC reply reached the driver, each command reached the fake VESC."""
    with RaceEnv() as env:
        obs, _ = env.reset(seed=2)
        daemon, lidar, vesc = env.daemon, env.loopback.lidar, env.loopback.vesc
        new_scans = 0
        for k in range(150):
            before = daemon.lidar.stats.scans
            obs, *_ = env.step((1.0, 0.2 if k < 75 else -0.2))
            assert daemon.lidar.stats.scans == lidar.scans_sent
            assert daemon.vesc.stats.frames_rx == vesc.frames_tx
            assert vesc.frames_rx == daemon.vesc.stats.frames_tx
            if daemon.lidar.stats.scans > before:  # a new scan in this step: it is the observation
                new_scans += 1
                assert obs["scan_time_s"] <= env.time_s
        latest = daemon.bus.latest(daemon.config.safety.scan_topic)
        assert np.array_equal(obs["scan"], np.asarray(latest.ranges, dtype=np.float32))
    assert 115 <= new_scans <= 125  # 40 Hz scans in 150 steps of 20 ms: 4 steps in 5 see one


def test_a_collision_ends_the_episode():
    # the safety controller off, so nothing stops the car before the inner wall 1 m to its left
    with RaceEnv("track", overrides=["safety.mode=off"]) as env:
        env.reset(seed=1)
        steps, terminated = 0, False
        while not terminated and steps < 500:
            obs, _, terminated, truncated, info = env.step((2.0, STEERING_MAX_RAD))
            steps += 1
        assert terminated and not truncated and info["collided"]
        assert env.world.collisions and obs["safety"]["interventions"] == 0
        assert steps < 200
        # latched: stepping on stays terminated
        assert env.step((0.0, 0.0))[2]
    # the same policy with the safety controller on (the sim config's): it stops the car short
    with RaceEnv("track") as env:
        env.reset(seed=1)
        ends = [env.step((2.0, STEERING_MAX_RAD)) for _ in range(steps + 50)]
        assert not any(terminated for _, _, terminated, _, _ in ends)
        obs, _, _, _, info = ends[-1]
        assert obs["safety"]["interventions"] >= 1 and not info["collided"]
        assert abs(info["speed_mps"]) < 0.01 and info["command"][0] < 0.01  # held short of the wall


def test_an_episode_is_truncated_at_its_length():
    with RaceEnv(max_episode_s=0.1) as env:
        env.reset()
        ends = [env.step((0.5, 0.0))[2:4] for _ in range(6)]
    assert ends == [(False, False)] * 4 + [(False, True)] * 2


def test_the_action_bounds_are_the_vesc_conversions_and_an_action_beyond_is_driven_at_them():
    """An action out of range is clamped silently; ``env.action_bounds`` says to what, from the
    episode's config: the VESC conversion's limits, not the car model's mechanical steering limit."""
    from racecar_hw.sim.car import CarParams  # noqa: PLC0415

    with RaceEnv("track") as env:
        env.reset(seed=1)
        low, high = env.action_bounds
        assert low == pytest.approx([-5.0, -0.26]) and high == pytest.approx([5.0, 0.26])
        assert high[1] < CarParams().max_steering_angle
        for _ in range(10):  # 0.2 s; the limiter turns 3.2 rad/s: at the bound after 0.08 s
            *_, info = env.step((0.5, 5.0))
        assert info["command"][1] == pytest.approx(high[1])  # the mux's output: clamped
        assert info["steering_rad"] == pytest.approx(high[1], abs=1e-3)  # what the wheels do
    with RaceEnv("track", overrides=["vesc.speed_max_mps=2", "vesc.steering_max_rad=0.2"]) as env:
        env.reset(seed=1)
        low, high = env.action_bounds
        assert low == pytest.approx([-2.0, -0.2]) and high == pytest.approx([2.0, 0.2])


def test_refusals():
    with RaceEnv() as env:
        with pytest.raises(RuntimeError, match="reset"):
            env.step((1.0, 0.0))
        with pytest.raises(RuntimeError, match="virtual clock"):
            RaceEnv()  # one per process: the clock is the process's
        env.reset()
        for bad in ((math.nan, 0.0), (1.0, math.inf), (1.0,), "fast"):
            with pytest.raises(ValueError, match="action"):
                env.step(bad)
        with pytest.raises(ValueError, match="poses"):
            env.reset(options={"poses": [[0.0, 0.0, 0.0]]})
        # the scenario twice: refused, not one of them run silently
        for same_or_not in ("wall", "track"):
            with pytest.raises(ValueError, match=r"both as the argument \('track'\) and in options"):
                env.reset("track", options={"scenario": same_or_not})
        # a bad seed or scenario is refused before the running episode ends: it steps on
        before = env.steps
        for bad_seed in (-1, 1.5, True):
            with pytest.raises(ValueError, match="seed must be a non-negative integer"):
                env.reset(seed=bad_seed)
        with pytest.raises(ConfigError):
            env.reset("no-such-scenario")
        assert env.step((0.5, 0.0))[4]["steps"] == before + 1
        assert clock.is_virtual()
    assert not clock.is_virtual()  # closed: the real clock is back
    env.close()  # twice is fine
    with pytest.raises(RuntimeError, match="closed"):
        env.reset()
    with RaceEnv(mux_input="nav_9") as env, pytest.raises(ValueError, match="nav_9"):
        env.reset()


@pytest.mark.parametrize("action", [
    np.array([[0.1, 1.5]]),  # f1tenth_gym's (num_agents, 2) [[steering, speed]]
    np.array([[1.5], [0.1]]), np.array([1.5, 0.1, 0.0]), ("1.5", "0.1"), (True, False),
    np.array([True, False]), np.array(["1.5", "0.1"]), np.array([1.5, 0.1], dtype=object),
    [1.5], [[1.5, 0.1]], (np.bool_(True), 0.1), (1.5 + 0j, 0.1), 1.5, None, {"speed": 1.5}, "ab",
])
def test_an_action_that_is_not_two_real_numbers_is_refused_saying_the_order(action):
    """Not reshaped into a pair: an f1tenth_gym (1, 2) array was taken as speed 0.1, steering 1.5."""
    from racecar_hw.sim.env import _action  # noqa: PLC0415

    with pytest.raises(ValueError) as err:
        _action(action)
    assert "(speed m/s, steering rad)" in str(err.value)
    assert "f1tenth_gym's [[steering, speed]] per agent is the other way round" in str(err.value)


@pytest.mark.parametrize("action", [
    (1.5, 0.1), [1.5, 0.1], [1, 0], (np.float32(1.5), np.int64(0)), np.array([1.5, 0.1]),
    np.array([1.5, 0.1], dtype=np.float32), np.array([1, 0]),
])
def test_an_action_of_two_real_numbers_is_speed_then_steering(action):
    from racecar_hw.sim.env import _action  # noqa: PLC0415

    speed, steering = _action(action)
    assert (speed, steering) == pytest.approx((float(action[0]), float(action[1])))
    assert type(speed) is float and type(steering) is float


@pytest.mark.parametrize(("kwargs", "words"), [
    ({"max_laps": 0}, "max_laps must be a whole number of laps from 1"),
    ({"max_laps": -1}, "max_laps must be a whole number"),
    ({"max_laps": "2"}, "max_laps must be a whole number"),
    ({"max_laps": 1.5}, "max_laps must be a whole number"),
    ({"max_laps": True}, "max_laps must be a whole number"),
    ({"lap_centre": (math.nan, math.nan)}, "lap_centre must be finite"),
    ({"lap_centre": (0.0, math.inf)}, "lap_centre must be finite"),
    ({"lap_centre": (1.0,)}, r"lap_centre must be \(x m, y m\)"),
    ({"lap_centre": "middle"}, r"lap_centre must be \(x m, y m\)"),
])
def test_bad_lap_settings_are_refused_when_the_env_is_made(kwargs, words):
    with pytest.raises(ValueError, match=words):
        RaceEnv(**kwargs)
    assert not clock.is_virtual()  # refused before it took the process's clock


def test_good_lap_settings_are_kept():
    with RaceEnv(max_laps=np.int64(2), lap_centre=np.array([1, -2])) as env:
        assert env.max_laps == 2 and env.lap_centre == (1.0, -2.0)


def test_a_scenario_refused_before_its_devices_start_leaves_the_running_episode_stepping(tmp_path):
    """What Episode.start would refuse before anything of the scenario starts is refused by reset
    before it ends the running episode: a bad ``config:`` key, a missing map, a bad firmware, a
    scenario with cars, a negative seed in a Scenario made in code, a start inside a wall, a driver
    on no mux input, a follow driver's bag that is not there (which started and failed the new
    episode after the running one had ended)."""
    track = load_scenario("track")
    bad = {
        "config": (load_scenario("track", ["config={safety: {nosuchkey: 1}}"]), "safety.nosuchkey"),
        "map": (load_scenario("track", [f"map={tmp_path / 'nope.yaml'}"]), "nope.yaml"),
        "firmware": (load_scenario("track", ["firmware=abc"]), "firmware: 'abc' is not X.YY, like 6.02"),
        "cars": ("two-cars", "several cars"),
        "seed": (dataclasses.replace(track, world=dataclasses.replace(track.world, seed=-5)), "negative"),
        "start": (load_scenario("track", ["start=[6.0, 5.75, 0.0]"]), "start_pose"),
        "driver": (load_scenario("track", ["drivers=[{input: nav_9}]"]), "nav_9"),
        "bag": (load_scenario("track", [f"drivers=[{{type: follow, bag: {tmp_path / 'nope.mcap'}}}]"]),
                r"scenario\.drivers\.0\.bag: bag not found: .*nope\.mcap"),
    }
    with RaceEnv() as env:
        env.reset(seed=1)
        for _ in range(5):
            info = env.step((1.0, 0.0))[4]
        for what, (scenario, words) in bad.items():
            with pytest.raises((ConfigError, ValueError), match=words):
                env.reset(scenario)
            after = env.step((1.0, 0.0))[4]  # the same episode, one step on
            assert after["steps"] == info["steps"] + 1, what
            assert after["time_s"] > info["time_s"] and after["distance_m"] > info["distance_m"], what
            info = after
        assert env.reset()[1]["steps"] == 0  # and a good one starts


def test_a_refused_scenario_says_why_and_the_env_starts_the_next(caplog):
    broken = load_scenario("track", ["drivers=[{input: nav_9}]"])
    with RaceEnv() as env:
        with pytest.raises(ConfigError, match=r"scenario\.drivers\.0\.input.*nav_9"):
            env.reset(broken)
        obs, info = env.reset()  # nothing of the refused one in the way
        assert obs["scan"].size and info["steps"] == 0
        assert env.step((0.5, 0.0))[4]["steps"] == 1
    assert "failed" not in caplog.text


def test_lap_progress_counts_turns_round_the_infield_from_the_start_line():
    assert infield_centre(load_shipped_map("room")) is None  # an open room: no laps
    centre = infield_centre(load_shipped_map("track"))
    assert centre is not None and load_shipped_map("track").is_occupied(*centre)
    # a car heading +x below the centre goes counter-clockwise: forwards
    laps = LapProgress((0.0, 0.0), (0.0, -2.0, 0.0))
    angles = np.linspace(-math.pi / 2, -math.pi / 2 + 2.5 * 2 * math.pi, 400)
    progress = [laps.update(2 * math.cos(a), 2 * math.sin(a)) for a in angles]
    assert progress[-1] == pytest.approx(2.5) and laps.laps == 2
    assert all(b >= a for a, b in zip(progress, progress[1:], strict=False))
    # started heading -x there: the same path is backwards
    backwards = LapProgress((0.0, 0.0), (0.0, -2.0, math.pi))
    for a in angles:
        backwards.update(2 * math.cos(a), 2 * math.sin(a))
    assert backwards.progress == pytest.approx(-2.5) and backwards.laps == 0


def test_the_loop_runs_until_a_time_with_everything_due_by_then_done():
    loop = VirtualTimeLoop()
    seen: list[tuple[str, int]] = []
    try:
        def chain(n: int) -> None:  # work that a timer starts, handed on through the ready queue
            seen.append((f"chain {n}", loop.now_ns()))
            if n:
                loop.call_soon(chain, n - 1)

        start = loop.now_ns()
        loop.call_later(0.02, chain, 5)     # exactly at the end
        loop.call_later(0.0201, seen.append, ("later", 0))
        loop.run_until_time(start + NS_PER_S // 50)
        assert loop.now_ns() == start + NS_PER_S // 50
        assert [name for name, _ in seen] == [f"chain {n}" for n in range(5, -1, -1)]
        assert {t for _, t in seen} == {start + NS_PER_S // 50}
        loop.run_until_time(start + NS_PER_S)  # no timer before the end: time jumps to it
        assert loop.now_ns() == start + NS_PER_S and seen[-1] == ("later", 0)
        with pytest.raises(ValueError):
            loop.run_until_time(start)
        handle = loop.call_later(1.0, seen.append, ("never", 0))
        with pytest.raises(RuntimeError, match="rewind"):
            loop.rewind()
        handle.cancel()
        loop.rewind()
        assert loop.now_ns() == SIM_EPOCH_NS
    finally:
        close(loop)
