"""Failed Zenoh logins are visible: counted by source in ``/diagnostics`` (read over Zenoh), with at
most a handful of log lines naming the source, from a real ``racecar-hw sim`` whose Zenoh listener
wants a user and password, and 100 real Zenoh sessions that present a wrong one; failed mutual-TLS
handshakes counted too (Zenoh names no address for them).

The parser of Zenoh's log lines is tested alone on lines Zenoh 1.10 wrote, and fuzzed."""

from __future__ import annotations

import json
import random
import re
import threading
import urllib.request
from concurrent.futures import ThreadPoolExecutor

import pytest
import zenoh
from conftest import wait_for
from live_sim import SimProcess
from test_net_zenoh_security import _tls_client, pki  # noqa: F401 - pki is a fixture
from zenoh_util import free_port

from racecar_hw.base.messages import DiagnosticArray
from racecar_hw.net import rmw
from racecar_hw.net.zenoh_config import ZenohAuthParams, session_config
from racecar_hw.net.zenoh_logins import LoginLineParser, peer_host
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.security_status import STATUS_NAME

ESC = "\x1b"
#: What Zenoh 1.10's tracing writer printed for one wrong password (trimmed where it says "...").
ZENOH_LINES = [
    f"{ESC}[2m2026-11-26T18:54:38.981952Z{ESC}[0m {ESC}[35mTRACE{ESC}[0m acc-0 ThreadId(05) {ESC}[2m"
    f"zenoh_transport::unicast::establishment::accept{ESC}[0m{ESC}[2m:{ESC}[0m Establishment Accept "
    "InitSyn: tcp/127.0.0.1:17999 => tcp/127.0.0.1:36868. Received: TransportMessage { body: "
    "InitSyn(InitSyn { version: 9, whatami: Client, ... }) }",
    f"{ESC}[2m2026-11-26T18:54:38.983813Z{ESC}[0m {ESC}[35mTRACE{ESC}[0m acc-0 ThreadId(05) {ESC}[2m"
    f"zenoh_transport::unicast::establishment::accept{ESC}[0m{ESC}[2m:{ESC}[0m Establishment Accept "
    "OpenSyn: tcp/127.0.0.1:17999 => tcp/127.0.0.1:36868. Received: TransportMessage { body: "
    "OpenSyn(OpenSyn { lease: 10s, ... }) }",
    f"{ESC}[2m2026-11-26T18:54:38.983962Z{ESC}[0m {ESC}[34mDEBUG{ESC}[0m acc-0 ThreadId(05) {ESC}[2m"
    f"zenoh_transport::unicast::establishment::accept{ESC}[0m{ESC}[2m:{ESC}[0m UsrPwd extension - Recv "
    "OpenSyn. Invalid password. at /root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/io/"
    "zenoh-transport/src/unicast/establishment/ext/auth/usrpwd.rs:424.",
]
#: What it wrote for a session without a client certificate, then one from another CA (mutual TLS):
#: tls-listener's error names no address.
TLS_LINES = [
    f"{ESC}[2m2026-11-26T19:00:16.947501Z{ESC}[0m {ESC}[33m WARN{ESC}[0m acc-0 ThreadId(06) {ESC}[2m"
    f"zenoh_link_tls::unicast{ESC}[0m{ESC}[2m:{ESC}[0m peer sent no certificates. Hint: increase the "
    "system open file limit.",
    f"{ESC}[2m2026-11-26T19:00:17.469550Z{ESC}[0m {ESC}[33m WARN{ESC}[0m acc-0 ThreadId(06) {ESC}[2m"
    f"zenoh_link_tls::unicast{ESC}[0m{ESC}[2m:{ESC}[0m invalid peer certificate: UnknownIssuer. Hint: "
    "increase the system open file limit.",
    f"{ESC}[2m2026-11-26T19:00:17.469550Z{ESC}[0m {ESC}[33m WARN{ESC}[0m acc-0 ThreadId(06) {ESC}[2m"
    f"zenoh_link_tls::unicast{ESC}[0m{ESC}[2m:{ESC}[0m Too many open files (os error 24). Hint: "
    "increase the system open file limit.",
]
GOOD, BAD = ("driver", "good-password-123"), ("driver", "wrong-password")
FAILED_LOGINS = 100
#: Most lines naming the source a run of 100 failed logins may write: the first at once, one
#: summary per 10 s, one at shutdown.
HANDFUL = 5


def test_the_parser_names_the_peer_of_a_wrong_password():
    parser = LoginLineParser()
    got = [parser.feed(line.encode()) for line in ZENOH_LINES]
    assert got == [None, None, ("127.0.0.1", "user/password: invalid password")]
    assert all(parser.is_zenoh(line.encode()) for line in ZENOH_LINES)
    assert not parser.is_zenoh(b"speed +0.00 m/s | steer +0.000 rad")


