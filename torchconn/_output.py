"""All-or-nothing outputs, shared by every command and by the Python API's writers.

- :func:`atomic_file` (and :func:`write_bytes_atomic`, :func:`write_table`,
  :func:`save_figure` on top of it) writes one file: a temporary file beside the target,
  flushed to disk, then renamed over it -- a crash never leaves a half-written file. The file
  follows the umask (``0o666 & ~umask``), and an error names the file being written.
- :class:`FolderLock` allows one writer per output folder: an OS file lock (``flock``) that the
  kernel releases however its holder dies, with a record of the holder (pid, host, start) for
  the message a second writer gets.
- :class:`OutputFolder` is a command's output folder, written whole or not at all: the files go
  to a staging folder beside the target, which is swapped into place at the end (an atomic
  exchange where the OS has one) together with a completion record, ``.torchconn-output.json``,
  naming the command and its files. A folder holding an earlier result of the same command is
  replaced whole; any other non-empty folder is refused. The leftovers of a killed run beside
  the target are removed by the next run on that target.
"""

from __future__ import annotations

import csv
import ctypes
import errno
import io
import json
import os
import re
import shutil
import socket
import stat
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ._cli import InputError, os_error_reason

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None

__all__ = ["atomic_file", "write_bytes_atomic", "write_table", "csv_bytes", "savez", "save_figure",
           "is_temporary", "file_mode", "OS_LITTER", "FolderLock", "FolderBusy", "OutputFolder", "RECORD"]

#: the completion record of an :class:`OutputFolder`, written into it last
RECORD = ".torchconn-output.json"
_RECORD_FORMAT = "torchconn.output/1"
#: files the operating system leaves in folders, not the user's: a folder holding only these
#: counts as empty
OS_LITTER = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})
#: test hook, to kill a run mid-write: ``SECONDS`` pauses after each file is written,
#: ``SECONDS:NAME`` only after files named ``NAME``
_PAUSE_ENV = "TORCHCONN_TEST_WRITE_PAUSE"
#: the names of :func:`atomic_file`'s temporary files: ``.<name>.<8 random>.tmp``
_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


# ============================================================================ one file
_umask_lock = threading.Lock()


def _umask() -> int:
    """The process's umask, read without changing it where Linux allows."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a new file gets from ``open``: ``0o666`` less the umask."""
    return 0o666 & ~_umask()


def _dir_mode() -> int:
    return 0o777 & ~_umask()


def is_temporary(name: str) -> bool:
    """Whether ``name`` is that of a temporary file :func:`atomic_file` makes (left behind only
    by a killed process)."""
    return _TEMPORARY.fullmatch(name) is not None


def _named(err: OSError, path: Path | str) -> OSError:
    """``err`` again, naming ``path`` (the file being written, not a temporary one)."""
    new = OSError(err.errno, err.strerror or str(err), str(path))
    new.__traceback__ = err.__traceback__
    return new


def _pause(path: Path) -> None:
    pause = os.environ.get(_PAUSE_ENV)
    if pause:
        seconds, _, name = pause.partition(":")
        if name in ("", path.name):
            time.sleep(float(seconds))


@contextmanager
def atomic_file(path: str | Path, mode: str = "wb", **open_kwargs) -> Iterator:
    """``with atomic_file(path, "w", newline="") as fh:`` -- write ``path`` all or nothing.

    Yields a file object (``open`` ``mode`` and keywords) on a temporary file in the same
    folder; when the block ends without error the file is flushed to disk, given the umask's
    mode and renamed over ``path``; on error it is removed and ``path`` is left as it was.
    Creates the folder. An ``OSError`` (a full disk, a read-only folder, a folder where the
    file should be) names ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise _named(err, path) from None
    try:
        with os.fdopen(fd, mode, **open_kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, file_mode())  # mkstemp makes it 0o600
        os.replace(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise _named(err, path) from None
        raise
    _pause(path)


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` with :func:`atomic_file`. Returns the path."""
    with atomic_file(path) as fh:
        fh.write(data)
    return Path(path)


def csv_bytes(columns, rows) -> bytes:
    """A CSV table (header row ``columns``, then ``rows``) as UTF-8 bytes."""
    buf = io.StringIO(newline="")
    writer = csv.writer(buf)
    writer.writerow(columns)
    writer.writerows(rows)
    return buf.getvalue().encode()


def write_table(path: str | Path, columns, rows) -> Path:
    """Write a CSV table (header row ``columns``, then ``rows``) atomically. Returns the path."""
    return write_bytes_atomic(path, csv_bytes(columns, rows))


