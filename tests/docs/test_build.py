"""The documentation site builds with warnings as errors, the notebooks executed in small mode.

Needs the ``docs`` extra (``pip install -c constraints.txt -e '.[docs]'``); skipped without it.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

from .common import DOCS

TOOLS = ("sphinx", "myst_nb", "pydata_sphinx_theme", "jupytext", "ipykernel")
MISSING = [t for t in TOOLS if importlib.util.find_spec(t) is None]


@pytest.mark.slow
@pytest.mark.skipif(bool(MISSING), reason=f"the docs extra is not installed (no {', '.join(MISSING)})")
def test_the_site_builds_without_warnings(tmp_path):
    # a fresh notebook cache, so that the notebooks run in this build
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               TORCHCONN_DOCS_CACHE=str(tmp_path / "jupyter_cache"))
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-j", "1", "-b", "html",
         "-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")],
        capture_output=True, text=True, env=env, timeout=1500)
    assert proc.returncode == 0, f"sphinx-build failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}"
    html = tmp_path / "html"
    for page in ("index", "getting-started", "api/index", "changelog", "validation"):
        assert (html / f"{page}.html").is_file(), page
    # every name in torchconn.__all__ has an API page
    import torchconn
    for name in torchconn.__all__:
        target = {"gaits": "torchconn.physics.gaits", "se2": "torchconn.physics.se2"}.get(
            name, f"torchconn.{name}")
        assert (html / "api" / "generated" / f"{target}.html").is_file(), name
    # the tutorials were executed: their pages hold the figures they drew
    tutorials = sorted((html / "tutorials" / "generated").glob("0*.html"))
    assert len(tutorials) == len(list((DOCS.parent / "notebooks").glob("0*.py")))
    for page in tutorials:
        assert "<img" in page.read_text(encoding="utf-8"), f"{page.name} shows no figure"
