"""The sweep store: cells, kill and resume, damage, one writer, equivalence across blocks."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torchconn._output import FolderBusy, FolderLock
from torchconn.sweep import __main__ as cli
from torchconn.sweep.config import load_config
from torchconn.sweep.experiment import experiment_cells
from torchconn.sweep.runner import run_sweep

ROOT = Path(__file__).resolve().parents[2]
TINY = """
name = "tiny"
seed = 11
error_bins = 12
block_trials = 4
[simulation]
n_cycles = 5
samples_per_cycle = 32
[estimator.regression]
n_bins = 16
fourier_order = 4
[[experiment]]
system = "3link"
noise_kind = "system"
levels = [1.0, 2.0]
trials = 8
"""


def _config(tmp_path: Path, text: str = TINY) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(text)
    return path


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def _sweep_cmd(config: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "torchconn.sweep", "--config", str(config), "--out", str(out),
            "--no-figures", *extra]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted serial run of the tiny config (block 4: four cells)."""
    tmp = tmp_path_factory.mktemp("reference")
    out = tmp / "out"
    assert cli.main(["--config", str(_config(tmp)), "--out", str(out), "--quiet",
                     "--no-figures"]) == 0
    return out


def test_the_cells_of_an_experiment():
    config = load_config(None, ["experiment.trials=10"])
    cells = experiment_cells(config.experiments[0], 4)
    assert [(c.level, c.start, c.stop) for c in cells[:3]] == [(0, 0, 4), (0, 4, 8), (0, 8, 10)]
    assert len(cells) == 3 * len(config.experiments[0].levels)
    assert len({c.name for c in cells}) == len(cells)


def test_results_do_not_depend_on_the_block_size(tmp_path, reference):
    expected = (reference / "results.csv").read_bytes()
    for block in (8, 12):
        out = tmp_path / f"block{block}"
        summary = run_sweep(load_config(_config(tmp_path), [f"block_trials={block}"]), out,
                            quiet=True, figures=False)
        assert len(summary.computed) == (2 if block >= 8 else 4)
        assert (out / "results.csv").read_bytes() == expected
        assert (out / "phase_errors.csv").read_bytes() == (
            reference / "phase_errors.csv").read_bytes()


def test_a_block_size_that_would_change_the_numbers_is_refused(tmp_path):
    with pytest.raises(ValueError, match="block_trials must be a multiple of 4"):
        load_config(_config(tmp_path), ["block_trials=6"])


@pytest.mark.slow  # two subprocess sweeps: ~20 s idle, ~1 min on a loaded machine
def test_killed_run_resumes_keeps_finished_cells_and_matches_byte_for_byte(tmp_path, reference):
    config, out = _config(tmp_path), tmp_path / "killed"
    proc = subprocess.Popen(_sweep_cmd(config, out, "--quiet"), env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not list(out.glob("cells/*/cell.json")):
        assert proc.poll() is None, "the run ended before a cell was stored"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    kept = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("cells/*/cell.json")}
    assert 1 <= len(kept) < 4, "the kill should land inside the experiment"
    assert not (out / "results.csv").exists()

    done = subprocess.run(_sweep_cmd(config, out), env=_env(), capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    assert "taking over the lock" in done.stderr and "no longer running" in done.stderr
    assert f"{len(kept)} already done" in done.stderr
    for name, mtime in kept.items():  # finished cells were reused, not rewritten
        assert (out / "cells" / name / "cell.json").stat().st_mtime_ns == mtime
    run = json.loads((out / "run.json").read_text())
    assert len(run["cells_computed_this_run"]) == 4 - len(kept)
    for table in ("results.csv", "phase_errors.csv", "traces.csv"):
        assert (out / table).read_bytes() == (reference / table).read_bytes()


@pytest.mark.parametrize("damage", ["truncate", "edit", "delete", "manifest"])
def test_damaged_cell_is_detected_reported_and_recomputed(tmp_path, reference, damage):
    out = tmp_path / "out"
    config = load_config(_config(tmp_path))
    run_sweep(config, out, quiet=True, figures=False)
    cell = sorted((out / "cells").iterdir())[1]
    target = cell / ("cell.json" if damage == "manifest" else "results.csv")
    data = target.read_bytes()
    if damage == "truncate":
        target.write_bytes(data[:len(data) // 2])
    elif damage == "edit":  # one digit changed: still a well-formed table
        i = data.rindex(b"e-0")
        target.write_bytes(data[:i - 1] + bytes([48 + (data[i - 1] - 47) % 10]) + data[i:])
    elif damage == "delete":
        target.unlink()
    else:
        target.write_bytes(data[:20])
    with pytest.warns(UserWarning) as warned:
        summary = run_sweep(config, out, quiet=False, figures=False)
    err = "\n".join(str(w.message) for w in warned)
    name = cell.name.rsplit("-", 1)[0]
    assert summary.computed == (name,) and summary.reused == 3
    reason = dict(summary.damaged)[name]
    assert {"truncate": "checksum", "edit": "checksum", "delete": "missing",
            "manifest": "cell.json unreadable"}[damage] in reason
    assert f"recomputing cell {name}: {reason}" in err
    assert (out / "results.csv").read_bytes() == (reference / "results.csv").read_bytes()
    assert run_sweep(config, out, quiet=True, figures=False).computed == ()


def test_second_run_into_a_held_folder_exits_naming_the_holder(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    with FolderLock(out):
        code = cli.main(["--config", str(_config(tmp_path)), "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and f"pid {os.getpid()}" in err and "in use" in err
        with pytest.raises(FolderBusy):
            run_sweep(load_config(_config(tmp_path)), out, quiet=True)
    assert not (out / "cells").exists() and not (out / "results.csv").exists()


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "out"
    out.mkdir()
    import socket

    (out / ".lock").write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(),
                                           "started": "2020-01-01T00:00:00+00:00"}))
    said = []
    with FolderLock(out, log=said.append):
        holder = json.loads((out / ".lock").read_text())
        assert holder["pid"] == os.getpid()
    assert len(said) == 1 and f"pid {dead.pid}" in said[0] and "no longer running" in said[0]
    assert (out / ".lock").read_text() == ""  # released cleanly


@pytest.mark.slow  # two subprocess sweeps
def test_concurrent_runs_never_double_compute(tmp_path, reference):
    """Two runs started together into one folder with --wait: one computes every cell, the
    other waits and reuses them all; the tables are the uninterrupted run's."""
    config, out = _config(tmp_path), tmp_path / "shared"
    procs = [subprocess.Popen(_sweep_cmd(config, out, "--wait"), env=_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    logs = [p.communicate(timeout=600)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], logs
    done = sorted(int(log.split(" already done")[0].rsplit(", ", 1)[1]) for log in logs)
    assert done == [0, 4]  # the second run recomputed nothing
    assert sum(log.count("] ") for log in logs) == 4  # four progress lines in all
    assert (out / "results.csv").read_bytes() == (reference / "results.csv").read_bytes()
    assert len(list(out.glob("cells/*/cell.json"))) == 4
