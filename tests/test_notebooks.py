"""Every example notebook runs top to bottom in small-data mode and writes its figures.

The notebooks in ``notebooks/`` are jupytext "percent" scripts (plain Python), picked up by the
pattern ``notebooks/0*.py``, so a new notebook is tested as soon as it exists. Each runs in a
subprocess with ``TORCHCONN_SMALL=1`` (few trials and cycles), the Agg backend and
``TORCHCONN_NB_OUT`` pointing into ``tmp_path``; a notebook writes its PNGs to
``$TORCHCONN_NB_OUT/<notebook name>/`` and lists them, one per line, in ``figures.txt`` there.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("0*.py"))

#: fewest figures each known notebook must produce; any other notebook must produce one
MIN_FIGURES = {"01_quickstart": 8, "02_paper_results": 5, "04_your_own_data": 5}

#: per-notebook wall-clock limit in small-data mode (the target is well under a minute)
TIMEOUT_S = 240

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_notebooks_are_found():
    assert NOTEBOOKS, f"no notebooks matching 0*.py in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_in_small_mode(notebook: Path, tmp_path: Path):
    env = dict(os.environ)
    env.pop("TORCHCONN_SWEEP_DIR", None)  # a user's sweep must not leak into the test
    env.update(
        TORCHCONN_SMALL="1",
        TORCHCONN_NB_OUT=str(tmp_path),
        MPLBACKEND="Agg",
        # tiny tensors: one intra-op thread is fastest, and avoids oversubscribing a busy machine
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
    )
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(notebook)], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=TIMEOUT_S,
    )
    elapsed = time.perf_counter() - start
    assert proc.returncode == 0, (
        f"{notebook.name} failed (exit code {proc.returncode}) after {elapsed:.0f} s\n"
        f"--- stdout (tail) ---\n{proc.stdout[-3000:]}\n"
        f"--- stderr (tail) ---\n{proc.stderr[-5000:]}"
    )

    out = tmp_path / notebook.stem
    manifest = out / "figures.txt"
    assert manifest.exists(), f"{notebook.name} wrote no {manifest.name} in {out}"
    listed = [line.strip() for line in manifest.read_text().splitlines() if line.strip()]
    for name in listed:
        path = out / name
        assert path.exists(), f"{notebook.name} lists {name} but did not write it"
        with path.open("rb") as fh:
            assert fh.read(8) == PNG_MAGIC, f"{path} is not a PNG file"
        assert path.stat().st_size > 2000, f"{path} is suspiciously small (empty figure?)"
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert set(listed) <= set(pngs)
    expected = MIN_FIGURES.get(notebook.stem, 1)
    assert len(pngs) >= expected, (
        f"{notebook.name} produced {len(pngs)} figures ({pngs}), expected at least {expected}"
    )