def test_the_parser_keeps_each_threads_link_apart():
    parser = LoginLineParser()
    a, b = (ZENOH_LINES[1].replace("127.0.0.1:36868", "10.0.0.7:5000"),
            ZENOH_LINES[1].replace("ThreadId(05)", "ThreadId(06)").replace("127.0.0.1:36868", "[::1]:6000"))
    fail_b = (ZENOH_LINES[2].replace("ThreadId(05)", "ThreadId(06)")
              .replace("Invalid password", "Invalid user"))
    assert parser.feed(a.encode()) is None and parser.feed(b.encode()) is None
    assert parser.feed(fail_b.encode()) == ("::1", "user/password: invalid user")
    assert parser.feed(ZENOH_LINES[2].encode()) == ("10.0.0.7", "user/password: invalid password")
    assert parser.feed(ZENOH_LINES[2].encode()) == ("unknown address", "user/password: invalid password")


def test_failed_tls_handshakes_are_counted_without_an_address_zenoh_does_not_log_one():
    parser = LoginLineParser()
    assert [parser.feed(line.encode()) for line in TLS_LINES] == [
        ("unknown address", "tls: peer sent no certificates"),
        ("unknown address", "tls: invalid peer certificate: UnknownIssuer"),
        None]  # not a login: the descriptor limit (the sockets' business)


def test_peer_hosts():
    assert peer_host("tcp/127.0.0.1:40112") == "127.0.0.1"
    assert peer_host("tls/[::1]:40112") == "::1"
    assert peer_host("tcp/192.168.1.20:7447#iface=eth0") == "192.168.1.20"


def test_the_parser_takes_any_bytes():
    rng = random.Random(7)
    parser = LoginLineParser()
    seeds = [line.encode() for line in ZENOH_LINES + TLS_LINES]
    for _ in range(5000):
        line = bytearray(rng.choice(seeds))
        for _ in range(rng.randint(1, 8)):
            at = rng.randrange(len(line))
            choice = rng.random()
            if choice < 0.4:
                line[at] = rng.randrange(256)
            elif choice < 0.7:
                del line[at:at + rng.randint(1, 40)]
            else:
                line[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 20)))
        found = parser.feed(bytes(line))
        assert found is None or (isinstance(found[0], str)
                                 and found[1].startswith(("user/password: ", "tls: ")))
        parser.is_zenoh(bytes(line))


def _wrong_login(port: int) -> bool:
    """One real Zenoh client session with a wrong password; True when it was refused."""
    config = session_config("client", [], [f"tcp/127.0.0.1:{port}"], auth=ZenohAuthParams(user=BAD[0],
                                                                                          password=BAD[1]))
    # one attempt, answered by the daemon's handshake (Zenoh's 10 s open timeout bounds it): a
    # total timeout would end a slow handshake on a loaded host before the daemon saw the password
    config.insert_json5("connect/timeout_ms", "0")
    try:
        session = zenoh.open(config)
    except zenoh.ZError:
        return True
    session.close()
    return False


