"""``racecar-hw bag info`` and ``racecar-hw bag recover`` on complete and interrupted bags of every format."""

from __future__ import annotations

import shutil
import sqlite3
import tracemalloc
from pathlib import Path

import pytest
import yaml

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
    assert f"recovered 5 messages into {out_path}" in capsys.readouterr().out
    assert [c.drive.speed for c in load_commands(out_path, CMD)] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert main(["bag", "info", str(out_path)]) == 0
    assert "complete:  yes" in capsys.readouterr().out
    assert main(["bag", "info", str(bag)]) == 0  # -o leaves the bag as it was, sqlite3 too
    assert "complete:  no: " in capsys.readouterr().out
    if fmt == "sqlite3":  # without -o, fixed in place
        assert main(["bag", "recover", str(bag)]) == 0
        assert f"recovered 5 messages into {bag}" in capsys.readouterr().out
        assert main(["bag", "info", str(bag)]) == 0
        assert "complete:  yes" in capsys.readouterr().out


def write_killed_split_set(tmp_path: Path, fmt: str, last: str) -> list[Path]:
    """Three closed splits of four commands each, then a fourth split as a recording killed just
    after opening it leaves it: ``opened`` (what reached the disk when the file was created:
    nothing for MCAP, the header for ROS 1, the empty tables for sqlite3), ``header`` (its header
    flushed too) or ``empty`` (0 bytes, e.g. a power loss before anything reached the disk).
    Returns the bag (ROS 2: the directory) or, ROS 1, the four split files."""
    work = tmp_path / "recording"
    work.mkdir()
    types = types_for(1 if fmt == "ros1" else 2)
    paths = [work / (f"run_{i}.bag" if fmt == "ros1" else f"run/run_{i}") for i in range(4)]
    meta = None
    for i in range(3):
        bag = BagFile(paths[i], fmt, "none", types, meta)
        meta = bag.meta
        for k in range(4):
            n = 4 * i + k
            msg = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=float(n)))
            bag.write(CMD, msg, T0 + n * 100_000_000)
        bag.flush()
        bag.close(last=False)
    opened = BagFile(paths[3], fmt, "none", types, meta)
    if last == "header":  # the header pushed to the file, no message yet
        if fmt == "ros1":
            opened._ros1._fh.flush()  # noqa: SLF001 - the file as the OS has it
        elif fmt == "mcap":
            opened._storage._fh.flush()  # noqa: SLF001
    snapshot = tmp_path / "killed"
    shutil.copytree(work, snapshot)  # what is on disk at the kill (the writer's buffers are lost)
    opened.abort()
    files = sorted(snapshot.rglob("run_*.*"))
    if last == "empty":
        files[-1].write_bytes(b"")
    return files if fmt == "ros1" else [snapshot / "run"]


