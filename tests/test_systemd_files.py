"""The shipped systemd unit and udev rules: settings, `systemd-analyze verify`, udev rule syntax."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CONFIG = Path(__file__).resolve().parents[1] / "config"
UNIT = CONFIG / "racecar-hw.service"
RULES = CONFIG / "99-racecar-hw.rules"


# --- the systemd unit -------------------------------------------------------------------------


def unit_entries(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) for every assignment; keys may repeat (DeviceAllow=)."""
    section = ""
    entries = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, sep, value = line.partition("=")
        assert sep and re.fullmatch(r"[A-Za-z][A-Za-z0-9]*", key), f"line {number}: {raw!r}"
        assert section, f"line {number}: assignment outside a section"
        entries.append((section, key, value))
    return entries


def unit_values(section: str, key: str) -> list[str]:
    return [v for s, k, v in unit_entries(UNIT.read_text()) if (s, k) == (section, key)]


def test_unit_settings() -> None:
    expect = {
        ("Service", "Type"): "notify",
        ("Service", "NotifyAccess"): "main",
        ("Service", "WatchdogSec"): "2s",
        ("Service", "Restart"): "on-failure",
        ("Service", "KillSignal"): "SIGTERM",
        ("Service", "User"): "racecar",
        ("Service", "SupplementaryGroups"): "dialout input",
        ("Install", "WantedBy"): "multi-user.target",
    }
    for (section, key), value in expect.items():
        assert unit_values(section, key) == [value], (section, key)
    assert unit_values("Service", "ExecStart") == [
        "/usr/local/bin/racecar-hw run --config /etc/racecar-hw/car.yaml"]
    assert unit_values("Service", "RestartSec") and unit_values("Service", "TimeoutStopSec")


def test_unit_sets_the_open_file_limit_above_what_network_clients_may_hold() -> None:
    from racecar_hw.net.foxglove_params import FoxgloveParams
    from racecar_hw.net.web import WebParams

    (value,) = unit_values("Service", "LimitNOFILE")
    soft, _, hard = value.partition(":")
    assert soft.isdigit() and (not hard or int(hard) >= int(soft))
    # the page's connections, the relay's and their upstream halves, with room for devices and Zenoh
    network = WebParams().max_connections + 2 * FoxgloveParams().max_connections
    assert int(soft) >= 1024 + network


def test_unit_hardening_keeps_serial_and_input_devices() -> None:
    assert unit_values("Service", "DevicePolicy") == ["closed"]
    allowed = unit_values("Service", "DeviceAllow")
    for device in ("char-ttyACM", "char-ttyUSB", "char-input"):
        assert f"{device} rw" in allowed
    # PrivateDevices= would hide /dev/ttyACM0 and friends altogether
    assert unit_values("Service", "PrivateDevices") in ([], ["false"], ["no"])
    families = unit_values("Service", "RestrictAddressFamilies")[0].split()
    assert {"AF_UNIX", "AF_INET"} <= set(families)  # notify socket; Ethernet Hokuyo


def systemd_analyze() -> str:
    tool = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
    if not Path(tool).exists():
        pytest.skip("systemd-analyze is not installed")
    return tool


def verify(tool: str, unit: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True, timeout=60,
                          check=False)


def installed_copy(tmp_path: Path, text: str) -> Path:
    """The unit with ExecStart's binary swapped for one that exists here.

    `systemd-analyze verify` refuses an ExecStart binary that is not executable on this machine;
    the venv's racecar-hw entry point stands in for /usr/local/bin/racecar-hw (the User= need not
    exist: verify does not resolve it).
    """
    entry_point = Path(sys.executable).parent / "racecar-hw"
    binary = entry_point if entry_point.exists() else Path("/bin/true")
    copy = tmp_path / "racecar-hw.service"
    copy.write_text(text.replace("/usr/local/bin/racecar-hw", str(binary)))
    return copy


def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    tool = systemd_analyze()
    result = verify(tool, installed_copy(tmp_path, UNIT.read_text()))
    assert result.returncode == 0, result.stderr
    # verify exits 0 on unknown keys and bad values, printing a warning per line: none allowed
    assert "racecar-hw.service" not in result.stderr, result.stderr


def test_verify_check_catches_a_typo(tmp_path: Path) -> None:
    """The check above is worth something: a misspelt key is reported."""
    tool = systemd_analyze()
    text = UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs=")
    result = verify(tool, installed_copy(tmp_path, text))
    assert "WatchdogSecs" in result.stderr


# --- the udev rules ---------------------------------------------------------------------------

MATCH_KEYS = {"ACTION", "DEVPATH", "KERNEL", "KERNELS", "SUBSYSTEM", "SUBSYSTEMS", "DRIVER", "DRIVERS",
              "ATTR", "ATTRS", "ENV", "TAG", "TAGS", "TEST", "PROGRAM", "RESULT", "NAME", "SYMLINK",
              "CONST", "SYSCTL", "LABEL"}
