"""The README works as written: two commands at the top, every --set example through check-config,
every command it names."""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

import pytest
import yaml

from racecar_hw.cli import build_parser, main
from racecar_hw.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def code_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced block."""
    return re.findall(r"^```(\w*)\n(.*?)^```", text, flags=re.M | re.S)


def test_the_top_has_exactly_two_commands_demo_and_tests() -> None:
    top = README.split("\n## ", 1)[0]
    blocks = code_blocks(top)
    assert [lang for lang, _ in blocks] == ["sh", "sh"]
    assert blocks[0][1].strip().endswith(".venv/bin/racecar-hw sim")
    assert blocks[1][1].strip().endswith(".venv/bin/python -m pytest -n 3")
    # CI runs the README's command (docs/tests.md)
    ci = (ROOT / ".ci" / "run").read_text()
    assert ".venv/bin/python -m pytest -q -n 3\n" in ci


def set_examples() -> list[str]:
    return sorted(set(re.findall(r"--set ([a-z_]+\.[\w.]+=\S+?)(?=[`\s)])", README)))


def test_the_readme_has_set_examples() -> None:
    assert "mux.inputs.1.timeout_s=0.5" in set_examples()
    assert len(set_examples()) >= 4


@pytest.mark.parametrize("config", ["config/car.yaml", "config/sim.yaml"])
@pytest.mark.parametrize("assignment", set_examples())
def test_every_set_example_passes_check_config(config, assignment, capsys) -> None:
    """Each --set of the README through check-config with both shipped configs; the one the README
    shows failing fails with the message it shows."""
    shown = re.search(r"\$ racecar-hw check-config --set " + re.escape(assignment) + r"\n(.*)\n", README)
    code = main(["check-config", str(ROOT / config), "--set", assignment])
    err = capsys.readouterr().err
    if shown is None:
        assert code == 0, err
        return
    assert code == 1
    expected = shown[1].split("...")[0]  # the README abbreviates the list of keys
    assert err.startswith(expected), (err, expected)


@pytest.mark.parametrize("config", ["config/car.yaml", "config/sim.yaml"])
def test_set_numbers_the_mux_inputs_as_check_config_lists_them(config, capsys) -> None:
    """Also the inputs Foxglove and Zenoh add after the configured ones (foxglove, cmd_vel). The car
    config leaves the live view off (it needs the foxglove extra): there it is switched on first."""
    file = [str(ROOT / config)]
    if config == "config/car.yaml":
        assert main(["check-config", *file]) == 0
        assert [i["name"] for i in yaml.safe_load(capsys.readouterr().out)["mux"]["inputs"][-2:]] == [
            "nav_3", "cmd_vel"]
        assert "`config/car.yaml` leaves the live view off: there input 6 is `cmd_vel`" in README
        file += ["--set", "foxglove.enabled=true"]
    assert main(["check-config", *file]) == 0
    listed = yaml.safe_load(capsys.readouterr().out)["mux"]["inputs"]
    assert [i["name"] for i in listed[-2:]] == ["foxglove", "cmd_vel"]
    assert "--set mux.inputs.6.timeout_s=0.5" in README and listed[6]["name"] == "foxglove"
    for index, shown in enumerate(listed):
        assert main(["check-config", *file, "--set", f"mux.inputs.{index}.timeout_s=0.75",
                     "--set", f"mux.inputs.{index}.priority=199"]) == 0, capsys.readouterr().err
        inputs = yaml.safe_load(capsys.readouterr().out)["mux"]["inputs"]
        assert inputs[index] == {**shown, "timeout_s": 0.75, "priority": 199}
        assert inputs[:index] + inputs[index + 1:] == listed[:index] + listed[index + 1:]
    # the added ones follow their features' settings, wherever those --set are
    assert main(["check-config", *file, "--set", "mux.inputs.7.priority=19",
                 "--set", "foxglove.teleop_timeout_s=0.4"]) == 0
    inputs = yaml.safe_load(capsys.readouterr().out)["mux"]["inputs"]
    assert (inputs[6]["name"], inputs[6]["timeout_s"], inputs[7]["priority"]) == ("foxglove", 0.4, 19)
    # one past the end: the error says which inputs there are and where the added ones come from
    assert main(["check-config", *file, "--set", "mux.inputs.8.timeout_s=0.5"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("racecar-hw check-config: mux.inputs.8.timeout_s: no mux input 8; the mux "
                          "has 8 inputs: 0 safety, 1 teleop, 2 nav_0, 3 nav_1, 4 nav_2, 5 nav_3, "
                          "6 foxglove, 7 cmd_vel"), err
    assert "foxglove.teleop" in err and "zenoh.cmd_vel" in err
    # without the features, there is no input 6
    assert main(["check-config", *file, "--set", "foxglove.enabled=false", "--set",
                 "zenoh.enabled=false", "--set", "dds.enabled=false",
                 "--set", "mux.inputs.6.timeout_s=0.5"]) == 1
    assert "the mux has 6 inputs" in capsys.readouterr().err


def test_every_command_line_in_the_configuration_section_works(capsys) -> None:
    """check-config lines run as written; a run line is checked with the same config and --sets."""
    lines = [line.split("#")[0].strip() for lang, body in code_blocks(README) if lang == "sh"
             for line in body.splitlines() if line.startswith("racecar-hw ")]
    checked = 0
    for line in lines:
        argv = shlex.split(line)[1:]
        if argv[0] == "run":
            config = argv[argv.index("--config") + 1]
            sets = [a for i, a in enumerate(argv) if i and argv[i - 1] == "--set"]
            argv = ["check-config", config, *[x for s in sets for x in ("--set", s)]]
        if argv[0] != "check-config":
            continue
        argv = [str(ROOT / a) if a.startswith("config/") else a for a in argv]
        assert main(argv) == 0, (line, capsys.readouterr().err)
        checked += 1
    assert checked >= 3


def test_scenario_set_examples_load() -> None:
    for scenario, assignment in [("wall", "drivers.0.speed_mps=4")]:
        assert f"--scenario-set {assignment}" in README
        assert load_scenario(scenario, [assignment]).drivers[0].speed_mps == 4


def test_every_command_in_the_table_exists(capsys) -> None:
    table = README.split("## Command line", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"^\| `racecar-hw ([\w-]+(?: (?:info|recover))?)", table, flags=re.M)
    assert {"run", "sim", "follow", "bag info", "bag recover", "check-config"} <= set(commands)
    parser = build_parser()
    for command in commands:
        with pytest.raises(SystemExit) as exc:
            parser.parse_args([*command.split(), "--help"])
        assert exc.value.code == 0, command
    capsys.readouterr()


def _options(command: str) -> set[str]:
    """The long options of a command (``bag info``: a sub-command's), but ``--help``."""
    parser = build_parser()
    for word in command.split():
        parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[word]
    return {o for a in parser._actions for o in a.option_strings if o.startswith("--")} - {"--help"}


def test_the_command_table_names_options_that_exist_and_every_option_of_sim() -> None:
    """A row names only options its command has; the sim row names all of them (it lacked
    --scenario-set and --out, which the README uses and points to)."""
    table = README.split("## Command line", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `racecar-hw ([\w-]+(?: (?:info|recover))?)([^`]*)` \|(.*)$", table, flags=re.M)
    for command, synopsis, _ in rows:
        named = set(re.findall(r"--[a-z][\w-]*", synopsis))
        assert named <= _options(command), (command, named - _options(command))
    sim = next(row for row in rows if row[0] == "sim")
    assert _options("sim") <= set(re.findall(r"--[a-z][\w-]*", sim[1] + sim[2])), \
        _options("sim") - set(re.findall(r"--[a-z][\w-]*", sim[1] + sim[2]))


#: Each test file that may skip, with what the README's list of skip reasons must name for it.
SKIP_REASONS = {
    "conftest.py": "../shared/fixtures/bags",
    "bag_ros1tools.py": "python3-rosbag",
    "live_sim.py": "chromium-driver",
    "netns.py": "unshare -n",
    "rplidar_sdk_peer.py": "pyrplidarsdk",
    "test_dds.py": "cyclonedds",
    "test_dds_ros2.py": "cyclonedds",
    "test_estop_live.py": "eclipse-zenoh",
    "test_layers.py": "import-linter",
    "test_link.py": "Python older than 3.11",
    "test_mavlink_security.py": "IPv6",
    "test_net_flood.py": "open-file limit",
    "test_net_parameters.py": "ros-rcl-interfaces",
    "test_net_rmw.py": "rosidl_adapter",
    "test_net_rosnode.py": "zenoh-ros2-sdk",
    "test_net_zenoh_security.py": "openssl",
    "test_net_zenoh_sim.py": "zenoh-ros2-sdk",
    "test_open_files.py": "open-file limit",
    "test_outbox.py": "an OS other than Linux",
    "test_sim_clock.py": "ros-*-msgs",
    "test_systemd_files.py": "udevadm",
}


def test_the_readme_names_every_reason_a_test_may_skip() -> None:
    """Every file with a skip is known here, and the README names its reason."""
    skipping = sorted(p.name for p in (ROOT / "tests").glob("*.py")
                      if re.search(r"pytest\.skip\(|importorskip\(|mark\.skipif\(", p.read_text())
                      and p.name != "test_readme.py")
    assert skipping == sorted(SKIP_REASONS)
    top = README.split("\n## ", 1)[0]
    for name, words in SKIP_REASONS.items():
        assert words in top, (name, words)
    assert "systemd-analyze" in top and "ros-*-msgs" in top and "selenium" in top


def test_fake_vesc_help_says_the_default_firmware_as_it_is_reported(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["fake-vesc", "--help"])
    assert "(default 6.02)" in capsys.readouterr().out.replace("\n", " ").replace("  ", " ")


def test_pyproject_names_the_package_config_is_installed_as() -> None:
    text = (ROOT / "pyproject.toml").read_text()
    assert "mapped into racecar_hw.shipped" in text and "mapped into racecar_hw.config" not in text
