"""Python callbacks from threads Python did not start (Zenoh's receiving threads), made cheap.

A library's own thread that calls into Python takes the GIL with ``PyGILState_Ensure`` and gives it
back with ``PyGILState_Release``. When that thread has no Python thread state, Ensure creates one and
the matching Release destroys it again, so every callback pays for building and tearing down a
thread state: about 20 us on this project's 2-core machine, measured as 55-63 us against 36-38 us of
CPU per sample for a Zenoh subscriber at 10,000 samples a second (docs/benchmarks.md, "The far
side"). :func:`hold_thread_state`, called at the top of such a callback, takes one more Ensure that
is never released. The C API asks for every Ensure to be matched by a Release; this one is left
unmatched on purpose, for the thread's lifetime: CPython deletes a thread state when its count
drops to zero, so the state stays, and later callbacks only take and give back the GIL. The count
does not hold the GIL.

In a thread Python started the extra count changes nothing: Python deletes a thread's state when
the thread ends, whatever its count. Written here with :mod:`ctypes` because no library exposes it.
"""

from __future__ import annotations

import ctypes
import threading

_held = threading.local()
_ensure = ctypes.pythonapi.PyGILState_Ensure


def hold_thread_state() -> None:
    """Keep the calling thread's Python thread state between callbacks (once per thread; cheap after)."""
    if not getattr(_held, "on", False):
        _ensure()
        _held.on = True
