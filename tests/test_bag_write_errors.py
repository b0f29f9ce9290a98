"""A bag that cannot be written is said as such, naming the file written: a bag file deleted or moved
while it is recorded, a recovery's output on a full disk. The physical world faked here is only the
disk: a folder removed (``rm -rf``) or renamed, and a full disk as a file-size limit."""

from __future__ import annotations

import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from racecar_hw.bags.follow import load_commands
from racecar_hw.bags.record import BagFile, Recorder, Ros2BagMetadata, record_params
from racecar_hw.bags.recover import inspect_bag, recover_bag
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import BagError, BagWriteError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time
from racecar_hw.cli import main as cli_main
from racecar_hw.rosmsg.typestore import types_for

FORMATS = ("mcap", "sqlite3", "ros1")
GONE = "the bag file was deleted or moved while recording"


def cmd(i: int) -> AckermannDriveStamped:
    return AckermannDriveStamped(Header(Time(200 + i, 7), "base_link"), AckermannDrive(speed=0.1 * i))


def open_bag(folder: Path, fmt: str) -> tuple[BagFile, Path]:
    """A bag file of ``fmt`` in ``folder`` holding a few flushed messages; and the file's path."""
    if fmt == "ros1":
        folder.mkdir()  # as the recorder makes it
        bag = BagFile(folder / "run_0.bag", fmt, "none", types_for(1))
        file = folder / "run_0.bag"
    else:
        bag = BagFile(folder / "run" / "run_0", fmt, "none", types_for(2))
        file = folder / "run" / f"run_0.{'mcap' if fmt == 'mcap' else 'db3'}"
    for i in range(5):
        bag.write("/cmd", cmd(i), (i + 1) * 1_000_000)
    bag.flush()
    return bag, file


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("how", ["deleted", "moved"])
def test_a_flush_into_a_bag_file_deleted_or_moved_says_so_naming_it(tmp_path, fmt, how):
    """ROS 1 flushed into a deleted file without a word (the recording "succeeded", its file gone);
    MCAP and sqlite3 failed only at metadata.yaml, with a raw FileNotFoundError or "attempt to write
    a readonly database"."""
    bag, file = open_bag(tmp_path / "bags", fmt)
    if how == "deleted":
        shutil.rmtree(tmp_path / "bags")
    else:
        (tmp_path / "bags").rename(tmp_path / "elsewhere")
    with pytest.raises(BagWriteError) as err:  # sqlite3 finds out at the write, the others at the flush
        bag.write("/cmd", cmd(9), 9_000_000)
        bag.flush()
    assert str(err.value) == f"{file}: {GONE}"
    bag.abort()


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_recording_whose_folder_is_deleted_stops_with_that_error(tmp_path, fmt):
    """The error is the recorder's write failure (what makes ``run`` and ``sim`` exit 1), found at
    the latest when the bag is closed."""
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path / "bags", fmt, name="run"))
    rec.start()
    for i in range(20):
        bus.publish("/cmd", cmd(i))
    shutil.rmtree(tmp_path / "bags")
    bus.publish("/cmd", cmd(21))
    stats = rec.stop()
    file = (tmp_path / "bags" / "run_0.bag" if fmt == "ros1"
            else tmp_path / "bags" / "run" / f"run_0.{'mcap' if fmt == 'mcap' else 'db3'}")
    assert stats.error == f"BagWriteError: {file}: {GONE}"


def test_metadata_written_into_a_deleted_folder_says_so(tmp_path):
    """Should the folder go between the storage file's check and metadata.yaml's writing."""
    meta = Ros2BagMetadata(tmp_path / "gone", "mcap")
    with pytest.raises(BagWriteError, match=r"gone: the bag folder was deleted or moved while recording$"):
        meta.write(None)


# --- a recovery whose output disk is full -----------------------------------------------------

#: The file-size limit standing in for a full disk: any file written past it fails with EFBIG.
DISK_BYTES = 8192


def unfinished_bag(folder: Path, fmt: str) -> Path:
    """A bag as a killed recorder leaves it (everything flushed, nothing closed), larger than
    :data:`DISK_BYTES`: 400 commands."""
    folder.mkdir()
    path = folder / ("run_0.bag" if fmt == "ros1" else "run/run_0")
    bag = BagFile(path, fmt, "none", types_for(1 if fmt == "ros1" else 2))
    for i in range(400):
        bag.write("/cmd", cmd(i), (i + 1) * 1_000_000)
    bag.flush()
    return path if fmt == "ros1" else path.parent


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def recover_on_a_full_disk(bag: Path, out: Path) -> subprocess.CompletedProcess[str]:
    def full_disk() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), no signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (DISK_BYTES, DISK_BYTES))

    command = [sys.executable, "-m", "racecar_hw.cli", "bag", "recover", str(bag), "-o", str(out)]
    return subprocess.run(command, capture_output=True, text=True, preexec_fn=full_disk, timeout=120,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_recovery_onto_a_full_disk_blames_the_output_and_leaves_nothing(tmp_path, fmt):
    """It said "cannot read bag <input>: damaged data (OSError: [Errno 28] No space left on
    device)" (MCAP, ROS 1), and sqlite3 with -o gave the Python list of copytree's (source,
    destination, error) and left OUT holding empty files, which the retry refused ("exists
    already")."""
    bag = unfinished_bag(tmp_path / "bags", fmt)
    before = snapshot(tmp_path / "bags")
    (tmp_path / "disk").mkdir()
    out = tmp_path / "disk" / ("out.bag" if fmt == "ros1" else "out")
    proc = recover_on_a_full_disk(bag, out)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr == f"racecar-hw bag: cannot write {out}: File too large\n"
    assert list((tmp_path / "disk").iterdir()) == []  # no OUT, no .partial folder beside it
    assert snapshot(tmp_path / "bags") == before
    # the disk has room again: the retry runs
    assert cli_main(["bag", "recover", str(bag), "-o", str(out)]) == 0
    assert inspect_bag(out).complete
    assert sum(1 for _ in load_commands(out, "/cmd")) == 400


def test_an_input_that_cannot_be_read_is_still_the_bags_fault(tmp_path):
    """The output's errors are told apart from the input's: a file of the bag that cannot be read
    (a link to nothing) is the bag's ("cannot read bag"), and the copy begun at OUT is removed."""
    bag = unfinished_bag(tmp_path / "bags", "sqlite3")
    (bag / "run_0.db3-wal").symlink_to(tmp_path / "nothing")
    out = tmp_path / "disk" / "out"
    with pytest.raises(BagError) as err:
        recover_bag(bag, out)
    assert str(err.value).startswith(f"cannot read bag file {bag / 'run_0.db3-wal'}: damaged data "
                                     "(FileNotFoundError: ")
    assert not isinstance(err.value, BagWriteError) and not out.exists()
