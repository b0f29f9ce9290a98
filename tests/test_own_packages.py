"""A foreign ``safety`` (or ``vesc``, ``mux``, ``lidar_drivers``) package stops every command at start.

The foreign package is a real distribution: a wheel built here and installed by pip into a
throwaway virtual environment that also sees this racecar-hw install, the way PyPI's ``safety``
ends up beside ours.
"""

from __future__ import annotations

import base64
import hashlib
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from racecar_hw.runtime.own_packages import OWN_PACKAGES, ForeignPackage, find_foreign_packages


def _wheel(tmp: Path, dist: str, version: str, files: dict[str, str]) -> Path:
    """A minimal but complete wheel (METADATA, WHEEL, RECORD) that pip installs as it is."""
    info = f"{dist}-{version}.dist-info"
    content = dict(files)
    content[f"{info}/METADATA"] = f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n"
    content[f"{info}/WHEEL"] = ("Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\n"
                                "Tag: py3-none-any\n")
    record = []
    for name, text in content.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(text.encode())}")
    record.append(f"{info}/RECORD,,")
    content[f"{info}/RECORD"] = "\n".join(record) + "\n"
    path = tmp / f"{dist}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as zf:
        for name, text in content.items():
            zf.writestr(name, text)
    return path


@pytest.fixture
def venv_with_foreign_safety(tmp_path):
    """A new venv that sees this environment's packages, with a foreign ``safety`` installed by pip."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    ours = sysconfig.get_paths()["purelib"]
    # Our environment's packages come after the new venv's own (addsitedir also runs its .pth files,
    # which is how an editable install of racecar-hw is found).
    (Path(site) / "zz_racecar_hw_env.pth").write_text(f"import site; site.addsitedir({ours!r})\n")
    executed = tmp_path / "foreign-code-ran"
    wheel = _wheel(tmp_path, "safety", "9.9.9", {
        "safety/__init__.py": f"open({str(executed)!r}, 'w').write('ran')\n",
        "safety/cli.py": "",
    })
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
                    "--no-index", str(wheel)], check=True, capture_output=True)
    return python, Path(site), executed


def test_all_our_packages_are_ours_here():
    assert find_foreign_packages() == []


def test_sim_refuses_a_foreign_safety_package_and_names_it(venv_with_foreign_safety, tmp_path):
    python, site, executed = venv_with_foreign_safety
    proc = subprocess.run([str(python), "-m", "racecar_hw.cli", "sim", "--duration", "1",
                           "--report", str(tmp_path / "report.json")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr
    assert "'safety' is not racecar-hw's" in err
    assert str(site / "safety" / "__init__.py") in err
    assert "safety 9.9.9" in err and "pip uninstall safety" in err
    assert "Traceback" not in err
    # Refused before anything ran: no foreign code executed, no sim started, no report written.
    assert not executed.exists()
    assert not (tmp_path / "report.json").exists()
    assert proc.stdout == ""


@pytest.mark.parametrize("command", [["--version"], ["check-config"], ["vesc-info", "--port", "/dev/null"]])
def test_every_command_checks_first(venv_with_foreign_safety, tmp_path, command):
    python, _, executed = venv_with_foreign_safety
    proc = subprocess.run([str(python), "-m", "racecar_hw.cli", *command],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2
    assert "'safety' is not racecar-hw's" in proc.stderr
    assert not executed.exists()


def test_a_missing_package_is_named(monkeypatch):
    found = find_foreign_packages(("no_such_package_of_ours",))
    assert len(found) == 1 and found[0].found is None
    assert "no_such_package_of_ours' is missing" in found[0].message()
    assert "pip install --force-reinstall" in found[0].message()


def test_a_package_overwritten_in_place_is_caught(tmp_path):
    """Same place, other bytes: the RECORD hash of an installed (not editable) racecar-hw differs."""
    from racecar_hw.runtime import own_packages

    init = tmp_path / "__init__.py"
    init.write_text("ours\n")
    digest = base64.urlsafe_b64encode(hashlib.sha256(b"ours\n").digest()).rstrip(b"=").decode()
    assert own_packages._hash_matches(init, f"sha256={digest}")
    init.write_text("theirs\n")
    assert not own_packages._hash_matches(init, f"sha256={digest}")
    assert own_packages._hash_matches(init, None)  # editable installs record no hash
    text = ForeignPackage("safety", init.resolve(), init, "safety 3.8.1").message()
    assert f"{init.resolve()} (installed by the distribution safety 3.8.1) was overwritten" in text
    assert "pip uninstall safety, then pip install --force-reinstall --no-deps racecar-hw" in text


def test_the_message_without_an_owner_says_what_to_do():
    pkg = ForeignPackage("mux", Path("/elsewhere/mux/__init__.py"), Path("/ours/mux/__init__.py"), None)
    text = pkg.message()
    assert "/elsewhere/mux/__init__.py" in text and "/ours/mux/__init__.py" in text
    assert "virtual environment of its own" in text


def test_the_guarded_names_are_the_design_cards():
    assert set(OWN_PACKAGES) == {"vesc", "lidar_drivers", "mux", "safety"}


def test_an_installed_wheels_record_is_read_beside_the_packages(tmp_path):
    """A wheel install keeps ``racecar_hw-<version>.dist-info/RECORD`` next to the packages; its hash
    of ``safety/__init__.py`` is what an overwrite is checked against."""
    from racecar_hw.runtime import own_packages

    (tmp_path / "safety").mkdir()
    init = tmp_path / "safety" / "__init__.py"
    init.write_text("ours\n")
    digest = base64.urlsafe_b64encode(hashlib.sha256(b"ours\n").digest()).rstrip(b"=").decode()
    info = tmp_path / "racecar_hw-0.1.0.dist-info"
    info.mkdir()
    (info / "RECORD").write_text(f"safety/__init__.py,sha256={digest},5\n"
                                 "racecar_hw-0.1.0.dist-info/RECORD,,\n")
    recorded = own_packages._recorded_hashes(tmp_path)
    assert recorded == {"safety/__init__.py": f"sha256={digest}"}
    assert own_packages._hash_matches(init, recorded["safety/__init__.py"])
    init.write_text("theirs\n")
    assert not own_packages._hash_matches(init, recorded["safety/__init__.py"])
    # two racecar-hw installs in one place: which RECORD is ours is unknown, the location check stays
    (tmp_path / "racecar_hw-0.0.9.dist-info").mkdir()
    (tmp_path / "racecar_hw-0.0.9.dist-info" / "RECORD").write_text("safety/__init__.py,sha256=x,1\n")
    assert own_packages._recorded_hashes(tmp_path) == {}
    assert own_packages._recorded_hashes(tmp_path / "nowhere") == {}


def test_the_check_itself_does_not_load_the_metadata_machinery():
    """Every command runs the check first; importlib.metadata (about 50 ms) loads only to name the
    owner of a foreign package."""
    code = ("import sys; from racecar_hw.runtime.own_packages import find_foreign_packages; "
            "assert find_foreign_packages() == []; print('importlib.metadata' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          check=True)
    assert proc.stdout.strip() == "False"