def savez(path: str | Path, **arrays) -> Path:
    """``numpy.savez`` into ``path`` atomically; like it, adds ``.npz`` to a name without it.
    Returns the path written."""
    path = Path(path)
    if not path.name.endswith(".npz"):
        path = path.with_name(path.name + ".npz")
    with atomic_file(path) as fh:
        np.savez(fh, **arrays)
    return path


def save_figure(fig, path: str | Path, **savefig_kwargs) -> Path:
    """``fig.savefig`` into ``path`` atomically, in the format its suffix names (default PNG).
    Returns the path."""
    path = Path(path)
    with atomic_file(path) as fh:
        fig.savefig(fh, format=path.suffix[1:] or "png", **savefig_kwargs)
    return path


# ============================================================================ one writer
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
        out: the output folder (its lock file's folder must exist).
        lock_file: the lock file (default ``out/.lock``). One beside ``out`` locks a folder
            that is replaced whole.
        wait: wait for the holder to finish instead of raising :class:`FolderBusy`.
        log: receives one line when a stale lock is taken over or when waiting starts.
        advice: what the :class:`FolderBusy` message advises.
        remove: delete the lock file on release (else it is left empty).

    A lock left by a killed run (whose record names a process that is gone) is taken over,
    with one line to ``log``.
    """

    def __init__(self, out: Path | str, *, lock_file: Path | str | None = None,
                 wait: bool = False, log: Callable[[str], object] = lambda msg: None,
                 advice: str = "wait for it to finish (or pass --wait), or choose another --out",
                 remove: bool = False):
        self.folder = Path(out)
        self.path = Path(lock_file) if lock_file is not None else self.folder / ".lock"
        self.wait, self.log, self.advice, self.remove = wait, log, advice, remove
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

    def _acquire(self):
        """The open lock file, locked; retried while a releasing holder deletes it."""
        while True:
            fh = self.path.open("a+")
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._holder()
                if not self.wait:
                    fh.close()
                    raise FolderBusy(f"output folder {self.folder} is in use by "
                                     f"{self.describe(holder)}; {self.advice}") from None
                self.log(f"waiting for {self.describe(holder)} to release {self.folder}")
                fcntl.flock(fh, fcntl.LOCK_EX)
            try:  # the file locked is still the one at the path (not deleted by its holder)
                same = os.stat(self.path).st_ino == os.fstat(fh.fileno()).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fh
            fh.close()

    def __enter__(self) -> "FolderLock":
        if fcntl is None:  # pragma: no cover - not on POSIX
            return self
        fh = self._acquire()
        stale = self._holder()
        if stale and stale.get("pid") != os.getpid():
            same_host = stale.get("host") == socket.gethostname()
            gone = same_host and isinstance(stale.get("pid"), int) and not _pid_alive(stale["pid"])
            self.log(f"taking over the lock left in {self.folder} by {self.describe(stale)}"
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
        if self.remove:  # while still held: the next holder checks that its file is this path
            self.path.unlink(missing_ok=True)
        else:
            self._fh.seek(0)
            self._fh.truncate()  # a clean exit leaves no holder behind
            self._fh.flush()
        fcntl.flock(self._fh, fcntl.LOCK_UN)
        self._fh.close()
        self._fh = None


# ============================================================================ one folder
def _older_sidecar(folder: Path, names) -> bool:
    """Whether ``folder`` holds a JSON sidecar of :func:`torchconn._provenance.write_sidecar`
    (its ``source_hash`` and ``versions``)."""
    for name in sorted(n for n in names if n.endswith(".json"))[:8]:
        try:
            fields = json.loads((folder / name).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(fields, dict) and {"source_hash", "versions"} <= fields.keys():
            return True
    return False


_AT_FDCWD, _RENAME_EXCHANGE = -100, 2


def _exchange(a: str, b: str) -> bool:
    """Swap the folders at ``a`` and ``b`` in one step (Linux ``renameat2``); False where the
    OS or file system has no such call."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError, TypeError):  # no such call here
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), b)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class OutputFolder:
    """``with OutputFolder(out, command=PROG) as folder:`` -- write a command's outputs into
    ``folder.path``; they appear in ``out`` all together when the block ends without error
    (or at :meth:`commit`), and not at all otherwise.

    On entry (before any work, so that an unusable ``out`` is found first): ``out`` must not be
    a file, and must be missing, empty, or hold an earlier result of the same ``command`` and
    nothing else (recognised by its completion record, :data:`RECORD`); one writer at a time
    (a :class:`FolderLock` on ``.<name>.lock`` beside ``out``); the leftovers of a killed run
    on ``out`` are removed; a staging folder ``.<name>.staging-*`` is made beside ``out``.
    Nothing is created where ``out`` is. On error everything made is removed again, and an
    ``OSError`` from writing names the file in ``out`` it was for.

    Args:
        out: the output folder.
        command: the command's name, recorded and checked in :data:`RECORD`.
        flag: the option that gave ``out``, for messages.
        log: receives one line when the leftovers of a killed run are removed or a stale
            lock is taken over (default: :func:`warnings.warn`, which a command prints as
            ``prog: warning: ...`` on stderr).
    """

    def __init__(self, out: Path | str, *, command: str, flag: str = "--out",
                 log: Callable[[str], object] | None = None):
        self.target = Path(out)
        self.command, self.flag = command, flag
        self.log = log or warnings.warn
        real = Path(os.path.realpath(self.target))
        self._real, self._parent = real, real.parent
        self._made: list[Path] = []  # parent folders created by this run
        self._lock: FolderLock | None = None
        self._stage: Path | None = None
        self.committed = False

    # ---------------------------------------------------------------- the target
    def _where(self) -> str:
        return f"{self.flag} {self.target}"

    def _check_target(self) -> None:
        """Refuse a file, a foreign non-empty folder, or an earlier result with extra files."""
        real = self._real
        if not real.exists():
            return
        if not real.is_dir():
            raise InputError(f"{self._where()}: is a file, expected a folder for the outputs")
        try:
            entries = {p.name for p in real.iterdir()} - OS_LITTER
        except OSError as err:
            raise InputError(f"{self._where()}: cannot read the folder ({os_error_reason(err)})") \
                from None
        if not entries:
            return
        record = self.read_record(real)
        if record is None and _older_sidecar(real, entries):
            raise InputError(
                f"{self._where()}: the folder holds the outputs of an older torchconn, which "
                f"did not mark them with {RECORD} as a result a re-run may replace; remove "
                "them or choose another folder")
        if record is None:
            raise InputError(
                f"{self._where()}: the folder is not empty and holds no earlier "
                f"{self.command} result (no {RECORD}); choose a new or empty folder (its "
                "contents are never deleted)")
        if record.get("command") != self.command:
            raise InputError(
                f"{self._where()}: the folder holds the result of {record.get('command')}, not "
                f"of {self.command}; choose another folder")
        files = record.get("files")
        ours = {Path(str(f)).parts[0] for f in (files if isinstance(files, list) else [])
                if str(f)} | {RECORD}
        extra = sorted(entries - ours)
        if extra:
            shown = ", ".join(extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5
                                            else "")
            raise InputError(
                f"{self._where()}: the folder holds an earlier {self.command} result, which "
                f"would be replaced, and files it did not write ({shown}); move them away or "
                "choose another folder")

    @staticmethod
    def read_record(folder: Path | str) -> dict | None:
        """The completion record of an output folder, None where there is none (or it does
        not parse)."""
        try:
            record = json.loads((Path(folder) / RECORD).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        if not isinstance(record, dict) or record.get("format") != _RECORD_FORMAT:
            return None
        return record

    def _make_parent(self) -> None:
        missing = []
        p = self._parent
        while not p.exists():
            missing.append(p)
            p = p.parent
        try:
            for p in reversed(missing):
                p.mkdir()
                self._made.append(p)
        except OSError as err:
            self._unmake_parent()
            raise InputError(f"{self._where()}: cannot create the output folder "
                             f"({os_error_reason(err)})") from None
        if not self._parent.is_dir():
            raise InputError(f"{self._where()}: cannot create the output folder "
                             f"({self._parent} is a file)")

    def _unmake_parent(self) -> None:
        for p in reversed(self._made):
            try:
                p.rmdir()
            except OSError:
                break
        self._made = []

    def _leftovers(self) -> list[Path]:
        name = re.escape(self._real.name)
        pattern = re.compile(rf"\.{name}\.(staging|old)-[a-z0-9_]{{8}}")
        return sorted(p for p in self._parent.iterdir() if pattern.fullmatch(p.name))

    def _clean_leftovers(self) -> None:
        """Remove what a killed run on this target left beside it (we hold the lock, so no
        live run owns them); restore its previous result if the kill came mid-swap."""
        old = [p for p in self._leftovers() if ".old-" in p.name]
        if not self._real.exists() and len(old) == 1 and self.read_record(old[0]):
            os.rename(old[0], self._real)
            self.log(f"restored the previous result in {self.target}, moved aside by an "
                     "interrupted run")
        gone = self._leftovers()
        for p in gone:
            shutil.rmtree(p, ignore_errors=True)
        if gone:
            self.log(f"removed the staging folder(s) of an interrupted run beside "
                     f"{self.target}: {', '.join(p.name for p in gone)}")

    # ---------------------------------------------------------------- the block
    @property
    def path(self) -> Path:
        """The staging folder: write the outputs here."""
        if self._stage is None:
            raise RuntimeError("OutputFolder.path is available inside the with block only")
        return self._stage

    def final(self, path: Path | str) -> Path:
        """Where a file written as ``path`` (in :attr:`path`, or a name) ends up in ``out``."""
        path = Path(path)
        if self._stage is not None and path.is_relative_to(self._stage):
            path = path.relative_to(self._stage)
        return self.target / path

    def __enter__(self) -> "OutputFolder":
        self._check_target()
        self._make_parent()
        lock_file = self._parent / f".{self._real.name}.lock"
        try:
            self._lock = FolderLock(self.target, lock_file=lock_file, log=self.log, remove=True,
                                    advice=f"wait for it to finish, or choose another {self.flag}")
            self._lock.__enter__()
        except OSError as err:
            self._lock = None
            self._unmake_parent()
            raise InputError(f"{self._where()}: cannot write in {self._parent} "
                             f"({os_error_reason(err)})") from None
        except BaseException:
            self._lock = None
            self._unmake_parent()
            raise
        try:
            self._check_target()  # again: it may have changed while we waited
            self._clean_leftovers()
            try:
                self._stage = Path(tempfile.mkdtemp(dir=self._parent,
                                                    prefix=f".{self._real.name}.staging-"))
            except OSError as err:
                raise InputError(f"{self._where()}: cannot write in {self._parent} "
                                 f"({os_error_reason(err)})") from None
        except BaseException:
            self._release(failed=True)
            raise
        return self

    def commit(self) -> Path:
        """Move the staged outputs into ``out`` (replacing an earlier result whole), with the
        completion record. Returns ``out``."""
        if self.committed:
            return self.target
        stage = self.path
        files = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
        write_bytes_atomic(stage / RECORD, (json.dumps({
            "format": _RECORD_FORMAT, "command": self.command, "files": files,
            "completed": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }, indent=2) + "\n").encode())
        self._check_target()  # files added to an earlier result during the run are kept
        real = self._real
        try:
            os.chmod(stage, stat.S_IMODE(real.stat().st_mode) if real.is_dir() else _dir_mode())
            _fsync_dir(stage)
            if not real.exists():
                os.rename(stage, real)
            elif _exchange(str(stage), str(real)):
                shutil.rmtree(stage, ignore_errors=True)  # it holds the earlier result now
            else:  # two steps: a kill between them leaves the earlier result beside, restored
                old = stage.with_name(stage.name.replace(".staging-", ".old-"))
                os.rename(real, old)
                try:
                    os.rename(stage, real)
                except BaseException:
                    os.rename(old, real)
                    raise
                shutil.rmtree(old, ignore_errors=True)
            _fsync_dir(self._parent)
        except OSError as err:
            raise _named(err, self.target) from None
        self.committed = True
        self._made = []
        return self.target

    def _release(self, failed: bool) -> None:
        if self._stage is not None and not self.committed:
            shutil.rmtree(self._stage, ignore_errors=True)
        self._stage = None
        if self._lock is not None:
            self._lock.__exit__(None, None, None)
            self._lock = None
        if failed:
            self._unmake_parent()

    def __exit__(self, kind, err, tb) -> None:
        try:
            if kind is None:
                self.commit()
        except BaseException as exc:
            kind, err = type(exc), exc
            self._translate_and_release(err)
            raise
        if kind is None:
            self._release(failed=False)
            return
        self._translate_and_release(err)

    def _translate_and_release(self, err: BaseException) -> None:
        """Release everything; an ``OSError`` naming a staged file is raised again naming the
        file in ``out`` instead."""
        stage = self._stage
        self._release(failed=True)
        if isinstance(err, OSError) and stage is not None and err.filename is not None:
            name = Path(os.fsdecode(err.filename))
            if name.is_relative_to(stage):
                raise _named(err, self.target / name.relative_to(stage)) from None
