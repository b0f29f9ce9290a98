"""The OS's name of a Python thread, so that ``top -H``, ``/proc/PID/task/*/comm`` and the
benchmarks' per-thread rows (CPU share, wake-ups) say which thread is which.

Python before 3.14 leaves every thread it starts named after the process (``python``); Linux
keeps up to 15 bytes per thread (``prctl(PR_SET_NAME)``). Elsewhere this does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
import threading

#: prctl's option to name the calling thread (linux/prctl.h)
PR_SET_NAME = 15
#: the longest name Linux keeps, in bytes (without the NUL)
MAX_NAME = 15

_libc: ctypes.CDLL | None = None


def name_this_thread(name: str | None = None) -> None:
    """Give the calling thread ``name`` (default: its Python name) at the OS, cut to 15 bytes."""
    global _libc  # noqa: PLW0603 - loaded once, on first use
    if not sys.platform.startswith("linux"):
        return
    text = (name if name is not None else threading.current_thread().name).encode("utf-8", "replace")
    try:
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        _libc.prctl(PR_SET_NAME, ctypes.c_char_p(text[:MAX_NAME]), 0, 0, 0)
    except (OSError, AttributeError):
        pass
