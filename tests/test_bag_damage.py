"""Damaged bags never reach the motor: one BagError naming the file and the cause, bounded memory,
commands checked, and ``racecar-hw follow`` / ``sim --follow`` refusing before anything starts.

The real bad bags come from ../shared/fixtures/bags (skipped where absent); the damaged ones are
made here from valid Ackermann bags.
"""

from __future__ import annotations

import math
import sqlite3
import struct
import subprocess
import sys
import tracemalloc
from pathlib import Path

import pytest
from fuzzing import TOPIC, write_bag

from racecar_hw.bags.follow import BagFollower, FollowerParams, load_commands
from racecar_hw.bags.recover import recover_bag
from racecar_hw.bags.validate import CommandLimits, check_storage
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import BagError
from racecar_hw.cli import main as cli_main
from vesc.fake import FakeVesc

T0 = 1_700_000_000 * 10**9
LIMITS = CommandLimits(5.0, 0.26)


def commands(n: int = 40, bad: dict[int, tuple[float, float]] | None = None,
             ) -> list[tuple[int, float, float]]:
    out = [(T0 + i * 50_000_000, 1.0 + 0.01 * i, 0.1) for i in range(n)]
    for i, (speed, steer) in (bad or {}).items():
        out[i] = (out[i][0], speed, steer)
    return out


def bag(tmp_path: Path, fmt: str, cmds: list[tuple[int, float, float]], name: str = "b") -> Path:
    return write_bag(tmp_path / (f"{name}.bag" if fmt == "ros1" else name), fmt, cmds)


def storage(path: Path) -> Path:
    return path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))


# --- commands are checked ----------------------------------------------------------------------


@pytest.mark.parametrize(("fmt", "bad", "says"), [
    ("ros1", {3: (math.nan, 0.1)}, "speed nan"),
    ("mcap", {7: (3e38, 0.0)}, "speed 3e+38 m/s, beyond the car's limit of 5 m/s"),
    ("sqlite3", {12: (1.0, -1.2)}, "steering -1.2 rad, beyond the car's limit of 0.26 rad"),
    ("mcap", {0: (math.inf, 0.0)}, "speed inf"),
])
def test_an_absurd_command_refuses_the_bag_naming_its_index_and_time(tmp_path, fmt, bad, says):
    path = bag(tmp_path, fmt, commands(bad=bad))
    index = next(iter(bad))
    with pytest.raises(BagError) as info:
        load_commands(path, TOPIC, limits=LIMITS)
    text = str(info.value)
    assert str(path) in text and says in text and f"message {index} on {TOPIC}" in text
    assert f"{index * 0.05:.3f} s into the recording" in text
    follower = BagFollower(Bus(), FollowerParams(bag=str(path), topic=TOPIC), limits=LIMITS)
    with pytest.raises(BagError, match=f"message {index} "):
        follower.load()


def test_commands_at_the_limits_load(tmp_path):
    path = bag(tmp_path, "ros1", commands(bad={0: (-5.0, 0.26), 1: (5.0, -0.26)}))
    assert len(load_commands(path, TOPIC, limits=LIMITS)) == 40


# --- memory is bounded -------------------------------------------------------------------------


