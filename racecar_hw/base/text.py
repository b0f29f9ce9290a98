"""Text from outside (a peer's type name, a damaged file's bytes) made fit for one log line.

A sender chooses what some refusals and error messages quote. Written as it came, a newline in it
would forge a second log line and an ANSI escape would repaint the operator's terminal; a long one
would fill the log. :func:`one_line` keeps the printable characters, turns every run of anything
else (whitespace, control characters) into one space and cuts the result to a length.
"""

from __future__ import annotations

#: What ends a cut text.
ELLIPSIS = "\u2026"


def one_line(text: object, limit: int) -> str:
    """``str(text)`` as one line of printable characters, at most ``limit`` long (cut with an
    ellipsis); empty when nothing printable is left."""
    shown = " ".join("".join(c if c.isprintable() else " " for c in str(text)).split())
    return shown if len(shown) <= limit else shown[:max(limit - 1, 0)] + ELLIPSIS