@pytest.mark.parametrize("last", ["opened", "header", "empty"])
@pytest.mark.parametrize("fmt", ["mcap", "sqlite3"])
def test_a_ros2_split_killed_as_it_opened_keeps_every_other_message(tmp_path, capsys, fmt, last):
    (bag,) = write_killed_split_set(tmp_path, fmt, last)
    last_file = sorted(bag.glob("run_*"))[-1]
    if fmt == "mcap" and last == "opened":
        assert last_file.stat().st_size == 0  # as the auditor's killed recording left it
    assert main(["bag", "info", str(bag)]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "format:    ROS 2 (" in out and "4 files" in out
    assert "complete:  no: " in out
    if last_file.stat().st_size == 0:
        assert f"no: {last_file.name} is empty (0 bytes" in out
    assert "messages:  12 (readable ones)" in out and "duration:  1.100 s" in out
    assert main(["bag", "recover", str(bag), "-o", str(tmp_path / "fixed")]) == 0, capsys.readouterr().err
    assert f"recovered 12 messages into {tmp_path / 'fixed'}" in capsys.readouterr().out
    assert [c.drive.speed for c in load_commands(tmp_path / "fixed", CMD)] == [float(i) for i in range(12)]
    assert main(["bag", "info", str(tmp_path / "fixed")]) == 0
    assert "complete:  yes" in capsys.readouterr().out


@pytest.mark.parametrize("last", ["opened", "empty"])
def test_a_ros1_split_killed_as_it_opened_is_an_empty_bag_and_the_others_are_whole(tmp_path, capsys,
                                                                                    last):
    """ROS 1 splits are separate bags (rosbag record --split): the last one holds nothing."""
    *closed, killed = write_killed_split_set(tmp_path, "ros1", last)
    for i, split in enumerate(closed):
        assert main(["bag", "info", str(split)]) == 0
        out = capsys.readouterr().out
        assert "complete:  yes" in out and "messages:  4\n" in out
        assert [c.drive.speed for c in load_commands(split, CMD)] == [float(4 * i + k) for k in range(4)]
    if last == "empty":
        assert main(["bag", "info", str(killed)]) == 1
        assert "is empty (0 bytes): nothing was flushed" in capsys.readouterr().err
        assert main(["bag", "recover", str(killed)]) == 1
        assert "is empty (0 bytes)" in capsys.readouterr().err
        return
    assert main(["bag", "info", str(killed)]) == 0
    out = capsys.readouterr().out
    assert "complete:  no: not indexed" in out and "messages:  0 (readable ones)" in out
    assert main(["bag", "recover", str(killed)]) == 0
    assert "recovered 0 messages into" in capsys.readouterr().out


def test_a_bag_whose_only_file_is_empty_has_nothing_to_recover(tmp_path, capsys):
    (bag,) = write_killed_split_set(tmp_path, "mcap", "opened")
    for split in sorted(bag.glob("run_*.mcap"))[:-1]:
        split.unlink()
    assert main(["bag", "info", str(bag)]) == 0
    assert "messages:  0 (readable ones)" in capsys.readouterr().out
    assert main(["bag", "recover", str(bag)]) == 1
    assert "nothing to recover: every file of" in capsys.readouterr().err


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


def test_info_of_a_bag_with_a_damaged_definition_is_one_printable_line(bag_fixtures, tmp_path, capsys):
    """Five bytes of a message definition inside the real rosbag2 MCAP bag made NULs: bag info's
    error was the reader's whole text, 25 lines with the NULs in them."""
    bag = tmp_path / "cdr_test"
    shutil.copytree(bag_fixtures / "ros2" / "mcap" / "cdr_test", bag)
    for part in bag.iterdir():
        part.chmod(0o644)
    mcap = bag / "cdr_test_0.mcap"
    data = mcap.read_bytes()
    at = data.rindex(b"uint16 UINT16_CONST")  # the definition's copy in the summary
    mcap.write_bytes(data[:at + 1] + b"\0" * 5 + data[at + 6:])
    assert main(["bag", "info", str(bag)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.rstrip("\n").isprintable()
    assert err.startswith(f"racecar-hw bag: cannot read bag {bag}: ") and "Traceback" not in err


@pytest.mark.parametrize("fmt", ["mcap", "ros1"])
def test_a_recovery_stopped_midway_leaves_nothing_and_the_next_one_runs(tmp_path, capsys, monkeypatch, fmt):
    """Ctrl-C while the recovered bag is written (KeyboardInterrupt from its third message): no
    half-written bag at the output, which a later recover would refuse to overwrite and bag info
    would call another interrupted recording; the bag itself is as it was; recovering again works."""
    from racecar_hw.bags import recover

    bag = write_bag(tmp_path, fmt, close=False)
    target = bag.with_name(f"{bag.stem}.recovered.bag" if fmt == "ros1" else f"{bag.name}.recovered")
    writer = recover.Ros1Writer if fmt == "ros1" else recover.Ros2Bag
    write = writer.write
    calls = []

    def interrupted(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return write(self, *args, **kwargs)

    monkeypatch.setattr(writer, "write", interrupted)
    with pytest.raises(KeyboardInterrupt):
        recover.recover_bag(bag)
    assert not target.exists() and sorted(p.name for p in bag.parent.iterdir()) == [bag.name]
    monkeypatch.setattr(writer, "write", write)
    assert main(["bag", "recover", str(bag)]) == 0
    assert f"recovered 5 messages into {target}" in capsys.readouterr().out
    assert [c.drive.speed for c in load_commands(target, CMD)] == [0.0, 1.0, 2.0, 3.0, 4.0]


def hot_database(folder: Path) -> Path:
    """A sqlite3 bag file (five messages) with a hot journal: a transaction cut off midway, as a
    killed process leaves it (the files are copied while the transaction is open)."""
    bag = write_bag(folder, "sqlite3", close=True)
    db, victim = bag / "run_0.db3", folder / "victim.db3"
    con = sqlite3.connect(db, isolation_level=None)
    con.execute("PRAGMA cache_size=1")
    con.execute("BEGIN")
    con.execute("DELETE FROM messages")
    con.execute("CREATE TABLE filler(x)")
    for _ in range(100):  # more than the cache holds: pages go to the file, the old ones to the journal
        con.execute("INSERT INTO filler VALUES (zeroblob(4000))")
    shutil.copy(db, victim)
    shutil.copy(db.with_name("run_0.db3-journal"), folder / "victim.db3-journal")
    con.execute("ROLLBACK")
    con.close()
    return victim


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def test_recover_takes_only_files_in_the_bag_whatever_metadata_yaml_names(tmp_path, capsys):
    """metadata.yaml listing ../victim/victim.db3 made recover open that database read-write (rolling
    back its journal: a file outside the bag changed) and write a metadata.yaml naming it."""
    victim = hot_database(tmp_path / "victim")
    outside = snapshot(victim.parent)
    bag = write_bag(tmp_path, "sqlite3", close=False)
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    listed = f"  - run_0.db3\n  - ../victim/victim.db3\n  - {victim}\n"
    meta.write_text(text.replace("  - run_0.db3\n", listed))
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "complete:  no: " in out and "messages:  5 (readable ones)" in out
    assert main(["bag", "recover", str(bag)]) == 0
    assert f"recovered 5 messages into {bag}" in capsys.readouterr().out
    assert snapshot(victim.parent) == outside
    info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == ["run_0.db3"]
    assert main(["bag", "info", str(bag)]) == 0
    assert "complete:  yes" in capsys.readouterr().out
    # a bag with nothing of its own: refused in one line, metadata.yaml left as it was
    (bag / "run_0.db3").unlink()
    meta.write_text(text.replace("  - run_0.db3\n", "  - ../victim/victim.db3\n"))
    assert main(["bag", "recover", str(bag)]) == 1
    assert capsys.readouterr().err == f"racecar-hw bag: {bag} holds no .mcap or .db3 file: not a ROS 2 bag\n"
    assert snapshot(victim.parent) == outside
    assert meta.read_text() == text.replace("  - run_0.db3\n", "  - ../victim/victim.db3\n")


def test_recover_in_place_refuses_a_linked_database(tmp_path, capsys):
    """SQLite rolls back the journal where a linked database really is: outside the bag."""
    victim = hot_database(tmp_path / "victim")
    outside = snapshot(victim.parent)
    bag = write_bag(tmp_path, "sqlite3", close=False)
    (bag / "run_1.db3").symlink_to(victim)
    assert main(["bag", "recover", str(bag)]) == 1
    err = capsys.readouterr().err
    assert err == (f"racecar-hw bag: {bag / 'run_1.db3'} is a symbolic link: not recovered in place, which "
                   "could change the file it points to outside the bag; give an output (-o OUT) to "
                   "recover a copy\n")
    assert snapshot(victim.parent) == outside
    assert main(["bag", "recover", str(bag), "-o", str(tmp_path / "copy")]) == 0
    assert "recovered 5 messages into" in capsys.readouterr().out
    assert snapshot(victim.parent) == outside
    assert not (tmp_path / "copy" / "run_1.db3").is_symlink()


LAUGHS = "".join(f"{a}: &{a} [{', '.join([f'*{b}'] * 10) if b else ', '.join(['lol'] * 10)}]\n"
                 for a, b in zip("abcdef", ["", *"abcde"], strict=True))


@pytest.mark.parametrize("fmt", ["sqlite3", "mcap"])
def test_metadata_with_yaml_aliases_is_refused_cheaply(tmp_path, capsys, fmt):
    """A 'billion laughs' (aliases nested 8 deep in 600 bytes; 6 here) in relative_file_paths: bag
    info turned it into a string, 833 MB and 28 s, then failed with a TypeError. rosbag2 never
    writes aliases: the metadata is not used, and the bag reads as one whose metadata.yaml is bad."""
    bag = write_bag(tmp_path, fmt, close=True)
    (bag / "metadata.yaml").write_text(LAUGHS + "rosbag2_bagfile_information:\n  version: 8\n"
                                       f"  storage_identifier: {fmt}\n  relative_file_paths: [*f]\n")
    tracemalloc.start()
    try:
        assert main(["bag", "info", str(bag)]) == 0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    out = capsys.readouterr().out
    assert "complete:  no: metadata.yaml is not usable: line 2, column 8: an alias (*a), which bag " \
           "metadata never has\n" in out
    assert "messages:  5 (readable ones)" in out
    assert peak < 8 * 2**20, peak


def test_a_recovered_sqlite3_bag_is_complete_though_sqlite_leaves_its_journal_zeroed(tmp_path, capsys):
    """A recording killed in a transaction leaves a hot journal. Recovery rolls it back; SQLite may
    keep the file with its header zeroed (no longer hot, as SQLite itself judges a journal), and
    ``bag info`` then went on calling the bag interrupted, and ``bag recover`` looped."""
    victim = hot_database(tmp_path / "hot")
    bag = write_bag(tmp_path, "sqlite3", close=False)
    shutil.copy(victim, bag / "run_0.db3")
    shutil.copy(victim.with_name("victim.db3-journal"), bag / "run_0.db3-journal")
    assert main(["bag", "info", str(bag)]) == 0
    assert "has a journal left by an interrupted write" in capsys.readouterr().out
    assert main(["bag", "recover", str(bag)]) == 0
    assert f"recovered 5 messages into {bag}" in capsys.readouterr().out
    journal = bag / "run_0.db3-journal"
    # what SQLite left (a cold journal, or none), never a journal SQLite would roll back again
    assert not journal.exists() or journal.read_bytes()[:1] in (b"", b"\0")
    zeroed = bytes(28) + b"x" * 1000  # as PERSIST or a rollback that could not delete leaves it
    journal.write_bytes(zeroed)
    assert main(["bag", "info", str(bag)]) == 0
    assert "complete:  yes" in capsys.readouterr().out
    assert main(["bag", "recover", str(bag)]) == 0
    assert "nothing to recover" in capsys.readouterr().out.lower()


def write_big_unfinished_bag(tmp_path: Path, fmt: str, compression: str, monkeypatch) -> Path:
    """Eight drive commands whose frame id is 1 MiB of "x" (8 MiB of messages, a few kB compressed), in
    ``compression`` chunks, left as a killed recorder leaves them (flushed, not closed). The recorder's
    own writers, except ROS 1 lz4 (written by rosbags: ours refuses it), whose index is then cut off."""

    messages = [(AckermannDriveStamped(Header(Time(1, 0), "x" * 2**20), AckermannDrive(speed=float(i))),
                 T0 + i * 100_000_000) for i in range(8)]
    if fmt == "ros1" and compression == "lz4":
        from rosbags.rosbag1 import Writer

        path = tmp_path / "big.bag"
        types = types_for(1)
        writer = Writer(path)
        writer.set_compression(Writer.CompressionFormat.LZ4)
        with writer:
            conn = writer.add_connection(CMD, "ackermann_msgs/msg/AckermannDriveStamped",
                                         typestore=types.store)
            for msg, t_ns in messages:
                writer.write(conn, t_ns, types.serialize(msg, 1))
        data = bytearray(path.read_bytes())
        at = data.index(b"index_pos=") + len(b"index_pos=")
        data[at:at + 8] = bytes(8)  # not indexed, as a killed recording
        path.write_bytes(data)
        return path
    path = tmp_path / ("big.bag" if fmt == "ros1" else "big/big_0")
    bag = BagFile(path, fmt, compression, types_for(1 if fmt == "ros1" else 2))  # (MCAP lz4 too: its chunks)
    for msg, t_ns in messages:
        bag.write(CMD, msg, t_ns)
    bag.flush()
    return path if fmt == "ros1" else path.parent


@pytest.mark.parametrize(("fmt", "compression", "kept"), [
    ("ros1", "bz2", "bz2"), ("ros1", "lz4", "none"), ("mcap", "zstd", "zstd"), ("mcap", "lz4", "lz4")])
def test_recover_keeps_the_chunk_compression_of_the_bag(tmp_path, capsys, monkeypatch, fmt, compression,
                                                        kept):
    """A recovered bag is written with its source's chunk compression where our writers have it (ROS 1
    bz2, MCAP zstd and lz4), so a small bag of compressible messages stays small: the 11 KB bz2 bag of
    sixteen 60 MB messages was recovered into 960 MB. ROS 1 lz4 (which the ROS 1 writer refuses, see
    docs/bags.md) is written uncompressed."""
    from racecar_hw.bags.recover import scan_mcap, scan_ros1

    bag = write_big_unfinished_bag(tmp_path, fmt, compression, monkeypatch)
    source = sum(f.stat().st_size for f in ([bag] if bag.is_file() else bag.iterdir()))
    assert source < 2**20
    out = tmp_path / ("out.bag" if fmt == "ros1" else "out")
    assert main(["bag", "recover", str(bag), "-o", str(out)]) == 0
    assert f"recovered 8 messages into {out}" in capsys.readouterr().out
    storage = out if fmt == "ros1" else out / "out.mcap"
    assert (storage.stat().st_size < 2**20) is (kept != "none"), storage.stat().st_size
    scan = scan_ros1 if fmt == "ros1" else scan_mcap

    def messages(path: Path) -> tuple[set[str], list[tuple[int, bytes]]]:
        """The chunk compressions of the file ``path`` and its messages (time in ns, bytes)."""
        found: list[tuple[int, bytes]] = []
        scanned = scan(path.read_bytes(), lambda _cid, t_ns, raw: found.append((t_ns, bytes(raw))))
        return scanned.compressions, found

    kept_compressions, recovered = messages(storage)
    assert kept_compressions == {kept}
    assert recovered == messages(bag if fmt == "ros1" else next(bag.glob("*.mcap")))[1]
    assert len(recovered) == 8
