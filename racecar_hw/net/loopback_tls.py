"""A throwaway TLS certificate for a server only our own relay may talk to.

The Foxglove SDK's server checks neither a token nor the ``Origin`` of a browser, so it listens on an
ephemeral loopback port behind :mod:`racecar_hw.net.relay`. A web page in a browser on the same
machine could still find that port (by trying ports) and talk to it directly; with TLS and a
certificate nobody trusts but the relay, it cannot: a browser refuses ``wss://`` to an unknown
certificate without asking anyone, and plain ``ws://`` gets no answer from a TLS server.

:func:`make_loopback_cert` makes a new self-signed certificate for ``127.0.0.1`` (ECDSA P-256) at each
start; the private key is never written to disk. :func:`pinned_context` is the client side that
trusts exactly that certificate.

The certificate is made by a short-lived child process (``python -m racecar_hw.net.loopback_tls``,
about a quarter of a second once at start; :class:`PendingCert` starts it early and collects it
when needed, so the caller goes on meanwhile) that hands the two PEM blocks back over a pipe: the
``cryptography`` library it needs would otherwise stay in the daemon for good, about 10 MB of its
memory (PSS) for one certificate (docs/install.md, "Memory").
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import ssl
import subprocess
import sys
from dataclasses import dataclass

from racecar_hw.base.errors import RacecarError

#: The address the certificate names (and the only one the server listens on).
LOOPBACK = "127.0.0.1"


@dataclass(frozen=True)
class LoopbackCert:
    """A PEM certificate for :data:`LOOPBACK` and its PKCS#8 PEM private key."""

    cert_pem: bytes
    key_pem: bytes


#: Python 3.11's -P: the child does not put its working directory first on sys.path, where a
#: stray ``cryptography`` folder would be imported instead of the library.
SAFE_PATH = ("-P",) if sys.version_info >= (3, 11) else ()
#: How long the child process may take to make the certificate (s): a loaded small computer.
MAKE_TIMEOUT_S = 30.0


class CertificateError(RacecarError):
    """The loopback certificate could not be made."""


#: The certificates this process made with ``reuse``, by their days of validity.
_made: dict[int, LoopbackCert] = {}


class PendingCert:
    """A certificate being made: the child process starts at once and :meth:`result` collects it,
    so the caller can do other work (start its other interfaces) meanwhile. :meth:`cancel` ends a
    child whose certificate is not wanted.

    With ``reuse``, a certificate this process already made with ``reuse`` (for as many days) is
    given back, and no child starts: the key stays in this process either way."""

    def __init__(self, valid_days: int = 3650, reuse: bool = False) -> None:
        self._error: OSError | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._days = valid_days if reuse else None
        if self._days is not None and self._days in _made:
            return
        try:
            self._process = subprocess.Popen([sys.executable, *SAFE_PATH, "-m", __name__, str(valid_days)],
                                             stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                             stderr=subprocess.PIPE)
        except OSError as err:
            self._error = err

    def result(self) -> LoopbackCert:
        """The certificate (waits for the child); :class:`CertificateError` if it failed."""
        if self._days is not None and self._days in _made:
            self.cancel()
            return _made[self._days]
        process, self._process = self._process, None
        if process is None:
            raise CertificateError(f"cannot make the loopback certificate: "
                                   f"{self._error or 'already collected'}")
        try:
            stdout, stderr = process.communicate(timeout=MAKE_TIMEOUT_S)
        except subprocess.TimeoutExpired as err:
            _reap(process)
            raise CertificateError(f"cannot make the loopback certificate: {err}") from err
        if process.returncode != 0:
            last = (stderr.decode(errors="replace").strip().splitlines() or ["no output"])[-1]
            raise CertificateError(f"cannot make the loopback certificate: {last}")
        try:
            pems = json.loads(stdout)
            made = LoopbackCert(pems["cert"].encode(), pems["key"].encode())
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            # a child that ran other code (an older racecar_hw first on PYTHONPATH, say) answers nothing
            raise CertificateError(f"cannot make the loopback certificate: the child process answered "
                                   f"{stdout[:60]!r} ({err})") from None
        if self._days is not None:
            _made[self._days] = made
        return made

    def cancel(self) -> None:
        """End the child if its certificate was not collected (safe to call twice)."""
        process, self._process = self._process, None
        if process is not None:
            _reap(process)

    def __del__(self) -> None:
        self.cancel()


def _reap(process: subprocess.Popen[bytes]) -> None:
    process.kill()
    process.communicate()


def make_loopback_cert(valid_days: int = 3650) -> LoopbackCert:
    """A new self-signed server certificate for :data:`LOOPBACK`, valid from a minute ago, made in a
    child process (:class:`CertificateError` if that fails)."""
    return PendingCert(valid_days).result()


def _generate(valid_days: int) -> LoopbackCert:
    """The certificate, made here (in the child process: it imports ``cryptography``)."""
    from cryptography import x509  # noqa: PLC0415 - only the child process needs it
    from cryptography.hazmat.primitives import hashes, serialization  # noqa: PLC0415
    from cryptography.hazmat.primitives.asymmetric import ec  # noqa: PLC0415
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: PLC0415

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "racecar-hw loopback")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=1))
            .not_valid_after(now + datetime.timedelta(days=valid_days))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address(LOOPBACK))]),
                           critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
            .sign(key, hashes.SHA256()))
    return LoopbackCert(
        cert.public_bytes(serialization.Encoding.PEM),
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                          serialization.NoEncryption()))


def pinned_context(cert_pem: bytes) -> ssl.SSLContext:
    """A client context that trusts ``cert_pem`` and nothing else (host name checked: 127.0.0.1)."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cadata=cert_pem.decode())
    return context


if __name__ == "__main__":  # the child process of make_loopback_cert: both PEM blocks as JSON on stdout
    made = _generate(int(sys.argv[1]))
    json.dump({"cert": made.cert_pem.decode(), "key": made.key_pem.decode()}, sys.stdout)
