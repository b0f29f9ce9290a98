"""The process's open-file limit (``RLIMIT_NOFILE``): raised to its hard limit while the daemon runs.

Many Linux systems start processes with a soft limit of 1,024 files and a far higher hard one. The
daemon's own budget is small (devices, Zenoh, the capped network surfaces: see docs/live-view.md,
"Connections"), but every socket counts, so it takes what it may: the soft limit is raised to the hard
one at start and put back when the daemon stops (a daemon run inside a longer-lived process leaves it
as it found it). The systemd unit sets both limits (``LimitNOFILE=``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

try:
    import resource
except ImportError:  # not on POSIX: nothing to raise
    resource = None  # type: ignore[assignment]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FileLimit:
    """The soft limit before and after raising it, and the hard limit (open files; -1: unlimited)."""

    before: int
    soft: int
    hard: int

    def restore(self) -> None:
        """Put the soft limit back to what it was before."""
        if resource is not None and self.soft != self.before:
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (self.before, self.hard))
            except (OSError, ValueError) as err:
                log.debug("cannot restore the open-file limit: %s", err)


def raise_open_file_limit() -> FileLimit | None:
    """Raise the soft ``RLIMIT_NOFILE`` to the hard limit and log what was done; None off POSIX."""
    if resource is None:
        return None
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == hard:
        log.info("open files: limit %s (soft = hard; nothing to raise)", _show(hard))
        return FileLimit(soft, soft, hard)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    except (OSError, ValueError) as err:
        log.warning("open files: cannot raise the soft limit %s to the hard limit %s (%s)", _show(soft),
                    _show(hard), err)
        return FileLimit(soft, soft, hard)
    log.info("open files: raised the soft limit from %s to the hard limit %s", _show(soft), _show(hard))
    return FileLimit(soft, hard, hard)


def _show(limit: int) -> str:
    return "unlimited" if resource is not None and limit == resource.RLIM_INFINITY else str(limit)
