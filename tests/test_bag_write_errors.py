"""A bag that cannot be written is said as such, naming the file written: a bag file deleted or moved
while it is recorded, a recovery's output on a full disk. The physical world faked here is only the
disk: a folder removed (``rm -rf``) or renamed, and a full disk as a file-size limit."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from racecar_hw.bags.record import BagFile, Recorder, Ros2BagMetadata, record_params
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import BagWriteError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time
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
