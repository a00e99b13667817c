"""One writer per output folder: an advisory lock on ``OUT/.lock`` naming its holder.

The lock is an OS file lock (``flock``), so the kernel releases it when the holding process
dies, however it dies: a lock left by a killed run is never a dead end. The file also records
the holder (pid, host, start time) for the message a second run prints, and is left behind on
a crash; the next run sees that record, confirms that the lock is free (on this host: that the
pid is gone) and takes over, saying so.
"""

from __future__ import annotations

import json
import os
import socket
import time
from datetime import datetime, timezone
from pathlib import Path

from .._cli import InputError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None

__all__ = ["FolderLock", "FolderBusy"]


class FolderBusy(InputError):
    """Another run holds the output folder."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class FolderLock:
    """``with FolderLock(out, wait=False, log=print):`` -- hold ``out`` for this process.

    Args:
        out: the output folder (must exist).
        wait: wait for the holder to finish instead of raising :class:`FolderBusy`.
        log: receives one line when a stale lock is taken over or when waiting starts.
    """

    def __init__(self, out: Path | str, *, wait: bool = False, log=lambda msg: None):
        self.path = Path(out) / ".lock"
        self.wait, self.log = wait, log
        self._fh = None

    def _holder(self) -> dict | None:
        try:
            text = self.path.read_text()
            return json.loads(text) if text.strip() else None
        except (OSError, ValueError):
            return None

    @staticmethod
    def describe(holder: dict | None) -> str:
        if not holder:
            return "another process (no holder recorded)"
        return (f"pid {holder.get('pid')} on host {holder.get('host')}, started "
                f"{holder.get('started')}")

    def __enter__(self) -> "FolderLock":
        if fcntl is None:  # pragma: no cover - not on POSIX
            return self
        fh = self.path.open("a+")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = self._holder()
            if not self.wait:
                fh.close()
                raise FolderBusy(
                    f"output folder {self.path.parent} is in use by {self.describe(holder)}; "
                    "wait for it to finish (or pass --wait), or choose another --out") from None
            self.log(f"waiting for {self.describe(holder)} to release {self.path.parent}")
            fcntl.flock(fh, fcntl.LOCK_EX)
        stale = self._holder()
        if stale and stale.get("pid") != os.getpid():
            same_host = stale.get("host") == socket.gethostname()
            gone = same_host and isinstance(stale.get("pid"), int) and not _pid_alive(stale["pid"])
            self.log(f"taking over the lock left in {self.path.parent} by {self.describe(stale)}"
                     + (" (no longer running)" if gone else " (released)"))
        fh.seek(0)
        fh.truncate()
        fh.write(json.dumps({
            "pid": os.getpid(), "host": socket.gethostname(),
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "since_epoch_s": time.time(),
        }))
        fh.flush()
        self._fh = fh
        return self

    def __exit__(self, *exc) -> None:
        if self._fh is None:
            return
        self._fh.seek(0)
        self._fh.truncate()  # a clean exit leaves no holder behind
        self._fh.flush()
        fcntl.flock(self._fh, fcntl.LOCK_UN)
        self._fh.close()
        self._fh = None
