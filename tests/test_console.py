"""Console output through a queue: a stream that stops taking bytes never blocks the writer."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

from conftest import wait_for

from racecar_hw.runtime.console import QueuedStream


def full_pipe() -> tuple[int, int]:
    """A pipe (read end, write end) whose buffer is already full: the next write blocks."""
    r, w = os.pipe()
    os.set_blocking(w, False)
    try:
        while True:
            os.write(w, b"x" * 65536)
    except BlockingIOError:
        pass
    os.set_blocking(w, True)
    return r, w


def test_writes_return_at_once_on_a_blocked_stream_and_arrive_in_order_with_a_note_of_drops():
    r, w = full_pipe()
    out = open(w, "w", encoding="utf-8")  # noqa: SIM115 - closed by the test
    stream = QueuedStream(out, max_pending=10)
    for i in range(50):  # the pipe takes nothing now; none of these may block
        assert stream.write(f"line {i}\n") == len(f"line {i}\n")
    assert 39 <= stream.dropped <= 40  # 10 queued, and maybe one already taken by the writer
    os.set_blocking(r, False)
    got = bytearray()

    def read_some() -> None:
        try:
            got.extend(os.read(r, 1 << 20))
        except BlockingIOError:
            pass

    wait_for(lambda: read_some() or stream.drain(0.0))  # the pipe moves: the queue empties
    stream.write("after\n")
    wait_for(lambda: read_some() or got.endswith(b"after\n"))
    lines = got.lstrip(b"x").decode().splitlines()
    kept = [int(line.split()[1]) for line in lines if line.startswith("line ")]
    assert kept[:10] == list(range(10)) and len(kept) == 50 - stream.dropped
    # in order, and each run of drops noted with its size where it was: before the next kept line
    # (the writer may free a slot while the writes still come, keeping a later one), or before
    # "after"
    expected, previous = [], -1
    for n in [*kept, 50]:
        if n - previous > 1:
            expected.append(f"[{n - previous - 1} console writes dropped while the stream was blocked]")
        if n < 50:
            expected.append(f"line {n}")
        previous = n
    assert lines == [*expected, "after"]
    stream.close()
    out.close()
    os.close(r)


def test_close_gives_up_on_a_stream_blocked_for_good():
    r, w = full_pipe()
    out = open(w, "w", encoding="utf-8")  # noqa: SIM115 - never closed: its writer stays blocked
    stream = QueuedStream(out)
    stream.write("stuck\n")
    stream.close(timeout_s=0.2)  # returns although the stream never takes the text
    assert stream.write("after close\n") == len("after close\n")  # ignored, never blocks
    os.close(r)  # the blocked writer now fails with EPIPE and ends


def test_a_daemon_whose_stderr_nobody_reads_still_runs_and_exits(tmp_path):
    # with a plain logging handler this child blocks for good once the pipe is full
    script = textwrap.dedent("""
        import logging
        from racecar_hw.runtime.console import setup_logging
        setup_logging(logging.INFO)
        log = logging.getLogger("racecar_hw.test")
        for i in range(5000):
            log.info("status line %d %s", i, "x" * 100)
        print("done", flush=True)
    """)
    out = tmp_path / "stdout.txt"
    with out.open("w") as stdout:
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=stdout,
                                stderr=subprocess.PIPE)
        try:
            rc = proc.wait(60)  # stderr is not read until the child has exited
        finally:
            proc.kill()
            proc.stderr.close()  # type: ignore[union-attr]
    assert rc == 0
    assert out.read_text() == "done\n"
