"""The sweep command: outputs, resuming, Dask backends."""

import csv
import json
from pathlib import Path

import pytest

from torchconn.sweep import __main__ as cli
from torchconn.sweep import experiment as experiment_module
from torchconn.sweep.config import load_config
from torchconn.sweep.runner import cell_fingerprint, run_sweep

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


def test_bad_config_is_reported(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[[experiment]]\nsystem = "4link"\nnoise_kind = "system"\n'
                   "levels = [1.0]\ntrials = 1\n")
    assert cli.main(["--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "[[experiment]] 0" in err and "system must be one of" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