@pytest.mark.slow
def test_100_failed_zenoh_logins_are_counted_in_diagnostics_with_a_handful_of_log_lines(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text(f"{GOOD[0]}:{GOOD[1]}\n")
    port = free_port()
    sim = SimProcess(["--scenario", "wall", "--scenario-set", "drivers=[]", "--duration", "300",
                      "--out", str(tmp_path / "sim"), "--set", "zenoh.enabled=true",
                      "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]',
                      "--set", f"zenoh.auth.dictionary_file={users}",
                      "--set", "web.port=0", "--set", "foxglove.port=0"], timeout_s=120)
    try:
        sim.wait_for("racecar-hw running")
        web = sim.port("web")
        # the operator's laptop, with the right password, reads /diagnostics over Zenoh
        config = session_config("client", [], [f"tcp/127.0.0.1:{port}"],
                                auth=ZenohAuthParams(user=GOOD[0], password=GOOD[1]))
        config.insert_json5("connect/timeout_ms", "60000")
        laptop = zenoh.open(config)
        try:
            types = ros2_types()
            seen: list[DiagnosticArray] = []
            lock = threading.Lock()

            def on_sample(sample: zenoh.Sample) -> None:
                msg = types.deserialize(sample.payload.to_bytes(), DiagnosticArray)
                assert isinstance(msg, DiagnosticArray)
                with lock:
                    seen.append(msg)

            key = rmw.topic_key(0, "/diagnostics", DiagnosticArray.ROS_TYPE,
                                rmw.type_hash(DiagnosticArray.ROS_TYPE))
            subscriber = laptop.declare_subscriber(key, on_sample)

            def security() -> dict[str, str] | None:
                with lock:
                    for msg in reversed(seen):
                        for status in msg.status:
                            if status.name == STATUS_NAME:
                                return {kv.key: kv.value for kv in status.values} | {
                                    "_level": str(status.level), "_message": status.message}
                return None

            wait_for(lambda: security() is not None, timeout=120)
            assert security()["refused in all"] == "0"

            with ThreadPoolExecutor(max_workers=4) as pool:
                refused = sum(pool.map(_wrong_login, [port] * FAILED_LOGINS))
            assert refused == FAILED_LOGINS  # every wrong password was refused by Zenoh

            def counted() -> int:
                values = security() or {}
                return int(values.get("zenoh: user/password: invalid password", "0"))

            wait_for(lambda: counted() >= FAILED_LOGINS, timeout=60)
            values = security()
            assert values is not None
            assert values["_level"] == "1"  # WARN: refused recently
            assert int(values["refused in all"]) >= FAILED_LOGINS
            assert any(k.startswith("source 127.0.0.1 (zenoh: user/password") for k in values)
            subscriber.undeclare()
        finally:
            laptop.close()
        # the status page shows the same counts
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/api/state", timeout=30) as res:
            page = json.loads(res.read())["refused"]
        assert page["recent"] is True
        row = next(r for r in page["counts"]
                   if (r["surface"], r["reason"]) == ("zenoh", "user/password: invalid password"))
        assert row["count"] >= FAILED_LOGINS
    finally:
        sim.stop()
    log = "\n".join(sim.lines)
    naming = [line for line in log.splitlines()
              if re.search(r"zenoh: refused 127\.0\.0\.1: user/password", line)]
    assert 1 <= len(naming) <= HANDFUL, naming
    # counts in the lines add up to what was refused (the first line is one)
    total = sum(int(m.group(1)) if (m := re.search(r", (\d+) times in the last", line)) else 1
                for line in naming)
    assert total >= FAILED_LOGINS
    assert "Traceback" not in log


def test_failed_tls_handshakes_are_counted_in_diagnostics(tmp_path, pki):  # noqa: F811 - the fixture
    port = free_port()
    sim = SimProcess(["--scenario", "wall", "--scenario-set", "drivers=[]", "--duration", "300",
                      "--out", str(tmp_path / "sim"), "--set", "zenoh.enabled=true",
                      "--set", f'zenoh.listen=["tls/127.0.0.1:{port}"]',
                      "--set", "zenoh.tls.enable_mtls=true",
                      "--set", f"zenoh.tls.listen_certificate={pki / 'server.pem'}",
                      "--set", f"zenoh.tls.listen_private_key={pki / 'server.key'}",
                      "--set", f"zenoh.tls.root_ca_certificate={pki / 'ca.pem'}",
                      "--set", "web.enabled=false", "--set", "foxglove.enabled=false"], timeout_s=120)
    try:
        sim.wait_for("racecar-hw running")
        refused = 0
        for name in (None, "intruder") * 3:  # no certificate; one from another CA
            config = _tls_client(port, pki, name)
            config.insert_json5("connect/timeout_ms", "0")  # one attempt each, as in _wrong_login
            try:
                zenoh.open(config).close()
            except zenoh.ZError:
                refused += 1
        assert refused == 6
        laptop = zenoh.open(_tls_client(port, pki, "client"))
        try:
            types = ros2_types()
            latest: dict[str, dict[str, str]] = {}

            def on_sample(sample: zenoh.Sample) -> None:
                msg = types.deserialize(sample.payload.to_bytes(), DiagnosticArray)
                for status in msg.status:
                    latest[status.name] = {kv.key: kv.value for kv in status.values}

            key = rmw.topic_key(0, "/diagnostics", DiagnosticArray.ROS_TYPE,
                                rmw.type_hash(DiagnosticArray.ROS_TYPE))
            subscriber = laptop.declare_subscriber(key, on_sample)

            def counts() -> tuple[int, int]:
                values = latest.get(STATUS_NAME, {})
                return (int(values.get("zenoh: tls: peer sent no certificates", "0")),
                        int(values.get("zenoh: tls: invalid peer certificate: UnknownIssuer", "0")))

            wait_for(lambda: counts() == (3, 3), timeout=60)
            assert "source unknown address (zenoh: tls: peer sent no certificates)" in latest[STATUS_NAME]
            subscriber.undeclare()
        finally:
            laptop.close()
    finally:
        sim.stop()
    assert "Traceback" not in "\n".join(sim.lines)
