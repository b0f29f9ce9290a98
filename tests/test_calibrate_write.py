"""``racecar-hw calibrate --write``: measured values into a config file as its invert flags state
them, stale keys cleared, and nothing written where the result would not load or would not mean
what was measured (racecar_hw.commands.calibrate_write)."""

from __future__ import annotations

from pathlib import Path

import pytest
from zenoh_util import ROOT

from racecar_hw.base.errors import ConfigError
from racecar_hw.commands.calibrate_write import check_writable, write
from racecar_hw.config import load_config
from vesc.ackermann import AckermannConversion

pytestmark = pytest.mark.quiet  # pure computation and small files

#: what the procedure measures: physical signs (a mirrored servo turns left with a positive gain)
MEASURED = {"speed_to_erpm_gain": 4702.5, "steering_angle_to_servo_offset": 0.5804,
            "steering_angle_to_servo_gain": 1.3349, "steering_angle_to_servo_gain_right": None}


def _car(tmp_path: Path, extra: str = "", indent: str = "  ") -> Path:
    text = (ROOT / "config" / "car.yaml").read_text()
    if extra:
        text = text.replace("\nvesc:\n", f"\nvesc:\n  {extra}\n", 1)
    if indent != "  ":
        text = "\n".join(indent + line[2:] if line.startswith("  ") and not line.startswith("   ") else line
                         for line in text.splitlines()) + "\n"
    path = tmp_path / "car.yaml"
    path.write_text(text)
    return path


def _effective(path) -> AckermannConversion:
    return AckermannConversion.from_params(load_config(path).vesc)


@pytest.mark.parametrize(("flags", "servo_sign", "motor_sign"), [
    ("", 1, 1), ("invert_servo: true", -1, 1), ("invert_motor: true", 1, -1)])
def test_the_written_gains_mean_what_was_measured_under_the_files_invert_flags(
        tmp_path, capsys, flags, servo_sign, motor_sign):
    """A mirrored servo configured with invert_servo: true gets the measured gain negated, so the
    car turns the way it is told (it once turned the other way after calibrating)."""
    path = _car(tmp_path, flags)
    written = write(path, MEASURED)
    assert written["steering_angle_to_servo_gain"] == servo_sign * 1.3349
    assert written["speed_to_erpm_gain"] == 4702.5  # a magnitude: invert_motor gives the direction
    conv = _effective(path)
    assert conv.servo_gain == pytest.approx(1.3349) and conv.servo_gain_right == pytest.approx(1.3349)
    assert conv.erpm_gain == pytest.approx(motor_sign * 4702.5)
    assert conv.steering_angle_to_servo_offset == 0.5804
    assert f"+++ {path}" in capsys.readouterr().out


def test_an_earlier_right_gain_is_cleared_when_both_sides_now_turn_alike(tmp_path):
    path = _car(tmp_path, "steering_angle_to_servo_gain_right: -1.9")
    write(path, MEASURED)
    vesc = load_config(path).vesc
    assert vesc.steering_angle_to_servo_gain_right is None and vesc.steering_angle_to_servo_gain == 1.3349
    fresh = _car(tmp_path)  # no such key: none is added
    write(fresh, MEASURED)
    assert "steering_angle_to_servo_gain_right" not in fresh.read_text()


def test_a_block_indented_by_four_keeps_its_indentation(tmp_path):
    path = _car(tmp_path, indent="    ")
    write(path, {**MEASURED, "steering_angle_to_servo_gain_right": 1.5})
    text = path.read_text()
    assert "\n    steering_angle_to_servo_gain_right: 1.5  # racecar-hw calibrate\n" in text
    assert load_config(path).vesc.steering_angle_to_servo_gain_right == 1.5


def test_a_flow_style_block_is_refused_and_the_file_left_as_it_was(tmp_path):
    path = tmp_path / "car.yaml"
    path.write_text("vesc: {port: /dev/vesc, wheelbase_m: 0.25}\n")
    before = path.read_text()
    with pytest.raises(ConfigError, match="--write: .* after the edit it would not load .* nothing written"):
        write(path, MEASURED)
    assert path.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["car.yaml"]


def test_a_symlinked_config_is_written_through_the_link_keeping_mode_and_owner(tmp_path):
    """The service's config is often a symlink, readable by the service's group: calibrating once
    replaced the link with a file of its own and left it 0644 (or 0600 under umask 077)."""
    import os

    real = _car(tmp_path)
    os.chmod(real, 0o640)
    link = tmp_path / "link.yaml"
    link.symlink_to(real)
    old_umask = os.umask(0o077)
    try:
        write(link, MEASURED)
    finally:
        os.umask(old_umask)
    assert link.is_symlink() and load_config(real).vesc.steering_angle_to_servo_gain == 1.3349
    assert (real.stat().st_mode & 0o777) == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["car.yaml", "link.yaml"]


def test_a_read_only_file_is_refused_before_the_car_moves(tmp_path):
    """0444: replacing it through a new file renamed over it needs only the directory's permission,
    and root may write it anyway; the mode's write bits are read, so this holds as root too."""
    path = _car(tmp_path)
    path.chmod(0o444)
    with pytest.raises(ConfigError, match=r"^--write: .*car\.yaml: read-only \(-r--r--r--"):
        check_writable(path)


@pytest.mark.parametrize("scratch", [".car.yaml.calibrate-check", ".car.yaml.calibrate"])
def test_a_file_whose_scratch_file_cannot_be_created_is_refused_before_the_car_moves(tmp_path, scratch):
    """The check opens the scratch file for writing, so any reason it cannot be created (a read-only
    directory, a read-only mount, here a directory in its place, which stops root as well) refuses."""
    path = _car(tmp_path)
    (tmp_path / scratch).mkdir()
    with pytest.raises(ConfigError, match=rf"^--write: .*car\.yaml: cannot create .*{scratch} "):
        check_writable(path)


def test_a_writable_file_passes_and_the_check_leaves_nothing_behind(tmp_path):
    path = _car(tmp_path)
    check_writable(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["car.yaml"]


@pytest.mark.parametrize("scratch", [".car.yaml.calibrate-check", ".car.yaml.calibrate"])
def test_an_os_error_while_writing_is_one_line_and_the_file_untouched(tmp_path, scratch):
    """After the drive (the directory made read-only meanwhile): a ConfigError naming --write, not a
    PermissionError's traceback after the values were shown."""
    path = _car(tmp_path)
    before = path.read_text()
    (tmp_path / scratch).mkdir()
    with pytest.raises(ConfigError, match=r"^--write: .*car\.yaml: .*; nothing written: put the snippet "):
        write(path, MEASURED)
    assert path.read_text() == before
