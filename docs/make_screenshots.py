"""Make the pictures in docs/: the status page on a phone-sized headless Chromium, and a run's figure.

``python docs/make_screenshots.py`` runs ``racecar-hw sim`` (the ``wall`` scenario at 2 m/s, so the
safety controller is limiting as the car nears the wall) and writes ``docs/status-page.png`` and
``docs/sim-report.png``. It needs Debian's chromium and chromium-driver (as the browser tests do).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DOCS = Path(__file__).resolve().parent
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"


def _browser():  # noqa: ANN202
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=412,1330",
                "--hide-scrollbars", "--disable-background-networking", "--no-first-run"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "racecar_hw.cli", "-v", "sim", "--no-status", "--scenario", "wall",
                   "--scenario-set", "drivers.0.speed_mps=2.0", "--set", "web.port=0",
                   "--set", "foxglove.enabled=false", "--out", tmp]
        log_path = Path(tmp) / "sim.log"
        with log_path.open("w") as log:
            proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=log, text=True)
            try:
                port = None
                deadline = time.monotonic() + 30
                while port is None and time.monotonic() < deadline:
                    match = re.search(r"web: status page on http://[^:]+:(\d+)/", log_path.read_text())
                    port = int(match.group(1)) if match else None
                    time.sleep(0.1)
                if port is None:
                    raise RuntimeError("the sim did not start its status page")
                driver = _browser()
                try:
                    driver.get(f"http://127.0.0.1:{port}/")
                    while "limiting" not in driver.find_element("id", "safety").text:
                        if time.monotonic() > deadline + 30:
                            raise RuntimeError("the safety controller never limited")
                        time.sleep(0.05)
                    driver.save_screenshot(str(DOCS / "status-page.png"))
                finally:
                    driver.quit()
                proc.wait(60)
            finally:
                if proc.poll() is None:
                    proc.terminate()
        shutil.copy(Path(tmp) / "wall.png", DOCS / "sim-report.png")
    print(DOCS / "status-page.png", DOCS / "sim-report.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
