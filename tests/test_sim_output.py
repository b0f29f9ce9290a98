"""Run outputs: the trajectory CSV and report numbers, the PNG plot, the generated maps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from racecar_hw.base.errors import RacecarError
from racecar_hw.base.resources import config_file
from racecar_hw.sim import mapgen
from racecar_hw.sim.car import CarParams, Collider
from racecar_hw.sim.occupancy import load_map, load_shipped_map
from racecar_hw.sim.plot import (
    ALLOWED_LABEL,
    ControlSample,
    Mark,
    as_marks,
    image_size,
    plot_run,
    plot_world,
    run_figure,
)
from racecar_hw.sim.raycast import RayCaster
from racecar_hw.sim.trajectory import (
    TrajectorySample,
    distance_travelled,
    read_csv,
    report,
    rest_time,
    stop_time,
    stopping_distance,
    write_csv,
)
from racecar_hw.sim.world import World


def braking_run() -> list[TrajectorySample]:
    """2 m/s along +x for 1 s, then braking at 4 m/s^2 to a stop, sampled at 10 ms."""
    out, x, v = [], 0.0, 2.0
    for k in range(200):
        t = k * 0.01
        out.append(TrajectorySample(t, x, 0.0, 0.0, v, 0.0))
        if t >= 1.0:
            v = max(v - 4.0 * 0.01, 0.0)
        x += v * 0.01
    return out


def test_csv_round_trip(tmp_path: Path) -> None:
    run = braking_run()
    path = tmp_path / "traj.csv"
    assert write_csv(path, run) == len(run)
    assert path.read_text().splitlines()[0] == "t,x,y,yaw,speed,steering"
    back = read_csv(path)
    assert len(back) == len(run)
    assert np.allclose(np.asarray(back), np.asarray(run), atol=1e-6)
    path.write_text("a,b\n1,2\n")
    with pytest.raises(RacecarError, match="not a trajectory CSV"):
        read_csv(path)


def test_report_numbers() -> None:
    run = braking_run()
    rep = report(run)
    # 2 m in the first second, then v^2 / 2a = 0.5 m of braking
    assert rep.distance_m == pytest.approx(2.5, abs=0.03)
    assert rep.duration_s == pytest.approx(1.99)
    assert rep.max_speed_mps == 2.0
    assert rep.displacement_m == pytest.approx(rep.distance_m)
    assert math.isnan(rep.min_clearance_m)
    assert rep.as_dict()["end_pose"] == rep.end_pose
    assert stop_time(run, 1.0) == pytest.approx(1.5, abs=0.02)
    assert stopping_distance(run, 1.0) == pytest.approx(0.5, abs=0.03)
    assert stopping_distance(run[:120], 1.0) is None
    assert distance_travelled(run) == pytest.approx(rep.distance_m)
    assert report([]).distance_m == 0.0


def test_the_car_comes_to_rest_where_it_stands_still_after_moving() -> None:
    run = braking_run()  # at rest from 1.5 s
    assert rest_time(run, 1.0) == stop_time(run, 1.0) == pytest.approx(1.5, abs=0.02)
    assert rest_time(run, 1.0, 1.3) is None  # still braking at 1.3 s
    assert rest_time(run, 1.6, 1.8) == pytest.approx(1.6)  # stood still throughout
    # standing at 1.6 s, then creeping 0.3 m at 0.3 m/s from 2.0 s to 3.0 s: it came to rest at 3 s
    creep = run + [TrajectorySample(2.0 + k * 0.01, run[-1].x + 0.003 * min(k, 100), 0.0, 0.0,
                                    0.3 if k < 100 else 0.0, 0.0) for k in range(200)]
    assert stop_time(creep, 1.6) == pytest.approx(1.6)  # the first standstill: before it crept
    assert rest_time(creep, 1.6) == pytest.approx(3.0)
    assert stopping_distance(creep, 1.6, rest_time(creep, 1.6)) == pytest.approx(0.3, abs=0.01)
    assert rest_time(creep, 1.6, 2.5) is None and rest_time([], 0.0) is None


def test_report_circle_and_clearance() -> None:
    p = CarParams()
    radius, speed = 2.0, 3.0
    delta = math.atan(p.wheelbase / radius)
    run = [TrajectorySample(k * 0.01, radius * math.sin(a), radius - radius * math.cos(a), a, speed, delta)
           for k, a in enumerate(np.arange(0, 2 * math.pi, speed * 0.01 / radius))]
    corridor = Collider(load_shipped_map("room"), p)
    rep = report(run, p.wheelbase, clearance=corridor.clearance, clearance_every=10)
    assert rep.max_lateral_accel_mps2 == pytest.approx(speed * speed / radius)
    assert rep.distance_m == pytest.approx(2 * math.pi * radius, rel=0.01)
    # a 2 m circle to the left of the start, in a room 10 m deep centred on the start: the top of the
    # circle (y = 4 m) has the wall 1 m away, minus half the car's width
    assert rep.min_clearance_m == pytest.approx(1.0 - 0.15, abs=0.05)


def _by_gid(fig, gid):
    return [a for ax in fig.axes for a in ax.get_children() if a.get_gid() == gid]


def test_plot_writes_a_png_of_the_right_size(tmp_path: Path) -> None:
    occ = load_shipped_map("track")
    run = [(k * 0.1, 0.1 * k, 0.0, 0.0, 1.0) for k in range(100)]
    out = tmp_path / "run.png"
    size = plot_run(out, occ, run, interventions=[(5.0, 0.0)], collisions=[(9.9, 0.0)],
                    obstacles=[(3.0, 0.5, 0.2)], title="test run")
    assert size == image_size(occ, with_series=False)
    with Image.open(out) as img:
        assert img.format == "PNG" and img.size == size
    small = plot_run(tmp_path / "small.png", occ, [], width_px=400)
    assert small[0] == 400


def test_the_figure_reads_in_metres_with_the_path_coloured_by_speed_and_the_events_marked() -> None:
    occ = load_shipped_map("room")
    run = [(k * 0.1, 0.1 * k, 0.05 * k, 0.0, 0.02 * k) for k in range(50)]
    series = [ControlSample(k * 0.1, 1.0, 0.9, 2.0 - 0.02 * k, 0.8, 0.1) for k in range(50)]
    fig = run_figure(occ, run, interventions=[{"t": 2.0, "x": 2.0, "y": 1.0, "reason": "obstacle"}],
                     collisions=[(4.5, 4.0, 2.0)], obstacles=[(3.0, 0.5, 0.2)], title="a run",
                     series=series, switches=[[0.0, "idle"], [0.5, "nav_0"], [3.0, "estop"]])
    ax_map, ax_speed, ax_steer, ax_source = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert (ax_map.get_xlabel(), ax_map.get_ylabel()) == ("x (m)", "y (m)")
    assert ax_map.get_title() == "a run" and ax_source.get_xlabel() == "sim time (s)"
    # the map spans the grid in metres
    w_m, h_m = occ.size_m
    x0, x1 = ax_map.get_xlim()
    assert x1 - x0 == pytest.approx(w_m) and x0 == pytest.approx(occ.origin[0])
    # the path: one segment per step (that moves), coloured by the speed at its end
    (path,) = _by_gid(fig, "path")
    assert len(path.get_segments()) == 49
    assert np.allclose(path.get_array(), [0.02 * k for k in range(1, 50)])
    assert any(ax.get_label() == "<colorbar>" and "speed (m/s)" in ax.get_ylabel() for ax in fig.axes)
    (ring,) = _by_gid(fig, "interventions")
    assert np.allclose(ring.get_offsets(), [[2.0, 1.0]])
    (cross,) = _by_gid(fig, "collisions")
    assert np.allclose(cross.get_offsets(), [[4.0, 2.0]])
    # interventions and collisions also stand on the time axis
    vertical = [line.get_xdata()[0] for line in ax_speed.get_lines()
                if line.get_xdata()[0] == line.get_xdata()[1]]
    assert 2.0 in vertical and 4.5 in vertical
    labels = [line.get_label() for line in ax_speed.get_lines() if not line.get_label().startswith("_")]
    assert labels == ["commanded", "output", ALLOWED_LABEL, "measured"]
    allowed = next(line for line in ax_speed.get_lines() if line.get_label().startswith("allowed"))
    assert max(allowed.get_ydata()) < ax_speed.get_ylim()[1]  # drawn on the plot even where it is high
    assert ax_speed.get_ylabel() == "speed (m/s)" and ax_steer.get_ylabel() == "steering (rad)"
    # the active source as spans: idle 0-0.5, nav_0 0.5-3, estop to the end of the run (4.9 s)
    spans = {gid: art.get_paths()[0].get_extents() for gid in ("source:idle", "source:nav_0", "source:estop")
             for art in _by_gid(fig, gid)}
    assert spans["source:nav_0"].x0 == pytest.approx(0.5) and spans["source:nav_0"].x1 == pytest.approx(3.0)
    assert spans["source:estop"].x1 == pytest.approx(4.9)
    assert "nav_0" in [t.get_text() for t in ax_source.texts]


def _allowed_line(fig):  # noqa: ANN001, ANN202
    ax_speed = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"][1]
    (line,) = [line for line in ax_speed.get_lines() if line.get_label() == ALLOWED_LABEL]
    return ax_speed, np.asarray(line.get_ydata(), dtype=float)


def test_the_allowed_speed_is_drawn_on_the_side_the_car_drives_and_holds_while_idle() -> None:
    """Reversing, the allowed |speed| is drawn below zero with the measured speed; not limiting, it
    runs along that side's edge; single idle ticks (nothing commanded or sent) do not drop it to 0."""
    occ = load_shipped_map("room")
    series = ([ControlSample(k * 0.1, 1.0, 1.0, 1.1, 0.9, 0.0) for k in range(10)]          # forwards
              + [ControlSample(1.0, 0.0, 0.0, 0.0, 0.5, 0.0)]                               # one idle tick
              + [ControlSample(1.1 + k * 0.1, -0.5, -0.5, 0.3, -0.4, 0.0) for k in range(10)]  # reverse
              + [ControlSample(2.1, 0.0, 0.0, 0.0, -0.1, 0.0)]                              # idle again
              + [ControlSample(2.2 + k * 0.1, -0.5, -0.5, math.inf, -0.5, 0.0) for k in range(5)])
    fig = run_figure(occ, [(0.0, 0.0, 0.0, 0.0, 0.0)], series=series)
    ax, allowed = _allowed_line(fig)
    assert allowed[:10] == pytest.approx([1.1] * 10)
    assert allowed[10] == pytest.approx(1.1)  # the idle tick keeps the value, no drop to 0
    assert allowed[11:21] == pytest.approx([-0.3] * 10)  # reversing: below zero, as measured
    assert allowed[21] == pytest.approx(-0.3)
    low, _ = ax.get_ylim()
    assert allowed[22:] == pytest.approx([low * 0.985] * 5)  # not limiting: along the bottom edge
    assert all(a < 0 for a, s in zip(allowed, series, strict=True) if s.commanded < 0)


