"""Resumable, checked storage of finished cells.

Each cell's tables go to ``OUT/cells/<cell>-<fingerprint>/`` and a ``cell.json`` written last
(atomically) records the fingerprint and a SHA-256 checksum of every table. The fingerprint
hashes everything that determines the cell's rows -- the experiment, the estimator, the seeds'
root, the cell's level and trials, and torchconn's version and source code -- so re-running
the same command skips finished cells, an interrupted run loses only the cells in flight, and
a changed config or a code change never reuses stale results. On load a missing, truncated or
edited file, or one that does not parse, makes :meth:`ResultStore.load` report the cell as
damaged (with the reason); the runner recomputes it.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from pathlib import Path

from .._provenance import write_bytes_atomic
from .experiment import PHASE_COLUMNS, RESULT_COLUMNS, TRACE_COLUMNS, Cell, ExperimentResult

__all__ = ["ResultStore", "write_csv", "read_csv_rows", "read_table"]

_TABLES = {"results": RESULT_COLUMNS, "phase_errors": PHASE_COLUMNS, "traces": TRACE_COLUMNS}
_MANIFEST = "cell.json"
_FORMAT = "torchconn.sweep.cell/1"


def _csv_bytes(columns, rows) -> bytes:
    buf = io.StringIO(newline="")
    writer = csv.writer(buf)
    writer.writerow(columns)
    writer.writerows(rows)
    return buf.getvalue().encode()


def write_csv(path: Path, columns, rows) -> None:
    """Write rows atomically (a temporary file renamed into place)."""
    write_bytes_atomic(Path(path), _csv_bytes(columns, rows))


def _parse(value: str):
    """A CSV cell back as an int or a float where it is one, else the string itself."""
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    return value


def read_csv_rows(path: Path, columns=None) -> list[tuple]:
    """Rows of a table written by :func:`write_csv`, numbers parsed back. With ``columns``,
    the header must match and every row must have that many fields (else ``ValueError``)."""
    return _rows(Path(path).read_bytes(), columns)


def _rows(data: bytes, columns=None) -> list[tuple]:
    reader = csv.reader(io.StringIO(data.decode("utf-8"), newline=""))
    header = next(reader, None)
    if columns is not None and tuple(header or ()) != tuple(columns):
        raise ValueError(f"header {header} is not {list(columns)}")
    rows = []
    for row in reader:
        if columns is not None and len(row) != len(columns):
            raise ValueError(f"line {reader.line_num} has {len(row)} fields, expected "
                             f"{len(columns)}")
        rows.append(tuple(_parse(v) for v in row))
    return rows


def read_table(path: Path | str) -> list[dict]:
    """Rows of a sweep CSV (``results.csv``, ``claims.csv``, ...) as dicts keyed by the header,
    numbers parsed back."""
    with Path(path).open(newline="") as fh:
        return [{k: _parse(v) for k, v in row.items()} for row in csv.DictReader(fh)]


class ResultStore:
    """Finished cells under ``OUT/cells/``; see the module docstring."""

    def __init__(self, out_dir: Path | str):
        self.root = Path(out_dir)
        (self.root / "cells").mkdir(parents=True, exist_ok=True)

    def cell_dir(self, cell: Cell, fingerprint: str) -> Path:
        return self.root / "cells" / f"{cell.name}-{fingerprint}"

    def save(self, cell: Cell, fingerprint: str, result: ExperimentResult) -> None:
        """Write the cell's tables, then its ``cell.json`` (checksums, fingerprint) last."""
        d = self.cell_dir(cell, fingerprint)
        d.mkdir(parents=True, exist_ok=True)
        sums = {}
        for table, columns in _TABLES.items():
            data = _csv_bytes(columns, getattr(result, table))
            write_bytes_atomic(d / f"{table}.csv", data)
            sums[f"{table}.csv"] = hashlib.sha256(data).hexdigest()
        manifest = {"format": _FORMAT, "cell": cell.name, "fingerprint": fingerprint,
                    "sha256": sums, "timings": result.timings}
        write_bytes_atomic(d / _MANIFEST, json.dumps(manifest, indent=2).encode())

    def load(self, cell: Cell, fingerprint: str) -> tuple[ExperimentResult | None, str | None]:
        """The stored cell, checked: ``(result, None)`` when intact, ``(None, None)`` when not
        stored, ``(None, reason)`` when damaged or incomplete."""
        d = self.cell_dir(cell, fingerprint)
        if not d.exists():
            return None, None
        path = d / _MANIFEST
        if not path.exists():
            return None, f"incomplete: no {_MANIFEST} (the run writing it was interrupted)"
        try:
            manifest = json.loads(path.read_text(encoding="utf-8"))
            sums, timings = manifest["sha256"], manifest["timings"]
            if manifest.get("format") != _FORMAT or manifest.get("fingerprint") != fingerprint:
                return None, f"{_MANIFEST} belongs to another cell or format"
        except (OSError, ValueError, KeyError, TypeError) as err:
            return None, f"{_MANIFEST} unreadable ({type(err).__name__}: {err})"
        tables = {}
        for table, columns in _TABLES.items():
            name = f"{table}.csv"
            try:
                data = (d / name).read_bytes()
            except FileNotFoundError:
                return None, f"{name} is missing"
            except OSError as err:
                return None, f"{name} unreadable ({err.strerror})"
            if not isinstance(sums, dict) or hashlib.sha256(data).hexdigest() != sums.get(name):
                return None, f"{name} does not match its checksum (truncated or edited)"
            try:
                tables[table] = _rows(data, columns)
            except (ValueError, UnicodeDecodeError, csv.Error) as err:
                return None, f"{name} does not parse ({err})"
        return ExperimentResult(timings=dict(timings), **tables), None
