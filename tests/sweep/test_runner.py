"""The sweep command: outputs, resuming, Dask backends."""

import csv
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from torchconn.sweep import __main__ as cli
from torchconn.sweep import experiment as experiment_module
from torchconn.sweep.config import load_config
from torchconn.sweep.runner import cell_fingerprint, default_jobs, run_sweep

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--cycles", "8", "--trials", "2", "--quiet"]
RESULT_COLUMNS = {"system", "noise_kind", "level", "trial", "model", "component", "metric",
                  "value"}


def _small_config(tmp_path: Path) -> Path:
    path = tmp_path / "small.toml"
    path.write_text("""
name = "small"
seed = 5
error_bins = 12
[simulation]
n_cycles = 8
[estimator.regression]
n_bins = 24
fourier_order = 6
[[experiment]]
system = "3link"
noise_kind = "system"
levels = [1.0, 2.0]
trials = 2
[[experiment]]
system = "3link"
noise_kind = "observation"
levels = [0.0, 0.01]
trials = 2
""")
    return path


def _rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def _check_outputs(out: Path, n_experiments: int) -> None:
    rows = _rows(out / "results.csv")
    assert RESULT_COLUMNS <= set(rows[0])
    assert {r["model"] for r in rows} == {"ground_truth", "data_driven", "analytic", "template"}
    assert {r["component"] for r in rows} == {"x", "y", "theta"}
    assert all(float(r["value"]) == float(r["value"]) for r in rows)  # no NaN
    claims = _rows(out / "claims.csv")
    assert [set(c) for c in claims][0] == {"claim", "holds", "evidence"} and len(claims) == 4
    sidecar = json.loads((out / "run.json").read_text())
    assert {"config", "seeds", "versions", "timings_s"} <= set(sidecar)
    assert len(sidecar["timings_s"]) == n_experiments
    assert list(out.glob("fig*.png"))


def test_default_sweep_runs_small(tmp_path):
    assert cli.main(["--out", str(tmp_path / "default"), *SMALL]) == 0
    _check_outputs(tmp_path / "default", n_experiments=3)
    assert (tmp_path / "default" / "fig4a_system_noise.png").stat().st_size > 1000


def test_quick_config_runs(tmp_path):
    out = tmp_path / "quick"
    assert cli.main(["--config", str(ROOT / "configs" / "quick.toml"), "--out", str(out),
                     "--cycles", "8", "--quiet", "--device", "cpu"]) == 0
    _check_outputs(out, n_experiments=2)
    assert json.loads((out / "run.json").read_text())["device"] == {"device": "cpu",
                                                                    "type": "cpu"}


def test_every_paper_config_parses():
    for name in ("fig3", "fig4a", "fig4b", "quick"):
        config = load_config(ROOT / "configs" / f"{name}.toml")
        assert config.experiments


def test_resume_after_interruption_gives_the_uninterrupted_table(tmp_path, monkeypatch):
    config = load_config(_small_config(tmp_path))
    run_sweep(config, tmp_path / "whole", quiet=True, figures=False)

    calls = []
    real = experiment_module.run_cell

    def dies_on_third(cfg, cell):
        calls.append(cell.name)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(cfg, cell)

    monkeypatch.setattr("torchconn.sweep.runner.run_cell", dies_on_third)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(config, tmp_path / "resumed", quiet=True, figures=False)
    stored = list((tmp_path / "resumed" / "cells").glob("*/cell.json"))
    assert len(stored) == 2  # the cells finished before the interruption were kept

    reran = []
    monkeypatch.setattr("torchconn.sweep.runner.run_cell",
                        lambda cfg, cell: reran.append(cell.name) or real(cfg, cell))
    summary = run_sweep(config, tmp_path / "resumed", quiet=True, figures=False)
    assert reran == calls[2:] + ["3link-observation-L1-t0-2"]  # only the missing cells ran
    assert summary.reused == 2 and summary.computed == tuple(reran)
    assert (tmp_path / "resumed" / "results.csv").read_text() == (
        tmp_path / "whole" / "results.csv").read_text()


def test_changed_config_never_reuses_stale_cells(tmp_path):
    path = _small_config(tmp_path)
    first = load_config(path)
    second = load_config(path, ["estimator.regression.fourier_order=5"])
    assert all(first.fingerprint(a) != second.fingerprint(b)
               for a, b in zip(first.experiments, second.experiments, strict=True))
    cells = [experiment_module.experiment_cells(e, 4)[0] for e in first.experiments]
    assert cell_fingerprint(first, cells[0]) != cell_fingerprint(second, cells[0])


def test_fingerprint_covers_torchconn_version_and_source(tmp_path, monkeypatch):
    config = load_config(_small_config(tmp_path))
    cell = experiment_module.experiment_cells(config.experiments[0], 4)[0]
    before = cell_fingerprint(config, cell)
    monkeypatch.setattr("torchconn.sweep.config.__version__", "999.0")
    after_upgrade = cell_fingerprint(config, cell)
    monkeypatch.undo()
    monkeypatch.setattr("torchconn.sweep.config.source_hash", lambda: "0" * 16)
    assert len({before, after_upgrade, cell_fingerprint(config, cell)}) == 3


