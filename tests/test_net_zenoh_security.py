"""The Zenoh section's credentials: refused when the config loads (check-config and the daemon
alike), naming the key; Zenoh's own open errors turned into one line naming the key; rmw_zenoh's
session settings in every session the daemon and its tools open."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import zenoh
from conftest import async_wait_for
from zenoh_util import ROOT, endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import LaserScan, stamp_now
from racecar_hw.config import load_config
from racecar_hw.net import rmw
from racecar_hw.net.topics import topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.net.zenoh_config import (
    RMW_ZENOH_SETTINGS,
    ZenohAuthParams,
    ZenohParams,
    ZenohTlsParams,
    session_config,
)
from racecar_hw.net.zenoh_security import dictionary_users
from safety.params import SafetyParams

OPEN_LISTEN = 'zenoh.listen=["tcp/0.0.0.0:7447"]'
SECRET = "s3cret-do-not-print"


def _refused(*overrides: str) -> ConfigError:
    with pytest.raises(ConfigError) as err:
        load_config(None, list(overrides))
    return err.value


def _pem(path, kind: str):
    path.write_text(f"-----BEGIN {kind}-----\nMAo=\n-----END {kind}-----\n")
    return path


# --- the user/password dictionary --------------------------------------------------------------


@pytest.mark.parametrize("content", ["", "\n\n", "   \n\t\n"])
@pytest.mark.parametrize("listen", [OPEN_LISTEN, 'zenoh.listen=["tcp/127.0.0.1:7447"]'])
def test_a_dictionary_with_no_user_is_refused_because_zenoh_would_let_everyone_in(tmp_path, content, listen):
    users = tmp_path / "users.txt"
    users.write_text(content)
    err = _refused(listen, f"zenoh.auth.dictionary_file={users}")
    assert err.key == "zenoh.auth.dictionary_file"
    assert "no user:password line" in str(err) and "anyone on the network" in str(err)


def test_a_missing_or_unreadable_dictionary_is_refused_naming_the_key(tmp_path):
    err = _refused(OPEN_LISTEN, f"zenoh.auth.dictionary_file={tmp_path / 'nowhere.txt'}")
    assert err.key == "zenoh.auth.dictionary_file" and "No such file" in str(err)
    err = _refused(OPEN_LISTEN, f"zenoh.auth.dictionary_file={tmp_path}")  # a directory
    assert err.key == "zenoh.auth.dictionary_file" and "cannot read" in str(err)
    binary = tmp_path / "users.bin"
    binary.write_bytes(b"driver:\xff\xfe\n")
    err = _refused(OPEN_LISTEN, f"zenoh.auth.dictionary_file={binary}")
    assert err.key == "zenoh.auth.dictionary_file" and "UTF-8" in str(err)


@pytest.mark.parametrize(("content", "line"), [
    (f"driver{SECRET}\n", 1),                  # no colon
    (f"driver:ok\n:{SECRET}\n", 2),            # no user
    (f"driver:ok\n\n{SECRET}:\n", 3),          # no password
    (f"driver:ok\n{SECRET}:   \n", 2),         # a blank password
])
def test_a_malformed_dictionary_line_is_refused_by_number_without_printing_it(tmp_path, content, line):
    users = tmp_path / "users.txt"
    users.write_text(content)
    err = _refused(OPEN_LISTEN, f"zenoh.auth.dictionary_file={users}")
    assert err.key == "zenoh.auth.dictionary_file"
    assert f"line {line} of" in str(err) and SECRET not in str(err)


def test_the_dictionary_is_read_as_zenoh_reads_it(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("driver:s3cret\r\n\n  laptop : a password: with colons  \n")
    assert dictionary_users(str(users), "k") == ["driver", "laptop"]
    load_config(None, [OPEN_LISTEN, f"zenoh.auth.dictionary_file={users}"])


@pytest.mark.parametrize(("overrides", "key"), [
    (["zenoh.auth.user=car:1", "zenoh.auth.password=pw"], "zenoh.auth.user"),
    (["zenoh.auth.user=' car1'", "zenoh.auth.password=pw"], "zenoh.auth.user"),
    (["zenoh.auth.user=car1", "zenoh.auth.password='pw '"], "zenoh.auth.password"),
    (["zenoh.auth.user=car1", 'zenoh.auth.password="p\\nw"'], "zenoh.auth.password"),
    (["zenoh.auth.password=pw"], "zenoh.auth.user"),
])
def test_the_daemons_own_user_and_password_must_be_matchable_by_a_dictionary(overrides, key):
    err = _refused(*overrides)
    assert err.key == key, str(err)


def test_a_password_may_hold_colons():
    config = load_config(None, ["zenoh.auth.user=car1", "zenoh.auth.password=pw:with:colons"])
    assert config.zenoh.auth.password == "pw:with:colons"


def test_check_config_and_the_daemon_both_refuse_an_empty_dictionary(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("")
    sets = ["--set", OPEN_LISTEN, "--set", f"zenoh.auth.dictionary_file={users}"]
    check = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "check-config", *sets],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
    report = tmp_path / "report.json"
    start = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "sim", "--duration", "5", "--no-status",
                            "--no-plot", *sets, "--report", str(report)],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
    for proc in (check, start):
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert "zenoh.auth.dictionary_file" in proc.stderr and "no user:password line" in proc.stderr
        assert "Traceback" not in proc.stderr
    assert not report.exists()  # the daemon never ran


# --- TLS ----------------------------------------------------------------------------------------


def test_mutual_tls_without_its_ca_is_refused_naming_the_key(tmp_path):
    cert, key = _pem(tmp_path / "car.pem", "CERTIFICATE"), _pem(tmp_path / "car.key", "PRIVATE KEY")
    tls = [f"zenoh.tls.listen_certificate={cert}", f"zenoh.tls.listen_private_key={key}"]
    err = _refused('zenoh.listen=["tls/0.0.0.0:7447"]', *tls, "zenoh.tls.enable_mtls=true")
    assert err.key == "zenoh.tls.root_ca_certificate"
    # plain TLS (no client certificates) lets anyone in: it is not authentication
    err = _refused('zenoh.listen=["tls/0.0.0.0:7447"]', *tls)
    assert err.key == "zenoh.listen[0]"


@pytest.mark.parametrize(("name", "kind"), [("listen_certificate", "CERTIFICATE"),
                                            ("listen_private_key", "PRIVATE KEY"),
                                            ("root_ca_certificate", "CERTIFICATE")])
def test_missing_or_non_pem_tls_files_are_refused_naming_the_key(tmp_path, name, kind):
    files = {"listen_certificate": _pem(tmp_path / "car.pem", "CERTIFICATE"),
             "listen_private_key": _pem(tmp_path / "car.key", "EC PRIVATE KEY"),
             "root_ca_certificate": _pem(tmp_path / "ca.pem", "CERTIFICATE")}
    base = ['zenoh.listen=["tls/0.0.0.0:7447"]', "zenoh.tls.enable_mtls=true"]
    load_config(None, base + [f"zenoh.tls.{n}={p}" for n, p in files.items()])
    for broken, words in ((tmp_path / "missing.pem", "No such file"),
                          (_pem(tmp_path / "other.pem", "PUBLIC KEY"), f"no PEM {kind.lower()}")):
        sets = [f"zenoh.tls.{n}={broken if n == name else p}" for n, p in files.items()]
        err = _refused(*base, *sets)
        assert err.key == f"zenoh.tls.{name}" and words in str(err), str(err)


def test_a_tls_listen_needs_a_certificate_even_on_loopback():
    err = _refused('zenoh.listen=["tls/127.0.0.1:7447"]')
    assert err.key == "zenoh.tls.listen_certificate" and "zenoh.listen[0]" in str(err)


@pytest.fixture
def pki(tmp_path):
    """A CA, a server certificate for 127.0.0.1 signed by it, a client certificate signed by it, and
    a client certificate signed by another CA (EC P-256 keys, made with the openssl command)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("the openssl command is not installed: no test certificates can be made")

    def run(*args: str) -> None:
        subprocess.run([openssl, *args], check=True, capture_output=True, cwd=tmp_path, timeout=60)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    # v3 certificates (webpki refuses v1 ones), each for its purpose
    (tmp_path / "server.ext").write_text("basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n"
                                         "subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    (tmp_path / "client.ext").write_text("basicConstraints=CA:FALSE\nextendedKeyUsage=clientAuth\n")
    for ca in ("ca", "other_ca"):
        run("req", "-x509", *ec, "-keyout", f"{ca}.key", "-out", f"{ca}.pem", "-days", "2",
            "-subj", f"/CN={ca}")
    for name, ca, ext in (("server", "ca", "server.ext"), ("client", "ca", "client.ext"),
                          ("intruder", "other_ca", "client.ext")):
        run("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
            "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", ext)
    return tmp_path


def _tls_client(port: int, pki, name: str | None) -> zenoh.Config:
    """A client session config for the daemon's tls/ endpoint, with ``name``'s certificate (None: none)."""
    tls = ZenohTlsParams(root_ca_certificate=str(pki / "ca.pem"), enable_mtls=name is not None)
    config = session_config("client", [], [f"tls/127.0.0.1:{port}"], tls=tls)
    if name is not None:
        config.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(pki / f"{name}.pem")))
        config.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(pki / f"{name}.key")))
    return config


