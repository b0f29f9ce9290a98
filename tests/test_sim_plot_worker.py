"""The run's plot drawn in a second process (racecar_hw.sim.plot_worker): the same PNG as drawn
in-process, and a figure drawn whatever becomes of the child."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from racecar_hw.sim.obstacles import Box
from racecar_hw.sim.occupancy import load_shipped_map
from racecar_hw.sim.plot import ControlSample, Mark, path_segments, plot_run
from racecar_hw.sim.plot_worker import PlotWorker


def _figure_args() -> tuple[tuple, dict]:
    """A run that drives, stands still for a while (rows that repeat the pose), then drives on."""
    occ = load_shipped_map("room")
    rows = [(k * 0.1, 0.1 * min(k, 20) + 0.1 * max(k - 60, 0), 0.02 * min(k, 20), 0.1,
             0.0 if 20 <= k < 60 else 1.0) for k in range(100)]
    series = [ControlSample(k * 0.1, 1.0, 0.9, 2.0, 0.8, 0.05) for k in range(100)]
    args = (occ, rows, [Mark(2.0, 0.4, 2.0)], [(9.5, 4.0, 0.8)],
            [Box(3.0, -1.0, 0.4, 0.4)])
    return args, {"title": "worker", "series": series, "switches": [[0.0, "idle"], [1.0, "nav_0"]]}


def test_the_worker_draws_the_same_png_as_this_process(tmp_path: Path) -> None:
    args, kwargs = _figure_args()
    here = plot_run(tmp_path / "here.png", *args, **kwargs)
    with PlotWorker.start() as worker:
        assert worker.submit(tmp_path / "there.png", *args, **kwargs).wait() == here
    assert (tmp_path / "there.png").read_bytes() == (tmp_path / "here.png").read_bytes()


def test_a_worker_that_died_leaves_the_plot_to_this_process(tmp_path: Path) -> None:
    args, kwargs = _figure_args()
    plot_run(tmp_path / "here.png", *args, **kwargs)
    with PlotWorker.start() as worker:
        assert worker._process is not None
        worker._process.kill()
        worker._process.wait()
        worker.submit(tmp_path / "there.png", *args, **kwargs).wait()
    assert (tmp_path / "there.png").read_bytes() == (tmp_path / "here.png").read_bytes()


def test_a_stopped_worker_is_given_up_after_its_timeout_and_the_plot_drawn_here(tmp_path: Path,
                                                                                monkeypatch) -> None:
    """A child that is stopped (SIGSTOP) or stuck once held the run's end, Ctrl-C and all, for
    good: after RESULT_TIMEOUT_S it is killed and the figure drawn in this process."""
    import signal

    from racecar_hw.sim import plot_worker

    monkeypatch.setattr(plot_worker, "RESULT_TIMEOUT_S", 1.0)
    args, kwargs = _figure_args()
    plot_run(tmp_path / "here.png", *args, **kwargs)
    with PlotWorker.start() as worker:
        process = worker._process
        assert process is not None
        process.send_signal(signal.SIGSTOP)
        worker.submit(tmp_path / "there.png", *args, **kwargs).wait()
        assert process.poll() is not None  # killed, not left stopped
    assert (tmp_path / "there.png").read_bytes() == (tmp_path / "here.png").read_bytes()


def test_a_figure_the_child_cannot_draw_is_drawn_here_and_raises_as_before(tmp_path: Path) -> None:
    args, kwargs = _figure_args()
    kwargs["switches"] = [[0.0]]  # a switch without its source: plot_run raises
    with PlotWorker.start() as worker:
        pending = worker.submit(tmp_path / "bad.png", *args, **kwargs)
        try:
            pending.wait()
        except ValueError:
            pass
        else:
            raise AssertionError("the in-process draw should raise what plot_run raises")


def test_closing_an_unused_worker_ends_its_child() -> None:
    worker = PlotWorker.start()
    process = worker._process
    assert process is not None
    worker.close()
    assert process.returncode is not None


def test_standing_still_draws_no_segment_and_keeps_the_speed_of_each_move() -> None:
    traj = np.array([[0.0, 0.0, 0.0, 0.0, 0.0], [0.1, 0.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.0, 0.0, 1.0],
                     [0.3, 0.1, 0.0, 0.0, 0.0], [0.4, 0.1, 0.2, 0.0, -2.0]])
    segments, speed = path_segments(traj)
    assert segments.tolist() == [[[0.0, 0.0], [0.1, 0.0]], [[0.1, 0.0], [0.1, 0.2]]]
    assert speed.tolist() == [1.0, 2.0]
