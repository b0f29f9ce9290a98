"""The status page: who may open it (token, Origin, Host), and the page itself in a real browser.

``racecar-hw sim`` runs in a subprocess. The access tests bind the page (and the Foxglove relay) to
every interface without a configured token, so the daemon generates one and prints it; requests are
made with aiohttp. The browser test drives the page in Debian's headless Chromium through selenium
and chromedriver (no browser download), clicks E-STOP and reads from the sim's log when the fake VESC
read the brake, and that it was the first motor command written after the request.
"""

from __future__ import annotations

import asyncio
import json
import re
import time

import aiohttp
import pytest
from live_sim import SimProcess, chromium, running_sim
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus


@pytest.fixture(scope="module")
def open_sim(tmp_path_factory):
    """A sim whose page and Foxglove relay listen on every interface, behind tokens."""
    with running_sim(["--scenario", "figure8", "--scenario-set", "drivers=[]", "--duration", "300",
                      "--set", "web.host=0.0.0.0", "--set", "web.port=0",
                      "--set", "foxglove.host=0.0.0.0", "--set", "foxglove.port=0",
                      "--set", "foxglove.token=fox-secret",
                      "--out", str(tmp_path_factory.mktemp("sim"))]) as proc:
        yield proc


def test_without_the_token_the_page_the_websocket_and_the_estop_get_401(open_sim):
    printed = open_sim.wait_for(r"racecar-hw: status page http://0\.0\.0\.0:(\d+)/\?token=(\S+) ")
    port, token = int(printed.group(1)), printed.group(2)
    base = f"http://127.0.0.1:{port}"

    async def main() -> None:
        async with aiohttp.ClientSession() as http:
            for url in (f"{base}/", f"{base}/?token=wrong", f"{base}/api/state"):
                async with http.get(url) as res:
                    assert res.status == 401, url
            for path in ("/api/estop", "/api/release"):
                async with http.post(base + path, json={}) as res:
                    assert res.status == 401
                async with http.post(base + path, json={}, headers={"Authorization": "Bearer nope"}) as res:
                    assert res.status == 401
            with pytest.raises(aiohttp.WSServerHandshakeError) as err:
                await http.ws_connect(f"{base}/ws")
            assert err.value.status == 401
            # none of that touched the car
            async with http.get(f"{base}/api/state?token={token}") as res:
                assert res.status == 200 and (await res.json())["mux"]["state"] == "running"
            async with http.get(f"{base}/?token={token}") as res:
                assert res.status == 200 and "E-STOP" in await res.text()
            # a page from another site cannot use the token it does not have, nor a browser's
            ws_url = f"ws://127.0.0.1:{port}/ws?token={token}"
            with pytest.raises(aiohttp.WSServerHandshakeError) as err:
                await http.ws_connect(ws_url, origin="http://evil.example")
            assert err.value.status == 403
            async with http.post(f"{base}/api/estop", json={}, headers={
                    "Authorization": f"Bearer {token}", "Origin": "http://evil.example"}) as res:
                assert res.status == 403
            # with the token, from the page's own origin: the state comes, the e-stop latches
            ws = await http.ws_connect(ws_url, origin=f"http://127.0.0.1:{port}")
            hello = json.loads((await ws.receive(timeout=10)).data)
            assert hello["op"] == "hello" and len(hello["shape"]["body"]) == 4
            deadline = time.monotonic() + 20
            while True:  # pushed about every 0.1 s; the lidar's rate once two scans are in
                state = json.loads((await ws.receive(timeout=10)).data)
                assert state["op"] == "state"
                if state["links"]["lidar"]["rate_hz"] and state["scan"]:
                    break
                assert time.monotonic() < deadline, state
            assert len(state["band"]) > 4 and state["mux"]["state"] == "running"
            await ws.close()
            auth = {"Authorization": f"Bearer {token}"}
            async with http.post(f"{base}/api/estop", json={}, headers=auth) as res:
                assert res.status == 200 and (await res.json())["state"]["mux"]["state"] == "estop"
            async with http.post(f"{base}/api/release", json={}, headers=auth) as res:
                assert res.status == 200 and (await res.json())["state"]["mux"]["state"] == "running"

    asyncio.run(main())


def test_the_foxglove_relay_wants_its_token(open_sim):
    port = open_sim.port("foxglove")

    async def main() -> None:
        with pytest.raises(InvalidStatus) as err:
            await connect(f"ws://127.0.0.1:{port}/", subprotocols=["foxglove.sdk.v1"])
        assert err.value.response.status_code == 401
        with pytest.raises(InvalidStatus):
            await connect(f"ws://127.0.0.1:{port}/?token=fox-secre", subprotocols=["foxglove.sdk.v1"])
        ws = await connect(f"ws://127.0.0.1:{port}/?token=fox-secret", subprotocols=["foxglove.sdk.v1"],
                           max_size=None)
        assert ws.subprotocol == "foxglove.sdk.v1"
        info = json.loads(await asyncio.wait_for(ws.recv(), 10))
        assert info["op"] == "serverInfo" and "services" in info["capabilities"]
        await ws.close()

    asyncio.run(main())