def test_a_reverse_wall_run_plots_the_allowed_speed_on_the_measured_side(tmp_path: Path) -> None:
    """The shipped reverse-wall scenario, run on the loopback (in lockstep): wherever the car
    reverses, the plotted allowed speed is below zero too (read from the figure's data, not its
    pixels)."""
    from lockstep_sim import run_lockstep

    result, loopback = run_lockstep("reverse-wall", out_dir=tmp_path)
    samples = loopback.control_samples
    fig = run_figure(loopback.map, [(0.0, 0.0, 0.0, 0.0, 0.0)], series=samples)
    _, allowed = _allowed_line(fig)
    reversing = [i for i, s in enumerate(samples) if s.commanded < -0.05 and s.measured < -0.05]
    assert len(reversing) > 10, "the scenario reverses"
    # below zero; exactly 0 where the safety controller stops the car at the wall
    assert all(allowed[i] <= 0 for i in reversing), [(samples[i], allowed[i]) for i in reversing
                                                      if allowed[i] > 0][:5]
    assert sum(allowed[i] < 0 for i in reversing) > len(reversing) / 2
    forwards = [i for i, s in enumerate(samples) if s.commanded > 0.05 and s.measured > 0.05]
    assert forwards and all(allowed[i] >= 0 for i in forwards)
    assert result.plot_png is not None and result.plot_png.exists()


