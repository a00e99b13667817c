"""Every example notebook runs top to bottom and writes its figures: in small-data mode by
default, at full size in the slow tests.

The notebooks in ``notebooks/`` are jupytext "percent" scripts (plain Python), picked up by the
pattern ``notebooks/0*.py``, so a new notebook is tested as soon as it exists. Each runs in a
subprocess with ``TORCHCONN_SMALL=1`` (few trials and cycles; unset at full size), the Agg
backend and ``TORCHCONN_NB_OUT`` pointing into ``tmp_path``; a notebook writes its PNGs to
``$TORCHCONN_NB_OUT/<notebook name>/`` and lists them, one per line, in ``figures.txt`` there.
The ``notebooks`` extra executes one as a notebook with ``jupytext --execute``.
"""

from __future__ import annotations

import importlib.util
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
#: per-notebook limit at full size (measured on one thread of a shared machine: 10-160 s)
FULL_TIMEOUT_S = 900

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _env(tmp_path: Path, small: bool) -> dict:
    env = dict(os.environ)
    env.pop("TORCHCONN_SWEEP_DIR", None)  # a user's sweep must not leak into the test
    env.pop("TORCHCONN_SMALL", None)
    env.update(
        TORCHCONN_NB_OUT=str(tmp_path),
        MPLBACKEND="Agg",
        # tiny tensors: one intra-op thread is fastest, and avoids oversubscribing a busy machine
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
    )
    if small:
        env["TORCHCONN_SMALL"] = "1"
    return env


def _run(command: list, notebook: Path, tmp_path: Path, small: bool, timeout: float) -> None:
    start = time.perf_counter()
    proc = subprocess.run(command, cwd=tmp_path, env=_env(tmp_path, small),
                          capture_output=True, text=True, timeout=timeout)
    elapsed = time.perf_counter() - start
    assert proc.returncode == 0, (
        f"{notebook.name} failed (exit code {proc.returncode}) after {elapsed:.0f} s\n"
        f"--- stdout (tail) ---\n{proc.stdout[-3000:]}\n"
        f"--- stderr (tail) ---\n{proc.stderr[-5000:]}"
    )


def _check_figures(notebook: Path, tmp_path: Path) -> None:
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


def test_notebooks_are_found():
    assert NOTEBOOKS, f"no notebooks matching 0*.py in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_in_small_mode(notebook: Path, tmp_path: Path):
    _run([sys.executable, str(notebook)], notebook, tmp_path, small=True, timeout=TIMEOUT_S)
    _check_figures(notebook, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_at_full_size(notebook: Path, tmp_path: Path):
    _run([sys.executable, str(notebook)], notebook, tmp_path, small=False,
         timeout=FULL_TIMEOUT_S)
    _check_figures(notebook, tmp_path)


@pytest.mark.slow
def test_the_notebooks_extra_executes_a_notebook(tmp_path: Path):
    # what the README's notebook instructions need: jupytext, nbconvert (its executor) and an
    # ipykernel kernel, all in the `notebooks` extra
    missing = [m for m in ("jupytext", "nbconvert", "ipykernel")
               if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"the notebooks extra is not installed (no {', '.join(missing)})")
    notebook = NOTEBOOK_DIR / "01_quickstart.py"
    executed = tmp_path / "01_quickstart.ipynb"
    _run([sys.executable, "-m", "jupytext", "--to", "ipynb", "--execute", "--run-path",
          str(NOTEBOOK_DIR), "--output", str(executed), str(notebook)], notebook, tmp_path,
         small=True, timeout=TIMEOUT_S)
    assert executed.stat().st_size > 10_000  # the cells' outputs, figures included
    _check_figures(notebook, tmp_path)