def test_with_mutual_tls_only_a_session_with_a_certificate_from_the_ca_gets_in(pki):
    port = free_port()
    config = load_config(None, [f'zenoh.listen=["tls/127.0.0.1:{port}"]', "zenoh.tls.enable_mtls=true",
                                f"zenoh.tls.listen_certificate={pki / 'server.pem'}",
                                f"zenoh.tls.listen_private_key={pki / 'server.key'}",
                                f"zenoh.tls.root_ca_certificate={pki / 'ca.pem'}"])
    scan = LaserScan(stamp_now("laser", 5), -1.0, 1.0, 0.5, 0.0, 0.025, 0.02, 10.0,
                     np.ones(5, np.float32), np.zeros(0, np.float32))
    key = rmw.topic_key(0, "/scan", LaserScan.ROS_TYPE, rmw.type_hash(LaserScan.ROS_TYPE))

    async def run() -> tuple[list, list[str]]:
        bus = Bus()
        bridge = ZenohBridge(bus, config.zenoh, topic_table(MuxParams(), SafetyParams()))
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        await loop.run_in_executor(None, bridge.open, loop)
        refused = []
        try:
            for name in (None, "intruder"):  # no certificate; one from another CA
                try:
                    await loop.run_in_executor(None, zenoh.open, _tls_client(port, pki, name))
                except zenoh.ZError:
                    refused.append(str(name))
            client = await loop.run_in_executor(None, zenoh.open, _tls_client(port, pki, "client"))
            try:
                samples: list = []
                client.declare_subscriber(key, samples.append)
                out = next(o for o in bridge._outs if o.row.bus == "/scan")
                await async_wait_for(lambda: out.matching, timeout=20)
                bus.publish("/scan", scan)
                await async_wait_for(lambda: samples, timeout=20)
            finally:
                client.close()
            return samples, refused
        finally:
            bridge.close()

    samples, refused = asyncio.run(run())
    assert refused == ["None", "intruder"]
    assert rmw.Attachment.decode(samples[0].attachment.to_bytes()).sequence_number == 1


