"""Write the recorded gamepad event streams in this folder (``teleop_<profile>.events``).

Each file is raw ``struct input_event`` records in the 64-bit little-endian layout (24 bytes:
sec, usec, type, code, value), as ``/dev/input/eventN`` delivers them on x86_64 and aarch64.
The session, identical for every profile in its own codes and ranges:

1. START (arm), speed stick centred;
2. LB held, speed stick fully up, steering stick fully left -> forward, left;
3. speed stick half down, steering stick fully right -> reverse at half speed, right;
4. RB pressed (autonomy) then released;
5. LB released (deadman off);
6. BACK (disarm).

Run ``python tests/data/make_events.py`` to regenerate; ``tests/test_teleop_gamepad.py`` checks the
committed files match this script.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
LAYOUT = "<qqHHi"
EV_SYN, EV_KEY, EV_ABS, EV_MSC = 0, 1, 3, 4
SYN_REPORT = 0

# (deadman, autonomy, arm, disarm, speed axis, steering axis, axis min, axis max)
PROFILES = {
    "f710_x": (0x136, 0x137, 0x13B, 0x13A, 0x01, 0x03, -32768, 32767),
    "f710_d": (0x124, 0x125, 0x129, 0x128, 0x01, 0x02, 0, 255),
    "ps4": (0x136, 0x137, 0x13B, 0x13A, 0x01, 0x03, 0, 255),
}


def session(profile: str) -> bytes:
    """The recorded session of ``profile`` as bytes."""
    deadman, autonomy, arm, disarm, speed, steer, lo, hi = PROFILES[profile]
    centre = (lo + hi) // 2
    t = [1_700_000_000, 0]
    out = bytearray()

    def event(kind: int, code: int, value: int) -> None:
        out.extend(struct.pack(LAYOUT, t[0], t[1], kind, code, value))

    def report(*events: tuple[int, int, int]) -> None:
        for e in events:
            event(*e)
        event(EV_SYN, SYN_REPORT, 0)
        t[1] += 10_000  # 10 ms between reports
        if t[1] >= 1_000_000:
            t[0] += 1
            t[1] -= 1_000_000

    report((EV_ABS, speed, centre), (EV_ABS, steer, centre))
    report((EV_MSC, 4, 0x90007), (EV_KEY, arm, 1))  # hid drivers send MSC_SCAN before keys
    report((EV_KEY, arm, 0))
    report((EV_KEY, deadman, 1))
    report((EV_ABS, speed, lo), (EV_ABS, steer, lo))  # up and left: raw minimum on both
    report((EV_ABS, speed, hi - (hi - lo) // 4), (EV_ABS, steer, hi))  # half down, right
    report((EV_KEY, autonomy, 1))
    report((EV_KEY, autonomy, 0))
    report((EV_ABS, speed, centre), (EV_ABS, steer, centre))
    report((EV_KEY, deadman, 0))
    report((EV_KEY, disarm, 1))
    report((EV_KEY, disarm, 0))
    return bytes(out)


def main() -> int:
    for name in PROFILES:
        (HERE / f"teleop_{name}.events").write_bytes(session(name))
    return 0


if __name__ == "__main__":
    sys.exit(main())
