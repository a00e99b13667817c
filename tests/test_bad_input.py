"""Bad input always gets a clear answer: exit code 2, one message naming the problem, no
traceback, and no partial result. The commands run in-process through ``main(argv)``; a few
cases run as subprocesses to see exactly what a user sees."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, Phaser, fit
from torchconn import discrepancy as _discrepancy  # noqa: F401 (registers the effects)
from torchconn.discrepancy import __main__ as discrepancy_cli
from torchconn.io.trajectory_files import write_csv
from torchconn.physics.gaits import FourierGait, reference_gait
from torchconn.physics.systems import NLinkSwimmer
from torchconn.simulation.rollout import simulate
from torchconn.sweep import __main__ as sweep_cli

ROOT = Path(__file__).resolve().parents[1]

GOOD_TOML = """
name = "bad-input"
seed = 3
error_bins = 12
[simulation]
n_cycles = 5
samples_per_cycle = 32
[estimator]
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
]


def _assert_clean_failure(code: int, err: str, fragments, out: Path | None) -> None:
    assert code == 2, err
    assert "Traceback" not in err and "internal error" not in err, err
    assert err.count("\n") <= 2, err  # one message, not a dump
    for fragment in fragments:
        assert fragment in err, f"{fragment!r} not in {err!r}"
    if out is not None:
        assert not out.exists() or not any(out.iterdir()), f"partial output in {out}"


