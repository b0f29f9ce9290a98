"""MCAP chunks carry their CRC-32: written by the recorder, read back by the independent ``mcap``
library, and checked by the follower (a real ``racecar-hw follow`` process), ``bag info`` and
``bag recover`` (which keeps the good chunks)."""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from racecar_hw.bags.follow import load_commands
from racecar_hw.bags.record import BagFile
from racecar_hw.bags.recover import inspect_bag
from racecar_hw.bags.validate import check_storage, mcap_chunk_crc_error
from racecar_hw.base.errors import BagError
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, LaserScan, Time
from racecar_hw.cli import main
from racecar_hw.rosmsg.typestore import types_for

CMD = "/vesc/low_level/ackermann_cmd_mux/input/teleop"
T0 = 1_700_000_000 * 10**9
COMMANDS_PER_CHUNK = 10
CHUNKS = 3


def write_recording(tmp_path: Path) -> Path:
    """A closed MCAP recording of 30 drive commands in three chunks (a flush closes each), plus a
    scan in each so a chunk has more than one channel's records."""
    path = tmp_path / "run" / "run_0"
    bag = BagFile(path, "mcap", "none", types_for(2))
    for i in range(COMMANDS_PER_CHUNK * CHUNKS):
        msg = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=0.1 * i))
        bag.write(CMD, msg, T0 + i * 50_000_000)
        if i % COMMANDS_PER_CHUNK == 0:
            bag.write("/scan", LaserScan(Header(Time(1, 0), "laser"), ranges=[1.0] * 360),
                      T0 + i * 50_000_000)
        if i % COMMANDS_PER_CHUNK == COMMANDS_PER_CHUNK - 1:
            bag.flush()
    bag.close()
    return path.parent


def chunk_offsets(mcap: Path) -> list[int]:
    """Byte offsets of the chunk records, walking the records from the magic."""
    data = mcap.read_bytes()
    pos, out = 8, []
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if op == 0x06:
            out.append(pos)
        if op == 0x02:
            break
        pos += 9 + length
    return out


def flip_a_bit_in_chunk(bag: Path, number: int) -> int:
    """Flip one bit in the records of chunk ``number`` (1 = the first) of the bag's MCAP file, in
    the last message's data; its byte offset."""
    mcap = next(bag.glob("*.mcap"))
    at = chunk_offsets(mcap)[number - 1]
    data = bytearray(mcap.read_bytes())
    (length,) = struct.unpack_from("<Q", data, at + 1)
    target = at + 9 + length - 3  # inside the chunk's last record, an uncompressed chunk
    data[target] ^= 0x10
    mcap.write_bytes(bytes(data))
    return at


def test_a_recording_has_non_zero_chunk_crcs_the_mcap_library_verifies(tmp_path):
    bag = write_recording(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    with mcap.open("rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == CHUNKS
    for chunk in chunks:
        assert chunk.uncompressed_crc != 0
        assert chunk.uncompressed_crc == zlib.crc32(chunk.data)  # uncompressed: data is the records
    with mcap.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        got = [m.log_time for _s, c, m in reader.iter_messages() if c.topic == CMD]
    assert got == [T0 + i * 50_000_000 for i in range(COMMANDS_PER_CHUNK * CHUNKS)]
    assert inspect_bag(bag).complete


def test_the_mcap_library_refuses_a_flipped_bit_so_the_crc_is_the_real_one(tmp_path):
    bag = write_recording(tmp_path)
    flip_a_bit_in_chunk(bag, 2)
    mcap = next(bag.glob("*.mcap"))
    with mcap.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        with pytest.raises(CRCValidationError):
            list(reader.iter_messages())


def test_follow_as_a_process_refuses_a_flipped_bit_naming_the_chunk(tmp_path):
    bag = write_recording(tmp_path)
    at = flip_a_bit_in_chunk(bag, 2)
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "follow", str(bag), "--set",
                           "gamepad.enabled=false"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.startswith("racecar-hw follow: ")
    assert f"chunk 2 (at byte {at}) fails its checksum" in proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_bag_info_reports_the_chunk_and_recover_keeps_the_good_chunks(tmp_path, capsys):
    bag = write_recording(tmp_path)
    at = flip_a_bit_in_chunk(bag, 2)
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "complete:  no: " in out and f"chunk 2 (at byte {at}) fails its checksum" in out
    assert f"messages:  {2 * COMMANDS_PER_CHUNK + 2} (readable ones)" in out  # chunks 1 and 3
    assert main(["bag", "recover", str(bag)]) == 0
    out = capsys.readouterr().out
    recovered = bag.with_name(f"{bag.name}.recovered")
    assert f"recovered {2 * COMMANDS_PER_CHUNK + 2} messages into {recovered}" in out
    assert f"left out (damaged): run_0.mcap: chunk 2 (at byte {at}) fails its checksum" in out
    speeds = [round(c.drive.speed, 6) for c in load_commands(recovered, CMD)]
    kept = [*range(COMMANDS_PER_CHUNK), *range(2 * COMMANDS_PER_CHUNK, 3 * COMMANDS_PER_CHUNK)]
    assert speeds == [round(0.1 * i, 6) for i in kept]
    assert inspect_bag(recovered).complete  # the recovered bag carries checksums too
    with next(recovered.glob("*.mcap")).open("rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert chunks and all(c.uncompressed_crc == zlib.crc32(c.data) != 0 for c in chunks)


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE])
def test_chunks_the_mcap_library_wrote_pass_and_a_wrong_crc_is_found_through_decompression(
        tmp_path, compression):
    """An independent writer's chunks (compressed or not, each with its CRC) pass the follower's
    check; the same file with one chunk's recorded CRC changed is refused naming that chunk."""
    path = tmp_path / "other.mcap"
    with path.open("wb") as f:
        writer = McapWriter(f, chunk_size=2000, compression=compression)
        writer.start("ros2", "test")
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        channel = writer.register_channel("/chatter", "cdr", schema)
        for i in range(60):
            writer.add_message(channel, T0 + i, bytes(range(256)) * 4, T0 + i)
        writer.finish()
    offsets = chunk_offsets(path)
    assert len(offsets) >= 3
    check_storage(path)
    assert mcap_chunk_crc_error(path) is None
    data = bytearray(path.read_bytes())
    data[offsets[1] + 9 + 24] ^= 0x01  # chunk 2's recorded CRC
    path.write_bytes(bytes(data))
    with pytest.raises(BagError, match=rf"chunk 2 \(at byte {offsets[1]}\) fails its checksum"):
        check_storage(path)
    assert f"chunk 2 (at byte {offsets[1]}) fails its checksum" in (mcap_chunk_crc_error(path) or "")
