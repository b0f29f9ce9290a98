"""``racecar-hw sim`` in a subprocess for the live-view tests, with its log read as it comes; and a
headless Chromium for the browser tests."""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


class SimProcess:
    """Runs ``racecar-hw -v sim ARGS``; every stderr line is kept with the time it was read."""

    def __init__(self, args: Sequence[str], timeout_s: float = 60.0, **popen: Any) -> None:
        # the Zenoh bridge (on by default, on a fixed port) is not what these tests are about
        command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--no-status", "--no-plot",
                   "--set", "zenoh.enabled=false", "--set", "dds.enabled=false", *args]
        # ``popen``: more for subprocess.Popen (a preexec_fn that lowers the file limit)
        self.proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                     **popen)
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.timeout_s = timeout_s

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def wait_for(self, pattern: str, timeout_s: float | None = None, start: int = 0) -> re.Match[str]:
        """The first log line from index ``start`` on that matches ``pattern``; fails after the timeout."""
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        regex = re.compile(pattern)
        seen = start
        with self._cond:
            while True:
                for line in self.lines[seen:]:
                    match = regex.search(line)
                    if match:
                        return match
                seen = len(self.lines)
                left = deadline - time.monotonic()
                if left <= 0 or (self.proc.poll() is not None and not self._reader.is_alive()):
                    tail = "\n".join(self.lines[-40:])
                    raise AssertionError(f"no log line matching {pattern!r} in time; log tail:\n{tail}")
                self._cond.wait(min(left, 0.2))

    def port(self, what: str) -> int:
        """The port ``foxglove`` or ``web`` listens on, from the start-up log."""
        pattern = {"foxglove": r"foxglove: live view on ws://[^:]+:(\d+)",
                   "web": r"web: status page on http://[^:]+:(\d+)/"}[what]
        return int(self.wait_for(pattern).group(1))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._reader.join(5)



@contextmanager
def running_sim(args: Sequence[str]) -> Iterator[SimProcess]:
    """A sim started with ``args`` once the daemon runs; stopped at the end."""
    proc = SimProcess(args)
    try:
        proc.wait_for("racecar-hw running")
        yield proc
    finally:
        proc.stop()


def chromium(*extra_args: str, window: str = "412,915") -> Any:
    """Debian's headless Chromium through selenium and chromedriver (no browser download); skips the
    test with the reason where they are not installed. ``extra_args`` go on its command line."""
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip(f"Debian chromium and chromium-driver are not installed ({CHROMIUM}, {CHROMEDRIVER}); "
                    ".ci/run installs them as root")
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={window}", "--disable-background-networking", "--disable-component-update",
                "--disable-sync", "--disable-default-apps", "--disable-extensions", "--no-first-run",
                "--metrics-recording-only", "--disable-client-side-phishing-detection", *extra_args):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
