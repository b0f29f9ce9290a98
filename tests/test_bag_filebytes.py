"""A storage file read where the scanners need it (racecar_hw/bags/filebytes.py): the same bytes as
the file holds, in any window size, and a file cut back while it is read refused in one line."""

from __future__ import annotations

import os
import random

import pytest

from racecar_hw.bags import filebytes
from racecar_hw.bags.filebytes import MemoryBytes, occurrences, open_file_bytes, pieces
from racecar_hw.base.errors import BagError


@pytest.mark.parametrize("window", [1, 7, 64, 1 << 20])
def test_reads_give_the_file_s_bytes_whatever_the_window(tmp_path, monkeypatch, window):
    monkeypatch.setattr(filebytes, "READ_AHEAD", window)
    rnd = random.Random(window)
    data = rnd.randbytes(5000)
    path = tmp_path / "f.bin"
    path.write_bytes(data)
    with open_file_bytes(path) as f:
        assert f.size == len(data)
        for _ in range(300):
            pos, n = rnd.randrange(0, 5100), rnd.randrange(0, 300)
            assert bytes(f.read(pos, n)) == data[pos:pos + n], (pos, n)
        assert b"".join(pieces(f, 13, 4000)) == data[13:4013]
        assert b"".join(pieces(f, 4990, 100)) == data[4990:]


@pytest.mark.parametrize("window", [3, 4, 5, 16, 1 << 20])
def test_occurrences_are_every_match_once_across_the_pieces(monkeypatch, window):
    """Every position of the pattern, in order, also where it straddles two pieces, and overlapping
    matches; none found twice."""
    monkeypatch.setattr(filebytes, "READ_AHEAD", window)
    rnd = random.Random(window)
    data = bytes(rnd.choice(b"ab") for _ in range(400)) + b"aaaa"
    for pattern in (b"ab", b"aba", b"aaaa"):
        naive = [i for i in range(len(data)) if data.startswith(pattern, i)]
        assert list(occurrences(MemoryBytes(data), pattern, 0, len(data))) == naive, pattern
        assert list(occurrences(MemoryBytes(data), pattern, 50, 300)) == [
            i for i in naive if i >= 50 and i + len(pattern) <= 300]


def test_a_file_cut_back_while_it_is_read_is_refused_in_one_line(tmp_path):
    """The size is the file's when opened; a file that ends sooner (cut back while a scan reads it)
    is refused naming it, where a memory map of it would have killed the process (SIGBUS)."""
    path = tmp_path / "cut.bag"
    path.write_bytes(bytes(3 << 20))
    with open_file_bytes(path) as f:
        assert len(f.read(0, 10)) == 10
        with path.open("r+b") as g:
            g.truncate(1 << 20)
        with pytest.raises(BagError) as err:
            f.read(2 << 20, 10)
    assert str(err.value) == (f"{path} has {1 << 20} bytes as it is read, {3 << 20} when it was opened "
                              "(is something cutting it back?); refused")


def test_a_fifo_is_refused_before_it_is_opened(tmp_path):
    fifo = tmp_path / "x.bag"
    os.mkfifo(fifo)
    with pytest.raises(BagError, match="is a FIFO, not a regular file"), open_file_bytes(fifo):
        pass


def test_a_scan_of_a_bag_cut_back_as_it_is_read_is_refused(tmp_path):
    """A ROS 1 bag cut back while :func:`scan_ros1` reads it (here by the scan's own callback, so
    deterministically) is refused naming it; it is not taken for a bag that ends there."""
    from racecar_hw.bags.recover import scan_ros1
    from racecar_hw.bags.ros1_writer import Ros1Writer

    path = tmp_path / "b.bag"
    with Ros1Writer(path, chunk_threshold=100) as w:
        c = w.add_connection("/blob", "std_msgs/String", "992ce8a1687cec8c8bd883ec73ca41d1", "string data\n")
        for i in range(40):
            w.write(c, 10**9 * (i + 1), bytes(4) + bytes(50_000))

    def cut(_cid: int, _t_ns: int, _payload: memoryview) -> None:
        with path.open("r+b") as g:
            g.truncate(path.stat().st_size // 2)

    with open_file_bytes(path) as data, pytest.raises(BagError, match=f"^{path} has .* as it is read"):
        scan_ros1(data, cut)
