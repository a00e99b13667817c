"""``torchconn-discrepancy`` on bad input: the whole config and every flag are checked before
the diagnosis starts (it is replaced here by a stand-in that fails the test if reached), with a
message naming the file and key or the flag."""

from __future__ import annotations

import pytest

from torchconn.discrepancy import DiscrepancySettings
from torchconn.discrepancy import __main__ as discrepancy_cli

from .common import (
    assert_clean_failure,
    lines,
    must_not_run,
    noise_csv,
    run_module,
    variant,
    write,
)

DIAGNOSE = "torchconn.discrepancy.__main__.diagnose"


class Reached(Exception):
    """The stand-in diagnosis was called: everything before it was accepted."""


def _reached(*args, **kwargs):
    raise Reached


def test_discrepancy_pure_noise_is_not_a_gait(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(DIAGNOSE, must_not_run)
    path = noise_csv(tmp_path, 600, seed=1)
    code = discrepancy_cli.main([str(path), "--links", "3", "--out", str(tmp_path / "o")])
    assert_clean_failure(code, capsys.readouterr().err, ["no periodic gait found"],
                         tmp_path / "o")


def test_discrepancy_unwritable_out_is_found_before_the_diagnosis(recording, tmp_path, capsys,
                                                                  monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setattr(DIAGNOSE, must_not_run)
    monkeypatch.setattr("torchconn.discrepancy.__main__.read_csv", must_not_run)
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(blocker / "d"),
                                 "--quiet"])
    assert_clean_failure(code, capsys.readouterr().err, ["--out", str(blocker / "d")], None)


def test_discrepancy_keeps_the_unknown_column_warning(recording, tmp_path, capsys, monkeypatch):
    rows = lines(recording)
    path = write(tmp_path, "extra.csv", "\n".join(
        [rows[0] + ",marker_quality"] + [row + ",1" for row in rows[1:]]))
    seen = []
    monkeypatch.setattr(DIAGNOSE, lambda traj, *a, **k: seen.append(traj) or must_not_run())
    code = discrepancy_cli.main([str(path), "--links", "3", "--out", str(tmp_path / "d"),
                                 "--quiet"])
    err = capsys.readouterr().err
    assert seen and code == 1  # the stand-in diagnosis fails after the file was read
    assert "warning:" in err and "ignoring unknown column(s) 'marker_quality'" in err


# (id, TOML text or None for a folder, fragments; True: the path is named too)
CONFIG_CASES = [
    ("folder", None, ["is a folder"]),
    ("toml", "[discrepancy]\nalpha = = 1\n", ["invalid TOML", "line 2"]),
    ("unknown-key", "[discrepancy]\nalpah = 0.05\n", ["'alpah'", "did you mean 'alpha'"]),
    ("bad-value", "[discrepancy]\ncandidates = 'flow'\n", ["candidates must be a list"]),
    ("string-for-int", "[discrepancy]\nn_folds = '3'\n",
     ["[discrepancy] n_folds must be an integer", "'3'"]),
    ("negative-bins", "[discrepancy]\nn_bins = -3\n", ["[discrepancy] n_bins must be >= 2"]),
    ("alpha-one", "[discrepancy]\nalpha = 1.0\n", ["[discrepancy] alpha must be < 1"]),
    ("nan", "[discrepancy]\nmin_gain = nan\n", ["min_gain must be a finite number"]),
    ("float-seed", "[discrepancy]\nseed = 1.5\n", ["seed must be an integer", "1.5"]),
    ("bool-as-string", "[discrepancy]\ntwin_intervals = 'yes'\n",
     ["twin_intervals must be true or false"]),
    ("upsample-zero", "[discrepancy]\nupsample = 0\n", ["upsample must be >= 1"]),
    ("candidate-numbers", "[discrepancy]\ncandidates = [1, 2]\n",
     ["candidates must be a list of effect names"]),
    ("candidate-typo", "[discrepancy]\ncandidates = ['ambient_flw']\n",
     ["unknown effect 'ambient_flw'", "did you mean 'ambient_flow'"]),
    ("not-a-table", "discrepancy = 3\n", ["[discrepancy] must be a table"]),
    ("another-command's", "[estimator]\nn_bins = 16\n", ["unknown section(s) [estimator]"]),
    ("latin-1", "# caf\u00e9\n".encode("latin-1"), ["line 1", "not UTF-8"]),
]


@pytest.mark.parametrize("case", CONFIG_CASES, ids=[c[0] for c in CONFIG_CASES])
def test_discrepancy_config(case, recording, tmp_path, capsys, monkeypatch):
    kind, text, fragments = case
    monkeypatch.setattr(DIAGNOSE, must_not_run)
    path = tmp_path / "d.toml"
    if text is None:
        path.mkdir()
    else:
        write(tmp_path, "d.toml", text)
    out = tmp_path / "o"
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(out),
                                 "--config", str(path)])
    assert_clean_failure(code, capsys.readouterr().err, [str(path), *fragments], out)
    assert not out.exists()  # refused before the output folder was made


