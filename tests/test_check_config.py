"""``racecar-hw check-config`` as a user runs it: every error at once, with file, line and a close
match; ``--describe`` in YAML, for one section. The command line runs in this process (its exit
code, standard output and error as a process gives them; tests/test_daemon_run.py runs
check-config as a process of its own)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.overrides import MAX_FLOW_DEPTH, parse_yaml
from racecar_hw.cli import main


@pytest.fixture
def check_config(capsys):
    """``racecar-hw check-config ARGS``, as a completed process (exit code, stdout, stderr)."""
    def run(*args: str) -> subprocess.CompletedProcess:
        capsys.readouterr()
        code = main(["check-config", *args])
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(["racecar-hw", "check-config", *args], code, out, err)

    return run


def test_two_typos_in_a_file_are_both_reported_with_their_lines_and_suggestions(tmp_path, check_config):
    cfg = tmp_path / "car.yaml"
    cfg.write_text("vesc:\n"
                   "  port: /dev/vesc\n"
                   "  speed_to_erpm_gian: 4614\n"      # line 3
                   "safety:\n"
                   "  mode: arc\n"
                   "  margn_m: 0.3\n"                  # line 6
                   "mux:\n"
                   "  rate_hz: -5\n")                  # line 8: a bad value too
    proc = check_config(str(cfg), "--set", "lidar.modle=ust-10lx")
    assert proc.returncode == 1 and proc.stdout == "" and "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert f"racecar-hw check-config: {cfg}:3: vesc.speed_to_erpm_gian: unknown key; did you mean " \
           "speed_to_erpm_gain?" in lines
    assert f"racecar-hw check-config: {cfg}:6: safety.margn_m: unknown key; did you mean margin_m?" in lines
    assert any(line.startswith(f"racecar-hw check-config: {cfg}:8: mux.rate_hz: -5") for line in lines)
    assert "racecar-hw check-config: lidar.modle: unknown key; did you mean model? (from --set " \
           "lidar.modle=ust-10lx)" in lines
    assert len(lines) == 4
    assert not any("allowed keys" in line for line in lines)  # no dump of every key


@pytest.mark.parametrize(("setting", "key"), [("mux.estop_topic=/odom", "mux.estop_topic"),
                                            ("lidar.topic=/estop", "lidar.topic"),
                                            ("mux.output_topic=/odom", "mux.output_topic")])
def test_two_things_on_one_topic_name_the_key_that_was_set(check_config, setting, key):
    """Not the Zenoh profile, which was not touched: the key whose value made the clash, and every
    key with that value, so the reader sees which one to change."""
    proc = check_config("--set", setting)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    topic = setting.split("=")[1]
    assert line.startswith(f"racecar-hw check-config: {key}: {topic} would be both "), line
    assert "each needs a topic of its own" in line and f"(from --set {setting})" in line
    assert "zenoh.profile" not in line


def test_a_clash_only_the_components_see_is_reported_too(check_config):
    """The gamepad's drive commands on the e-stop's Bool topic passes every key's own check; the
    daemon's components, built without starting, find it, and check-config reports it like the
    others, with the --set it came from."""
    proc = check_config("--set", "gamepad.enabled=true", "--set", "gamepad.topic=/estop")
    assert proc.returncode == 1 and proc.stdout == "" and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line.startswith("racecar-hw check-config: gamepad.topic: /estop carries std_msgs/msg/Bool, "
                           "not ackermann_msgs/msg/AckermannDriveStamped"), line
    assert line.endswith("(from --set gamepad.topic=/estop)")


def test_flow_nesting_is_refused_past_its_limit_as_it_is_scanned():
    """PyYAML's scanner slows with the square of the nesting (10 KB of brackets took it 4 s before
    the composer's recursion failed): text deeper than MAX_FLOW_DEPTH is refused where it goes too
    deep, and text at the limit parses."""
    at_limit = parse_yaml("[" * MAX_FLOW_DEPTH + "]" * MAX_FLOW_DEPTH, "text")
    for _ in range(MAX_FLOW_DEPTH - 1):
        at_limit, = at_limit
    assert at_limit == []
    with pytest.raises(ConfigError, match=rf"text is not valid YAML: line 2, column {MAX_FLOW_DEPTH + 4}: "
                                          "nested too deep"):
        parse_yaml("a: 1\nb: " + "{" * (MAX_FLOW_DEPTH + 1) + "}" * (MAX_FLOW_DEPTH + 1), "text")
    # brackets in a quoted string are text, not nesting
    assert parse_yaml("a: '" + "[" * 500 + "'", "text") == {"a": "[" * 500}


@pytest.mark.parametrize(("setting", "key", "words"), [
    ("mux.max_decel_mps2=0.05", "mux.max_decel_mps2", "is below safety.max_decel_mps2 (4.0)"),
    ("vesc.brake_current_a=0", "vesc.brake_current_a", "out of range; allowed: 1.0 to 200.0")])
def test_settings_that_would_let_the_car_brake_late_or_coast_are_refused(check_config, setting, key, words):
    """A limiter braking at 0.05 m/s^2 still drove 1.51 m/s 10 s after its input went silent; a brake
    current of 0 A releases the motor. The safety controller counts on neither."""
    proc = check_config("--set", setting)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line.startswith(f"racecar-hw check-config: {key}: ") and words in line, line
    assert check_config("--set", setting, "--set", "safety.mode=off").returncode == (
        0 if key.startswith("mux") else 1)


@pytest.mark.parametrize(("content", "words"), [
    (b"vesc:\n  port: /dev/ttyACM0 \xb5\n", "is not UTF-8 text (byte 0xb5 at offset 27)"),
    (b"vesc: " + b"[" * 5000 + b"]" * 5000 + b"\n", "is not valid YAML: line 1, column 71: nested too deep"),
    (b"vesc:\n  poll_rate_hz: " + b"9" * 5000 + b"\n", "is not valid YAML: Exceeds the limit"),
    (b"vesc:\n  port: /dev/a\n  port: /dev/b\n", "line 3, column 3: found the key 'port' twice"),
    (b"vesc:\n  port: [\n", "line 3, column 1: expected the node content")])
def test_a_file_that_does_not_parse_is_one_line(tmp_path, check_config, content, words):
    """Text that is not UTF-8, nesting too deep, an integer too long, a key given twice (PyYAML would
    keep the last one silently) and a syntax error: one line each, with the file, no traceback."""
    cfg = tmp_path / "car.yaml"
    cfg.write_bytes(content)
    proc = check_config(str(cfg))
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line.startswith(f"racecar-hw check-config: {cfg}") and words in line, line
    deep = check_config("--set", "vesc.port=" + "[" * 3000)
    assert deep.returncode == 1 and len(deep.stderr.splitlines()) == 1 and "nested too deep" in deep.stderr


@pytest.mark.parametrize(("setting", "words"), [
    ("lidar.tcp=127.0.0.1:99999",
     "lidar.tcp: '127.0.0.1:99999': port '99999' is not a port number (0-65535)"),
    ("lidar.tcp=host:-5", "lidar.tcp: 'host:-5': port '-5' is not a port number (0-65535)"),
    ("lidar.tcp=10.0.0.1:0", "lidar.tcp: '10.0.0.1:0': port 0 is no lidar's port"),
    ("vesc.servo_min=0.9", "vesc.servo_min: 0.9 is above servo_max 0.85")])
def test_a_check_across_a_sections_keys_names_the_full_key_and_its_set(check_config, setting, words):
    """A lidar port out of range passed check-config and then made the daemon log a traceback on
    every reconnect; a section's own checks named their key without the section (``servo_min``)
    and so could not point at the --set that caused them."""
    proc = check_config("--set", setting)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line == f"racecar-hw check-config: {words} (from --set {setting})", line


@pytest.mark.parametrize(("sets", "words"), [
    (["lidar.model=urg-04lx", "lidar.port=/dev/sensors/hokuyo"],
     "lidar.tcp: the urg-04lx is a USB lidar with no Ethernet port; set lidar.port for it and "
     "lidar.tcp: null"),
    (["lidar.model=a2m8", "lidar.port=/dev/sensors/rplidar"],
     "lidar.tcp: the a2m8 is a serial lidar with no Ethernet port; set lidar.port for it and "
     "lidar.tcp: null"),
    (["lidar.port=/dev/ttyACM0"],
     "lidar.tcp: lidar.port and lidar.tcp are both set; set one: lidar.port for USB, lidar.tcp for "
     "Ethernet; the other null")])
def test_a_lidar_port_beside_the_shipped_tcp_is_refused_at_the_tcp_line(tmp_path, check_config, sets, words):
    """The shipped config sets lidar.tcp; a USB model's lidar.port beside it passed and the driver
    dialled the USB lidar over TCP forever (tcp won), and an RPLIDAR's tcp was ignored."""
    cfg = tmp_path / "car.yaml"
    cfg.write_text("lidar:\n  model: ust-10lx\n  tcp: 192.168.0.10:10940\n"
                   "safety: {scan_timeout_s: 0.3, scan_period_s: 0.1}\n")  # an RPLIDAR's sweep
    args = [a for s in sets for a in ("--set", s)]
    proc = check_config(str(cfg), *args)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line == f"racecar-hw check-config: {cfg}:3: {words}", line
    assert check_config(str(cfg), *args, "--set", "lidar.tcp=null").returncode == 0


