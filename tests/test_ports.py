"""Port clashes, one rule for Zenoh, the Foxglove live view and the status page (docs/live-view.md,
"Ports"): ``sim`` takes free ports and prints them; ``run`` refuses in one line naming the key.

The test suite never binds the default ports (7447, 8765, 8080): here three free ports stand in for
them, held by listening sockets as another program would hold the defaults.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest
import yaml
from live_sim import SimProcess

from racecar_hw.config import load_config, move_to_free_ports, taken_listeners
from racecar_hw.net.ports import PortLock


@contextlib.contextmanager
def held_ports(n: int) -> Iterator[list[int]]:
    """``n`` loopback ports, each held by a listening socket until the block ends."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            s.listen()
            socks.append(s)
        yield [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _sets(zenoh: int, foxglove: int, web: int) -> list[str]:
    return [f'zenoh.listen=["tcp/127.0.0.1:{zenoh}"]', f"foxglove.port={foxglove}", f"web.port={web}"]


def test_taken_ports_are_found_and_moved_for_all_three_interfaces():
    with held_ports(3) as (z, f, w):
        # the car config leaves the live view off (its extra): switched on here
        config = load_config(None, [*_sets(z, f, w), "foxglove.enabled=true"])
        assert [t.key for t in taken_listeners(config)] == ["zenoh.listen[0]", "foxglove.port", "web.port"]
        moved = move_to_free_ports(config)
        assert [m.key for m, _ in moved] == ["zenoh.listen[0]", "foxglove.port", "web.port"]
        assert config.foxglove.port not in (f, 0) and config.web.port not in (w, 0)
        assert config.zenoh.listen[0] != f"tcp/127.0.0.1:{z}"
        assert moved[1][1] == f"ws://127.0.0.1:{config.foxglove.port}"
        assert moved[2][1] == f"http://127.0.0.1:{config.web.port}/"
        assert not taken_listeners(config)


@contextlib.contextmanager
def held_udp_port() -> Iterator[int]:
    """A loopback UDP port held by a bound socket until the block ends (a ground station's, or
    another racecar-hw's MAVLink link)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def test_the_mavlink_links_udp_port_follows_the_same_rule():
    """It once was outside the rule: ``run`` failed with a traceback and drove on without the
    ground station; ``sim`` said nothing."""
    with held_udp_port() as held:
        config = load_config(None, ["mavlink.enabled=true", f"mavlink.bind_port={held}",
                                    "zenoh.enabled=false", "web.enabled=false", "foxglove.enabled=false"])
        assert [(t.key, t.kind) for t in taken_listeners(config)] == [("mavlink.bind_port", "udp")]
        ((moved, where),) = move_to_free_ports(config)
        assert moved.key == "mavlink.bind_port" and config.mavlink.bind_port not in (held, 0)
        assert where == f"udp 127.0.0.1:{config.mavlink.bind_port}"
        assert not taken_listeners(config)


@pytest.mark.slow
def test_a_sim_started_while_its_ports_are_held_runs_on_printed_free_ports():
    with held_ports(3) as (z, f, w):
        sim = SimProcess(["--duration", "60", "--set", "zenoh.enabled=true",
                          *[a for s in _sets(z, f, w) for a in ("--set", s)]])
        try:
            zenoh = sim.wait_for(rf"zenoh.listen\[0\] 127.0.0.1:{z} is taken .*; "
                                 r"Zenoh \(ROS 2 topics\) is on tcp/127.0.0.1:(\d+) instead")
            fox = sim.wait_for(rf"foxglove.port 127.0.0.1:{f} is taken .*; the Foxglove live view is on "
                               r"ws://127.0.0.1:(\d+) instead")
            web = sim.wait_for(rf"web.port 127.0.0.1:{w} is taken .*; the status page is on "
                               r"http://127.0.0.1:(\d+)/ instead")
            sim.wait_for("racecar-hw running")
            assert sim.port("foxglove") == int(fox.group(1)) != f
            assert sim.port("web") == int(web.group(1)) != w
            sim.wait_for(rf"zenoh bridge up: .*listen \['tcp/127.0.0.1:{zenoh.group(1)}'\]")
            with socket.create_connection(("127.0.0.1", int(web.group(1))), timeout=10):
                pass  # the page listens where the line said
        finally:
            sim.stop()


@pytest.mark.slow
def test_run_refuses_a_taken_port_in_one_line_naming_the_key(tmp_path):
    for key in ("foxglove", "web"):
        with held_ports(1) as (held,):
            cfg = tmp_path / f"{key}.yaml"
            cfg.write_text(yaml.safe_dump({
                "vesc": {"port": str(tmp_path / "no-vesc")}, "lidar": {"enabled": False},
                "gamepad": {"enabled": False}, "zenoh": {"enabled": False},
                "foxglove": {"port": held, "enabled": key == "foxglove"},
                "web": {"port": held, "enabled": key == "web"}}))
            stderr = _one_line_refusal(cfg)
        assert stderr.startswith(f"racecar-hw run: {key}.port: 127.0.0.1:{held} is already in use"), stderr
    with held_udp_port() as held:
        cfg = tmp_path / "mavlink.yaml"
        cfg.write_text(yaml.safe_dump({
            "vesc": {"port": str(tmp_path / "no-vesc")}, "lidar": {"enabled": False},
            "gamepad": {"enabled": False}, "zenoh": {"enabled": False}, "web": {"enabled": False},
            "foxglove": {"enabled": False}, "mavlink": {"enabled": True, "bind_port": held}}))
        stderr = _one_line_refusal(cfg)
    assert stderr.startswith(f"racecar-hw run: mavlink.bind_port: 127.0.0.1:{held} is already in use"), stderr


def _one_line_refusal(cfg) -> str:
    """``racecar-hw run --config cfg``'s standard error, once it exited 1 in one line, no traceback."""
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "run", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    return proc.stderr


@pytest.mark.slow
def test_two_sims_started_together_on_the_same_free_ports_both_run():
    """Both found the ports free, both bound them, and the second exited (a reviewer's two sims
    started at once, 3 of 3). One takes the ports; the other, held off by the PortLock until the
    first listens, then finds them taken and moves."""
    with held_ports(3) as (z, f, w):
        pass  # three ports nobody holds now
    args = ["--duration", "60", "--set", "zenoh.enabled=true",
            *[a for s in _sets(z, f, w) for a in ("--set", s)]]
    sims = [SimProcess(args), SimProcess(args)]
    try:
        for sim in sims:
            sim.wait_for("racecar-hw running")
        moved = [any(f"zenoh.listen[0] 127.0.0.1:{z} is taken" in line for line in sim.lines) for sim in sims]
        assert sorted(moved) == [False, True], [sim.lines[-20:] for sim in sims]
        assert all(sim.proc.poll() is None for sim in sims)
    finally:
        for sim in sims:
            sim.stop()


def test_the_port_lock_holds_off_a_second_holder_until_the_first_lets_go(tmp_path):
    lock_file = tmp_path / "ports.lock"
    holder = subprocess.Popen([sys.executable, "-c", f"""
import sys, time
from racecar_hw.net.ports import PortLock
lock = PortLock(__import__("pathlib").Path({str(lock_file)!r}))
assert lock.acquire()
print("held", flush=True)
sys.stdin.readline()
lock.release()
print("released", flush=True)
sys.stdin.readline()
"""], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        second = PortLock(lock_file)
        assert not second.acquire(wait_s=0.2)  # held elsewhere: given up after the wait
        holder.stdin.write("\n")
        holder.stdin.flush()
        assert holder.stdout.readline() == "released\n"
        assert second.acquire(wait_s=30)
        second.release()
        second.release()  # twice is harmless
    finally:
        holder.kill()
        holder.wait()
    link = tmp_path / "link.lock"
    link.symlink_to(tmp_path / "elsewhere")
    assert not PortLock(link).acquire(wait_s=0)  # a symbolic link is not followed
    assert not (tmp_path / "elsewhere").exists()