def test_refused_requests_are_summarised_in_the_log_not_logged_one_by_one(open_sim):
    printed = open_sim.wait_for(r"racecar-hw: status page http://0\.0\.0\.0:(\d+)/\?token=(\S+) ")
    base = f"http://127.0.0.1:{printed.group(1)}"
    start = len(open_sim.lines)

    async def main() -> float:
        began = time.monotonic()
        async with aiohttp.ClientSession() as http:
            for _ in range(2000):
                async with http.get(f"{base}/api/state") as res:
                    # and the connection closes: a refused client keeps no connection slot
                    assert res.status == 401 and res.headers.get("Connection", "").lower() == "close"
        return time.monotonic() - began

    elapsed = asyncio.run(main())
    # a line for the first of its kind, then one summary per 10 s (Refusals' interval) with the count
    # (the count since the last line: test_net_relay.py checks the wording); was a line per request
    lines = [line for line in open_sim.lines[start:] if "web: refused" in line]
    assert len(lines) <= 2 + elapsed / 10, lines
    assert all("web: refused 127.0.0.1: request without the token (401)" in line for line in lines), lines


def test_blank_lines_hold_no_slot_and_malformed_requests_are_refusals_not_tracebacks(open_sim):
    """Anyone who can connect: connections that send only line ends (which aiohttp skips, waiting on)
    do not keep the operator out once every slot is taken, and requests that do not parse are
    counted refusals, not an ERROR traceback each in the daemon's log."""
    from racecar_hw.net.web_params import WebParams

    printed = open_sim.wait_for(r"racecar-hw: status page http://0\.0\.0\.0:(\d+)/\?token=(\S+) ")
    port, token = int(printed.group(1)), printed.group(2)
    start = len(open_sim.lines)

    async def main() -> None:
        holders = []
        for _ in range(WebParams().max_connections):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"\r\n\r\n")
            await writer.drain()
            holders.append((reader, writer))
        # every slot held by an unfinished request: the operator's request takes the oldest's
        url, limit = f"http://127.0.0.1:{port}/api/state?token={token}", aiohttp.ClientTimeout(total=20)
        async with aiohttp.ClientSession(timeout=limit) as http, http.get(url) as res:
            assert res.status == 200
        assert await asyncio.wait_for(holders[0][0].read(), 20) == b""  # closed by the daemon
        for _, writer in holders:
            writer.close()
        for _ in range(50):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"GET / HTTP/1.1\r\nBad Header: x\r\n\r\n")
            answer = await asyncio.wait_for(reader.read(), 20)
            assert re.match(rb"HTTP/1\.[01] 400 ", answer), answer[:80]
            writer.close()

    asyncio.run(main())
    open_sim.wait_for(r"web: refused 127\.0\.0\.1: too many connections: closed the oldest", start=start)
    open_sim.wait_for(r"web: refused 127\.0\.0\.1: malformed request \(400\)", start=start)
    logged = "\n".join(open_sim.lines[start:])
    assert "Traceback" not in logged and "Error handling request" not in logged, logged[-2000:]


@pytest.fixture(scope="module")
def loopback_sim(tmp_path_factory):
    """A sim whose page listens on loopback without a token (the default)."""
    with running_sim(["--scenario", "figure8", "--scenario-set", "drivers=[]", "--duration", "300",
                      "--set", "web.port=0", "--set", "foxglove.enabled=false",
                      "--out", str(tmp_path_factory.mktemp("sim"))]) as proc:
        yield proc


def test_an_open_loopback_page_refuses_a_foreign_host_name_and_origin(loopback_sim):
    from racecar_hw.net.auth import local_host_header, same_origin

    base = f"http://127.0.0.1:{loopback_sim.port('web')}"

    async def main() -> None:
        async with aiohttp.ClientSession() as http:
            async with http.get(f"{base}/") as res:
                assert res.status == 200
            # DNS rebinding: a page of evil.example resolved to 127.0.0.1 names its own host
            async with http.get(f"{base}/", headers={"Host": "evil.example:8080"}) as res:
                assert res.status == 403
            evil = {"Origin": "http://evil.example"}
            async with http.post(f"{base}/api/estop", json={}, headers=evil) as res:
                assert res.status == 403
            async with http.get(f"{base}/api/state") as res:
                assert (await res.json())["mux"]["state"] == "running"

    asyncio.run(main())

    # DNS rebinding: evil.example resolving to 127.0.0.1 reaches the port, but names itself
    assert not local_host_header("evil.example:8080") and local_host_header("127.0.0.1:8080")
    assert local_host_header("localhost") and local_host_header("[::1]:8080")
    assert same_origin(None, "127.0.0.1:8080") and same_origin("http://127.0.0.1:8080", "127.0.0.1:8080")
    assert not same_origin("http://127.0.0.1:8081", "127.0.0.1:8080") and not same_origin("null", "x")