@pytest.mark.parametrize(("item", "words"), [
    ("{frame_id: odom, child_frame_id: laser}",
     "frame 'laser' already has parent 'base_link'; a frame cannot also be a child of 'odom'"),
    ("{frame_id: laser, child_frame_id: base_link}", "'laser' -> 'base_link' would close a cycle")])
def test_a_transform_tree_error_names_its_item_and_line_with_the_other_errors(tmp_path, check_config,
                                                                              item, words):
    """A second parent or a cycle was reported without file, line or key, and only once every
    other error was fixed (the daemon built the tree)."""
    cfg = tmp_path / "car.yaml"
    cfg.write_text("static_transforms:\n"
                   "  - {frame_id: base_link, child_frame_id: laser}\n"
                   f"  - {item}\n"                                         # line 3
                   "  - {frame_id: base_link, child_frame_id: cam, xyz: [1, 2]}\n"
                   "safety:\n  margn_m: 1\n")
    proc = check_config(str(cfg))
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.splitlines() == [
        f"racecar-hw check-config: {cfg}:6: safety.margn_m: unknown key; did you mean margin_m?",
        f"racecar-hw check-config: {cfg}:4: static_transforms[2].xyz: expected 3 values, got 2",
        f"racecar-hw check-config: {cfg}:3: static_transforms[1]: {words}"], proc.stderr


