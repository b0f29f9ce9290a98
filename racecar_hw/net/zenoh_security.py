"""Checks of the ``zenoh`` section's credentials when the config loads, and Zenoh's open errors
turned into errors that name the key to fix.

Why the files are read at load time and not left to Zenoh: Zenoh reads them only when the session
opens, and one case it does not refuse at all. A user/password dictionary with no entry (an empty
file) makes Zenoh 1.10 turn user/password authentication *off* (``usrpwd.rs``: no entries and no
own credentials, no authenticator), so every session gets in, without a word. The dictionary's
format is Zenoh's: one ``user:password`` per line, split at the first ``:``, both sides trimmed
and non-empty, blank lines skipped; any other line makes Zenoh refuse to open.

Nothing here ever puts a password, or a line that may hold one, into a message.
"""

from __future__ import annotations

import re
from pathlib import Path

from racecar_hw.base.errors import ConfigError


def dictionary_users(path: str, key: str) -> list[str]:
    """The user names in a Zenoh user/password dictionary file, as Zenoh reads it.

    Raises :class:`ConfigError` naming ``key`` when the file is missing, unreadable, not UTF-8 text,
    has a line that is not ``user:password`` (named by its number), or has no entry at all.
    """
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except OSError as err:
        raise ConfigError(key, f"cannot read the user/password dictionary {path}: "
                               f"{err.strerror or err}") from None
    except UnicodeDecodeError:
        raise ConfigError(key, f"{path} is not UTF-8 text; expected user:password lines") from None
    users = []
    for number, raw in enumerate(text.split("\n"), start=1):
        line = raw.strip()
        if not line:
            continue
        user, sep, password = line.partition(":")
        if not sep or not user.strip() or not password.strip():
            raise ConfigError(key, f"line {number} of {path} is not user:password (a user name, a "
                                   "colon, a password, neither empty); Zenoh would refuse to start")
        users.append(user.strip())
    if not users:
        raise ConfigError(key, f"{path} has no user:password line. Zenoh turns user/password "
                               "authentication off when the dictionary is empty: anyone on the network "
                               "could read the car and drive it. Add a line such as "
                               "laptop:<a long random password>")
    return users


def check_credentials(user: str, password: str, user_key: str, password_key: str) -> None:
    """Refuse a user name or password that no Zenoh dictionary could ever match.

    The other side's dictionary splits each line at its first ``:`` and trims both parts, so a user
    name holding ``:``, or either one with surrounding blanks or a line break, is always refused
    there (and the link keeps failing with nothing that says why). Both empty: no credentials.
    """
    if bool(user) != bool(password):
        raise ConfigError(password_key if user else user_key, "user and password go together")
    if not user:
        return
    if ":" in user:
        raise ConfigError(user_key, "a user name cannot hold ':' (Zenoh's dictionary splits each line "
                                    "at its first ':')")
    for name, value in ((user_key, user), (password_key, password)):
        if value != value.strip() or "\n" in value or "\r" in value:
            raise ConfigError(name, "no line breaks and no blanks at either end (Zenoh's dictionary "
                                    "trims them, so it could never match)")


def check_pem(path: str, key: str, kind: str) -> None:
    """Refuse a TLS file that is missing, unreadable, or holds no PEM block of ``kind``
    (``CERTIFICATE`` or ``PRIVATE KEY``, which also matches ``RSA PRIVATE KEY`` and ``EC PRIVATE KEY``)."""
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise ConfigError(key, f"cannot read {path}: {err.strerror or err}") from None
    if not re.search(rb"-----BEGIN [A-Z0-9 ]*" + kind.encode() + rb"-----", data):
        raise ConfigError(key, f"{path} holds no PEM {kind.lower()} (a '-----BEGIN ...{kind}-----' "
                               "block)")


# --- Zenoh's open errors ------------------------------------------------------------------------

#: Zenoh appends the Rust source location of each error: `` at /root/.cargo/.../tcp.rs:61.``
_SOURCE_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")

#: What to do when a listen port is taken (docs/interop.md says the same).
PORT_IN_USE = ("{endpoint} is already in use: another program holds it, such as rmw_zenohd or zenohd on "
               "this machine, or a second racecar-hw. Stop it; or keep it and run the daemon as a peer "
               "beside it on another port, e.g. zenoh.listen: [\"tcp/127.0.0.1:7448\"] and "
               "zenoh.connect: [\"{endpoint}\"]; or set zenoh.enabled: false")


def zenoh_error_text(err: BaseException | str) -> str:
    """Zenoh's error message on one line, without the Rust source locations it appends."""
    text = " ".join(_SOURCE_LOCATION.sub("", str(err)).split())
    return text if text.endswith((".", "!", "?")) else text + "."


def open_error(err: BaseException | str, mode: str, listen: list[str], connect: list[str],
               has_auth: bool, key: str = "zenoh") -> ConfigError:
    """A one-line :class:`ConfigError` for a failed ``zenoh.open``, naming the key to fix.

    Recognised: a listen port in use (``listen[i]``, with what to do), an address this machine does
    not have, the user/password dictionary (``auth.dictionary_file``), the TLS files and mTLS
    settings (``tls.*``). Anything else, such as a client that reached no router (a wrong
    user/password looks the same from here), names ``connect`` in client mode and ``listen``
    otherwise, with Zenoh's message.
    """
    text = zenoh_error_text(err)
    lowered = text.lower()

    def failed_listen() -> tuple[str, str]:
        """The key and endpoint of the listen Zenoh names (by its full text, else its address)."""
        for whole in (True, False):
            for i, endpoint in enumerate(listen):
                bare = endpoint.split("#", 1)[0].split("?", 1)[0]
                if (bare if whole else bare.partition("/")[2]) in text:
                    return f"{key}.listen[{i}]", bare
        return f"{key}.listen", "the endpoint"

    if "address already in use" in lowered:
        where, endpoint = failed_listen()
        return ConfigError(where, PORT_IN_USE.format(endpoint=endpoint))
    if "cannot assign requested address" in lowered:
        where, endpoint = failed_listen()
        return ConfigError(where, f"no network interface of this machine has the address of {endpoint}: "
                                  "listen on one of its addresses (or 0.0.0.0, with authentication)")
    if "unable to connect" in lowered:
        check = (f"is it running, and are {key}.auth.user and password right" if has_auth
                 else f"is it running, and does it want a user and password ({key}.auth.user, password)")
        return ConfigError(f"{key}.connect", f"no router let this daemon in at {', '.join(connect)}, and "
                                             f"client mode opens only through one: {check}? (Zenoh: {text})")
    if "usrpwd" in lowered or "user-password" in lowered:
        return ConfigError(f"{key}.auth.dictionary_file", f"Zenoh refused the user/password settings: {text}")
    if "tls" in lowered or "certificate" in lowered or "trust anchor" in lowered:
        if "root" in lowered or "trust anchor" in lowered:
            name = "root_ca_certificate"
        elif "private key" in lowered:
            name = "listen_private_key"
        elif "certificate" in lowered:
            name = "listen_certificate"
        else:
            name = None
        where = f"{key}.tls.{name}" if name else f"{key}.tls"
        return ConfigError(where, f"Zenoh could not use the TLS settings: {text}")
    where = f"{key}.connect" if mode == "client" else f"{key}.listen"
    return ConfigError(where, f"Zenoh could not start ({mode} mode, listen {listen}, connect {connect}): "
                              f"{text}")
