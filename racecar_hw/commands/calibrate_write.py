"""``racecar-hw calibrate --write``: the measured values into a config file, checked before it is
replaced.

The procedure measures the car as it is: ERPM per m/s of driving (a magnitude, as
``speed_to_erpm_gain`` is: ``invert_motor`` gives the direction) and servo position per radian of
left turn with its physical sign (the servo positions actually sent against the turns measured).
``invert_servo`` negates the configured steering gains, so where the file sets it the measured
ones are written negated. The file's ``vesc:`` block is edited line by line, keeping comments and the block's
indentation; a right-turn gain left from an earlier calibration is set to null when both sides now
turn alike. The edited text must load as a valid config whose conversion gives back the measured
gains and offset; otherwise nothing is written and the reason names ``--write`` (a flow-style
``vesc: {...}`` block, for one, is left for a person to edit).

:func:`check_writable` runs before the car moves: a read-only file (no write permission bit, or none
for us) is refused, not replaced (renaming a new file over it needs only the directory's
permission), and so is a file whose scratch files (the loading check's beside it, the replacement's
beside the file a symlink points at) cannot be created. An OS error in :func:`write` itself is a
ConfigError too: one line, the file untouched.
"""

from __future__ import annotations

import contextlib
import difflib
import math
import os
import re
import stat
from pathlib import Path

from racecar_hw.base.errors import ConfigError
from racecar_hw.config import Config, load_config
from vesc.ackermann import AckermannConversion
from vesc.params import VescParams

#: Written keys whose value the file's ``invert_servo`` negates.
_SERVO_KEYS = ("steering_angle_to_servo_gain", "steering_angle_to_servo_gain_right")
RIGHT_GAIN = "steering_angle_to_servo_gain_right"


def configured(measured: dict[str, float | None], vesc: VescParams) -> dict[str, float | None]:
    """The values to configure for the ``measured`` ones under ``vesc``'s ``invert_servo``."""
    out = dict(measured)
    for key in _SERVO_KEYS:
        value = out.get(key)
        if vesc.invert_servo and value is not None:
            out[key] = -value
    return out


def write(path: Path, measured: dict[str, float | None]) -> dict[str, float | None]:
    """Put the ``measured`` values into the config at ``path`` as :func:`configured` says, print the
    diff and return what was written; ConfigError naming ``--write`` (file untouched) when the result
    would not be a valid config stating the measurement, or reading or writing it failed."""
    try:
        before = path.read_text()
        values = configured(measured, _load(path, before, "as it is").vesc)
        after = edited(before, values)
        vesc = _load(path, after, "after the edit").vesc
        if configured(measured, vesc) != values:  # the edit changed a flag's meaning: never silently
            raise ConfigError("--write", f"{path}: the edit would change invert_servo; "
                                         "nothing written: put the snippet above in by hand")
        _check(path, vesc, measured)
        _replace(path, after)
    except OSError as err:  # after the drive: one line, the values are on the screen above
        raise ConfigError("--write", f"{path}: {_why(err)}; nothing written: put the snippet above "
                                     "in by hand") from None
    diff = difflib.unified_diff(before.splitlines(keepends=True), after.splitlines(keepends=True),
                                str(path), str(path))
    print(f"\nwritten to {path}:\n" + "".join(diff), end="")
    return values