def test_a_good_file_prints_the_effective_config(tmp_path, check_config):
    cfg = tmp_path / "car.yaml"
    cfg.write_text("vesc:\n  speed_to_erpm_gain: 4000\n")
    proc = check_config(str(cfg))
    assert proc.returncode == 0, proc.stderr
    assert yaml.safe_load(proc.stdout)["vesc"]["speed_to_erpm_gain"] == 4000.0


def test_describe_prints_yaml_values_and_honours_a_section(check_config):
    proc = check_config("--describe", "vesc")
    assert proc.returncode == 0, proc.stderr
    keys = [line for line in proc.stdout.splitlines() if not line.startswith(" ")]
    assert keys and all(line.startswith("vesc.") for line in keys)
    assert "vesc.usb_serial: null" in keys and "vesc.invert_motor: false" in keys
    assert not any("None" in line or "False" in line for line in keys)
    everything = check_config("--describe")
    assert "mux.rate_hz: 50.0" in everything.stdout and "safety.mode: arc" in everything.stdout
    wrong = check_config("--describe", "vsec")
    assert wrong.returncode == 1
    assert wrong.stderr == "racecar-hw check-config: vsec: unknown section; did you mean vesc?\n"


def test_a_sim_section_is_refused_and_points_at_the_scenario(tmp_path, check_config):
    """The config once took a ``sim:`` section of any keys and values and nothing read it: a typo or
    a negative wheelbase there passed. The simulated car and world are a scenario's."""
    cfg = tmp_path / "car.yaml"
    cfg.write_text("vesc:\n  port: /dev/vesc\nsim:\n  car: {wheelbase: -5}\n")
    proc = check_config(str(cfg))
    assert proc.returncode == 1 and proc.stdout == "" and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line.startswith(f"racecar-hw check-config: {cfg}:3: sim: unknown section; allowed sections: "
                           ), line
    assert "racecar-hw sim --scenario FILE" in line
    assert ", sim," not in line and "static_transforms, status" in line
    proc = check_config("--set", "sim.garbage=1", "--set", "sim.car.wheelbase=-5")
    assert proc.returncode == 1 and "sim: unknown section" in proc.stderr
    assert "sim" not in yaml.safe_load(check_config().stdout)
    assert check_config("--describe", "sim").returncode == 1


