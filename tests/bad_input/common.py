"""What every bad-input test asserts, and the files they start from.

A refused input gets exit code 2, one message naming the problem (file, line, column, key) and
no traceback, and leaves no output; a doubtful one (``warn``) runs with exit code 0 and a
``warning:`` line that gives its evidence.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def assert_clean_failure(code: int, err: str, fragments, out: Path | None) -> None:
    """Exit code 2, one message holding every fragment, no traceback, no partial output."""
    assert code == 2, err
    assert "Traceback" not in err and "internal error" not in err, err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and errors[0] == err.splitlines()[-1], err  # one message, last
    # one message, not a dump (warnings about the input may come before it)
    assert sum(": warning: " not in line for line in err.splitlines()) <= 2, err
    for fragment in fragments:
        assert fragment in err, f"{fragment!r} not in {err!r}"
    if out is not None:
        assert not out.exists() or not any(out.iterdir()), f"partial output in {out}"


def assert_warned(code: int, err: str, fragments) -> None:
    """Exit code 0, a ``warning:`` line holding every fragment, no traceback."""
    assert code == 0, err
    assert "Traceback" not in err and "internal error" not in err, err
    warned = [line for line in err.splitlines() if ": warning: " in line]
    assert any(all(f in line for f in fragments) for line in warned), \
        f"no warning with {fragments!r} in {err!r}"


def must_not_run(*args, **kwargs):
    raise AssertionError("computation started before the input was checked")


def lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def variant(recording: Path, tmp_path: Path, line: int, column: str, value: str) -> Path:
    """The recording with ``value`` in ``column`` on file line ``line`` (1: the header)."""
    rows = lines(recording)
    header = rows[0].split(",")
    cells = rows[line - 1].split(",")
    cells[header.index(column)] = value
    rows[line - 1] = ",".join(cells)
    path = tmp_path / f"bad_{column}.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def run_module(*argv: str) -> subprocess.CompletedProcess:
    """``python -m argv...`` with this checkout first on the path (what a user sees)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", *argv], env=env, capture_output=True,
                          text=True, timeout=300)


def noise_csv(tmp_path: Path, n: int, seed: int) -> Path:
    """A trajectory CSV of white noise (no gait): ``n`` rows, 2 joints."""
    rng = np.random.default_rng(seed)
    table = np.column_stack([np.arange(n) * 0.1, rng.normal(size=(n, 5)) * 0.1])
    path = tmp_path / "noise.csv"
    np.savetxt(path, table, delimiter=",", header="t,x,y,theta,r1,r2", comments="")
    return path
