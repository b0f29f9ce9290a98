"""A lean car: the daemon imports the libraries of the simulator, the Foxglove live view and MAVLink
only when their feature is on, and a feature switched on without its extra says so in one line
naming the pip command (docs/install.md, "Extras")."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import tomllib
from conftest import NO_DDS, reaped, wait_for
from zenoh_util import free_port

from lidar_drivers.scip_fake import FakeHokuyo
from racecar_hw.cli import main
from racecar_hw.runtime.extras import EXTRAS
from vesc.fake import FakeVesc

ROOT = Path(__file__).resolve().parents[1]
#: The top-level modules of the extras, and what pymavlink may pull in.
EXTRA_MODULES = {"matplotlib", "PIL", "pymavlink", "lxml", "foxglove", "cryptography", "mcap", "zstandard"}

#: Runs the command line in this very process, as the console script does, and at its exit (after
#: SIGTERM's orderly shutdown) writes every module the process imported to the file in argv[1].
#: argv[2] lists modules to make absent first (a None in sys.modules: Python then finds no such
#: module, as when it is not installed).
WRAPPER = textwrap.dedent("""
    import json, sys
    out, hidden, argv = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3:]
    sys.modules.update(dict.fromkeys(hidden))
    from racecar_hw.cli import main
    code = main(argv)
    with open(out, "w") as f:
        json.dump(sorted(sys.modules), f)
    sys.exit(code)
