"""Reading a user's text files (data tables, TOML configs) with one set of checks.

:func:`read_text` returns a file's text (UTF-8, a byte-order mark dropped) or raises an error
that names the file and says what it holds instead: a folder, a missing file, a symbolic-link
loop, a compressed or binary file (gzip, ZIP/Excel, HDF5, NumPy, PDF, ...), UTF-16 text, or
bytes that are not UTF-8 (with the line). :func:`read_toml` parses a TOML file read that way;
:func:`check_distinct` refuses one file given twice.
"""

from __future__ import annotations

import collections
import errno
import hashlib
import os
import tomllib
import warnings
from os import PathLike
from pathlib import Path

__all__ = ["read_text", "read_toml", "check_file", "file_kind", "check_distinct"]

#: leading bytes of files that are not text, and what they are
_MAGIC = (
    (b"\x1f\x8b", "gzip-compressed; decompress it first (gunzip FILE)"),
    (b"PK\x03\x04", "a ZIP archive (an Excel .xlsx workbook is one); export the sheet as CSV "
     "text"),
    (b"\xd0\xcf\x11\xe0", "an old Office document (.xls); export the sheet as CSV text"),
    (b"\x89HDF", "an HDF5 file"),
    (b"\x93NUMPY", "a NumPy .npy array"),
    (b"%PDF", "a PDF document"),
    (b"SQLite format 3", "an SQLite database"),
    (b"PAR1", "a Parquet file"),
    (b"BZh", "bzip2-compressed; decompress it first"),
    (b"\xfd7zXZ", "xz-compressed; decompress it first"),
)


def _where(path: Path, flag: str | None) -> str:
    return f"{flag} {path}" if flag else str(path)


def check_file(path: str | PathLike, what: str, flag: str | None = None) -> Path:
    """``path`` as a :class:`~pathlib.Path` once it is known to name a readable file.

    Args:
        what: what the file should be, e.g. ``"a trajectory CSV file"``.
        flag: the command-line flag or argument that named it, for the message.

    Raises:
        FileNotFoundError: no such file (or a broken symbolic link).
        ValueError: a folder.
        OSError: a symbolic-link loop, or another reason it cannot be read.
    """
    path = Path(path)
    where = _where(path, flag)
    try:
        path.stat()
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise OSError(f"{where}: a symbolic link loop (the link points back to itself); "
                          f"expected {what}") from None
        if err.errno == errno.ENOENT:
            broken = " (a broken symbolic link)" if path.is_symlink() else ""
            raise FileNotFoundError(f"{where} not found{broken}; expected {what}") from None
        raise OSError(f"{where}: cannot read it ({err.strerror}); expected {what}") from None
    if os.path.isdir(path):
        raise ValueError(f"{where} is a folder, expected {what}")
    return path


def file_kind(data: bytes) -> str | None:
    """What a non-text file is, from its first bytes (None: not recognised as binary)."""
    for magic, kind in _MAGIC:
        if data.startswith(magic):
            return kind
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        return "UTF-16 text (not UTF-8); save it as UTF-8 (or ASCII)"
    if b"\0" in data[:4096]:
        return "binary data (NUL bytes), not text"
    return None


def read_text(path: str | PathLike, what: str, flag: str | None = None) -> str:
    """The text of ``path`` (UTF-8; a leading byte-order mark is dropped).

    Raises:
        FileNotFoundError, OSError: see :func:`check_file`.
        ValueError: naming the file when it is a folder, compressed, binary, UTF-16 or not
            UTF-8 (with the line of the first bad byte).
    """
    path = check_file(path, what, flag)
    where = _where(path, flag)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise OSError(f"{where}: cannot read it ({err.strerror})") from None
    kind = file_kind(data)
    if kind is not None:
        raise ValueError(f"{where}: the file is {kind}; expected {what}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = data[:err.start].count(b"\n") + 1
        raise ValueError(f"{where}, line {line}: not UTF-8 text (byte 0x{data[err.start]:02x}); "
                         f"save it as UTF-8 (or ASCII); expected {what}") from None


def read_toml(path: str | PathLike, flag: str | None = None) -> dict:
    """Parse the TOML file ``path`` (UTF-8, a byte-order mark dropped).

    Raises:
        ValueError: naming ``flag`` and the file, for unreadable text (:func:`read_text`) or
            invalid TOML (with tomllib's line and column).
    """
    text = read_text(path, "a TOML file", flag)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{_where(Path(path), flag)}: invalid TOML: {err}") from None


def check_distinct(paths, what: str = "input") -> None:
    """Refuse a file named twice in ``paths``; warn about two files with identical contents.

    Either would be read as two independent recordings of the same trials.

    Raises:
        ValueError: naming both positions (1-based) and the paths, when two name one file.
    """
    paths = [Path(p) for p in paths]
    stats = {}
    for i, p in enumerate(paths):
        try:
            stats[i] = p.stat()
        except OSError:
            continue  # the reader names it
    seen = {}
    for i, info in stats.items():
        key = (info.st_dev, info.st_ino)
        if key in seen:
            j = seen[key]
            names = f"({paths[j]})" if paths[j] == paths[i] else f"({paths[j]} and {paths[i]})"
            raise ValueError(
                f"{what}s {j + 1} and {i + 1} name the same file {names}: its trials would be "
                "fitted twice as if independent; pass each file once")
        seen[key] = i
    sizes = collections.Counter(info.st_size for info in stats.values())
    digests = {}
    for i, info in stats.items():
        if sizes[info.st_size] < 2 or not os.path.isfile(paths[i]):
            continue
        digest = hashlib.sha256(paths[i].read_bytes()).hexdigest()
        if digest in digests:
            j = digests[digest]
            warnings.warn(f"{paths[j]} and {paths[i]} ({what}s {j + 1} and {i + 1}) have "
                          "identical contents: the same recording under two names? Their trials "
                          "are fitted as independent recordings", stacklevel=3)
        digests.setdefault(digest, i)
