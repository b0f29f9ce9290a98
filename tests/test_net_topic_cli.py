"""``racecar-hw topic list | echo | hz | pub`` against ``racecar-hw sim``, each in its own process."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
import yaml
from zenoh_util import ROOT, endpoint, free_port, start_sim, switches

from racecar_hw.cli import main


def _command(port: int, args: tuple[str, ...]) -> list[str]:
    return [sys.executable, "-m", "racecar_hw.cli", "topic", "--connect", endpoint(port), *args]


def _topic(port: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(_command(port, args), capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def _topics(port: int, *commands: tuple[str, ...], timeout: float = 90) -> list[subprocess.CompletedProcess]:
    """Commands that do not affect each other's outcome, in processes started together (each
    start-up is about two seconds of imports): their results, in order."""
    procs = [subprocess.Popen(_command(port, args), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, cwd=ROOT) for args in commands]
    results = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=timeout)
            results.append(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    return results


SCAN_LISTED = r"^/scan\s+\[sensor_msgs/msg/LaserScan\]\s+publishers: /racecar_hw"
CMD_VEL_LISTED = r"^/cmd_vel\s+\[geometry_msgs/msg/Twist\].*subscribers: /racecar_hw"


@pytest.mark.slow
def test_topic_list_echo_hz_and_pub_work_against_the_sim(tmp_path):
    port = free_port()
    # ended by SIGINT once the tools are done, however long they take on a loaded machine
    sim = start_sim(tmp_path, port, duration=180.0)
    try:
        listed = _topic(port, "list", "-v")
        # the sim may still start: its publishers and its subscribers join the graph one by one
        while sim.proc.poll() is None and not all(re.search(row, listed.stdout, re.M)
                                                  for row in (SCAN_LISTED, CMD_VEL_LISTED)):
            listed = _topic(port, "list", "-v")
        # together: none of these drives the car (the active source is still idle), and a bad pub
        # is refused before it publishes
        unknown, odom, active, bad = _topics(
            port, ("echo", "/no_such_topic", "-n", "1"), ("echo", "/odom", "-n", "1"),
            ("echo", "/vesc/low_level/ackermann_cmd_mux/active", "-n", "1"),
            ("pub", "/estop", "std_msgs/msg/Bool", "{data: maybe}"))
        pub = _topic(port, "pub", "/vesc/high_level/ackermann_cmd_mux/input/nav_0",
                     "ackermann_msgs/msg/AckermannDriveStamped", "{drive: {speed: 0.4}}", "--rate", "20",
                     "--times", "20")
        # alone: other processes starting beside it would take the sim's CPU and the lidar's rate
        hz = _topic(port, "hz", "/scan", "--duration", "2.5")
        report = sim.interrupt()
    finally:
        sim.kill()
    assert listed.returncode == 0, listed.stderr
    out = listed.stdout
    assert re.search(SCAN_LISTED, out, re.M)
    assert re.search(CMD_VEL_LISTED, out, re.M)
    assert odom.returncode == 0, odom.stderr
    first = yaml.safe_load(odom.stdout.split("---")[0])
    assert first["header"]["frame_id"] == "odom" and first["child_frame_id"] == "base_link"
    assert active.returncode == 0 and yaml.safe_load(active.stdout.split("---")[0])["data"] == "idle"
    rates = [float(m) for m in re.findall(r"average rate ([\d.]+) Hz", hz.stdout)]
    # the UST-10LX's 40 Hz; a loaded machine makes the sim's fake lidar skip sweeps, never burst
    assert rates and 20.0 < rates[-1] < 50.0, hz.stdout
    assert pub.returncode == 0 and pub.stdout.count("publishing #") == 20
    assert "nav_0" in switches(report)
    assert 0.3 < report["max_speed_mps"] < 0.5
    assert bad.returncode == 1 and "expected true or false" in bad.stderr and "Traceback" not in bad.stderr
    assert unknown.returncode == 1 and "not in the ROS graph" in unknown.stderr


@pytest.mark.slow
def test_a_wrong_type_is_refused_by_topic_pub_and_counted_by_the_daemon(tmp_path):
    """``topic pub`` names the type the daemon takes and exits 1; a sample of the wrong type put
    straight on Zenoh (as a ROS 2 node would) is counted and logged by the daemon."""
    import time

    import zenoh

    from racecar_hw.net import rmw

    port = free_port()
    sim = start_sim(tmp_path, port, duration=180.0)
    topic = "/vesc/high_level/ackermann_cmd_mux/input/nav_0"
    try:
        listed = _topic(port, "list")
        while topic not in listed.stdout and sim.proc.poll() is None:  # the sim may still start
            listed = _topic(port, "list")
        wrong, right = _topics(port, ("pub", topic, "ackermann_msgs/msg/AckermannDrive", "{speed: 0.5}"),
                               ("pub", topic, "ackermann_msgs/msg/AckermannDriveStamped",
                                "{drive: {speed: 0.0}}"))
        session = zenoh.open(zenoh.Config.from_json5(
            f'{{mode: "client", connect: {{endpoints: ["{endpoint(port)}"]}}, '
            f'scouting: {{multicast: {{enabled: false}}}}}}'))
        try:
            ros_type = "ackermann_msgs/msg/AckermannDrive"
            key = rmw.topic_key(0, topic, ros_type, rmw.type_hash(ros_type))
            publisher = session.declare_publisher(key)
            # a type name that would forge a log line and repaint the terminal, if logged as sent
            head, _, hash_ = key.rpartition("/")
            forger = session.declare_publisher(f"{head.rpartition('/')[0]}/evil\nFORGED line\x1b[2J_/{hash_}")
            from racecar_hw.base.messages import AckermannDrive
            from racecar_hw.rosmsg.typestore import ros2_types

            payload = ros2_types().serialize(AckermannDrive(speed=0.5))
            deadline = time.monotonic() + 60
            sent = 0
            while time.monotonic() < deadline and sent < 200:  # until the daemon's guard matched
                sent += 1
                publisher.put(payload, attachment=rmw.encode_attachment(sent, time.time_ns(), bytes(16)))
                forger.put(payload, attachment=rmw.encode_attachment(sent, time.time_ns(), bytes(16)))
                time.sleep(0.02)
            publisher.undeclare()
            forger.undeclare()
        finally:
            session.close()
        sim.interrupt()
    finally:
        sim.kill()
    assert wrong.returncode == 1, wrong.stdout + wrong.stderr
    assert "publishing" not in wrong.stdout and "Traceback" not in wrong.stderr
    assert wrong.stderr.count("\n") == 1
    assert f"{topic} takes ackermann_msgs/msg/AckermannDriveStamped" in wrong.stderr
    assert "not ackermann_msgs/msg/AckermannDrive" in wrong.stderr
    assert right.returncode == 0, right.stderr
    lines = [line for line in sim.log.splitlines() if "wrong type ackermann_msgs" in line]
    assert lines, sim.log[-3000:]
    assert (f"zenoh: refused {topic}: wrong type ackermann_msgs/msg/AckermannDrive (it takes "
            f"ackermann_msgs/msg/AckermannDriveStamped)") in lines[0]
    # the forger's type name is logged on the refusal's own line, its newline and escape blanked
    assert "wrong type evil FORGED line [2J_" in sim.log, sim.log[-3000:]
    assert "\x1b" not in sim.log and not any(line.startswith("FORGED") for line in sim.log.splitlines())
    # rate-limited: the first at once, then summaries (one at shutdown), not 200 lines
    assert len(lines) <= 3
    assert re.search(r"of a wrong type|(\d+) in all", sim.log)


@pytest.mark.parametrize(("msgtype", "values", "words"), [
    ("sensor_msgs/msg/LaserScan", "{ranges: 5}", "is not a sensor_msgs/msg/LaserScan"),
    ("std_msgs/msg/Header", "{stamp: {sec: 99999999999}}", "is not a std_msgs/msg/Header"),
    ("std_msgs/msg/Header", "{stamp: {sec: .inf}}", "cannot convert float infinity to integer"),
    ("sensor_msgs/msg/LaserScan", "{ranges: [1, 2], intensities: {a: 1}}",
     "is not a sensor_msgs/msg/LaserScan")])
def test_values_the_message_cannot_hold_are_one_clear_error_before_anything_is_sent(msgtype, values, words):
    """An infinite integer, a number where an array goes, an integer past its range: a TopicError
    naming the values and the type (they were tracebacks, after the Zenoh session was open).
    Refused before the session is used: none is given."""
    import argparse

    from racecar_hw.commands.topic import MESSAGE_CLASSES, TopicError, _pub

    if msgtype not in MESSAGE_CLASSES:
        pytest.fail(f"{msgtype} is not publishable any more: pick another type for this test")
    args = argparse.Namespace(topic="/x", type=msgtype, values=values, ros_distro="jazzy")
    with pytest.raises(TopicError, match=re.escape(words)) as err:
        _pub(None, 0, args)
    assert "\n" not in str(err.value)


def test_a_connect_without_its_protocol_is_one_line_naming_the_fix(capsys):
    """``--connect localhost:7447`` said "is the daemon running?" with Zenoh's JSON5 parse error."""
    assert main(["topic", "--connect", "localhost:7447", "list"]) == 1
    assert capsys.readouterr().err == (
        "racecar-hw topic: --connect: 'localhost:7447' is not a Zenoh endpoint (like tcp/127.0.0.1:7447); "
        "protocols: tcp, udp, tls, quic, ws, unixsock-stream; did you mean 'tcp/localhost:7447'?\n")
