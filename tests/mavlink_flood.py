"""A MAVLink flood for the tests and the benchmark: forged datagrams to a UDP port, as fast as one
process can send them, for a bounded time.

``python tests/mavlink_flood.py PORT SECONDS [--host 127.0.0.1]``

The datagrams are real pymavlink-built MAVLink 2 frames in the ground station's name (system 255,
component 190): HEARTBEAT, MANUAL_CONTROL at full throttle and ARM, signed with a random key (so
the signature fails) and stamped ten years ahead, and the same messages unsigned. They are built
first; the process then prints ``ready`` and sends them round-robin from one socket in a tight
loop (the clock read every 256 datagrams) until SECONDS have passed, and prints one JSON line
``{"sent": N, "seconds": S, "source": "host:port"}``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import socket
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

#: Ten years ahead of 2015-01-01 in signing units (10 µs): far beyond any clock.
FAR_FUTURE = 2_000_000_000_000_00


class _Out:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def forged_frames() -> list[bytes]:
    """Forged (random key, far-future) and unsigned frames in the ground station's name."""
    out = _Out()
    for signed in (True, False):
        mav = mavlink.MAVLink(out, 255, 190)
        if signed:
            mav.signing.secret_key = os.urandom(32)
            mav.signing.timestamp = FAR_FUTURE
            mav.signing.sign_outgoing = True
        for _ in range(4):
            mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            mav.manual_control_send(1, 0, 0, 1000, 0, 0)
            mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    return out.frames


def flood(host: str, port: int, seconds: float) -> dict[str, object]:
    """Send forged datagrams to ``host:port`` for ``seconds``; what was sent."""
    frames = forged_frames()
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    source_host, source_port = sock.getsockname()[:2]
    print("ready", flush=True)
    addr = (host, port)
    sendto = sock.sendto
    cycle = itertools.cycle(frames)
    sent = 0
    start = time.monotonic()
    end = start + seconds
    while time.monotonic() < end:
        for frame in itertools.islice(cycle, 256):
            try:
                sendto(frame, addr)
            except OSError:  # e.g. ECONNREFUSED from an ICMP error once the port is gone
                continue
            sent += 1
    elapsed = time.monotonic() - start
    sock.close()
    return {"sent": sent, "seconds": elapsed, "source": f"{source_host}:{source_port}"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port", type=int)
    parser.add_argument("seconds", type=float)
    parser.add_argument("--host", default="127.0.0.1")
    args = parser.parse_args(argv)
    print(json.dumps(flood(args.host, args.port, args.seconds)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
