"""``racecar-hw bag info`` and ``racecar-hw bag recover`` on complete and interrupted bags of every format."""

from __future__ import annotations

from pathlib import Path

import pytest

from racecar_hw.bags.follow import load_commands
from racecar_hw.bags.record import BagFile
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time
from racecar_hw.cli import main
from racecar_hw.rosmsg.typestore import types_for

CMD = "/vesc/low_level/ackermann_cmd_mux/input/teleop"
T0 = 1_700_000_000 * 10**9


def write_bag(tmp_path: Path, fmt: str, close: bool) -> Path:
    """Five commands 0.1 s apart; without ``close`` the file is left as a killed recorder leaves it
    (everything flushed, nothing closed)."""
    path = tmp_path / ("run_0.bag" if fmt == "ros1" else "run/run_0")
    bag = BagFile(path, fmt, "none", types_for(1 if fmt == "ros1" else 2))
    for i in range(5):
        msg = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=float(i)))
        bag.write(CMD, msg, T0 + i * 100_000_000)
    bag.flush()
    if close:
        bag.close()
    return path if fmt == "ros1" else path.parent


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3", "ros1"])
def test_info_of_a_complete_bag(tmp_path, capsys, fmt):
    bag = write_bag(tmp_path, fmt, close=True)
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "complete:  yes" in out
    assert "messages:  5\n" in out and "duration:  0.400 s" in out
    assert "start:     2023-11-14 22:13:20.000000 UTC (1700000000.000000000)" in out
    assert "end:       2023-11-14 22:13:20.400000 UTC (1700000000.400000000)" in out
    assert f"{CMD}  ackermann_msgs/msg/AckermannDriveStamped         5 msgs" in out
    assert main(["bag", "recover", str(bag)]) == 0
    assert "is complete (5 messages): nothing to recover" in capsys.readouterr().out


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3", "ros1"])
def test_info_and_recover_of_an_interrupted_bag(tmp_path, capsys, fmt):
    bag = write_bag(tmp_path, fmt, close=False)
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "complete:  no: " in out and f"recover with: racecar-hw bag recover {bag}" in out
    assert "messages:  5" in out and "duration:  0.400 s" in out
    out_path = tmp_path / ("fixed.bag" if fmt == "ros1" else "fixed")
    assert main(["bag", "recover", str(bag), "-o", str(out_path)]) == 0
    recovered = bag if fmt == "sqlite3" else out_path  # sqlite3: metadata.yaml fixed in place
    assert f"recovered 5 messages into {recovered}" in capsys.readouterr().out
    assert [c.drive.speed for c in load_commands(recovered, CMD)] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert main(["bag", "info", str(recovered)]) == 0
    assert "complete:  yes" in capsys.readouterr().out


def test_bag_errors_are_one_line(tmp_path, capsys):
    assert main(["bag", "info", str(tmp_path / "missing")]) == 1
    assert capsys.readouterr().err == f"racecar-hw bag: bag not found: {tmp_path / 'missing'}\n"
    (tmp_path / "empty.bag").write_bytes(b"")
    assert main(["bag", "recover", str(tmp_path / "empty.bag")]) == 1
    assert "is empty (0 bytes)" in capsys.readouterr().err
    (tmp_path / "notabag").mkdir()
    assert main(["bag", "info", str(tmp_path / "notabag")]) == 1
    assert "holds no .mcap or .db3 file" in capsys.readouterr().err


def test_info_says_the_real_tools_bags_are_complete(bag_fixtures, capsys):
    """Bags recorded by the real rosbag and rosbag2 (no messages, unsorted chunks, LZ4, a sqlite3
    bag in WAL mode) are complete; bag info never changes them (the fixtures are read-only)."""
    bags = [*sorted((bag_fixtures / "ros1").glob("*.bag")),
            *sorted(p for p in (bag_fixtures / "ros2").glob("*/*") if p.is_dir())]
    assert len(bags) >= 8
    for bag in bags:
        if bag.stat().st_size == 0:
            assert main(["bag", "info", str(bag)]) == 1
            continue
        assert main(["bag", "info", str(bag)]) == 0, capsys.readouterr().err
        assert "complete:  yes" in capsys.readouterr().out, bag