def test_marks_accept_every_shape_a_report_holds() -> None:
    class Event:
        t, x, y = 1.0, 2.0, 3.0

    shapes = [(2.0, 3.0), (1.0, 2.0, 3.0), {"x": 2, "y": 3, "t": 1, "reason": "obstacle"}, Event(),
              Mark(2.0, 3.0)]
    assert as_marks(shapes) == [Mark(2.0, 3.0), Mark(2.0, 3.0, 1.0), Mark(2.0, 3.0, 1.0, "obstacle"),
                                Mark(2.0, 3.0, 1.0), Mark(2.0, 3.0)]


@pytest.mark.parametrize("name", sorted(mapgen.SPECS))
def test_mapgen_reproduces_the_shipped_maps(tmp_path: Path, name: str) -> None:
    pgm, yml = mapgen.write_map(mapgen.SPECS[name], tmp_path)
    assert yml.read_text() == config_file("maps", f"{name}.yaml").read_text()
    with Image.open(pgm) as new, Image.open(config_file("maps", f"{name}.pgm")) as old:
        assert new.mode == old.mode == "L"
        assert np.array_equal(np.asarray(new), np.asarray(old))
    generated, shipped = load_map(yml), load_shipped_map(name)
    assert np.array_equal(generated.data, shipped.data) and generated.origin == shipped.origin
    assert config_file("maps", f"{name}.pgm").stat().st_size < 150_000


