"""The real ROS 1 bag tools (Debian python3-rosbag) as a test peer, run by /usr/bin/python3.

They are never imported into the venv: each helper runs a small script in a subprocess that talks
JSON on stdin/stdout.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

from racecar_hw.base.messages import AckermannDrive

SYSTEM_PYTHON = "/usr/bin/python3"

_WRITE = r'''
import json, sys
import genpy.dynamic, rosbag, rospy
req = json.load(sys.stdin)
SEP = "=" * 80 + "\n"
full = ("Header header\nAckermannDrive drive\n\n"
        + SEP + "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n\n"
        + SEP + "MSG: ackermann_msgs/AckermannDrive\n" + req["drive_def"])
ADS = genpy.dynamic.generate_dynamic("ackermann_msgs/AckermannDriveStamped", full)[
    "ackermann_msgs/AckermannDriveStamped"]
bag = rosbag.Bag(req["path"], "w", compression=req["compression"])
try:
    for i, (t_ns, speed, steer) in enumerate(req["commands"]):
        m = ADS()
        m.header.seq = i
        m.header.stamp = rospy.Time(t_ns // 10**9, t_ns % 10**9)
        m.header.frame_id = "base_link"
        m.drive.speed = speed
        m.drive.steering_angle = steer
        bag.write(req["topic"], m, t=m.header.stamp)
finally:
    bag.close()
print(json.dumps({"md5": ADS._md5sum}))
'''

_READ = r'''
import json, sys
import genpy, rosbag

def plain(v):
    if isinstance(v, genpy.TVal):
        return v.to_nsec()
    if hasattr(v, "__slots__") and hasattr(v, "_slot_types"):
        return {s: plain(getattr(v, s)) for s in v.__slots__}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, bytes):
        return list(v)
    return v

out = []
with rosbag.Bag(sys.argv[1]) as bag:
    for topic, msg, t in bag.read_messages():
        out.append({"topic": topic, "type": msg._type, "md5": msg._md5sum, "t": t.to_nsec(),
                    "msg": plain(msg)})
print(json.dumps(out))
'''


def require_rosbag() -> None:
    """Skip (with the reason) where the system Python cannot import the real rosbag."""
    try:
        done = subprocess.run([SYSTEM_PYTHON, "-c", "import rosbag, genpy.dynamic"],
                              capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as err:
        pytest.skip(f"{SYSTEM_PYTHON} is not usable ({err}); install python3-rosbag")
    if done.returncode != 0:
        pytest.skip(f"{SYSTEM_PYTHON} cannot import rosbag: apt-get install python3-rosbag "
                    "python3-genpy python3-genmsg python3-std-msgs")


def write_real_bag(path: Path, topic: str, commands: list[tuple[int, float, float]],
                   compression: str = "none") -> str:
    """Write AckermannDriveStamped (t_ns, speed, steering) with the real rosbag; returns the md5."""
    require_rosbag()
    req = {"path": str(path), "topic": topic, "compression": compression,
           "drive_def": AckermannDrive.MSGDEF, "commands": commands}
    done = subprocess.run([SYSTEM_PYTHON, "-c", _WRITE], input=json.dumps(req), text=True,
                          capture_output=True, timeout=120, check=True)
    return json.loads(done.stdout)["md5"]


def read_real_bag(path: Path) -> list[dict[str, Any]]:
    """Every message of a ROS 1 bag as the real rosbag reads it (plain JSON values)."""
    require_rosbag()
    done = subprocess.run([SYSTEM_PYTHON, "-c", _READ, str(path)], text=True,
                          capture_output=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def rosbag_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """Run the real ``rosbag`` command (``rosbag reindex``, ``info``, ``fix``) and return its result."""
    require_rosbag()
    return subprocess.run([SYSTEM_PYTHON, "/usr/bin/rosbag", *map(str, args)], text=True,
                          capture_output=True, timeout=120)


def append_with_real_rosbag(path: Path) -> None:
    """Open the bag in the real rosbag's append mode and close it, writing nothing."""
    require_rosbag()
    done = subprocess.run([SYSTEM_PYTHON, "-c", "import rosbag, sys; rosbag.Bag(sys.argv[1], 'a').close()",
                           str(path)], text=True, capture_output=True, timeout=120)
    assert done.returncode == 0, done.stderr
