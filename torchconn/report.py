"""A command's report: plain-language sections, tables and figures in one self-contained HTML file.

A :class:`Report` collects what a command found, in the order a reader needs it: paragraphs,
bulleted findings, small tables and figures. :meth:`Report.text` gives the same content as
the lines a command prints; :meth:`Report.html` one HTML page with every figure embedded as a
PNG (``data:`` URI), no script, no external style sheet and no link outside the page, so it
opens anywhere and can be mailed or archived as it is. :func:`trust` grades an estimate by the
size of its confidence band against its own size, the words the reports use for "can this be
trusted".

Example::

    report = Report("torchconn-fit: prickleback.csv")
    report.section("What was fitted", ["5.4 cycles of 131 samples, gait 1.9 Hz, 5 links"])
    report.table("Held-out R²", ["component", "model"], [["v_x", "0.23"]])
    png, caption = render_png(fig)  # torchconn.plotting
    report.figure(png, caption)
    report.write("out/report.html")
"""

from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._output import write_bytes_atomic

__all__ = ["Report", "trust", "TRUST_LEVELS"]

#: (largest relative band half-width, word) from best to worst; beyond the last, "poorly"
TRUST_LEVELS = ((0.1, "well"), (0.3, "roughly"))

_STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; max-width: 60rem;
       margin: 2rem auto; padding: 0 1rem; color: #222; line-height: 1.45; }
h1 { font-size: 1.5rem; } h2 { font-size: 1.2rem; margin-top: 2rem;
     border-bottom: 1px solid #ddd; padding-bottom: .2rem; }
table { border-collapse: collapse; margin: .5rem 0 1rem; }
th, td { border: 1px solid #ccc; padding: .25rem .6rem; text-align: right; }
th:first-child, td:first-child { text-align: left; }
thead th { background: #f3f3f3; }
figure { margin: 1rem 0 2rem; } figure img { max-width: 100%; height: auto; }
figcaption { font-size: .92rem; color: #444; margin-top: .3rem; }
.note { color: #555; font-size: .9rem; }
"""


def trust(value, se) -> tuple[str, float]:
    """How well an estimate is determined: ``(word, ratio)`` where ``ratio`` is the RMS of
    the 95 % band half-width (``1.96 · se``) over the RMS of the estimate, both over every
    entry (array-likes of one shape; NaNs skipped), and ``word`` is ``"well"`` (ratio below
    0.1), ``"roughly"`` (below 0.3) or ``"poorly"``; ``("not estimated", nan)`` where there
    is nothing finite."""
    v = np.asarray(value, dtype=float)
    s = np.asarray(se, dtype=float)
    ok = np.isfinite(v) & np.isfinite(s)
    if not ok.any():
        return "not estimated", math.nan
    size = math.sqrt(float(np.mean(v[ok] ** 2)))
    half = 1.96 * math.sqrt(float(np.mean(s[ok] ** 2)))
    ratio = half / size if size > 0 else math.inf
    for limit, word in TRUST_LEVELS:
        if ratio < limit:
            return word, ratio
    return "poorly", ratio


@dataclass
class _Block:
    kind: str  # "section", "table" or "figure"
    title: str = ""
    lines: list[str] = field(default_factory=list)
    columns: list[str] = field(default_factory=list)
    rows: list[list[str]] = field(default_factory=list)
    png: bytes = b""
    note: str = ""


class Report:
    """A command's findings, written as text (:meth:`text`) or one HTML page (:meth:`html`).

    Args:
        title: the page's heading, e.g. ``"torchconn-fit: fish.csv"``.
        intro: a first paragraph (optional).
    """

    def __init__(self, title: str, intro: str = ""):
        self.title = title
        self.intro = intro
        self._blocks: list[_Block] = []

    def section(self, title: str, lines: list[str], note: str = "") -> "Report":
        """A heading with findings, one per line (a bulleted list in HTML), and a ``note``
        in small print below them."""
        self._blocks.append(_Block("section", title, [str(x) for x in lines], note=note))
        return self

    def table(self, title: str, columns: list[str], rows: list[list], note: str = ""
              ) -> "Report":
        """A small table (``rows`` of cells, each formatted with ``str``)."""
        self._blocks.append(_Block("table", title, columns=[str(c) for c in columns],
                                   rows=[[str(c) for c in row] for row in rows], note=note))
        return self

    def figure(self, png: bytes, caption: str) -> "Report":
        """A figure, the bytes of its PNG (:func:`torchconn.plotting.render_png` renders a
        matplotlib ``Figure`` as the commands write it), embedded with its ``caption`` (what
        it shows and what good looks like)."""
        if not isinstance(png, bytes | bytearray):
            raise TypeError(f"Report.figure: png must be the bytes of a PNG, got "
                            f"{type(png).__name__} (render a Figure with "
                            "torchconn.plotting.render_png)")
        self._blocks.append(_Block("figure", note=caption, png=bytes(png)))
        return self

    @property
    def n_figures(self) -> int:
        return sum(block.kind == "figure" for block in self._blocks)

    def text(self) -> list[str]:
        """The report's sections and tables as printable lines (figures are left out)."""
        out = [self.title] + ([self.intro] if self.intro else [])
        for block in self._blocks:
            if block.kind == "section":
                out.append(f"{block.title}:")
                out += [f"  - {line}" for line in block.lines]
            elif block.kind == "table":
                out.append(f"{block.title}:")
                widths = [max(len(r[k]) for r in [block.columns, *block.rows])
                          for k in range(len(block.columns))]
                for row in [block.columns, *block.rows]:
                    out.append("  " + "  ".join(cell.rjust(w) if k else cell.ljust(w)
                                                for k, (cell, w) in enumerate(zip(row, widths, strict=True))))
            if block.kind != "figure" and block.note:
                out.append(f"  ({block.note})")
        return out

    def html(self) -> str:
        """One self-contained HTML page (figures embedded, no scripts, no outside links)."""
        e = html.escape
        parts = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
                 f"<title>{e(self.title)}</title>", f"<style>{_STYLE}</style>", "</head>",
                 "<body>", f"<h1>{e(self.title)}</h1>"]
        if self.intro:
            parts.append(f"<p>{e(self.intro)}</p>")
        n = 0
        for block in self._blocks:
            if block.kind == "section":
                parts.append(f"<h2>{e(block.title)}</h2>")
                parts.append("<ul>" + "".join(f"<li>{e(x)}</li>" for x in block.lines)
                             + "</ul>")
            elif block.kind == "table":
                parts.append(f"<h2>{e(block.title)}</h2>")
                head = "".join(f"<th>{e(c)}</th>" for c in block.columns)
                body = "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>"
                               for row in block.rows)
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody>"
                             "</table>")
            else:
                n += 1
                data = base64.b64encode(block.png).decode("ascii")
                parts.append(f'<figure id="figure-{n}"><img alt="Figure {n}" '
                             f'src="data:image/png;base64,{data}">'
                             f"<figcaption><b>Figure {n}.</b> {e(block.note)}</figcaption>"
                             "</figure>")
                continue
            if block.note:
                parts.append(f'<p class="note">{e(block.note)}</p>')
        parts += ["</body>", "</html>"]
        return "\n".join(parts) + "\n"

    def write(self, path: str | Path) -> Path:
        """Write :meth:`html` to ``path`` atomically (a crash leaves no half-written file)."""
        return write_bytes_atomic(path, self.html().encode("utf-8"))
