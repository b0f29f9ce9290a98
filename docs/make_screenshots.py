"""Make the pictures in docs/: the status page, a run's figure, and the Foxglove layout in Lichtblick.

``python docs/make_screenshots.py`` runs ``racecar-hw sim`` (the ``wall`` scenario at 2 m/s, so the
safety controller is limiting as the car nears the wall) and writes ``docs/status-page.png`` (the page
on a phone-sized headless Chromium) and ``docs/sim-report.png``.

``python docs/make_screenshots.py --lichtblick DIR`` also writes ``docs/lichtblick-view.png``: the
Lichtblick web app built in ``DIR`` (its ``web/.webpack`` folder), served from this machine with the
shipped layout ``config/foxglove/racecar-lichtblick.json`` as its default layout, connected to the
``wall`` scenario at 2 m/s (the car starts driving 20 s in, once Lichtblick has loaded), captured
3.3 s later, as the wall enters the swept band. Lichtblick is not published built: build its web
app from its source (github.com/lichtblick-suite/lichtblick) with Node 20 or newer::

    export COREPACK_ENABLE_DOWNLOAD_PROMPT=0 ELECTRON_SKIP_BINARY_DOWNLOAD=1
    export PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1
    corepack yarn install
    corepack yarn web:build:prod        # writes web/.webpack

(Behind a partial npm mirror, as on the development machine: ``COREPACK_NPM_REGISTRY`` and
``YARN_NPM_REGISTRY_SERVER`` pointed at it, and ``resolutions`` in ``package.json`` for the few
versions it lacked: ``@lichtblick/tsconfig`` 1.0.0 with ``"ignoreDeprecations": "6.0"`` added to its
``base.json``, ``@lichtblick/rosbag2`` and ``rosbag2-web`` 1.0.0, ``@lichtblick/eslint-plugin``
1.0.4, ``flatbuffers_reflection`` 0.0.7.) Neither node_modules nor the build belong in this
repository.

Everything needs Debian's chromium and chromium-driver (as the browser tests do); the 3D panel draws
with WebGL on SwiftShader.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parent
LAYOUT = DOCS.parent / "config" / "foxglove" / "racecar-lichtblick.json"
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
#: Where Lichtblick's index.html takes a default layout (its Dockerfile fills it the same way).
LAYOUT_PLACEHOLDER = "/*LICHTBLICK_SUITE_DEFAULT_LAYOUT_PLACEHOLDER*/"
#: Seconds of driving at 2 m/s before the Lichtblick picture (the wall enters the swept band).
DRIVE_S = 3.3


def _browser(window: str, *extra: str) -> Any:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", f"--window-size={window}", "--hide-scrollbars",
                "--disable-background-networking", "--no-first-run", *extra):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


class _Sim:
    """``racecar-hw -v sim ARGS`` with its log in a file; :meth:`wait_for` reads it."""

    def __init__(self, args: list[str], out: Path) -> None:
        command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--no-status",
                   "--set", "zenoh.enabled=false", *args, "--out", str(out)]
        self.log_path = out / "sim.log"
        self._log = self.log_path.open("w")
        self.proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=self._log, text=True)

    def wait_for(self, pattern: str, timeout_s: float = 60.0) -> re.Match[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            match = re.search(pattern, self.log_path.read_text())
            if match:
                return match
            if self.proc.poll() is not None:
                break
            time.sleep(0.1)
        raise RuntimeError(f"the sim did not log {pattern!r}; see {self.log_path}")

    def stop(self, wait: bool = False) -> None:
        if wait:
            self.proc.wait(120)
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(30)
        self._log.close()


def status_page_and_report() -> None:
    """docs/status-page.png and docs/sim-report.png from one ``wall`` run at 2 m/s."""
    with tempfile.TemporaryDirectory() as tmp:
        sim = _Sim(["--scenario", "wall", "--scenario-set", "drivers.0.speed_mps=2.0",
                    "--set", "web.port=0", "--set", "foxglove.enabled=false"], Path(tmp))
        try:
            port = int(sim.wait_for(r"web: status page on http://[^:]+:(\d+)/", 30).group(1))
            driver = _browser("412,1330", "--disable-gpu")
            try:
                driver.get(f"http://127.0.0.1:{port}/")
                deadline = time.monotonic() + 60
                while "limiting" not in driver.find_element("id", "safety").text:
                    if time.monotonic() > deadline:
                        raise RuntimeError("the safety controller never limited")
                    time.sleep(0.05)
                driver.save_screenshot(str(DOCS / "status-page.png"))
            finally:
                driver.quit()
        finally:
            sim.stop(wait=True)
        shutil.copy(Path(tmp) / "wall.png", DOCS / "sim-report.png")
    print(DOCS / "status-page.png", DOCS / "sim-report.png")


def _serve_lichtblick(web_dir: Path) -> http.server.ThreadingHTTPServer:
    """Lichtblick's files on a free loopback port, index.html with the shipped layout as the default."""
    index = (web_dir / "index.html").read_text()
    if LAYOUT_PLACEHOLDER not in index:
        raise RuntimeError(f"{web_dir / 'index.html'} has no {LAYOUT_PLACEHOLDER}: "
                           "not a Lichtblick web build?")
    page = index.replace(LAYOUT_PLACEHOLDER, LAYOUT.read_text()).encode()

    class Files(http.server.SimpleHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the http.server name
            if self.path.split("?")[0] in ("/", "/index.html"):
                self.send_response(200)
                self.send_header("Content-Type", "text/html")
                self.send_header("Content-Length", str(len(page)))
                self.end_headers()
                self.wfile.write(page)
            else:
                super().do_GET()

        def log_message(self, *args: object) -> None:
            pass

    files = functools.partial(Files, directory=str(web_dir))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), files)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def lichtblick_view(web_dir: Path) -> None:
    """docs/lichtblick-view.png: Lichtblick with the shipped layout, live on a ``wall`` run."""
    server = _serve_lichtblick(web_dir)
    with tempfile.TemporaryDirectory() as tmp:
        sim = _Sim(["--scenario", "wall", "--duration", "60", "--scenario-set", "drivers.0.speed_mps=2.0",
                    "--scenario-set", "drivers.0.from_s=20", "--set", "web.enabled=false",
                    "--set", "foxglove.port=0"], Path(tmp))
        try:
            port = int(sim.wait_for(r"foxglove: live view on ws://[^:]+:(\d+)", 30).group(1))
            driver = _browser("1600,1000", "--use-angle=swiftshader", "--enable-unsafe-swiftshader")
            try:
                driver.get(f"http://127.0.0.1:{server.server_port}/?ds=foxglove-websocket"
                           f"&ds.url=ws://127.0.0.1:{port}/")
                # the car starts 20 s in, and needs about 4 s to the wall: 3.3 s in, the wall is at the
                # end of its swept band and the safety controller begins to limit
                sim.wait_for(r"mux source idle -> nav_0", 120)
                started = time.monotonic()
                for close in driver.find_elements("css selector", "[data-testid=sidebar-close-left]"):
                    close.click()  # the empty settings sidebar
                time.sleep(max(0.0, started + DRIVE_S - time.monotonic()))
                driver.save_screenshot(str(DOCS / "lichtblick-view.png"))
            finally:
                driver.quit()
        finally:
            sim.stop()
            server.shutdown()
    print(DOCS / "lichtblick-view.png")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--lichtblick", type=Path, metavar="DIR",
                        help="a Lichtblick web build (its web/.webpack): also make docs/lichtblick-view.png")
    parser.add_argument("--only-lichtblick", action="store_true", help="make only docs/lichtblick-view.png")
    args = parser.parse_args()
    if args.only_lichtblick and args.lichtblick is None:
        parser.error("--only-lichtblick needs --lichtblick DIR")
    if not args.only_lichtblick:
        status_page_and_report()
    if args.lichtblick is not None:
        lichtblick_view(args.lichtblick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
