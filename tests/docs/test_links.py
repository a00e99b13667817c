"""Internal links in the README and the docs' Markdown pages resolve: relative files exist and
``#anchors`` name a heading of the target page."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from .common import LINK_PAGES, ROOT, anchors, slug, without_code

LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def internal_links(page: Path) -> list[str]:
    text = without_code(page.read_text(encoding="utf-8"))
    return [t for t in LINK.findall(text) if not re.match(r"^[a-z][a-z0-9+.-]*:", t)]


def test_slug_matches_github():
    assert slug("Reading the report") == "reading-the-report"
    assert slug("Choosing `--links`") == "choosing---links"
    assert slug("`prickleback()`: a swimming rock prickleback") == \
        "prickleback-a-swimming-rock-prickleback"


@pytest.mark.parametrize("page", LINK_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_internal_links_resolve(page):
    broken = []
    for target in internal_links(page):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no file {dest}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor} in {dest.name}")
    assert not broken, f"{page.relative_to(ROOT)}: broken links:\n" + "\n".join(broken)


def test_a_missing_file_or_heading_is_found(tmp_path):
    (tmp_path / "a.md").write_text("# Title\n\n## Choosing `--links`\n\n```md\n# not a heading\n```\n")
    page = tmp_path / "b.md"
    page.write_text("[ok](a.md#choosing---links) [gone](c.md) [bad](a.md#not-a-heading) "
                    "`[code](x.md)` [web](https://example.org)\n")
    assert internal_links(page) == ["a.md#choosing---links", "c.md", "a.md#not-a-heading"]
    assert anchors(tmp_path / "a.md") == {"title", "choosing---links"}