ASSIGN_KEYS = {"NAME", "SYMLINK", "OWNER", "GROUP", "MODE", "ENV", "TAG", "RUN", "OPTIONS", "ATTR",
               "SYSCTL", "IMPORT", "GOTO", "LABEL", "SECLABEL", "PROGRAM"}
KEYS_WITH_ATTRIBUTE = {"ATTR", "ATTRS", "ENV", "SYSCTL", "TEST", "IMPORT", "RUN", "CONST", "SECLABEL"}
PAIR = re.compile(r'\s*([A-Z_]+)(?:\{([^{}"]+)\})?\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*')


def parse_rule(line: str) -> list[tuple[str, str | None, str, str]]:
    """(key, attribute, operator, value) pairs of one rule line; AssertionError when malformed."""
    pairs = []
    pos = 0
    while pos < len(line):
        m = PAIR.match(line, pos)
        assert m, f"malformed at column {pos}: {line[pos:]!r}"
        key, attr, op, value = m.groups()
        if op in ("==", "!="):
            assert key in MATCH_KEYS, f"{key} cannot be matched"
        else:
            assert key in ASSIGN_KEYS, f"{key} cannot be assigned"
        assert (attr is not None) == (key in KEYS_WITH_ATTRIBUTE) or key == "RUN", f"{key}{{{attr}}}"
        pairs.append((key, attr, op, value))
        pos = m.end()
        if pos < len(line):
            assert line[pos] == ",", f"expected ',' at column {pos}: {line!r}"
            pos += 1
    return pairs


def rules() -> list[list[tuple[str, str | None, str, str]]]:
    out = []
    for raw in RULES.read_text().splitlines():
        line = raw.strip()
        if line and not line.startswith("#"):
            assert not line.endswith("\\"), "continued lines are not used here"
            out.append(parse_rule(line))
    return out


def test_rules_parse_and_assign_valid_names() -> None:
    parsed = rules()
    assert len(parsed) == 3
    for pairs in parsed:
        assert any(op == "==" for _, _, op, _ in pairs), "a rule without a match applies to every device"
        for key, _, op, value in pairs:
            if key == "SYMLINK":
                assert op == "+=", "SYMLINK= would drop the names other rules gave"
                for name in value.split():
                    assert re.fullmatch(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*", name), name
                    assert ".." not in name.split("/")
            if key == "MODE":
                assert re.fullmatch(r"0[0-7]{3}", value), value
            if key == "ATTRS" and op == "==":
                assert re.fullmatch(r"[0-9a-f]{4}", value), f"USB ids are 4 lowercase hex digits: {value}"


@pytest.mark.parametrize(("vendor", "product", "symlink"), [
    ("0483", "5740", "vesc"),
    ("15d1", "0000", "sensors/hokuyo"),
    ("10c4", "ea60", "sensors/rplidar"),
])
def test_rules_name_each_device(vendor: str, product: str, symlink: str) -> None:
    for pairs in rules():
        found = {(k, a): v for k, a, _, v in pairs}
        if found.get(("ATTRS", "idVendor")) == vendor and found.get(("ATTRS", "idProduct")) == product:
            assert found[("SUBSYSTEM", None)] == "tty"
            assert found[("SYMLINK", None)] == symlink
            assert found[("GROUP", None)] == "dialout"
            assert found[("MODE", None)] == "0660"
            return
    raise AssertionError(f"no rule for {vendor}:{product}")


def test_rule_parser_rejects_malformed_lines() -> None:
    for bad in ('SUBSYSTEM=="tty" SYMLINK+="vesc"',            # missing comma
                'ATTRS{idVendor}=="0483", SYMLINK+=vesc',     # unquoted value
                'GROUP=="dialout"',                            # GROUP cannot be matched
                'ATTRS=="0483"',                               # ATTRS needs {attribute}
                'SUBSYSTEM=="tty", FOO="bar"'):                # unknown key
        with pytest.raises(AssertionError):
            parse_rule(bad)


def test_rules_pass_udevadm_verify() -> None:
    """`udevadm verify` exists from systemd 254; Debian 12 ships 252, where only the parser above runs."""
    tool = shutil.which("udevadm")
    if tool is None:
        pytest.skip("udevadm is not installed")
    probe = subprocess.run([tool, "verify", "--help"], capture_output=True, text=True, timeout=30,
                           check=False)
    if probe.returncode != 0:
        pytest.skip("this udevadm has no 'verify' command (systemd < 254)")
    result = subprocess.run([tool, "verify", str(RULES)], capture_output=True, text=True, timeout=60,
                            check=False)
    assert result.returncode == 0, result.stdout + result.stderr
