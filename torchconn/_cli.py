"""Plumbing shared by every command (``sweep``, ``fit``, ``discrepancy``, ...).

- :func:`add_threads` adds ``--threads`` (default 1) and :func:`set_threads` applies it: the
  work is many small tensor operations, and torch's default of one thread per core
  oversubscribes a machine that is busy with other work.
- :func:`hold_freed_memory` keeps the memory of freed large tensors for reuse in a command's
  process, instead of returning it to the system and faulting in fresh pages next time.
- :func:`add_device` adds ``--device`` (default ``cpu``) and :func:`resolve_device` checks a
  device name (the flag, or a config key) against what this machine has.
- :func:`prepare_output` creates an output folder and proves it writable *before* any work.
- :func:`run_command` runs a command's body and turns expected errors (bad input, unreadable
  or unwritable files) into one clear line on stderr and exit code 2, never a traceback;
  warnings are printed as ``prog: warning: ...`` lines.
- :func:`check_keys` reports unknown keys of a settings table with the valid ones and the
  closest match ("did you mean ...").
"""

from __future__ import annotations

import argparse
import ctypes
import os
import re
import sys
import traceback
import uuid
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

import torch

from ._checks import did_you_mean, unknown_keys_message

__all__ = ["InputError", "check_center_frame", "add_threads", "set_threads", "hold_freed_memory",
           "add_device", "resolve_device",
           "prepare_output", "run_command", "check_keys", "did_you_mean", "os_error_reason"]

#: set to 1 to see the traceback of an unexpected error
DEBUG_ENV = "TORCHCONN_DEBUG"


class InputError(ValueError):
    """Bad input a user can fix: the message names the input and what was expected."""


def check_keys(table: dict, known: Iterable[str], where: str) -> None:
    """Raise :class:`InputError` listing ``table``'s keys that are not in ``known``, with the
    closest valid key and all of them."""
    known = [str(k) for k in known]
    unknown = [k for k in table if k not in known]
    if unknown:
        raise InputError(unknown_keys_message(where, unknown, known))


def check_center_frame(n_links: int, frame: str | None, hint: str = "pass --frame com-mean"
                       ) -> None:
    """Raise :class:`InputError` where the center body frame (the middle link, the default)
    meets an even ``--links``; ``hint`` says what to do instead, in the command's words."""
    if (frame or "center") == "center" and n_links % 2 == 0:
        raise InputError(f"--links {n_links}: the center body frame (the middle link) needs an "
                         f"odd number of links; {hint}")


def add_threads(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--threads", type=int, default=1,
        help="torch threads (default 1: the work is many small tensor operations, which extra "
        "threads slow down, badly on a busy machine)")


def set_threads(n: int) -> None:
    """Set torch's intra-op thread count (``--threads``)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise InputError(f"--threads must be an integer >= 1, got {n!r}")
    torch.set_num_threads(n)


#: glibc's ``mallopt`` parameters (malloc.h): blocks above the mmap threshold get pages of
#: their own, returned to the system when freed; heap space above the trim threshold is returned
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def hold_freed_memory() -> None:
    """Keep freed memory in this process for reuse (glibc: blocks up to 256 MiB come from the
    heap, and up to 1 GiB of free heap is kept); elsewhere nothing.

    By default glibc gives each block above 32 MiB pages of its own and returns them when it
    is freed, so a command that allocates and frees tensors of tens of MB thousands of times
    (the sweep) spends much of its time in the kernel faulting in zeroed pages: a fifth of a
    9-link sweep cell's CPU time. A process-wide setting: for a command's own process, not a
    library call's.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library this process runs on
    except (OSError, AttributeError):  # not glibc
        return
    mallopt(_M_MMAP_THRESHOLD, 256 << 20)
    mallopt(_M_TRIM_THRESHOLD, 1 << 30)


#: the device names ``--device`` accepts
DEVICE_NAMES = "cpu, cuda, cuda:N or mps"


