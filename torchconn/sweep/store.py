"""Resumable storage of finished experiments.

Each experiment's tables go to ``OUT/cells/<name>-<fingerprint>/`` and a ``done.json`` written
last (atomically) marks it complete. The fingerprint hashes everything that determines the
results, so re-running the same command skips finished experiments, an interrupted run loses
nothing already stored, and a changed config never reuses stale results.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

from .experiment import PHASE_COLUMNS, RESULT_COLUMNS, TRACE_COLUMNS, ExperimentResult

__all__ = ["ResultStore", "write_csv", "read_csv_rows", "read_table"]

_TABLES = {"results": RESULT_COLUMNS, "phase_errors": PHASE_COLUMNS, "traces": TRACE_COLUMNS}


def write_csv(path: Path, columns, rows) -> None:
    """Write rows atomically (a temporary file renamed into place)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        writer.writerows(rows)
    os.replace(tmp, path)


def _parse(value: str):
    """A CSV cell back as an int or a float where it is one, else the string itself."""
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    return value


def read_csv_rows(path: Path) -> list[tuple]:
    """Rows of a table written by :func:`write_csv`, numbers parsed back."""
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        next(reader)
        return [tuple(_parse(v) for v in row) for row in reader]


def read_table(path: Path | str) -> list[dict]:
    """Rows of a sweep CSV (``results.csv``, ``claims.csv``, ...) as dicts keyed by the header,
    numbers parsed back."""
    with Path(path).open(newline="") as fh:
        return [{k: _parse(v) for k, v in row.items()} for row in csv.DictReader(fh)]


class ResultStore:
    def __init__(self, out_dir: Path | str):
        self.root = Path(out_dir)
        (self.root / "cells").mkdir(parents=True, exist_ok=True)

    def cell_dir(self, name: str, fingerprint: str) -> Path:
        return self.root / "cells" / f"{name}-{fingerprint}"

    def is_done(self, name: str, fingerprint: str) -> bool:
        return (self.cell_dir(name, fingerprint) / "done.json").exists()

    def save(self, name: str, fingerprint: str, result: ExperimentResult) -> None:
        d = self.cell_dir(name, fingerprint)
        d.mkdir(parents=True, exist_ok=True)
        for table, columns in _TABLES.items():
            write_csv(d / f"{table}.csv", columns, getattr(result, table))
        tmp = d / "done.json.tmp"
        tmp.write_text(json.dumps({"timings": result.timings}, indent=2))
        os.replace(tmp, d / "done.json")

    def load(self, name: str, fingerprint: str) -> ExperimentResult:
        d = self.cell_dir(name, fingerprint)
        timings = json.loads((d / "done.json").read_text())["timings"]
        tables = {t: read_csv_rows(d / f"{t}.csv") for t in _TABLES}
        return ExperimentResult(timings=timings, **tables)
