"""Who may connect: loopback binds are open to the car's own users; anything else needs a token.

A token is compared in constant time (:func:`secrets.compare_digest`). Browsers also get an
``Origin`` check on WebSocket upgrades and POSTs (a page on another site must not drive the car
through the user's browser), and on an open loopback bind a ``Host`` check (DNS rebinding).
"""

from __future__ import annotations

import secrets
from urllib.parse import urlsplit

from racecar_hw.base.loopback import is_loopback


def new_token() -> str:
    """A fresh random token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def token_ok(given: str | None, expected: str) -> bool:
    """Whether ``given`` is the token, compared in constant time; no token expected: always."""
    if not expected:
        return True
    return given is not None and secrets.compare_digest(given.encode(), expected.encode())


def bearer(header: str | None) -> str | None:
    """The token in an ``Authorization: Bearer <token>`` header, or None."""
    if not header:
        return None
    scheme, _, value = header.partition(" ")
    return value.strip() if scheme.lower() == "bearer" and value.strip() else None


def same_origin(origin: str | None, host: str | None) -> bool:
    """Whether a browser's ``Origin`` is the page's own ``Host``; no Origin (not a browser): True."""
    if origin is None:
        return True
    if not host:
        return False
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == host.lower()


def local_host_header(host: str | None) -> bool:
    """Whether a ``Host`` header names this machine (a loopback address or localhost, any port)."""
    if not host:
        return False
    name = urlsplit(f"//{host}").hostname or ""
    return is_loopback(name)


def browser_origin_allowed(origin: str | None, user_agent: str | None, allowed: tuple[str, ...]) -> bool:
    """Whether a WebSocket client with this ``Origin`` may use an open (token-less) loopback server.

    * no Origin: not a browser (a script, a tool, a local program): yes;
    * an origin listed in ``allowed`` (exactly, case aside; ``"null"`` may be listed): yes;
    * a page served by this machine (http or https on a loopback host, any port): yes;
    * a page with no web origin (``null``, ``file://``, an app's own scheme) whose ``User-Agent``
      names Electron: a desktop app (Foxglove, Lichtblick) showing its own files: yes. A web page
      cannot send such a handshake: its opaque frames say ``null`` with the browser's own
      User-Agent, and no browser lets a page set the headers of a WebSocket handshake;
    * anything else (a page of any other site): no.
    """
    if origin is None:
        return True
    origin = origin.strip().lower().rstrip("/")
    if origin in allowed:
        return True
    parts = urlsplit(origin)
    if parts.scheme in ("http", "https"):
        return is_loopback(parts.hostname or "")
    return "electron/" in (user_agent or "").lower()