""")


def run_car(vesc: FakeVesc, lidar: FakeHokuyo, tmp_path: Path, *sets: str,
            hidden: tuple[str, ...] = ()) -> tuple[set[str], str]:
    """``racecar-hw run --config config/car.yaml`` on the fakes, with the live interfaces on free
    ports, until it drives the fake VESC; then SIGTERM. The modules its process had imported, and
    its log."""
    host, port = lidar.tcp_address
    sets = (f"vesc.port={tmp_path / 'vesc'}", f"lidar.tcp={host}:{port}",
            "foxglove.port=0", "web.port=0", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
            NO_DDS, *sets)  # DDS stays off: its discovery would reach every test's participants
    modules = tmp_path / "modules.json"
    argv = ["run", "--config", str(ROOT / "config" / "car.yaml"), *[x for s in sets for x in ("--set", s)]]
    proc = subprocess.Popen([sys.executable, "-c", WRAPPER, str(modules), json.dumps(hidden), *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        wait_for(lambda: proc.poll() is not None or (lidar.clients > 0 and len(vesc.commands) > 20),
                 timeout=60)
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err[-2000:]
    return set(json.loads(modules.read_text())), err


def top_level(modules: set[str]) -> set[str]:
    return {m.split(".", 1)[0] for m in modules}


def test_the_car_daemon_runs_without_the_sim_and_mavlink_libraries(fakes, tmp_path):
    vesc, lidar = fakes
    modules, _ = run_car(vesc, lidar, tmp_path)
    # the process was the daemon with the car's interfaces (the status page, Zenoh) ...
    assert {"racecar_hw.daemon", "racecar_hw.net.web", "racecar_hw.net.zenoh_bridge", "zenoh",
            "aiohttp"} <= modules
    # ... and neither the simulator, the live view nor the MAVLink link, nor their libraries
    assert not EXTRA_MODULES & top_level(modules), sorted(EXTRA_MODULES & top_level(modules))
    assert not {m for m in modules if m.startswith(("racecar_hw.sim", "racecar_hw.teleop.mavlink_gcs",
                                                    "racecar_hw.net.foxglove_server"))}


def test_mavlink_and_foxglove_switched_on_are_imported_in_the_daemon(fakes, tmp_path):
    """The same measurement sees the imports when the features are on (the check above can fail)."""
    vesc, lidar = fakes
    modules, _ = run_car(vesc, lidar, tmp_path, "mavlink.enabled=true", "mavlink.bind_port=0",
                         "mavlink.gcs_address=127.0.0.1:0", "foxglove.enabled=true")
    assert {"pymavlink", "racecar_hw.teleop.mavlink_gcs", "foxglove",
            "racecar_hw.net.foxglove_server"} <= modules
    # the live view's TLS certificate was made by a child process: cryptography is not kept here
    assert not {"matplotlib", "PIL", "cryptography"} & top_level(modules)


def test_the_live_view_without_its_extra_is_one_warning_and_the_car_drives(fakes, tmp_path):
    """On by default (the car config turns it off): a config that predates the extra still drives."""
    vesc, lidar = fakes
    modules, err = run_car(vesc, lidar, tmp_path, "foxglove.enabled=true", hidden=("foxglove",))
    lines = [line for line in err.splitlines() if "foxglove" in line]
    assert lines == [line for line in lines if "the Foxglove live view needs foxglove-sdk, which the "
                     "foxglove extra installs: pip install 'racecar-hw[foxglove]'; or set "
                     "foxglove.enabled: false" in line] and len(lines) == 1, err[-2000:]
    assert "Traceback" not in err
    assert "racecar_hw.net.foxglove_server" not in modules


def test_every_extra_is_declared_in_pyproject():
    text = (ROOT / "pyproject.toml").read_text()
    declared = tomllib.loads(text)["project"]["optional-dependencies"]

    def dists(name: str) -> set[str]:  # with the extras it names (racecar-hw[foxglove])
        out: set[str] = set()
        for requirement in declared[name]:
            if requirement.startswith("racecar-hw["):
                for other in requirement[len("racecar-hw["):-1].split(","):
                    out |= dists(other)
            else:
                out.add(re.split(r"[<>=;\[ ]", requirement)[0].lower())
        return out

    for name, extra in EXTRAS.items():
        assert dists(name) == {dist.lower() for dist, _ in extra.modules}, name
    dependencies = " ".join(tomllib.loads(text)["project"]["dependencies"]).lower()
    assert not any(dist.lower() in dependencies for e in EXTRAS.values() for dist, _ in e.modules)
    assert "racecar-hw[sim,mavlink]" in declared["test"]


def _hidden(monkeypatch, *modules: str) -> None:
    """Make Python see ``modules`` as not installed (a ``None`` in sys.modules: import raises
    ModuleNotFoundError and ``importlib.util.find_spec`` finds nothing)."""
    for name in modules:
        monkeypatch.setitem(sys.modules, name, None)


def test_mavlink_on_without_its_extra_is_one_line_naming_pip(monkeypatch, capsys):
    _hidden(monkeypatch, "pymavlink")
    code = main(["run", "--no-status", "--set", "vesc.enabled=false", "--set", "lidar.enabled=false",
                 "--set", "gamepad.enabled=false", "--set", "zenoh.enabled=false", "--set", NO_DDS,
                 "--set", "foxglove.port=0", "--set", "web.port=0", "--set", "mavlink.enabled=true"])
    err = capsys.readouterr().err
    assert code == 1
    assert err == ("racecar-hw run: mavlink.enabled: the MAVLink ground-station link needs pymavlink, "
                   "which the mavlink extra installs: pip install 'racecar-hw[mavlink]'\n")


@pytest.mark.parametrize("hidden, named", [
    (("matplotlib",), "matplotlib"), (("PIL",), "Pillow"), (("matplotlib", "PIL"), "matplotlib and Pillow"),
    (("matplotlib", "PIL", "foxglove"), "matplotlib, Pillow and foxglove-sdk")])
def test_sim_without_its_extra_is_one_line_naming_pip(monkeypatch, capsys, tmp_path, hidden, named):
    _hidden(monkeypatch, *hidden)
    code = main(["sim", "--no-status", "--duration", "1", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1
    assert err == (f"racecar-hw sim: the simulator (its maps and plot) needs {named}, which the sim "
                   "extra installs: pip install 'racecar-hw[sim]'\n")
    assert not list(tmp_path.iterdir())  # refused before anything ran
    # the list of scenarios needs no extra
    assert main(["sim", "--list"]) == 0
    assert "figure8" in capsys.readouterr().out


def test_calibrate_sim_without_its_extra_is_one_line_naming_pip(monkeypatch, capsys):
    _hidden(monkeypatch, "matplotlib")
    assert main(["calibrate", "--sim"]) == 1
    assert capsys.readouterr().err == (
        "racecar-hw calibrate: calibrate --sim (the simulator) needs matplotlib, which the sim extra "
        "installs: pip install 'racecar-hw[sim]'\n")


def test_mcap_recording_without_its_extra_is_one_line_naming_pip(monkeypatch, capsys, tmp_path):
    """The recorder (off in the car config) writes MCAP by default; sqlite3 and ROS 1 need no extra."""
    from racecar_hw.bags.writers import McapStorage
    from racecar_hw.runtime.extras import MissingExtra

    _hidden(monkeypatch, "mcap")
    assert main(["check-config", "--set", "recorder.enabled=true"]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.rstrip().endswith(
        "recorder.format: recording MCAP bags (or format: sqlite3 or ros1) needs mcap, which the mcap "
        "extra installs: pip install 'racecar-hw[mcap]'"), err
    assert main(["check-config", "--set", "recorder.enabled=true", "--set", "recorder.format=sqlite3"]) == 0
    assert main(["check-config"]) == 0  # the car config records nothing
    capsys.readouterr()
    # recovering an MCAP bag writes one too: the same line, not a traceback
    with pytest.raises(MissingExtra, match=r"pip install 'racecar-hw\[mcap\]'"):
        McapStorage(tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists()