def test_corridor_geometry() -> None:
    m = load_shipped_map("corridor")
    # count free cells across the corridor at several stations: exactly 30 cells of 0.05 m
    for x in (0.0, 5.0, 15.0, 25.0):
        i, _ = m.world_to_cell(x, 0.0)
        assert int((~m.occupied[:, int(i)]).sum()) == 30
    i0, j0 = m.world_to_cell(0.0, 0.0)
    free_run = ~m.occupied[int(j0)]
    assert free_run.sum() * m.resolution == pytest.approx(30.0)  # 30 m long
    assert RayCaster(m).cast(0.0, 0.0, 0.0, np.array([0.0]), 40.0)[0] >= 25.0


def test_room_and_track_layout() -> None:
    room = RayCaster(load_shipped_map("room"))
    assert room.cast(0.0, 0.0, 0.0, np.array([0.0]), 30.0)[0] >= 6.0 + 0.45
    track = load_shipped_map("track")
    w, h = track.size_m
    assert (w, h) == pytest.approx((20.0, 14.0))
    caster = RayCaster(track)
    up, down = caster.cast(0.0, 0.0, 0.0, np.array([math.pi / 2, -math.pi / 2]), 30.0)
    assert up + down == pytest.approx(2.0, abs=0.05)  # the bottom corridor is 2 m wide
    # the loop is closed: a point in every corridor (right, top, left) and the room is free
    for x, y in [(14.75, 5.0), (10.0, 11.25), (-2.75, 5.0), (9.0, 7.5)]:
        assert not bool(track.is_occupied(x, y))
    assert bool(track.is_occupied(2.0, 4.0))  # the central block
    # the room's doorway (image x 12..14 m) opens onto the top corridor
    assert not bool(track.is_occupied(9.0, 9.9)) and bool(track.is_occupied(7.5, 9.9))


def test_mapgen_command_writes_every_map(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert mapgen.main([str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"{n}.{ext}" for n in mapgen.SPECS for ext in ("pgm", "yaml"))
    assert "corridor.yaml" in capsys.readouterr().out


def test_plot_and_report_of_a_world(tmp_path: Path) -> None:
    p = CarParams()
    world = World(load_shipped_map("room"), p, (0.0, 0.0, 0.0), lambda: 3.0 * p.speed_to_erpm_gain)
    world.add_obstacle(4.0, 1.5, box=(0.5, 0.3), yaw=0.5)
    world.add_obstacle(4.0, -1.5, radius=0.3)
    for _ in range(1000):
        world.step(0.005)
    rep = world.report()
    assert world.collided and rep.min_clearance_m == 0.0
    assert rep.distance_m == pytest.approx(8.0 - 0.45, abs=0.03)
    assert rep.max_speed_mps == pytest.approx(3.0)
    out = tmp_path / "world.png"
    assert plot_world(out, world, interventions=[(2.0, 0.0)], width_px=600) == image_size(
        world.map, 600, with_series=False)
    with Image.open(out) as img:
        assert img.format == "PNG"
    csv_path = tmp_path / "world.csv"
    write_csv(csv_path, world.samples)
    assert report(read_csv(csv_path)).end_pose == pytest.approx(rep.end_pose, abs=1e-5)