def _ros1_first_chunk_data_len_at(data: bytes) -> int:
    """The offset of the first chunk record's data length field."""
    pos = 13
    while True:
        (hlen,) = struct.unpack_from("<I", data, pos)
        header = data[pos + 4:pos + 4 + hlen]
        (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
        if b"op=\x05" in header:
            return pos + 4 + hlen
        pos += 8 + hlen + dlen


def _mcap_first_chunk_at(data: bytes) -> int:
    pos = 8
    while data[pos] != 0x06:
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    return pos


def _refused_without_allocating(path: Path, match: str, **kw) -> None:
    tracemalloc.start()
    try:
        with pytest.raises(BagError, match=match):
            load_commands(path, TOPIC, **kw)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20, peak


def test_a_chunk_declaring_4_gb_is_refused_before_it_is_read(tmp_path):
    ros1 = bag(tmp_path, "ros1", commands())
    data = bytearray(ros1.read_bytes())
    struct.pack_into("<I", data, _ros1_first_chunk_data_len_at(data), 0xFFFFFFF0)
    ros1.write_bytes(data)
    _refused_without_allocating(ros1, r"declares 4294967280 bytes, but only \d+ follow")

    mcap = bag(tmp_path, "mcap", commands(), "m")
    file = storage(mcap)
    data = bytearray(file.read_bytes())
    at = _mcap_first_chunk_at(data)
    struct.pack_into("<Q", data, at + 9 + 16, 2**40)  # the chunk's uncompressed size
    file.write_bytes(data)
    _refused_without_allocating(mcap, "declares 1099511627776 bytes uncompressed, over the limit")


def test_a_message_over_max_message_bytes_is_refused(tmp_path):
    db = bag(tmp_path, "sqlite3", commands(), "s")
    with pytest.raises(BagError, match=r"a message of \d+ bytes, over the limit of 40"):
        check_storage(db, 40)
    ros1 = bag(tmp_path, "ros1", commands())
    with pytest.raises(BagError, match="over the limit of 1024 .max_message_bytes."):
        load_commands(ros1, TOPIC, max_message_bytes=1024)  # its chunks hold more than that
    assert len(load_commands(ros1, TOPIC, max_message_bytes=2**20)) == 40


# --- one error type ----------------------------------------------------------------------------


def _damaged(tmp_path: Path) -> dict[str, Path]:
    """Bags damaged in the ways a user meets: a cut file, garbage in the index, a bad header."""
    out = {}
    cut = bag(tmp_path, "ros1", commands(), "cut")
    cut.write_bytes(cut.read_bytes()[:-300])
    out["ros1 cut short"] = cut
    flipped = bag(tmp_path, "ros1", commands(), "flipped")
    data = bytearray(flipped.read_bytes())
    data[-40] ^= 0xFF  # inside the chunk infos at the end
    flipped.write_bytes(data)
    out["ros1 index byte flipped"] = flipped
    mcap = bag(tmp_path, "mcap", commands(), "mcap-cut")
    file = storage(mcap)
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    out["mcap cut in half"] = mcap
    db = bag(tmp_path, "sqlite3", commands(), "sqlite-header")
    file = storage(db)
    data = bytearray(file.read_bytes())
    data[:16] = b"not a database!!"
    file.write_bytes(data)
    out["sqlite3 header overwritten"] = db
    out["nan speed"] = bag(tmp_path, "mcap", commands(bad={5: (math.nan, 0.0)}), "nan")
    return out


def test_damaged_bags_give_one_bag_error_from_the_follower_and_the_recovery(tmp_path):
    for what, path in _damaged(tmp_path).items():
        with pytest.raises(BagError) as info:
            load_commands(path, TOPIC, limits=LIMITS)
        text = str(info.value)
        assert "\n" not in text and (str(path) in text or str(storage(path)) in text), (what, text)
        try:
            recover_bag(path, tmp_path / f"recovered-{len(what)}")
        except BagError as err:  # a recovery may fail, but only with BagError
            assert "\n" not in str(err)


def test_a_broken_sqlite_storage_from_recovery_is_a_bag_error(tmp_path):
    db = bag(tmp_path, "sqlite3", commands(), "s")
    con = sqlite3.connect(storage(db))
    con.execute("DROP TABLE messages")
    con.commit()
    con.close()
    with pytest.raises(BagError, match="sqlite3 storage is damaged"):
        load_commands(db, TOPIC)
    with pytest.raises(BagError):
        recover_bag(db)


# --- the command line: refuse before the car is touched ----------------------------------------


@pytest.fixture
def fake_vesc(device_thread, tmp_path):
    vesc = FakeVesc(str(tmp_path / "vesc"))
    device_thread.spawn(vesc.serve())
    return vesc


def _fixture_bags(fixtures: Path) -> list[Path]:
    return [*sorted((fixtures / "ros1").glob("*.bag")),
            *sorted(p for kind in ("mcap", "sqlite3") for p in (fixtures / "ros2" / kind).iterdir())]


def _one_line_naming(err: str, path: Path) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    named = [path, path.resolve(), *path.glob("*"), *path.resolve().glob("*")]
    assert any(str(p) in lines[0] for p in named), err


def _follow_refuses(bags: list[Path], vesc: FakeVesc, capsys: pytest.CaptureFixture[str]) -> None:
    for path in bags:
        code = cli_main(["follow", str(path), "--set", f"vesc.port={vesc.path}",
                         "--set", "gamepad.enabled=false", "--set", "status.enabled=false"])
        _, err = capsys.readouterr()
        assert code == 1, (path, err)
        _one_line_naming(err, path)
    assert vesc.commands == [] and vesc.frames_rx == 0  # the VESC port was never even opened


def test_follow_refuses_each_damaged_bag_in_one_line_and_sends_nothing(tmp_path, fake_vesc, capsys):
    _follow_refuses(list(_damaged(tmp_path).values()), fake_vesc, capsys)


def test_follow_refuses_each_real_bad_bag(bag_fixtures, fake_vesc, capsys):
    """The fixtures: a zero-byte file, a bag without messages, bags without an Ackermann topic, and
    the ROS 2 talker whose metadata does not match its storage."""
    _follow_refuses(_fixture_bags(bag_fixtures), fake_vesc, capsys)


def test_run_with_a_follower_configured_refuses_a_damaged_bag(tmp_path, fake_vesc, capsys):
    path = _damaged(tmp_path)["nan speed"]
    code = cli_main(["run", "--no-status", "--set", "follower.enabled=true", "--set", f"follower.bag={path}",
                     "--set", f"follower.topic={TOPIC}", "--set", f"vesc.port={fake_vesc.path}",
                     "--set", "gamepad.enabled=false"])
    _, err = capsys.readouterr()
    assert code == 1 and "speed nan" in err
    _one_line_naming(err, path)
    assert fake_vesc.frames_rx == 0


def test_follow_as_a_process_exits_1_with_one_line(tmp_path):
    path = _damaged(tmp_path)["mcap cut in half"]
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "follow", str(path), "--set",
                           "gamepad.enabled=false"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    _one_line_naming(proc.stderr, path)
    assert proc.stderr.startswith("racecar-hw follow: ")


def test_sim_follow_refuses_a_damaged_bag_before_the_simulation_starts(tmp_path, capsys, request):
    bags = [_damaged(tmp_path)["ros1 cut short"], _damaged(tmp_path / "nan")["nan speed"]]
    try:
        bags.append(request.getfixturevalue("bag_fixtures") / "ros1" / "empty-file.bag")
    except pytest.skip.Exception:
        pass
    for path in bags:
        code = cli_main(["sim", "--follow", str(path), "--no-status", "--out", str(tmp_path / "out")])
        out, err = capsys.readouterr()
        assert code == 1 and not out, (path, out, err)
        _one_line_naming(err, path)
    assert not (tmp_path / "out").exists()  # no run, so no report