@pytest.mark.parametrize("case", SWEEP_CASES, ids=[c[0] for c in SWEEP_CASES])
def test_sweep_config(case, tmp_path, capsys):
    _, text, argv, fragments = case
    config = tmp_path / "sweep.toml"
    config.write_text(text)
    out = tmp_path / "out"
    code = sweep_cli.main(["--config", str(config), "--out", str(out), "--quiet", *argv])
    _assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def test_sweep_toml_error_names_the_file_and_line(tmp_path, capsys):
    config = tmp_path / "broken.toml"
    config.write_text(GOOD_TOML.replace("trials = 2", "trials = = 2"))
    code = sweep_cli.main(["--config", str(config), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    line = GOOD_TOML.splitlines().index("trials = 2") + 1
    _assert_clean_failure(code, err, [str(config), f"line {line}"], tmp_path / "o")


@pytest.mark.parametrize("kind", ["missing", "folder", "binary"])
def test_sweep_config_path(kind, tmp_path, capsys):
    path = tmp_path / "c.toml"
    if kind == "folder":
        path.mkdir()
    elif kind == "binary":
        path.write_bytes(b"\xff\xfe\x00\x01garbage")
    code = sweep_cli.main(["--config", str(path), "--out", str(tmp_path / "o")])
    expect = {"missing": "not found", "folder": "is a folder", "binary": "not UTF-8"}[kind]
    _assert_clean_failure(code, capsys.readouterr().err, [str(path), expect], tmp_path / "o")


@pytest.mark.parametrize("where", ["under-a-file", "is-a-file"])
def test_sweep_unwritable_out_is_found_before_any_work(where, tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    out = blocker / "out" if where == "under-a-file" else blocker
    config = tmp_path / "sweep.toml"
    config.write_text(GOOD_TOML)
    monkeypatch.setattr("torchconn.sweep.runner.run_cell", _must_not_run)
    code = sweep_cli.main(["--config", str(config), "--out", str(out), "--quiet"])
    _assert_clean_failure(code, capsys.readouterr().err, ["--out", str(out)], None)
    assert blocker.read_text() == "x"


def test_sweep_workers_without_dask(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    monkeypatch.setattr("torchconn.sweep.runner.run_cell", _must_not_run)
    config = tmp_path / "sweep.toml"
    config.write_text(GOOD_TOML)
    out = tmp_path / "o"
    code = sweep_cli.main(["--config", str(config), "--out", str(out), "--workers", "2"])
    _assert_clean_failure(code, capsys.readouterr().err, ["need Dask", "pip install"], out)


def _must_not_run(*args, **kwargs):
    raise AssertionError("computation started before the input was checked")


# ---------------------------------------------------------------------------- recordings
@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A valid 3-link recording: one trial, 6 cycles, 32 samples per cycle."""
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=6,
                    samples_per_cycle=32, substeps=4, seeds=[1])
    path = tmp_path_factory.mktemp("data") / "good.csv"
    write_csv(traj[0] if traj.batch_shape else traj, path)
    return path


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _variant(recording: Path, tmp_path: Path, line: int, column: str, value: str) -> Path:
    """The recording with ``value`` in ``column`` on file line ``line`` (1: the header)."""
    lines = _lines(recording)
    header = lines[0].split(",")
    cells = lines[line - 1].split(",")
    cells[header.index(column)] = value
    lines[line - 1] = ",".join(cells)
    path = tmp_path / f"bad_{column}.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# (id, builder(recording, tmp_path) -> path, fragments (format with {path}))
DATA_CASES = [
    ("huge-r1", lambda rec, tmp: _variant(rec, tmp, 40, "r1", "1e300"),
     ["line 40", "column 'r1'", "implausible value '1e300'"]),
    ("huge-x", lambda rec, tmp: _variant(rec, tmp, 17, "x", "1e300"),
     ["line 17", "column 'x'", "implausible value '1e300'"]),
    ("huge-theta", lambda rec, tmp: _variant(rec, tmp, 5, "theta", "-3e12"),
     ["line 5", "column 'theta'", "implausible"]),
    ("degrees", lambda rec, tmp: _variant(rec, tmp, 9, "r2", "87.5"),
     ["line 9", "column 'r2'", "degrees?"]),
    ("infinite", lambda rec, tmp: _variant(rec, tmp, 12, "y", "inf"),
     ["line 12", "column 'y'", "infinite"]),
    ("non-numeric", lambda rec, tmp: _variant(rec, tmp, 30, "r1", "abc"),
     ["line 30", "column 'r1'", "non-numeric value 'abc'"]),
    ("time-not-increasing", lambda rec, tmp: _variant(rec, tmp, 20, "t", "0"),
     ["line 20", "strictly increasing"]),
    ("time-empty", lambda rec, tmp: _variant(rec, tmp, 20, "t", ""),
     ["line 20", "column 't' is empty"]),
    ("binary", lambda rec, tmp: (tmp / "b.csv").write_bytes(bytes(range(256)) * 4) and tmp / "b.csv",
     ["b.csv", "binary data"]),
    ("utf16", lambda rec, tmp: (tmp / "u.csv").write_bytes(rec.read_text().encode("utf-16"))
     and tmp / "u.csv", ["u.csv", "UTF-16"]),
    ("latin1", lambda rec, tmp: (tmp / "l.csv").write_bytes(
        rec.read_text().replace("theta", "th\u00e9ta", 1).encode("latin-1")) and tmp / "l.csv",
     ["l.csv", "line 1", "not UTF-8"]),
    ("missing-file", lambda rec, tmp: tmp / "nope.csv", ["nope.csv"]),
    ("folder", lambda rec, tmp: (tmp / "d.csv").mkdir() or tmp / "d.csv", ["d.csv", "folder"]),
    ("empty-file", lambda rec, tmp: _write(tmp, "e.csv", ""), ["e.csv", "empty"]),
    ("header-only", lambda rec, tmp: _write(tmp, "h.csv", _lines(rec)[0] + "\n"),
     ["h.csv", "no data rows"]),
    ("missing-column", lambda rec, tmp: _write(tmp, "m.csv", "\n".join(
        ",".join(c for i, c in enumerate(row.split(",")) if i != 3) for row in _lines(rec))),
     ["m.csv", "missing required column", "'theta'"]),
    ("ragged-row", lambda rec, tmp: _write(tmp, "r.csv", "\n".join(
        _lines(rec)[:10] + [_lines(rec)[10] + ",1"] + _lines(rec)[11:])),
     ["r.csv", "line 11", "fields"]),
    ("non-uniform-time", lambda rec, tmp: _variant(rec, tmp, 50, "t",
                                                   str(float(_lines(rec)[49].split(",")[0]) + 0.05)),
     ["line 5", "not uniformly sampled"]),  # line 50 or 51: both steps are off
    ("all-nan-column", lambda rec, tmp: _write(tmp, "n.csv", "\n".join(
        [_lines(rec)[0]] + [",".join(row.split(",")[:2] + ["nan"] + row.split(",")[3:])
                            for row in _lines(rec)[1:]])),
     ["n.csv", "column 'y' has no values"]),
    ("nul-in-text", lambda rec, tmp: (tmp / "z.csv").write_bytes(
        rec.read_bytes()[:200] + b"\0" + rec.read_bytes()[200:]) and tmp / "z.csv",
     ["z.csv", "binary data"]),
]


@pytest.mark.parametrize("case", DATA_CASES, ids=[c[0] for c in DATA_CASES])
def test_fit_recording(case, recording, tmp_path, capsys):
    _, build, fragments = case
    path = build(recording, tmp_path)
    out = tmp_path / "out"
    code = fit.main([str(path), "--links", "3", "--out", str(out)])
    _assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def test_fit_wrong_joint_count(recording, tmp_path, capsys):
    code = fit.main([str(recording), "--links", "4", "--out", str(tmp_path / "o")])
    _assert_clean_failure(code, capsys.readouterr().err, ["2 joint column", "n_joints=3"],
                          tmp_path / "o")


def test_fit_pure_noise_is_not_a_gait(tmp_path, capsys):
    rng = np.random.default_rng(0)
    n = 400
    table = np.column_stack([np.arange(n) * 0.1, rng.normal(size=(n, 5)) * 0.1])
    path = tmp_path / "noise.csv"
    np.savetxt(path, table, delimiter=",", header="t,x,y,theta,r1,r2", comments="")
    code = fit.main([str(path), "--links", "3", "--out", str(tmp_path / "o")])
    _assert_clean_failure(code, capsys.readouterr().err, ["no periodic gait found"],
                          tmp_path / "o")


def test_discrepancy_pure_noise_is_not_a_gait(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("torchconn.discrepancy.__main__.diagnose", _must_not_run)
    rng = np.random.default_rng(1)
    n = 600
    table = np.column_stack([np.arange(n) * 0.1, rng.normal(size=(n, 5)) * 0.1])
    path = tmp_path / "noise.csv"
    np.savetxt(path, table, delimiter=",", header="t,x,y,theta,r1,r2", comments="")
    code = discrepancy_cli.main([str(path), "--links", "3", "--out", str(tmp_path / "o")])
    _assert_clean_failure(code, capsys.readouterr().err, ["no periodic gait found"],
                          tmp_path / "o")


@pytest.mark.parametrize("argv,fragments", [
    (["--grid", "0"], ["--grid must be >= 2"]),
    (["--links", "1"], ["--links must be >= 2"]),
    (["--n-bins", "2"], ["n_bins must be >= 3", "got 2"]),
    (["--fourier-order", "30"], ["fourier_order"]),
    (["--window", "-1"], ["--window must be a positive number"]),
    (["--threads", "0"], ["--threads must be an integer >= 1"]),
], ids=["grid-0", "links-1", "n-bins-2", "fourier-order", "window", "threads"])
def test_fit_options_checked_before_work(argv, fragments, recording, tmp_path, capsys,
                                         monkeypatch):
    monkeypatch.setattr("torchconn.fit.read_csv", _must_not_run)
    out = tmp_path / "o"
    links = [] if argv[0] == "--links" else ["--links", "3"]
    code = fit.main([str(recording), *links, "--out", str(out), *argv])
    _assert_clean_failure(code, capsys.readouterr().err, fragments, out)
    assert not out.exists()


def test_fit_too_few_cycles_for_the_complexity_says_how_many_are_needed(recording, tmp_path,
                                                                        capsys):
    # 6 cycles at 32 samples per cycle; 48 bins half a spacing wide hold ~2 samples each
    out = tmp_path / "o"
    code = fit.main([str(recording), "--links", "3", "--out", str(out), "--metric", "no",
                     "--complexity", "fixed", "--window", "0.5"])
    _assert_clean_failure(code, capsys.readouterr().err,
                          ["phase bins cannot be fitted", "this recording has 6.0 cycles",
                           "need at least", "cycles per trial", "--complexity"], out)


def test_metric_with_too_few_cycles_says_how_many_are_needed():
    # 5-link, 3 cycles at 126 samples per cycle: the tied metric's 130 coefficients need 390
    seeds = [1]
    wave = FourierGait(torch.tensor([[0.0] * 4, [0.7, 0.0, -0.7, 0.0], [0.0, 0.7, 0.0, -0.7]],
                                    dtype=torch.float64))
    traj = simulate(NLinkSwimmer(5), wave, eta=0.025, n_cycles=3, samples_per_cycle=126,
                    seeds=seeds)
    with pytest.raises(ValueError, match=r"need at least 3·P = 390 \(about 3\.\d cycles at the "
                                         r"12\d samples per cycle of this recording\).*"
                                         r"or leave the metric out: metric=False"):
        ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).fit(traj)
    # and so it does: the connection alone fits
    est = ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).set_params(
        regression__metric=False).fit(traj)
    assert est.model_.M is None


def test_fit_unwritable_out_is_found_before_fitting(recording, tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setattr("torchconn.fit.read_csv", _must_not_run)
    code = fit.main([str(recording), "--links", "3", "--out", str(blocker / "sub")])
    _assert_clean_failure(code, capsys.readouterr().err, ["--out", "cannot create"], None)


# ---------------------------------------------------------------------------- discrepancy
def test_discrepancy_unwritable_out_is_found_before_the_diagnosis(recording, tmp_path, capsys,
                                                                  monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setattr("torchconn.discrepancy.__main__.diagnose", _must_not_run)
    monkeypatch.setattr("torchconn.discrepancy.__main__.read_csv", _must_not_run)
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(blocker / "d"),
                                 "--quiet"])
    _assert_clean_failure(code, capsys.readouterr().err, ["--out", str(blocker / "d")], None)


def test_discrepancy_keeps_the_unknown_column_warning(recording, tmp_path, capsys, monkeypatch):
    lines = _lines(recording)
    path = _write(tmp_path, "extra.csv", "\n".join(
        [lines[0] + ",marker_quality"] + [row + ",1" for row in lines[1:]]))
    seen = []
    monkeypatch.setattr("torchconn.discrepancy.__main__.diagnose",
                        lambda traj, *a, **k: seen.append(traj) or _must_not_run())
    code = discrepancy_cli.main([str(path), "--links", "3", "--out", str(tmp_path / "d"),
                                 "--quiet"])
    err = capsys.readouterr().err
    assert seen and code == 1  # the stand-in diagnosis fails after the file was read
    assert "warning:" in err and "ignoring unknown column(s) 'marker_quality'" in err


@pytest.mark.parametrize("kind", ["folder", "toml", "unknown-key", "bad-value"])
def test_discrepancy_config(kind, recording, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("torchconn.discrepancy.__main__.diagnose", _must_not_run)
    path = tmp_path / "d.toml"
    if kind == "folder":
        path.mkdir()
    else:
        path.write_text({"toml": "[discrepancy]\nalpha = = 1\n",
                         "unknown-key": "[discrepancy]\nalpah = 0.05\n",
                         "bad-value": "[discrepancy]\ncandidates = 'flow'\n"}[kind])
    out = tmp_path / "o"
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(out),
                                 "--config", str(path)])
    fragments = {"folder": ["is a folder"], "toml": ["invalid TOML", "line 2"],
                 "unknown-key": ["'alpah'", "did you mean 'alpha'"],
                 "bad-value": ["candidates must be a list"]}[kind]
    _assert_clean_failure(code, capsys.readouterr().err, [str(path), *fragments]
                          if kind != "unknown-key" else fragments, out)


def test_discrepancy_bad_value_in_data(recording, tmp_path, capsys):
    path = _variant(recording, tmp_path, 25, "theta", "1e300")
    out = tmp_path / "o"
    code = discrepancy_cli.main([str(path), "--links", "3", "--out", str(out), "--quiet"])
    _assert_clean_failure(code, capsys.readouterr().err,
                          ["line 25", "column 'theta'", "implausible"], out)


# ---------------------------------------------------------------------------- subprocesses
def _run(*argv: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", *argv], env=env, capture_output=True,
                          text=True, timeout=300)


def test_subprocess_sweep_bad_set_index(tmp_path):
    config = _write(tmp_path, "s.toml", GOOD_TOML)
    done = _run("torchconn.sweep", "--config", str(config), "--out", str(tmp_path / "o"),
                "--set", "experiment.5.trials=2")
    _assert_clean_failure(done.returncode, done.stderr, ["index 5"], tmp_path / "o")


def test_subprocess_fit_binary_file(tmp_path):
    path = tmp_path / "x.csv"
    path.write_bytes(np.arange(100, dtype=np.float64).tobytes())
    done = _run("torchconn.fit", str(path), "--links", "3", "--out", str(tmp_path / "o"))
    _assert_clean_failure(done.returncode, done.stderr, ["x.csv", "binary data"],
                          tmp_path / "o")


def test_subprocess_discrepancy_out_under_a_file(recording, tmp_path):
    blocker = _write(tmp_path, "f", "x")
    done = _run("torchconn.discrepancy", str(recording), "--links", "3", "--out",
                str(blocker / "o"))
    _assert_clean_failure(done.returncode, done.stderr, ["--out", "cannot create"], None)


def test_threads_flag_sets_torch_threads(tmp_path, capsys):
    before = torch.get_num_threads()
    try:
        config = _write(tmp_path, "s.toml", GOOD_TOML.replace("trials = 2", "trials = 0"))
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
    config = _write(tmp_path, "s.toml", GOOD_TOML)
    code = sweep_cli.main(["--config", str(config), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "internal error (RuntimeError): simulated bug" in err and "TORCHCONN_DEBUG" in err
    assert not (tmp_path / "o" / "results.csv").exists()