def test_dask_backends_match_the_serial_run(tmp_path):
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    config = load_config(_small_config(tmp_path))
    run_sweep(config, tmp_path / "serial", quiet=True, figures=False)
    run_sweep(config, tmp_path / "local", workers=2, quiet=True, figures=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, host="127.0.0.1") as cluster:
        assert cluster.scheduler_address.startswith("tcp://")
        run_sweep(config, tmp_path / "remote", scheduler=cluster.scheduler_address, quiet=True,
                  figures=False)
    serial = (tmp_path / "serial" / "results.csv").read_text()
    assert (tmp_path / "local" / "results.csv").read_text() == serial
    assert (tmp_path / "remote" / "results.csv").read_text() == serial


def test_local_jobs_match_the_serial_run(tmp_path):
    config = load_config(_small_config(tmp_path))
    run_sweep(config, tmp_path / "serial", quiet=True, figures=False)
    summary = run_sweep(config, tmp_path / "jobs", jobs=3, quiet=True, figures=False)
    assert len(summary.computed) == 4
    for table in ("results.csv", "phase_errors.csv", "traces.csv", "claims.csv"):
        assert (tmp_path / "jobs" / table).read_bytes() == (
            tmp_path / "serial" / table).read_bytes()
    run, serial = (json.loads((tmp_path / name / "run.json").read_text())
                   for name in ("jobs", "serial"))
    assert run["jobs"] == 3 and serial["jobs"] == 1
    assert len(run["cpu_time_s"]["jobs"]) == 3 and min(run["cpu_time_s"]["jobs"]) > 0
    assert serial["cpu_time_s"]["jobs"] == [] and serial["cpu_time_s"]["this_process"] > 0


def test_a_jobs_warnings_reach_the_caller(tmp_path, monkeypatch):
    config = load_config(_small_config(tmp_path))
    real = experiment_module.run_cell

    def warns(cfg, cell):  # in the job process (forked, or the test's own process)
        warnings.warn(f"note from {cell.name}", UserWarning, stacklevel=1)
        return real(cfg, cell)

    monkeypatch.setattr("torchconn.sweep.runner.run_cell", warns)
    with pytest.warns(UserWarning) as caught:
        run_sweep(config, tmp_path / "out", jobs=2, quiet=True, figures=False)
    assert sorted(str(w.message) for w in caught if "note from" in str(w.message)) == sorted(
        f"note from {cell.name}" for cell in experiment_module.experiment_cells(
            config.experiments[0], 4) + experiment_module.experiment_cells(
            config.experiments[1], 4))


def test_a_job_process_that_dies_is_reported_and_finished_cells_are_kept(tmp_path,
                                                                         monkeypatch):
    config = load_config(_small_config(tmp_path))
    real = experiment_module.run_cell

    def dies_on_observation(cfg, cell):
        if cell.experiment.noise_kind == "observation":
            os._exit(9)  # as if killed (out of memory)
        return real(cfg, cell)

    monkeypatch.setattr("torchconn.sweep.runner.run_cell", dies_on_observation)
    with pytest.raises(RuntimeError, match="a job process ended abruptly .* cells unfinished; "
                       "the cells finished are kept: run again, with fewer --jobs"):
        run_sweep(config, tmp_path / "out", jobs=2, quiet=True, figures=False)
    assert not (tmp_path / "out" / "results.csv").exists()
    monkeypatch.undo()
    summary = run_sweep(config, tmp_path / "out", jobs=2, quiet=True, figures=False)
    assert set(summary.computed) <= {c.name for c in experiment_module.experiment_cells(
        config.experiments[1], 4)} | {c.name for c in experiment_module.experiment_cells(
            config.experiments[0], 4)}
    assert summary.reused + len(summary.computed) == 4


def test_default_jobs_use_the_cores_given_the_threads_and_the_memory(tmp_path, monkeypatch):
    from torchconn.sweep import runner

    config = load_config(_small_config(tmp_path))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    monkeypatch.setattr(runner, "_available_memory", lambda: 1 << 40)
    assert [default_jobs(config, t) for t in (1, 2, 3, 8, 16)] == [8, 4, 2, 1, 1]
    # room for three jobs of this config's largest cells, and for none of the default's
    trial_samples = 2 * 8 * 64
    need = runner._JOB_BASE_BYTES + runner._JOB_BYTES_PER_TRIAL_SAMPLE * trial_samples
    monkeypatch.setattr(runner, "_available_memory", lambda: 3 * need + 1)
    assert default_jobs(config, 1) == 3
    assert default_jobs(load_config(None), 1) == 1


def test_the_sweep_commands_process_keeps_freed_memory():
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's allocator only")
    # a 64 MB block allocated and freed 20 times: by default each time fresh pages from the
    # system (one fault per 4 kB page), kept for reuse after hold_freed_memory
    code = """
import resource, sys, torch
from torchconn._cli import hold_freed_memory
if sys.argv[1] == "hold":
    hold_freed_memory()
torch.empty(8 << 20, dtype=torch.float64).fill_(1.0)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    torch.empty(8 << 20, dtype=torch.float64).fill_(1.0)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
    faults = {mode: int(subprocess.run([sys.executable, "-c", code, mode], capture_output=True,
                                       text=True, check=True).stdout)
              for mode in ("default", "hold")}
    assert faults["default"] > 20 * 10_000 and faults["hold"] < faults["default"] / 10, faults


def test_bad_config_is_reported(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[[experiment]]\nsystem = "4link"\nnoise_kind = "system"\n'
                   "levels = [1.0]\ntrials = 1\n")
    assert cli.main(["--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "[[experiment]] 0" in err and "system must be one of" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
