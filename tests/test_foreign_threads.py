"""racecar_hw.runtime.foreign_threads: a Zenoh receiving thread keeps its Python thread state
between callbacks once it called hold_thread_state(), and builds a new one per callback otherwise."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

from conftest import wait_for
from zenoh_util import endpoint, free_port

from racecar_hw.runtime.foreign_threads import hold_thread_state


def _callback_states(hold: bool) -> list[int]:
    """Per sample received over TCP (Zenoh's receiving thread, a direct callback): how many samples
    that thread's Python state had seen before."""
    import zenoh  # noqa: PLC0415 - in the fresh process the test starts
    port = free_port()
    scouting = {"multicast": {"enabled": False}}
    listen = zenoh.open(zenoh.Config.from_json5(json.dumps(
        {"mode": "peer", "listen": {"endpoints": [endpoint(port)]}, "scouting": scouting})))
    connect = zenoh.open(zenoh.Config.from_json5(json.dumps(
        {"mode": "peer", "connect": {"endpoints": [endpoint(port)]}, "scouting": scouting})))
    local = threading.local()
    seen: list[int] = []

    def on_sample(sample: object) -> None:
        if hold:
            hold_thread_state()
        seen.append(getattr(local, "count", 0))
        local.count = getattr(local, "count", 0) + 1

    try:
        listen.declare_subscriber("states/x", zenoh.handlers.Callback(on_sample, indirect=False))
        publisher = connect.declare_publisher("states/x")
        wait_for(lambda: publisher.matching_status.matching, timeout=30)
        for n in range(50):
            publisher.put(b"%d" % n)
            wait_for(lambda n=n: len(seen) > n, timeout=30)  # one at a time: each its own callback
    finally:
        connect.close()
        listen.close()
    return seen


def test_a_held_thread_state_outlives_the_callback_and_an_unheld_one_does_not():
    """In a fresh process (Zenoh's receiving threads are the process's, so a hold taken by any
    earlier test would stay): first without the hold, every callback gets a new thread state (what
    the hold saves is real), then with it the state carries over."""
    script = ("import json, sys; sys.path[:0] = sys.argv[1:]; import test_foreign_threads as t; "
              "print(json.dumps([t._callback_states(hold=False), t._callback_states(hold=True)]))")
    run = subprocess.run([sys.executable, "-c", script, str(Path(__file__).parent)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    unheld, held = json.loads(run.stdout.strip().splitlines()[-1])
    assert unheld == [0] * 50
    # a new state only at each receiving thread's first callback (Zenoh's receiving runtime has two
    # threads; they share the samples, 25 each when they alternate: counts 0 to 24)
    assert len(held) == 50 and 1 <= held.count(0) <= 4
