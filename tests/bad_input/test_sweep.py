"""``torchconn-sweep`` on bad input: the whole config (every key, type, range, ``--set`` path)
is checked before any cell runs, and every message names the file and the key."""

from __future__ import annotations

import sys

import pytest
import torch

from torchconn import fit
from torchconn.sweep import __main__ as sweep_cli

from .common import assert_clean_failure, must_not_run, run_module, write

GOOD_TOML = """
name = "bad-input"
seed = 3
error_bins = 12
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
trials = 2
"""


def _edit(old: str, new: str) -> str:
    assert old in GOOD_TOML
    return GOOD_TOML.replace(old, new, 1)


# (id, TOML text, extra argv, fragments the message must hold)
SWEEP_CASES = [
    ("unknown-top-key", "nmae = 'x'\n" + GOOD_TOML.replace('name = "bad-input"\n', ""), [],
     ["unknown key", "'nmae'", "did you mean 'name'", "valid keys"]),
    ("unknown-simulation-key", _edit("n_cycles = 5", "n_cycle = 5"), [],
     ["[simulation]", "'n_cycle'", "did you mean 'n_cycles'"]),
    ("unknown-estimator-key", _edit("n_bins = 16", "nbins = 16"), [],
     ["[estimator]", "'nbins'", "did you mean 'n_bins'"]),
    ("unknown-experiment-key", _edit("trials = 2", "trails = 2"), [],
     ["[[experiment]] 0", "'trails'", "did you mean 'trials'"]),
    ("set-index-out-of-range", GOOD_TOML, ["--set", "experiment.5.trials=2"],
     ["--set experiment.5.trials=2", "index 5", "1 [[experiment]]"]),
    ("set-not-a-number", GOOD_TOML, ["--set", "experiment.trials=abc"],
     ["trials must be an integer", "'abc'", "--set experiment.trials=abc"]),
    ("set-without-equals", GOOD_TOML, ["--set", "simulation.n_cycles"],
     ["--set simulation.n_cycles", "section.key=value"]),
    ("set-into-a-value", GOOD_TOML, ["--set", "seed.x=1"], ["seed", "not a table"]),
    ("set-unknown-key", GOOD_TOML, ["--set", "simulation.cycles=4"],
     ["'cycles'", "did you mean 'n_cycles'"]),
    ("error-bins-zero", _edit("error_bins = 12", "error_bins = 0"), [],
     ["error_bins must be >= 2", "got 0"]),
    ("error-bins-above-samples", _edit("error_bins = 12", "error_bins = 64"), [],
     ["error_bins = 64", "samples_per_cycle = 32"]),
    ("trials-fraction", _edit("trials = 2", "trials = 2.5"), [],
     ["trials must be an integer", "2.5"]),
    ("trials-zero", GOOD_TOML, ["--trials", "0"], ["trials must be >= 1", "got 0"]),
    ("cycles-negative", _edit("n_cycles = 5", "n_cycles = -5"), [],
     ["n_cycles must be >= 2", "-5"]),
    ("cycles-fewer-than-estimator-needs", _edit("n_cycles = 5", "n_cycles = 3"), [],
     ["n_cycles = 3 is too few", "min_cycles"]),
    ("samples-per-cycle-tiny", _edit("samples_per_cycle = 32", "samples_per_cycle = 2"), [],
     ["samples_per_cycle must be >= 8", "got 2"]),
    ("eta-nan", _edit("n_cycles = 5", "n_cycles = 5\neta = nan"), [],
     ["eta must be a finite number"]),
    ("eta-negative", _edit("n_cycles = 5", "n_cycles = 5\neta = -0.1"), [], ["eta must be"]),
    ("substeps-odd", _edit("n_cycles = 5", "n_cycles = 5\nsubsteps = 3"), [],
     ["substeps must be even", "got 3"]),
    ("unknown-system", _edit('system = "3link"', 'system = "4link"'), [],
     ["system must be one of", "'4link'"]),
    ("noise-kind-typo", _edit('noise_kind = "system"', 'noise_kind = "sytem"'), [],
     ["noise_kind must be one of", "did you mean 'system'"]),
    ("levels-empty", _edit("levels = [1.0, 2.0]", "levels = []"), [], ["levels must be"]),
    ("levels-negative", _edit("levels = [1.0, 2.0]", "levels = [-1.0]"), [],
     ["levels must be >= 0", "-1.0"]),
    ("levels-not-a-list", _edit("levels = [1.0, 2.0]", 'levels = "high"'), [],
     ["levels must be a list", "'high'"]),
    ("levels-duplicated", _edit("levels = [1.0, 2.0]", "levels = [1.0, 1.0]"), [],
     ["levels must be distinct"]),
    ("seed-negative", _edit("seed = 3", "seed = -1"), [], ["seed must be >= 0", "got -1"]),
    ("seed-string", _edit("seed = 3", 'seed = "x"'), [], ["seed must be an integer", "'x'"]),
    ("phase-typo", _edit("seed = 3", 'seed = 3\nphase = "estimate"'), [],
     ["phase must be one of", "did you mean 'estimated'"]),
    ("block-not-multiple-of-4", GOOD_TOML, ["--block", "6"],
     ["block_trials must be a multiple of 4"]),
    ("no-experiment", GOOD_TOML.split("[[experiment]]")[0], [], ["no [[experiment]]"]),
    ("duplicate-experiments", GOOD_TOML + GOOD_TOML.split("fourier_order = 4")[1], [],
     ["experiment names must be unique"]),
    ("experiment-as-table", _edit("[[experiment]]", "[experiment]"), [],
     ["experiment must be an array of [[experiment]] tables"]),
    ("experiment-missing-system", _edit('system = "3link"\n', ""), [],
     ["[[experiment]] 0", "missing required key 'system'"]),
    ("simulation-not-a-table", GOOD_TOML.replace("[simulation]\nn_cycles = 5\n"
                                                 "samples_per_cycle = 32\n",
                                                 "simulation = 5\n"), [],
     ["simulation must be a [section] table"]),
    ("traces-not-bool", _edit("trials = 2", "trials = 2\ntraces = \"yes\""), [],
     ["traces must be true or false"]),
    ("estimator-range", _edit("fourier_order = 4", "fourier_order = 9"), [],
     ["[estimator]", "fourier_order"]),
    ("name-with-slash", _edit('name = "bad-input"', 'name = "a/b"'), [],
     ["name must be a non-empty name usable as a folder name"]),
    ("toml-syntax", _edit("trials = 2", "trials = = 2"), [], ["invalid TOML", "line "]),
    ("threads-zero", GOOD_TOML, ["--threads", "0"], ["--threads must be an integer >= 1"]),
    ("workers-negative", GOOD_TOML, ["--workers", "-1"], ["--workers must be"]),
    ("workers-and-scheduler", GOOD_TOML, ["--workers", "2", "--scheduler", "tcp://x:1"],
     ["either --workers", "--scheduler"]),
    ("jobs-zero", GOOD_TOML, ["--jobs", "0"], ["--jobs must be an integer >= 1", "0"]),
    ("jobs-and-workers", GOOD_TOML, ["--jobs", "2", "--workers", "2"],
     ["either --jobs", "--workers"]),
    # ---- added: values that were accepted, and names the message must give
    ("alpha-zero", _edit("n_cycles = 5", "n_cycles = 5\nalpha = 0.0"), [],
     ["[simulation]", "alpha must be > 0"]),
    ("levels-inf", _edit("levels = [1.0, 2.0]", "levels = [inf]"), [],
     ["levels[0] must be a finite number", "inf"]),
    ("levels-text", _edit("levels = [1.0, 2.0]", "levels = [1.0, 'x']"), [],
     ["levels[1] must be a finite number", "'x'"]),
    ("seed-fraction", _edit("seed = 3", "seed = 3.5"), [],
     ["sweep.toml", "seed must be an integer", "3.5"]),
    ("device-unknown", _edit("seed = 3", "seed = 3\ndevice = 'gpu'"), [],
     ["device 'gpu'", "unknown device"]),
    ("experiment-not-tables", "experiment = [1, 2]\n", [], ["[[experiment]] 0 must be a table"]),
    ("experiment-omega-negative", _edit("trials = 2", "trials = 2\nomega = -0.1"), [],
     ["[[experiment]] 0", "omega must be >= 0"]),
    ("estimator-stage-not-table", _edit("[estimator.regression]",
                                        "[estimator]\nphaser = 'x'\n[estimator.regression]"),
     [], ["phaser must be a table"]),
    ("set-empty-key", GOOD_TOML, ["--set", "simulation..x=2"], ["--set simulation..x=2",
                                                               "empty key"]),
    ("set-negative-index", GOOD_TOML, ["--set", "experiment.-1.trials=2"],
     ["index -1 is out of range"]),
    ("trials-huge", _edit("trials = 2", "trials = 100001"), [], ["trials must be <= 100000"]),
    ("empty-config", "", [], ["no [[experiment]]"]),
]