def add_device(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--device", default="cpu", metavar="DEVICE",
        help="where the tensors live: cpu (default), cuda or cuda:N (mps is refused: it has no "
        "float64). The data are read on the CPU, moved once, and the outputs written from CPU "
        "copies. CPU and CUDA draw different random numbers from the same seeds")


def resolve_device(name, where: str = "--device"):
    """The :class:`torch.device` a device name (``cpu``, ``cuda``, ``cuda:N``, ``mps``) means on
    this machine.

    Raises:
        InputError: naming ``where`` (the flag or config key), when the name is not a device, or
            the device is not available here (no CUDA in this torch build, no GPU ``N``), or it
            cannot run torchconn (MPS has no float64).
    """
    text = str(name).strip() if isinstance(name, (str, torch.device)) else None
    match = re.fullmatch(r"(cpu|cuda|mps)(?::(\d+))?", text or "")
    if match is None or (match[2] is not None and match[1] != "cuda"):
        raise InputError(f"{where} {name!r}: unknown device; expected {DEVICE_NAMES}")
    kind, index = match[1], match[2]
    build = f"torch {torch.__version__}"
    if kind == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"{where} {text}: CUDA is not available on this machine ({build})")
        count = torch.cuda.device_count()
        if index is not None and int(index) >= count:
            raise InputError(f"{where} {text}: this machine has {count} CUDA device(s), "
                             f"cuda:0 to cuda:{count - 1}")
    elif kind == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise InputError(f"{where} mps: MPS is not available on this machine ({build})")
        # a known limitation of Apple's MPS framework (pytorch/pytorch#122602)
        raise InputError(f"{where} mps: the MPS backend has no float64, and torchconn estimates "
                         "in float64; use --device cpu")
    return torch.device(text)


def prepare_output(path: Path | str, flag: str = "--out") -> Path:
    """Create the output folder ``path`` and check that files can be written in it.

    Raises:
        InputError: naming ``flag`` and the path, when it is a file, lies under a file, or is
            not writable.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: is a file, expected a folder for the outputs")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{flag} {path}: cannot create the output folder ({os_error_reason(err)})") \
            from None
    probe = path / f".write-test-{uuid.uuid4().hex}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise InputError(f"{flag} {path}: the output folder is not writable ({os_error_reason(err)})") \
            from None
    return path


def os_error_reason(err: OSError) -> str:
    """The short reason of an ``OSError`` for a message: its ``strerror`` (e.g. "Permission
    denied"), else the name of its type."""
    return err.strerror or type(err).__name__


def run_command(prog: str, body: Callable[[], int]) -> int:
    """Run ``body()`` and return its exit code; expected errors become ``prog: error: ...`` on
    stderr and exit code 2, an interrupt exit code 130, and an unexpected error one line
    (exit code 1; the traceback with ``TORCHCONN_DEBUG=1``)."""
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{prog}: warning: {message}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.showwarning = show
        # other libraries' deprecations (torch.func's own use of torch.jit, ...) are for
        # developers, not for the user of a command; torchconn's own are shown
        for category in (DeprecationWarning, PendingDeprecationWarning, FutureWarning):
            warnings.filterwarnings("ignore", category=category, module=r"(?!torchconn)")
        try:
            return body()
        except KeyboardInterrupt:
            print(f"{prog}: interrupted", file=sys.stderr)
            return 130
        except (ValueError, OSError) as err:  # InputError, parse errors, file errors
            print(f"{prog}: error: {_message(err)}", file=sys.stderr)
            return 2
        except Exception as err:
            if os.environ.get(DEBUG_ENV):
                traceback.print_exc()
            print(f"{prog}: internal error ({type(err).__name__}): {err}\n"
                  f"This is a bug in torchconn, not in your input; set {DEBUG_ENV}=1 for the "
                  "traceback and report it.", file=sys.stderr)
            return 1


def _message(err: BaseException) -> str:
    if isinstance(err, OSError) and err.filename is not None and str(err.filename) not in str(
            err.args[-1] if err.args else ""):
        return f"{err.filename}: {os_error_reason(err)}"
    return str(err)