@pytest.mark.parametrize(("setting", "words"), [
    ("gamepad.topic=relative", "gamepad.topic: 'relative' is not an absolute topic name"),
    ("gamepad.autonomy_lock_topic=lock", "gamepad.autonomy_lock_topic: 'lock' is not an absolute topic name"),
    ("gamepad.rescan_max_s=0.1", "gamepad.rescan_max_s: must not be below rescan_min_s"),
    ("keyboard.topic=teleop", "keyboard.topic: 'teleop' is not an absolute topic name"),
    ("vesc.gamepad.x=1", "vesc.gamepad: unknown key; allowed keys: "),
    ("foo.bar=1", "foo: unknown section; allowed sections: "),
    ("sim.car.wheelbase=-5", "sim: unknown section; allowed sections: "),
    (".x=1", ".x: a part of the key is empty; an override must look like section.key=value"),
    ("vesc..port=/dev/x", "vesc..port: a part of the key is empty; "),
    ("mux.inputs.x.timeout_s=1", "mux.inputs.x")])
def test_an_error_from_a_set_names_the_users_key_and_the_set(check_config, setting, words):
    """The gamepad's checks named a section ``teleop`` there is none of; a section or key the --set
    made (foo, vesc.gamepad) was blamed on the file and its line; an empty part of a key was applied
    as a section named ''; a --set that could not be applied came without its origin."""
    proc = check_config("--set", setting)
    assert proc.returncode == 1 and proc.stdout == "" and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line.startswith(f"racecar-hw check-config: {words}"), line
    assert line.endswith(f" (from --set {setting})"), line
    assert "car.yaml" not in line


def test_a_foxglove_host_that_needs_a_token_is_blamed_on_where_the_host_was_set(tmp_path, check_config):
    """The check named foxglove.token, which nobody had set, so the error was blamed on the line of the
    file's ``foxglove:`` section instead of the ``--set foxglove.host=...`` that made it."""
    proc = check_config("--set", "foxglove.enabled=true", "--set", "foxglove.host=0.0.0.0")
    assert proc.returncode == 1 and proc.stdout == "" and "Traceback" not in proc.stderr
    line, = proc.stderr.splitlines()
    assert line.startswith("racecar-hw check-config: foxglove.host: '0.0.0.0' is not loopback: set "
                           "foxglove.token"), line
    assert line.endswith(" (from --set foxglove.host=0.0.0.0)") and "car.yaml" not in line, line
    cfg = tmp_path / "car.yaml"
    cfg.write_text("foxglove:\n  enabled: true\n  host: 0.0.0.0\n")  # line 3
    line, = check_config(str(cfg)).stderr.splitlines()
    assert line.startswith(f"racecar-hw check-config: {cfg}:3: foxglove.host: '0.0.0.0' is not loopback"), \
        line
    assert check_config("--set", "foxglove.enabled=true", "--set", "foxglove.host=0.0.0.0",
                        "--set", "foxglove.token=secret").returncode == 0