@pytest.mark.parametrize("argv,fragments", [
    (["--alpha", "1"], ["--alpha must be < 1"]),
    (["--alpha", "nan"], ["--alpha must be a finite number"]),
    (["--folds", "1"], ["--folds must be >= 2"]),
    (["--drag-ratio", "-2"], ["--drag-ratio must be a positive number", "-2"]),
    (["--drag-ratio", "nan"], ["--drag-ratio must be a positive number"]),
    (["--link-lengths", "1", "2"], ["--link-lengths must give 3 positive numbers", "--links 3"]),
    (["--link-lengths", "0.5", "-0.2", "0.7"], ["--link-lengths", "-0.2"]),
    (["--known", "ambient_flow:u_x=inf"], ["--known", "must be a finite number"]),
    (["--known", "time_lag:tau=abc"], ["--known", "is not a number"]),
    (["--fps", "-1"], ["--fps must be a positive number"]),
    (["--threads", "0"], ["--threads must be an integer >= 1"]),
], ids=["alpha-1", "alpha-nan", "folds-1", "drag-negative", "drag-nan", "link-count",
        "link-negative", "known-inf", "known-text", "fps", "threads"])
def test_discrepancy_flags_checked_before_work(argv, fragments, recording, tmp_path, capsys,
                                               monkeypatch):
    monkeypatch.setattr(DIAGNOSE, must_not_run)
    monkeypatch.setattr("torchconn.discrepancy.__main__.read_csv", must_not_run)
    out = tmp_path / "o"
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(out), *argv])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)
    assert not out.exists()


def test_discrepancy_reads_a_config_with_a_byte_order_mark(recording, tmp_path, capsys,
                                                           monkeypatch):
    seen = []
    monkeypatch.setattr(DIAGNOSE, lambda traj, system, settings, **k: seen.append(settings)
                        or _reached())
    path = write(tmp_path, "d.toml", b"\xef\xbb\xbf[discrepancy]\nalpha = 0.05\n")
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(tmp_path / "o"),
                                 "--config", str(path), "--quiet"])
    assert code == 1 and seen and seen[0].alpha == 0.05, capsys.readouterr().err


def test_discrepancy_warns_that_conversion_flags_do_not_apply_to_csvs(recording, tmp_path,
                                                                      capsys, monkeypatch):
    monkeypatch.setattr(DIAGNOSE, _reached)
    code = discrepancy_cli.main([str(recording), "--links", "3", "--out", str(tmp_path / "o"),
                                 "--fps", "30", "--quiet"])
    err = capsys.readouterr().err
    assert code == 1  # the stand-in diagnosis was reached
    assert "warning: --fps ignored" in err and "trajectory CSVs" in err


@pytest.mark.parametrize("kwargs,match", [
    (dict(n_folds="3"), r"DiscrepancySettings\.n_folds must be an integer"),
    (dict(alpha=1.0), r"DiscrepancySettings\.alpha must be < 1"),
    (dict(n_boot=0), r"DiscrepancySettings\.n_boot must be >= 1"),
    (dict(candidates="ambient_flow"), r"candidates must be a list of effect names"),
    (dict(candidates=("warp_drive",)), r"unknown effect 'warp_drive'"),
])
def test_discrepancy_settings_api(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DiscrepancySettings(**kwargs)


def test_discrepancy_bad_value_in_data(recording, tmp_path, capsys):
    path = variant(recording, tmp_path, 25, "theta", "1e300")
    out = tmp_path / "o"
    code = discrepancy_cli.main([str(path), "--links", "3", "--out", str(out), "--quiet"])
    assert_clean_failure(code, capsys.readouterr().err,
                         ["line 25", "column 'theta'", "implausible"], out)


@pytest.mark.parametrize("name,build,fragments", [
    ("empty", lambda rec, tmp: write(tmp, "e.csv", ""), ["e.csv", "empty"]),
    ("twice", lambda rec, tmp: None, ["inputs 1 and 2 name the same file"]),
    ("folder", lambda rec, tmp: tmp, ["is a folder"]),
    ("negative-power", lambda rec, tmp: write(tmp, "p.csv", "\n".join(
        [lines(rec)[0]] + [row[:row.rindex(",") + 1] + ("-" + row[row.rindex(",") + 1:]
                                                          if row[-1] != "," else "")
                           for row in lines(rec)[1:]])), ["column 'power'", "negative"]),
])
def test_discrepancy_bad_recordings(name, build, fragments, recording, tmp_path, capsys,
                                    monkeypatch):
    monkeypatch.setattr(DIAGNOSE, must_not_run)
    path = build(recording, tmp_path)
    files = [str(recording), str(recording)] if path is None else [str(path)]
    out = tmp_path / "o"
    code = discrepancy_cli.main([*files, "--links", "3", "--out", str(out), "--quiet"])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def test_subprocess_discrepancy_out_under_a_file(recording, tmp_path):
    blocker = write(tmp_path, "f", "x")
    done = run_module("torchconn.discrepancy", str(recording), "--links", "3", "--out",
                      str(blocker / "o"))
    assert_clean_failure(done.returncode, done.stderr, ["--out", "cannot create"], None)
