"""A lock file (``O_CREAT | O_EXCL``, holding the owner's pid, host and start time) so that two
runs on one cell, or two installs into one store, cannot interleave; what a cell is keyed by,
stale locks and ``$SLIDECAL_LOCK_DIR``: docs/UNATTENDED.md.
"""

from __future__ import annotations

import hashlib
import os
import platform
import tempfile
import time
from pathlib import Path

from slidecal.solver.errors import InputError


def cell_lock_path(key: str) -> Path:
    """The lock file of a cell key (a robot host or a cell file path), in ``$SLIDECAL_LOCK_DIR``
    or the temporary directory."""
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    directory = Path(os.environ.get("SLIDECAL_LOCK_DIR") or tempfile.gettempdir())
    return directory / f"slidecal-cell-{digest}.lock"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    return True


class Lock:
    """An exclusive lock file; a context manager. ``what`` names the locked thing in messages;
    ``stale``: after :meth:`acquire`, the stale lock taken over (None when there was none)."""

    def __init__(self, path: str | Path, what: str) -> None:
        self.path = Path(path)
        self.what = what
        self.stale: str | None = None
        self._held = False

    def acquire(self) -> Lock:
        """Take the lock or raise ``InputError`` naming the process that holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        body = f"{os.getpid()} {platform.node()} {time.time():.0f}\n".encode()
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                if holder is None:  # stale: its process is gone; take it over
                    continue
                pid, host = holder
                raise InputError(
                    f"{self.what} is in use by process {pid} on {host} (lock {self.path}); "
                    "wait for it to finish, or remove the lock if that process is not slidecal"
                ) from None
            with os.fdopen(fd, "wb") as f:
                f.write(body)
                f.flush()
                os.fsync(f.fileno())
            self._held = True
            return self
        raise InputError(f"could not take the lock {self.path}; remove it and retry")

    def _holder(self) -> tuple[int, str] | None:
        """(pid, host) of the lock's owner, or None after removing a stale lock."""
        try:
            text = self.path.read_text().split()
        except FileNotFoundError:
            return None
        try:
            pid, host = int(text[0]), text[1]
        except (IndexError, ValueError):
            pid, host = -1, platform.node()
        if host == platform.node() and (pid <= 0 or not _pid_alive(pid)):
            self.stale = f"stale lock of process {pid} (no longer running) taken over"
            self.path.unlink(missing_ok=True)
            return None
        return pid, host

    def release(self) -> None:
        """Remove the lock (only when held by this object)."""
        if self._held:
            self._held = False
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> Lock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