def test_a_set_that_cannot_be_applied_is_reported_with_the_files_errors(tmp_path, check_config):
    cfg = tmp_path / "car.yaml"
    cfg.write_text("vesc:\n  speed_to_erpm_gian: 4614\n")
    proc = check_config(str(cfg), "--set", ".x=1", "--set", "lidar.modle=a1")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.splitlines() == [
        "racecar-hw check-config: .x: a part of the key is empty; an override must look like "
        "section.key=value (from --set .x=1)",
        f"racecar-hw check-config: {cfg}:2: vesc.speed_to_erpm_gian: unknown key; did you mean "
        "speed_to_erpm_gain?",
        "racecar-hw check-config: lidar.modle: unknown key; did you mean model? (from --set lidar.modle=a1)"]


def _string_keys(*, topics: bool) -> list[str]:
    """Every config key (a list's first item for a list of sections) whose name ends so: ``topic``
    (``lidar.topic``, ``safety.scan_topic``), or ``frame_id``, ``port`` and ``device`` (a device path)
    and ``host`` (an address to listen on)."""
    from racecar_hw.config import describe_config

    ends = ("topic",) if topics else ("frame_id", "port", "device", "host")
    return [key.replace("[]", ".0") for key, default, _ in describe_config()
            if key.split(".")[-1].endswith(ends) and (isinstance(default, str) or default is None)
            and key != "follower.topic"]  # a topic in the bag; empty: the bag's only one


def _enabled(key: str) -> list[str]:
    """--sets that switch on the section of ``key``, so its checks run."""
    section = key.split(".")[0]
    extra = ["--set", "follower.bag=/nonexistent.bag"] if section == "follower" else []
    return ["--set", f"{section}.enabled=true", *extra] if section in (
        "setpoint", "figure8", "follower", "keyboard", "mavlink", "foxglove") else []


@pytest.mark.parametrize("key", _string_keys(topics=True))
@pytest.mark.parametrize("value", ["", "scan"])
def test_every_topic_must_be_absolute(check_config, key, value):
    """lidar.topic, safety.scan_topic, the set-point's topics and more took a relative or empty name
    (and nothing ever met on it) while the mux, keyboard and gamepad topics refused one."""
    proc = check_config(*_enabled(key), "--set", f"{key}={value}")
    assert proc.returncode == 1, (key, proc.stdout[-300:])
    line = proc.stderr.splitlines()[0]
    assert f"{key.replace('.0.', '[0].')}: {value!r} is not an absolute topic name" in line \
        or f"{key}: {value!r} is not an absolute topic name" in line, line
    assert line.endswith(f"(from --set {key}={value})"), line


@pytest.mark.parametrize("key", _string_keys(topics=False))
def test_every_frame_id_device_and_host_must_not_be_empty(check_config, key):
    """``--set vesc.port=`` passed, and run then looked for a serial device at ''; an empty VESC
    odometry, base or IMU frame passed while an empty static_transforms frame_id was refused; an
    empty ``web.host`` or ``foxglove.host`` (which binds every interface) and an empty
    ``gamepad.device`` (a substring of every pad's name) passed too."""
    proc = check_config(*_enabled(key), "--set", f"{key}=")
    assert proc.returncode == 1, (key, proc.stdout[-300:])
    line = proc.stderr.splitlines()[0]
    assert line.endswith(f"must not be empty (from --set {key}=)"), line
    assert {"vesc.port", "vesc.odom_frame_id", "vesc.base_frame_id", "vesc.imu_frame_id", "lidar.port",
            "lidar.frame_id", "static_transforms.0.frame_id", "web.host", "foxglove.host",
            "gamepad.device"} <= set(_string_keys(topics=False))


