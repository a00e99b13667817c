"""Resumable, checked storage of finished cells.

Each cell's tables go to ``OUT/cells/<cell>-<fingerprint>/`` and a ``cell.json`` written last
(atomically) records the fingerprint and a SHA-256 checksum of every table. The fingerprint
hashes everything that determines the cell's rows -- the experiment, the estimator, the seeds'
root, the cell's level and trials, and torchconn's version and source code -- so re-running
the same command skips finished cells, an interrupted run loses only the cells in flight, and
a changed config or a code change never reuses stale results. On load a missing, truncated or
edited file, or one that does not parse, makes :meth:`ResultStore.load` report the cell as
damaged (with the reason); the runner recomputes it. :meth:`ResultStore.clean` removes what
can never be used again: the temporary files of a killed run, and stale cells -- computed by
other code, superseded by the current config's cell of the same name, or left incomplete.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import re
import shutil
from pathlib import Path

from .._output import csv_bytes, is_temporary, write_bytes_atomic
from .._provenance import source_hash
from .experiment import PHASE_COLUMNS, RESULT_COLUMNS, TRACE_COLUMNS, Cell, ExperimentResult

__all__ = ["ResultStore", "read_csv_rows", "read_table"]

_TABLES = {"results": RESULT_COLUMNS, "phase_errors": PHASE_COLUMNS, "traces": TRACE_COLUMNS}
_MANIFEST = "cell.json"
_FORMAT = "torchconn.sweep.cell/1"
#: a cell folder's name: ``<cell name>-<16 hex digits of its fingerprint>``
_CELL_DIR = re.compile(r"(?P<cell>.+)-(?P<fingerprint>[0-9a-f]{16})")


def _parse(value: str):
    """A CSV cell back as an int or a float where it is one, else the string itself."""
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    return value


def read_csv_rows(path: Path, columns=None) -> list[tuple]:
    """Rows of a table written by :func:`~torchconn._output.write_table`, numbers parsed back.
    With ``columns``, the header must match and every row must have that many fields (else
    ``ValueError``)."""
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
    numbers parsed back.

    Raises:
        ValueError: when the sweep that wrote it has not finished (its folder has no
            ``run.json``, written last): the tables may be of two runs.
    """
    folder = Path(path).parent
    if (folder / "cells").is_dir() and not (folder / "run.json").exists():
        raise ValueError(f"{path}: the sweep writing {folder} has not finished (no run.json, "
                         "which is written last); run it again to complete it")
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
            data = csv_bytes(columns, getattr(result, table))
            write_bytes_atomic(d / f"{table}.csv", data)
            sums[f"{table}.csv"] = hashlib.sha256(data).hexdigest()
        manifest = {"format": _FORMAT, "cell": cell.name, "fingerprint": fingerprint,
                    "source_hash": source_hash(), "sha256": sums, "timings": result.timings}
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

    def clean(self, plan, log=lambda msg: None) -> tuple[list[str], list[tuple[str, str]]]:
        """Remove what can never be used again, and say what it was.

        Removes the temporary files a killed run left (in ``OUT`` and in the cell folders) and
        the stale cell folders: those computed by other code (their ``cell.json`` records
        another source hash, or none), those of a cell in ``plan`` stored under another
        fingerprint (a changed config), and incomplete ones not in ``plan``. Cells of other
        configs computed by this code are kept for reuse; only folders named as the store
        names them are considered.

        Args:
            plan: ``(cell, fingerprint)`` of the current run.
            log: receives one line per stale cell folder before it is removed, and one for
                the temporary files removed.

        Returns:
            the temporary files removed (paths relative to ``OUT``), and ``(folder, reason)``
            for each stale cell folder removed.
        """
        planned = {self.cell_dir(cell, fp).name for cell, fp in plan}
        names = {cell.name for cell, _ in plan}
        temporary = []
        for folder in [self.root, *sorted(p for p in (self.root / "cells").iterdir()
                                          if p.is_dir())]:
            for p in sorted(folder.iterdir()):
                if p.is_file() and (is_temporary(p.name) or p.name.startswith(".write-test-")):
                    p.unlink(missing_ok=True)
                    temporary.append(str(p.relative_to(self.root)))
        if temporary:
            log(f"removed {len(temporary)} temporary file(s) of an interrupted run: "
                + ", ".join(temporary))
        stale = []
        for d in sorted((self.root / "cells").iterdir()):
            match = _CELL_DIR.fullmatch(d.name)
            if not d.is_dir() or match is None or d.name in planned:
                continue
            reason = self._stale(d, match["cell"] in names)
            if reason is not None:
                log(f"removing stale cell folder cells/{d.name}: {reason}")
                stale.append((d.name, reason))
                shutil.rmtree(d)
        return temporary, stale

    @staticmethod
    def _stale(d: Path, superseded: bool) -> str | None:
        try:
            manifest = json.loads((d / _MANIFEST).read_text(encoding="utf-8"))
            if not isinstance(manifest, dict) or manifest.get("format") != _FORMAT:
                raise ValueError
        except (OSError, ValueError):
            return "incomplete or damaged, and not a cell of this run"
        if manifest.get("source_hash") != source_hash():
            return "computed by other torchconn code"
        if superseded:
            return "superseded: the config now gives this cell another fingerprint"
        return None
