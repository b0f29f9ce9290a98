"""The gamepad's e-stop buttons: B latches the mux e-stop, B and START held together release it.

The release needs the combination held for ``hold_s`` seconds (monotonic ns from ``clock``) with
the speed stick centred; it fires once per hold. What a latch and a release do is the caller's
(the daemon latches and releases the mux e-stop as the gamepad operator).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from racecar_hw.base.clock import NS_PER_S

if TYPE_CHECKING:
    from racecar_hw.teleop.gamepad import PadFrame

log = logging.getLogger(__name__)


class EstopButtons:
    """Watches the pad's frames for the e-stop button and the release combination."""

    def __init__(self, hold_s: float, clock: Callable[[], int],
                 on_estop: Callable[[], object] | None = None,
                 on_release: Callable[[], object] | None = None) -> None:
        self._hold_ns = int(hold_s * NS_PER_S)
        self._clock = clock
        #: called when B is pressed
        self.on_estop = on_estop
        #: called once when B and START have been held together for ``hold_s``
        self.on_release = on_release
        #: since when (monotonic ns) B and START are held together; None: not both
        self._combo_since: int | None = None
        self._combo_done = False

    def frame(self, estop: int, arm: int, frame: PadFrame) -> None:
        """B (button code ``estop``; negative: the pad has none) latches the e-stop; B and START
        (``arm``) held together start the release combination's clock."""
        if estop < 0:
            return
        if estop in frame.pressed and self.on_estop is not None:
            self.on_estop()
        if estop in frame.buttons and arm in frame.buttons:
            if self._combo_since is None:
                self._combo_since = self._clock()
                self._combo_done = False
        else:
            self._combo_since = None

    def check_release(self, speed_centred: bool) -> None:
        """Release once the combination has been held long enough (with the speed stick centred)."""
        since = self._combo_since
        if since is None or self._combo_done:
            return
        if self._clock() - since < self._hold_ns:
            return
        self._combo_done = True
        if not speed_centred:
            log.warning("gamepad: e-stop release refused: centre the speed stick first")
        elif self.on_release is not None:
            self.on_release()


__all__ = ["EstopButtons"]