def test_a_set_numbers_the_mux_locks_and_inputs_as_check_config_lists_them(check_config):
    """The car config's autonomy lock (the gamepad's) is lock 0, as check-config lists it, and the
    inputs are 0..6 with cmd_vel; a --set past them said ``(0..-1)`` and ``(0..5)``, without its
    origin."""
    proc = check_config("--set", "mux.locks.0.timeout_s=1")
    assert proc.returncode == 0, proc.stderr
    assert yaml.safe_load(proc.stdout)["mux"]["locks"] == [
        {"name": "autonomy", "topic": "/vesc/autonomy_lock", "priority": 50, "timeout_s": 1.0}]
    added = ("(check-config lists them; autonomy is added by gamepad.autonomy_lock (with the gamepad "
             "on), when no lock is on gamepad.autonomy_lock_topic)")
    for sets, words in [
        (["mux.locks.1.timeout_s=1"], "mux.locks.1.timeout_s: no mux lock 1; the mux has 1 lock: 0 autonomy "
                                      + added),
        (["gamepad.enabled=false", "mux.locks.0.timeout_s=1"],
         "mux.locks.0.timeout_s: no mux lock 0; the mux has 0 locks " + added),
        (["mux.inputs.x.timeout_s=1"], "mux.inputs.x.timeout_s: no mux input 'x'; the mux has 7 inputs: "
                                       "0 safety, 1 teleop, 2 nav_0, 3 nav_1, 4 nav_2, 5 nav_3, 6 cmd_vel ")]:
        proc = check_config(*[arg for s in sets for arg in ("--set", s)])
        assert proc.returncode == 1 and "Traceback" not in proc.stderr
        line, = proc.stderr.splitlines()
        assert line.startswith(f"racecar-hw check-config: {words}"), line
        assert line.endswith(f" (from --set {sets[-1]})"), line


@pytest.mark.parametrize(("setting", "words"), [
    ("static_transforms.0.xyz=[.nan,0,0]", "static_transforms[0].xyz[0]: NaN is not allowed"),
    ("static_transforms.x.xyz=[1,0,0]", "static_transforms.x: 'x' is not a list index; the list has 2 "
                                        "items (0..1)"),
    ("static_transforms.2.xyz=[1,0,0]", "static_transforms.2: index 2 is out of range; the list has 2 "
                                        "items (0..1)"),
    ("mux.estop_release_sources=[web,web]", "mux.estop_release_sources[1]: 'web' is listed twice")])
def test_an_element_of_a_list_is_one_error(check_config, setting, words):
    """A NaN in xyz was reported, then (its element taken out) 'expected 3 values, got 2' too; an
    index that is no number was said to be out of range."""
    proc = check_config("--set", setting)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.splitlines() == [f"racecar-hw check-config: {words} (from --set {setting})"]


@pytest.mark.parametrize(("rotation", "refused"), [
    ("ypr: [0.0, 0.0, 3.14159265]", True),     # upside down: the z rate is the yaw rate negated
    ("ypr: [0.0, 0.5, 0.0]", True),            # pitched
    ("quaternion: [1.0, 0.0, 0.0, 0.0]", True),
    ("ypr: [1.5707963, 0.0, 0.0]", False),     # turned about z: z still up
    ("ypr: [0.0, 0.05, 0.0]", False)])         # a few degrees off level
def test_an_imu_mount_with_roll_or_pitch_is_refused(tmp_path, check_config, rotation, refused):
    """The driver's gyro odometry and bias and calibrate read the IMU's z rate as the yaw rate,
    untransformed: an upside-down ``base_link -> imu`` was accepted and turned left into right."""
    text = (Path(__file__).parents[1] / "config" / "car.yaml").read_text()
    row = "{frame_id: base_link, child_frame_id: imu, xyz: [0.12, 0.0, 0.04]}"
    assert row in text
    cfg = tmp_path / "car.yaml"
    cfg.write_text(text.replace(row, row[:-1] + f", {rotation}}}"))
    proc = check_config(str(cfg))
    assert proc.returncode == (1 if refused else 0), proc.stderr
    if refused:
        line, = proc.stderr.splitlines()
        assert "static_transforms[1]: base_link -> imu tilts the IMU's z axis" in line, line
        assert check_config(str(cfg), "--set", "vesc.imu=false").returncode == 0
