"""The Markdown files the docs tests read, and helpers to take them apart."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = ROOT / "README.md"

#: the pages whose examples the tests run: the README and the hand-written guides (not the
#: changelog, whose examples record past versions, nor the generated or built files)
EXAMPLE_PAGES = [README, *sorted(p for p in DOCS.rglob("*.md")
                                  if not p.relative_to(DOCS).parts[0].startswith("_")
                                  and p.relative_to(DOCS).parts[0] not in ("validation", "tutorials")
                                  and p.name != "changelog.md")]

#: every Markdown page whose links are checked
LINK_PAGES = [README, *sorted(p for p in DOCS.rglob("*.md")
                               if not p.relative_to(DOCS).parts[0].startswith("_")
                               and "generated" not in p.relative_to(DOCS).parts)]

FENCE = re.compile(r"^(```+|~~~+)\s*([\w{}-]*)[^\n]*\n(.*?)^\1\s*$", re.S | re.M)


def code_blocks(path: Path, language: str) -> list[tuple[int, str]]:
    """The fenced code blocks of ``language`` in ``path``: (line of the fence, code)."""
    text = path.read_text(encoding="utf-8")
    return [(text.count("\n", 0, m.start()) + 1, m.group(3))
            for m in FENCE.finditer(text) if m.group(2) == language]


def without_fences(text: str) -> str:
    """``text`` with fenced code blocks blanked (their lines are not headings or links)."""
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def without_code(text: str) -> str:
    """``text`` with fenced blocks and inline code blanked (their links are not links)."""
    return re.sub(r"`[^`\n]*`", "``", without_fences(text))


def slug(heading: str) -> str:
    """The anchor GitHub and MyST (``myst_heading_anchors``) give a heading."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The heading anchors of a Markdown file (duplicates get ``-1``, ``-2``, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for line in without_fences(path.read_text(encoding="utf-8")).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        s = slug(m.group(1))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out