# --- the page in a real browser ---------------------------------------------------------------------

def _until(predicate, timeout_s: float = 20.0, what: str = ""):
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what or predicate}"
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.alone  # it measures the pace of the machine (docs/tests.md, "Alone")
def test_the_page_shows_the_car_and_its_estop_latches_until_a_deliberate_release(tmp_path):
    driver = chromium()  # first: skips at once where there is no browser
    # circles at 1.0 and 0.6 m/s in turn, two seconds each: the speed on the page keeps changing
    steps = [[2.0 * k, 0.6 if k % 2 else 1.0, 0.25] for k in range(150)]
    driver_spec = {"type": "script", "input": "nav_0", "steps": steps}
    sim = SimProcess(["--scenario", "figure8", "--scenario-set", "drivers=" + json.dumps([driver_spec]),
                      "--duration", "300",
                      "--set", "web.port=0", "--set", "foxglove.enabled=false", "--out", str(tmp_path)])
    try:
        port = sim.port("web")
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.common.by import By

        driver.get(f"http://127.0.0.1:{port}/")
        text = lambda ident: driver.find_element(By.ID, ident).text  # noqa: E731
        _until(lambda: text("link") == "connected", what="the page's WebSocket")
        # the speed shown changes while the car drives
        first = _until(lambda: text("measured") if text("measured") not in ("–", "") else None)
        _until(lambda: text("measured") != first, what="the speed to change")
        _until(lambda: float(text("measured").split()[0]) > 0.9, what="the car at 1 m/s")
        assert text("source") == "nav_0" and text("armed") == "ARMED"
        assert text("refused") == "none"  # nothing refused: the counts cell says so

        log_from = len(sim.lines)
        driver.find_element(By.ID, "estop").click()
        # the click's time is taken in the page, when its pointerdown handler runs (the wall clock in
        # ms, the machine's clock the sim logs with): what selenium and chromedriver take to deliver
        # the click is the test's, not the car's; the page's fetch, the server and the loop count
        clicked_s = _until(lambda: driver.execute_script("return window.racecar.estopClickedAt")) / 1000.0
        timing = sim.wait_for(r"sim: e-stop from web page \S+ at wall ([\d.]+); fake VESC: brake (.+) "
                              r"at wall ([\d.]+) \(\+[\d.]+ ms\), (.+)$", start=log_from)
        arrived_s, brake, brake_s, how = (float(timing.group(1)), timing.group(2), float(timing.group(3)),
                                          timing.group(4))
        print(f"click -> request in the daemon {1000 * (arrived_s - clicked_s):.1f} ms, "
              f"-> brake ({brake}) read by the fake VESC {1000 * (brake_s - clicked_s):.1f} ms")
        # the e-stop brakes at once: the first motor command written after the request is the brake
        # (not one step of a ramp down), and it is on the wire within 0.2 s of the click
        assert how == "the first motor command written after the request" and brake == "SET_RPM 0"
        assert 0.0 <= brake_s - clicked_s < 0.2
        _until(lambda: text("estop") == "E-STOP LATCHED", what="the page to show the latch")
        _until(lambda: text("estop-by").startswith("latched by web page (127.0.0.1) at "),
               what="the page to say who latched it")
        _until(lambda: abs(float(text("measured").split()[0])) < 0.02, what="the car to stop")
        # it stays stopped while the figure-8 driver keeps commanding; a short press does not release
        release = driver.find_element(By.ID, "release")
        assert release.is_enabled()
        release.click()
        until = time.monotonic() + 3.0
        while time.monotonic() < until:
            assert abs(float(text("measured").split()[0])) < 0.05 and text("estop") == "E-STOP LATCHED"
            time.sleep(0.1)
        # press and hold for the full two seconds releases it
        ActionChains(driver).click_and_hold(release).pause(2.6).release().perform()
        _until(lambda: text("estop") == "E-STOP", what="the release")
        _until(lambda: float(text("measured").split()[0]) > 0.3, what="the car to drive again")
        # the daemon goes away: the page says so at once
        sim.stop()
        _until(lambda: "CONNECTION LOST" in text("link"), timeout_s=5.0, what="the lost connection shown")
    finally:
        driver.quit()
        sim.stop()


def test_the_page_is_one_self_contained_file():
    from importlib import resources

    page = resources.files("racecar_hw.net").joinpath("static/status.html").read_text()
    # no script, style or font from elsewhere: the page works on a car without internet
    assert not re.search(r"""(src|href)=["']https?://""", page)
    assert 'name="viewport"' in page
