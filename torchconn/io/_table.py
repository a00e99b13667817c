"""Delimited text tables the way people save them, read without pandas.

:func:`read_table` reads a CSV-like file (:func:`torchconn._files.read_text`: UTF-8, a byte-order
mark dropped, binary and compressed files named) and finds its layout from the header and the
first rows, where that is unambiguous:

- the separator: comma, tab, semicolon, ``|`` or runs of blanks -- the one that splits the
  header and the rows into the same number of fields (the most fields wins);
- quoted cells (``"t","x"``) as the :mod:`csv` module reads them;
- lines starting with ``#`` are comments; a last comment line right before an all-numeric
  first row is the header when its fields match the rows (``numpy.savetxt``'s ``# t,x,...``);
- decimal commas (``0,5``) in a file whose separator is not the comma.

A decimal comma in a comma-separated file cannot be told from a separator; the field-count
error says so.
"""

from __future__ import annotations

import collections
import csv
import re
from os import PathLike
from pathlib import Path

from .._files import read_text

__all__ = ["read_table", "first_rows", "headerless", "DELIMITERS"]

#: separators tried, in this order of preference at equal field counts (" ": runs of blanks)
DELIMITERS = (",", "\t", ";", "|", " ")
_NAMES = {",": "commas", "\t": "tabs", ";": "semicolons", "|": "'|'", " ": "blanks"}
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+(?:[eE][+-]?\d+)?$")
#: rows looked at to choose the separator
_SNIFF_ROWS = 20


def _split(line: str, delimiter: str) -> list[str]:
    if delimiter == " ":
        return line.split()
    return next(csv.reader([line], delimiter=delimiter, skipinitialspace=True))


def _is_number(cell: str) -> bool:
    cell = cell.strip()
    if cell.lower() in ("", "nan", "na", "null"):
        return True
    try:
        float(cell.replace(",", "."))
        return True
    except ValueError:
        return False


def _choose_delimiter(header: str, rows: list[str]) -> str:
    """The separator that splits ``header`` and most of ``rows`` alike, into the most fields."""
    best, best_n = None, 1
    for d in DELIMITERS:
        n = len(_split(header, d))
        if n <= best_n:
            continue
        if rows:
            mode, _ = collections.Counter(len(_split(r, d)) for r in rows).most_common(1)[0]
            if mode != n:
                continue
        best, best_n = d, n
    if best is not None:
        return best
    # nothing consistent: the separator that splits the header most, so that the field-count
    # check names the first line that disagrees
    return max(DELIMITERS[:-1], key=lambda d: len(_split(header, d)))


def _layout(path: Path, what: str, header_rows: int | None):
    """Line numbers and texts of the content lines (blank and ``#`` comment lines left out, a
    ``numpy.savetxt`` comment header put back), and the separator."""
    text = read_text(path, what)
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    numbers, texts, comments = [], [], {}
    for number, line in enumerate(text.split("\n"), 1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped[0] == "#":
            comments[number] = stripped.lstrip("#").strip()
            continue
        numbers.append(number)
        texts.append(line)
    if not texts:
        return numbers, texts, ","
    delimiter = _choose_delimiter(texts[0], texts[1:_SNIFF_ROWS + 1])
    first = _split(texts[0], delimiter)
    # numpy.savetxt's header is a comment line right before the first row
    above = comments.get(numbers[0] - 1)
    if header_rows in (None, 1) and above and all(map(_is_number, first)):
        cells = _split(above, delimiter)
        if len(cells) == len(first) and not all(map(_is_number, cells)):
            numbers.insert(0, numbers[0] - 1)
            texts.insert(0, above)
    return numbers, texts, delimiter


def _parse(path: Path, numbers: list[int], texts: list[str], delimiter: str,
           error) -> list[list[str]]:
    """The cells of every line in ``texts``."""
    if delimiter != " ":  # one reader for all lines, unless a quoted cell spans lines
        try:
            rows = list(csv.reader(texts, delimiter=delimiter, skipinitialspace=True))
        except csv.Error:
            rows = None
        if rows is not None and len(rows) == len(texts):
            return rows
    rows = []
    for number, line in zip(numbers, texts, strict=True):
        try:
            rows.append(_split(line, delimiter))
        except csv.Error as err:
            raise error(f"{path}, line {number}: not valid CSV ({err})") from None
    return rows


def first_rows(path: str | PathLike, what: str, n: int) -> list[list[str]]:
    """The cells of the first ``n`` rows of a delimited text file (layout as
    :func:`read_table` finds it, blank and comment lines skipped, nothing checked)."""
    path = Path(path)
    numbers, texts, delimiter = _layout(path, what, None)
    return _parse(path, numbers[:n], texts[:n], delimiter, ValueError)


def headerless(path: str | PathLike, what: str) -> bool:
    """True when the first row of a delimited text file holds only numbers (no header)."""
    first = first_rows(path, what, 1)
    return bool(first) and all(map(_is_number, first[0]))


def read_table(
    path: str | PathLike,
    what: str,
    *,
    header_rows: int | None = 1,
    error: type[Exception] = ValueError,
) -> tuple[list[list[str]], list[list[str]], list[int], str]:
    """Header rows, data rows, their line numbers and the separator of a delimited text file.

    Args:
        path: the file.
        what: what it should be, for messages (e.g. ``"a trajectory CSV file"``).
        header_rows: rows of header (``None``: one if the first row holds a non-number).
        error: the exception class raised for a malformed table.

    Returns:
        ``(heads, rows, lines, delimiter)``: ``heads`` the header rows' cells (stripped),
        ``rows`` every data row's cells, ``lines`` their 1-based line numbers in the file.
        Blank and ``#`` comment lines are skipped. With a decimal comma, data cells have it
        replaced by a point.

    Raises:
        error: naming the file and line, for a row whose field count differs from the header.
        FileNotFoundError, OSError, ValueError: from :func:`torchconn._files.read_text`.
    """
    path = Path(path)
    numbers, texts, delimiter = _layout(path, what, header_rows)
    parsed = _parse(path, numbers, texts, delimiter, error)
    if header_rows is None:
        header_rows = int(bool(parsed) and not all(map(_is_number, parsed[0])))
    heads = [[c.strip() for c in cells] for cells in parsed[:header_rows]]
    rows = parsed[header_rows:]
    lines = numbers[header_rows:]
    if delimiter != "," and any(_DECIMAL_COMMA.match(c.strip()) for r in rows[:_SNIFF_ROWS]
                                for c in r):
        rows = [[c.replace(",", ".") if _DECIMAL_COMMA.match(c.strip()) else c for c in r]
                for r in rows]
    width = len(heads[0]) if heads else (len(rows[0]) if rows else 0)
    if delimiter == " ":  # blank-separated: empty trailing cells cannot be written but by omission
        rows = [r + [""] * (width - len(r)) if len(r) < width else r for r in rows]
    for cells, number in zip(rows, lines, strict=True):
        if len(cells) != width:
            raw = texts[numbers.index(number)]
            hint = ""
            if delimiter == "," and len(cells) > width and "." not in raw and re.search(
                    r"\d,\d", raw):
                hint = ("; decimal commas ('0,5') in a comma-separated file? write decimals "
                        "with a point, or separate the columns with ';'")
            what_has = (f"the header has {width} ({', '.join(heads[0])})" if heads
                        else f"the first row has {width}")
            raise error(f"{path}, line {number}: {len(cells)} fields, but {what_has}; fields "
                        f"separated by {_NAMES[delimiter]}{hint}")
    return heads, rows, lines, delimiter