# --- Zenoh's own errors at open, when a file changed after the config was loaded ----------------


def _open_bridge(params: ZenohParams) -> ConfigError:
    """Open a bridge with ``params`` as given (not validated): the error it raises."""
    async def run() -> ConfigError:
        bus = Bus()
        bridge = ZenohBridge(bus, params, topic_table(MuxParams(), SafetyParams()))
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        try:
            await loop.run_in_executor(None, bridge.open, loop)
        except ConfigError as err:
            return err
        finally:
            bridge.close()
        raise AssertionError("the bridge opened")

    return asyncio.run(run())


def test_zenohs_open_errors_name_the_auth_and_tls_keys_in_one_line(tmp_path):
    here = [endpoint(free_port())]
    cases = [
        (ZenohParams(listen=here, auth=ZenohAuthParams(dictionary_file=str(tmp_path / "gone.txt"))),
         "zenoh.auth.dictionary_file"),
        (ZenohParams(listen=["tls/" + here[0].split("/", 1)[1]],
                     tls=ZenohTlsParams(listen_certificate=str(tmp_path / "car.pem"),
                                        listen_private_key=str(tmp_path / "car.key"))),
         "zenoh.tls.listen_private_key"),
        (ZenohParams(mode="client", listen=[], connect=here), "zenoh.connect"),
    ]
    for params, key in cases:
        err = _open_bridge(params)
        assert err.key == key, str(err)
        assert "\n" not in str(err) and ".rs:" not in str(err), str(err)


def test_the_daemon_says_in_one_line_what_to_do_when_its_port_is_taken(tmp_path):
    """``racecar-hw run`` refuses (``sim`` would move to a free port: docs/live-view.md, "Ports")."""
    port = free_port()
    holder = zenoh.open(session_config("router", [endpoint(port)], []))  # as rmw_zenohd would
    try:
        proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "run", "--no-status",
                               "--set", f'zenoh.listen=["{endpoint(port)}"]',
                               "--set", f"vesc.port={tmp_path / 'no-vesc'}", "--set", "lidar.enabled=false",
                               "--set", "gamepad.enabled=false", "--set", "foxglove.enabled=false",
                               "--set", "web.enabled=false"],
                              capture_output=True, text=True, timeout=120, cwd=ROOT)
    finally:
        holder.close()
    assert proc.returncode == 1
    lines = [line for line in proc.stderr.splitlines() if "zenoh.listen" in line]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert f"zenoh.listen[0]: {endpoint(port)} is already in use" in lines[0]
    assert "rmw_zenohd" in lines[0] and "zenoh.connect" in lines[0]


# --- rmw_zenoh's session settings ----------------------------------------------------------------


@pytest.mark.parametrize("mode", ["router", "peer", "client"])
def test_every_session_carries_rmw_zenohs_transport_and_query_settings(mode):
    config = session_config(mode, [], [])
    expected = {"queries_default_timeout": 600000, "transport/unicast/open_timeout": 60000,
                "transport/unicast/accept_timeout": 60000, "transport/unicast/accept_pending": 10000,
                "transport/unicast/max_sessions": 10000, "transport/link/tx/lease": 60000,
                "transport/link/tx/keep_alive": 2}
    for path, value in expected.items():
        assert RMW_ZENOH_SETTINGS[path] == value
        assert json.loads(config.get_json(path)) == value, path