@pytest.mark.parametrize("case", SWEEP_CASES, ids=[c[0] for c in SWEEP_CASES])
def test_sweep_config(case, tmp_path, capsys):
    _, text, argv, fragments = case
    config = tmp_path / "sweep.toml"
    config.write_text(text)
    out = tmp_path / "out"
    code = sweep_cli.main(["--config", str(config), "--out", str(out), "--quiet", *argv])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def test_sweep_toml_error_names_the_file_and_line(tmp_path, capsys):
    config = tmp_path / "broken.toml"
    config.write_text(GOOD_TOML.replace("trials = 2", "trials = = 2"))
    code = sweep_cli.main(["--config", str(config), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    line = GOOD_TOML.splitlines().index("trials = 2") + 1
    assert_clean_failure(code, err, [str(config), f"line {line}"], tmp_path / "o")


@pytest.mark.parametrize("kind", ["missing", "folder", "binary"])
def test_sweep_config_path(kind, tmp_path, capsys):
    path = tmp_path / "c.toml"
    if kind == "folder":
        path.mkdir()
    elif kind == "binary":
        path.write_bytes(b"\xff\xfe\x00\x01garbage")
    code = sweep_cli.main(["--config", str(path), "--out", str(tmp_path / "o")])
    expect = {"missing": "not found", "folder": "is a folder", "binary": "not UTF-8"}[kind]
    assert_clean_failure(code, capsys.readouterr().err, [str(path), expect], tmp_path / "o")


@pytest.mark.parametrize("where", ["under-a-file", "is-a-file"])
def test_sweep_unwritable_out_is_found_before_any_work(where, tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    out = blocker / "out" if where == "under-a-file" else blocker
    config = tmp_path / "sweep.toml"
    config.write_text(GOOD_TOML)
    monkeypatch.setattr("torchconn.sweep.runner.run_cell", must_not_run)
    code = sweep_cli.main(["--config", str(config), "--out", str(out), "--quiet"])
    assert_clean_failure(code, capsys.readouterr().err, ["--out", str(out)], None)
    assert blocker.read_text() == "x"


def test_sweep_workers_without_dask(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    monkeypatch.setattr("torchconn.sweep.runner.run_cell", must_not_run)
    config = tmp_path / "sweep.toml"
    config.write_text(GOOD_TOML)
    out = tmp_path / "o"
    code = sweep_cli.main(["--config", str(config), "--out", str(out), "--workers", "2"])
    assert_clean_failure(code, capsys.readouterr().err, ["need Dask", "pip install"], out)




def test_sweep_reads_configs_with_a_byte_order_mark_and_windows_line_ends(tmp_path, capsys,
                                                                          monkeypatch):
    seen = []
    monkeypatch.setattr("torchconn.sweep.runner.run_cell",
                        lambda *a, **k: seen.append(1) or must_not_run())
    for name, data in (("bom", b"\xef\xbb\xbf" + GOOD_TOML.encode()),
                       ("crlf", GOOD_TOML.replace("\n", "\r\n").encode())):
        config = write(tmp_path, f"{name}.toml", data)
        # --jobs 1: the first cell runs in this process, where `seen` records it
        code = sweep_cli.main(["--config", str(config), "--out", str(tmp_path / name),
                               "--quiet", "--jobs", "1"])
        assert code == 1 and seen, capsys.readouterr().err  # read; the first cell was next
        seen.clear()


def test_subprocess_sweep_bad_set_index(tmp_path):
    config = write(tmp_path, "s.toml", GOOD_TOML)
    done = run_module("torchconn.sweep", "--config", str(config), "--out", str(tmp_path / "o"),
                "--set", "experiment.5.trials=2")
    assert_clean_failure(done.returncode, done.stderr, ["index 5"], tmp_path / "o")


def test_threads_flag_sets_torch_threads(tmp_path, capsys):
    before = torch.get_num_threads()
    try:
        config = write(tmp_path, "s.toml", GOOD_TOML.replace("trials = 2", "trials = 0"))
        sweep_cli.main(["--config", str(config), "--out", str(tmp_path / "o"), "--threads", "2"])
        assert torch.get_num_threads() == 2
        fit.main([str(tmp_path / "missing.csv"), "--links", "3", "--out", str(tmp_path / "f")])
        assert torch.get_num_threads() == 1  # the default, in every command
    finally:
        torch.set_num_threads(before)


def test_an_internal_error_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr("torchconn.sweep.runner.run_cell", broken)
    config = write(tmp_path, "s.toml", GOOD_TOML)
    code = sweep_cli.main(["--config", str(config), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "internal error (RuntimeError): simulated bug" in err and "TORCHCONN_DEBUG" in err
    assert not (tmp_path / "o" / "results.csv").exists()