def check_writable(path: Path) -> None:
    """ConfigError naming ``--write`` and ``path`` unless :func:`write` could replace the file: it
    has a write permission bit and we may write it (the bits are read as well as ``os.access`` asked:
    root may write anything, and a 0444 config is meant to stay as it is), and its scratch files
    can be created (a real open, whatever the reason it fails: permissions, a read-only mount)."""
    try:
        real = path.resolve()
        mode = os.stat(real).st_mode
    except OSError as err:
        raise ConfigError("--write", f"{path}: {_why(err)}") from None
    if not mode & 0o222 or not os.access(real, os.W_OK):
        raise ConfigError("--write", f"{path}: read-only ({stat.filemode(mode)}, no write permission "
                                     "for us): make it writable first, or leave out --write")
    for scratch in _scratch(path):
        try:
            fd = os.open(scratch, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        except OSError as err:
            raise ConfigError("--write", f"{path}: cannot create {scratch} ({err.strerror}): the file is "
                                         "replaced through a new file beside it") from None
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(scratch)


def _scratch(path: Path) -> tuple[Path, Path]:
    """The loading check's file (beside ``path``) and the replacement's (beside the file it names)."""
    real = path.resolve()
    return path.with_name(f".{path.name}.calibrate-check"), real.with_name(f".{real.name}.calibrate")


def _why(err: OSError) -> str:
    return f"{err.strerror or err} ({err.filename})" if err.filename else str(err.strerror or err)


def _replace(path: Path, text: str) -> None:
    """Replace the file ``path`` names (through a symlink: the file it points at) with ``text`` at
    once, keeping its mode and, where allowed, its owner: a config the service's user can read
    stays readable (a plain rewrite under a tight umask made it 0600 root's, and replaced a
    symlink with a copy)."""
    real = path.resolve()
    tmp = _scratch(path)[1]
    st = os.stat(real)
    try:
        with open(tmp, "w", encoding="utf-8") as out:
            out.write(text)
            out.flush()
            os.fsync(out.fileno())
        os.chmod(tmp, st.st_mode & 0o7777)
        with contextlib.suppress(PermissionError):
            os.chown(tmp, st.st_uid, st.st_gid)
        os.replace(tmp, real)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def edited(text: str, values: dict[str, float | None]) -> str:
    """``text`` with each of ``values`` set under its block-style ``vesc:`` key (a new key at the
    block's indentation; a None value sets an existing key to null and adds none)."""
    lines = text.splitlines(keepends=True)
    start = next((i for i, line in enumerate(lines) if re.match(r"^vesc:\s*(#.*)?$", line)), None)
    if start is None:
        lines += (["\n"] if lines and not lines[-1].endswith("\n") else []) + ["vesc:\n"]
        start = len(lines) - 1
    end = next((i for i in range(start + 1, len(lines)) if re.match(r"^\S", lines[i])), len(lines))
    while end > start + 1 and not lines[end - 1].strip():  # new keys go after the block's last line
        end -= 1
    indent = next((m.group(1) for line in lines[start + 1:end]
                   if (m := re.match(r"^(\s+)[^\s#]", line))), "  ")
    for key, value in values.items():
        shown = "null" if value is None else repr(value)
        pattern = re.compile(rf"^(\s+){re.escape(key)}:\s*[^#\n]*(#.*)?$")
        for i in range(start + 1, end):
            m = pattern.match(lines[i].rstrip("\n"))
            if m and m.group(1) == indent:
                comment = f"  {m.group(2)}" if m.group(2) else ""
                lines[i] = f"{indent}{key}: {shown}{comment}\n"
                break
        else:
            if value is not None:
                lines.insert(end, f"{indent}{key}: {shown}  # racecar-hw calibrate\n")
                end += 1
    return "".join(lines)


def _load(path: Path, text: str, when: str) -> Config:
    """``text`` loaded as the config file at ``path`` would be (beside it, for relative paths)."""
    tmp = _scratch(path)[0]
    try:
        tmp.write_text(text)
        return load_config(tmp)
    except ConfigError as err:
        raise ConfigError("--write", f"{path}: {when} it would not load ({err}); nothing "
                                     "written: put the snippet above in by hand") from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _check(path: Path, vesc: VescParams, measured: dict[str, float | None]) -> None:
    """The written config's conversion gives back the measured gains and offset."""
    conv = AckermannConversion.from_params(vesc)
    left = measured.get("steering_angle_to_servo_gain")
    right = measured.get(RIGHT_GAIN) or left
    wants = (("speed_to_erpm_gain", conv.speed_to_erpm_gain, measured.get("speed_to_erpm_gain")),
             ("steering_angle_to_servo_offset", conv.steering_angle_to_servo_offset,
              measured.get("steering_angle_to_servo_offset")),
             ("steering_angle_to_servo_gain", conv.servo_gain, left),
             (RIGHT_GAIN, conv.servo_gain_right, right))
    for key, got, want in wants:
        if want is not None and not math.isclose(got, want, rel_tol=1e-9, abs_tol=1e-9):
            raise ConfigError("--write", f"{path}: vesc.{key} would mean {got} where {want} was measured; "
                                         "nothing written: put the snippet above in by hand")
