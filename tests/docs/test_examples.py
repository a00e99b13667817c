"""Every ```python example in the README and the guides runs, in a temporary folder."""

from __future__ import annotations

import os

import matplotlib
import pytest

from .common import EXAMPLE_PAGES, ROOT, code_blocks

matplotlib.use("Agg")

EXAMPLES = [pytest.param(code, id=f"{page.relative_to(ROOT)}:{line}")
            for page in EXAMPLE_PAGES for line, code in code_blocks(page, "python")]


def test_the_readme_and_the_guides_have_examples():
    pages = {e.id.split(":")[0] for e in EXAMPLES}
    assert "README.md" in pages and any(p.startswith("docs/guides/") for p in pages)


@pytest.mark.parametrize("code", EXAMPLES)
def test_example_runs(code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    exec(compile(code, "<example>", "exec"), {"__name__": "__example__"})
    assert os.getcwd() == str(tmp_path)
