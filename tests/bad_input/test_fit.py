"""``torchconn-fit`` and its Python API (read_csv, Trajectory, ConnectionEstimator) on bad input.

Refused inputs: exit code 2 and one message naming file, line, column or key, no traceback, no
output. Doubtful inputs (units, wrapping, copies): exit code 0 and a warning with its evidence.
Layouts that are unambiguous (tabs, semicolons with decimal commas, a quoted header, comments,
a byte-order mark, Windows line ends) are read exactly as the plain CSV.
"""

from __future__ import annotations

import gzip
import math
import os
import warnings

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, Phaser, Trajectory, fit
from torchconn.io.trajectory_files import read_csv
from torchconn.physics.gaits import FourierGait
from torchconn.physics.systems import NLinkSwimmer
from torchconn.simulation.rollout import simulate

from .common import (
    assert_clean_failure,
    assert_warned,
    lines,
    must_not_run,
    noise_csv,
    run_module,
    variant,
    write,
)


def _csv(tmp, name: str, header, values: np.ndarray) -> "os.PathLike":
    body = "\n".join(",".join("" if np.isnan(v) else repr(float(v)) for v in row)
                     for row in values)
    return write(tmp, name, ",".join(header) + "\n" + body + "\n")


def _scaled(columns, factor=None, fn=None):
    """A builder: the recording with ``columns`` multiplied by ``factor`` (or mapped by fn)."""
    def build(rec, tmp, table):
        header, values = table
        values = values.copy()
        idx = [header.index(c) for c in columns]
        values[:, idx] = fn(values[:, idx]) if fn is not None else values[:, idx] * factor
        return _csv(tmp, "scaled.csv", header, values)
    return build


def _dropped(column):
    def build(rec, tmp, table):
        header, values = table
        j = header.index(column)
        return _csv(tmp, "dropped.csv", header[:j] + header[j + 1:], np.delete(values, j, 1))
    return build


# (id, builder(recording, tmp_path) -> path, fragments of the message)
DATA_CASES = [
    ("huge-r1", lambda rec, tmp: variant(rec, tmp, 40, "r1", "1e300"),
     ["line 40", "column 'r1'", "implausible value '1e300'"]),
    ("huge-x", lambda rec, tmp: variant(rec, tmp, 17, "x", "1e300"),
     ["line 17", "column 'x'", "implausible value '1e300'"]),
    ("huge-theta", lambda rec, tmp: variant(rec, tmp, 5, "theta", "-3e12"),
     ["line 5", "column 'theta'", "implausible"]),
    ("degrees", lambda rec, tmp: variant(rec, tmp, 9, "r2", "87.5"),
     ["line 9", "column 'r2'", "degrees?"]),
    ("infinite", lambda rec, tmp: variant(rec, tmp, 12, "y", "inf"),
     ["line 12", "column 'y'", "infinite"]),
    ("non-numeric", lambda rec, tmp: variant(rec, tmp, 30, "r1", "abc"),
     ["line 30", "column 'r1'", "non-numeric value 'abc'"]),
    ("time-not-increasing", lambda rec, tmp: variant(rec, tmp, 20, "t", "0"),
     ["line 20", "strictly increasing"]),
    ("time-empty", lambda rec, tmp: variant(rec, tmp, 20, "t", ""),
     ["line 20", "column 't' is empty"]),
    ("binary", lambda rec, tmp: write(tmp, "b.csv", bytes(range(256)) * 4),
     ["b.csv", "binary data"]),
    ("utf16", lambda rec, tmp: write(tmp, "u.csv", rec.read_text().encode("utf-16")),
     ["u.csv", "UTF-16"]),
    ("latin1", lambda rec, tmp: write(tmp, "l.csv", rec.read_text().replace(
        "theta", "th\u00e9ta", 1).encode("latin-1")), ["l.csv", "line 1", "not UTF-8"]),
    ("missing-file", lambda rec, tmp: tmp / "nope.csv", ["nope.csv"]),
    ("folder", lambda rec, tmp: (tmp / "d.csv").mkdir() or tmp / "d.csv", ["d.csv", "folder"]),
    ("empty-file", lambda rec, tmp: write(tmp, "e.csv", ""), ["e.csv", "empty"]),
    ("header-only", lambda rec, tmp: write(tmp, "h.csv", lines(rec)[0] + "\n"),
     ["h.csv", "no data rows"]),
    ("missing-column", lambda rec, tmp: write(tmp, "m.csv", "\n".join(
        ",".join(c for i, c in enumerate(row.split(",")) if i != 3) for row in lines(rec))),
     ["m.csv", "missing required column", "'theta'"]),
    ("ragged-row", lambda rec, tmp: write(tmp, "r.csv", "\n".join(
        lines(rec)[:10] + [lines(rec)[10] + ",1"] + lines(rec)[11:])),
     ["r.csv", "line 11", "fields"]),
    ("non-uniform-time", lambda rec, tmp: variant(
        rec, tmp, 50, "t", str(float(lines(rec)[49].split(",")[0]) + 0.05)),
     ["line 5", "not uniformly sampled"]),  # line 50 or 51: both steps are off
    ("all-nan-column", lambda rec, tmp: write(tmp, "n.csv", "\n".join(
        [lines(rec)[0]] + [",".join(row.split(",")[:2] + ["nan"] + row.split(",")[3:])
                           for row in lines(rec)[1:]])),
     ["n.csv", "column 'y' has no values"]),
    ("nul-in-text", lambda rec, tmp: write(
        tmp, "z.csv", rec.read_bytes()[:200] + b"\0" + rec.read_bytes()[200:]),
     ["z.csv", "binary data"]),
    # ---- added: compressed, archives, links, dialects that cannot be read, duplicates
    ("gzip", lambda rec, tmp: write(tmp, "g.csv", gzip.compress(rec.read_bytes())),
     ["g.csv", "gzip-compressed", "decompress"]),
    ("gzip-suffix", lambda rec, tmp: write(tmp, "g.csv.gz", gzip.compress(rec.read_bytes())),
     ["g.csv.gz", "gzip-compressed"]),
    ("excel", lambda rec, tmp: write(tmp, "w.xlsx", b"PK\x03\x04" + os.urandom(200)),
     ["w.xlsx", "ZIP archive", "export the sheet as CSV"]),
    ("symlink-loop", lambda rec, tmp: (os.symlink(tmp / "loop.csv", tmp / "loop.csv"),
                                       tmp / "loop.csv")[1],
     ["loop.csv", "symbolic link loop"]),
    ("decimal-comma-with-commas", lambda rec, tmp: write(tmp, "dc.csv", "\n".join(
        [lines(rec)[0]] + [row.replace(",", ";").replace(".", ",").replace(";", ",")
                           for row in lines(rec)[1:]])),
     ["dc.csv", "line 2", "decimal commas ('0,5') in a comma-separated file"]),
    ("trial-text", lambda rec, tmp: write(tmp, "tt.csv", "\n".join(
        ["trial," + lines(rec)[0]] + [("a," if i < 90 else "b,") + row
                                      for i, row in enumerate(lines(rec)[1:])])),
     ["tt.csv", "line 2", "column 'trial'", "non-numeric value 'a'"]),
    ("trial-fraction", lambda rec, tmp: write(tmp, "tf.csv", "\n".join(
        ["trial," + lines(rec)[0]] + [("0.5," if i < 90 else "1,") + row
                                      for i, row in enumerate(lines(rec)[1:])])),
     ["tf.csv", "column 'trial'", "must be integers", "'0.5'"]),
    ("one-row", lambda rec, tmp: write(tmp, "one.csv", "\n".join(lines(rec)[:2]) + "\n"),
     ["one.csv", "1 sample(s)", "at least 2"]),
    ("duplicate-t", lambda rec, tmp: write(tmp, "dt.csv", "\n".join(
        lines(rec)[:30] + [lines(rec)[29]] + lines(rec)[30:]) + "\n"),
     ["dt.csv", "line 31", "strictly increasing"]),
]

# (id, builder(recording, tmp_path, table) -> path, fragments): the power column and units
VALUE_CASES = [
    ("power-negative", _scaled(["power"], -1.0),
     ["column 'power'", "100% of the values are negative", "lines 2, 3", "sign flipped"]),
    ("power-zero", _scaled(["power"], 0.0), ["column 'power'", "every value is 0"]),
    ("power-mean-removed", _scaled(["power"], fn=lambda p: p - np.nanmean(p)),
     ["column 'power'", "mean removed"]),
    ("joints-in-degrees", _scaled(["r1", "r2"], fn=np.degrees),
     ["column 'r1'", "implausible value", "degrees?"]),
]

# (id, builder(recording, tmp_path, table) -> path, fragments of the warning)
WARN_CASES = [
    ("small-degrees", _scaled(["r1", "r2"], fn=lambda r: np.degrees(r) * 0.1),
     ["column 'r1'", "beyond ±π", "degrees?"]),
    ("millimetres", _scaled(["x", "y"], 85.0),
     ["columns 'x', 'y'", "per gait cycle", "millimetres or pixels"]),
    ("pixels", _scaled(["x", "y"], fn=lambda xy: xy * 400 + 640),
     ["columns 'x', 'y'", "per radian of joint motion", "millimetres or pixels"]),
    ("heading-in-degrees", _scaled(["theta"], fn=np.degrees),
     ["column 'theta'", "more than a full turn", "degrees?"]),
    ("wrapped-joints", _scaled(["r1", "r2"], fn=lambda r: np.angle(np.exp(1j * (r + 2.8)))),
     ["column 'r1'", "jump(s) of about 2π", "wrapped to (−π, π]; unwrapped", "lines "]),
    ("joints-barely-move", _scaled(["r1", "r2"], 1e-4), ["change by only", "rad within a gait"]),
    ("constant-position", _scaled(["x", "y"], 0.0), ["column 'x'", "same value (0) in every row"]),
]


@pytest.mark.parametrize("case", DATA_CASES, ids=[c[0] for c in DATA_CASES])
def test_fit_recording(case, recording, tmp_path, capsys):
    _, build, fragments = case
    path = build(recording, tmp_path)
    out = tmp_path / "out"
    code = fit.main([str(path), "--links", "3", "--out", str(out)])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


@pytest.mark.parametrize("case", VALUE_CASES, ids=[c[0] for c in VALUE_CASES])
def test_fit_implausible_values(case, recording, table, tmp_path, capsys):
    _, build, fragments = case
    path = build(recording, tmp_path, table)
    out = tmp_path / "out"
    code = fit.main([str(path), "--links", "3", "--out", str(out), "--no-figures"])
    assert_clean_failure(code, capsys.readouterr().err, [str(path), *fragments], out)


@pytest.mark.parametrize("case", WARN_CASES, ids=[c[0] for c in WARN_CASES])
def test_fit_doubtful_values_are_warned_of_with_evidence(case, recording, table, tmp_path,
                                                         capsys):
    _, build, fragments = case
    path = build(recording, tmp_path, table)
    code = fit.main([str(path), "--links", "3", "--out", str(tmp_path / "o"), "--no-figures",
                     "--metric", "no", "--folds", "0"])
    assert_warned(code, capsys.readouterr().err, [str(path), *fragments])


def test_fit_same_file_twice_is_refused_and_a_copy_warned_of(recording, tmp_path, capsys):
    out = tmp_path / "o"
    code = fit.main([str(recording), str(recording), "--links", "3", "--out", str(out)])
    assert_clean_failure(code, capsys.readouterr().err,
                         ["inputs 1 and 2 name the same file", str(recording), "pass each file "
                          "once"], out)
    copy = write(tmp_path, "copy.csv", recording.read_bytes())
    code = fit.main([str(recording), str(copy), "--links", "3", "--out", str(out),
                     "--no-figures", "--metric", "no", "--folds", "0"])
    assert_warned(code, capsys.readouterr().err, [str(recording), str(copy),
                                                 "identical contents"])


def test_fit_wrong_joint_count(recording, tmp_path, capsys):
    code = fit.main([str(recording), "--links", "4", "--out", str(tmp_path / "o")])
    assert_clean_failure(code, capsys.readouterr().err, ["2 joint column", "n_joints=3",
                                                        "--links 4"], tmp_path / "o")


def test_fit_pure_noise_is_not_a_gait(tmp_path, capsys):
    path = noise_csv(tmp_path, 400, seed=0)
    code = fit.main([str(path), "--links", "3", "--out", str(tmp_path / "o")])
    assert_clean_failure(code, capsys.readouterr().err, ["no periodic gait found"],
                         tmp_path / "o")


# ---------------------------------------------------------------------------- layouts
def _dialects(rec) -> dict:
    text = rec.read_text()
    rows = text.splitlines()
    return {
        "bom": b"\xef\xbb\xbf" + text.encode(),
        "crlf": text.replace("\n", "\r\n"),
        "tabs": text.replace(",", "\t"),
        "semicolons-decimal-comma": text.replace(",", ";").replace(".", ","),
        "semicolons": text.replace(",", ";"),
        "quoted-header": ",".join(f'"{h}"' for h in rows[0].split(",")) + "\n"
                         + "\n".join(rows[1:]) + "\n",
        "comment-lines": "# recorded 2024-05-01\n# rig 3\n" + text,
        "numpy-savetxt-header": "# " + text,
        "blanks": "\n".join(" ".join(r.split(",")) for r in rows) + "\n",
        "upper-case-header": rows[0].upper() + "\n" + "\n".join(rows[1:]) + "\n",
        "blank-lines": "\n\n".join(rows) + "\n",
        "trailing-commas": "\n".join(r + "," for r in rows) + "\n",
    }


DIALECTS = ["bom", "crlf", "tabs", "semicolons-decimal-comma", "semicolons", "quoted-header",
            "comment-lines", "numpy-savetxt-header", "blanks", "upper-case-header",
            "blank-lines", "trailing-commas"]


@pytest.mark.parametrize("name", DIALECTS)
def test_unambiguous_layouts_read_as_the_plain_csv(name, recording, tmp_path):
    path = write(tmp_path, "d.csv", _dialects(recording)[name])
    good = read_csv(recording)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = read_csv(path)
    for a, b in ((got.t, good.t), (got.pose, good.pose), (got.r, good.r),
                 (got.power, good.power)):
        assert torch.equal(torch.nan_to_num(a, nan=-7.0), torch.nan_to_num(b, nan=-7.0)), name


@pytest.fixture(scope="module")
def good_fit(recording, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "out"
    assert fit.main([str(recording), "--links", "3", "--out", str(out), "--no-figures"]) == 0
    return (out / "connection.csv").read_text()


@pytest.mark.parametrize("name", ["semicolons-decimal-comma", "quoted-header"])
def test_fit_reads_other_layouts_to_the_same_model(name, recording, good_fit, tmp_path,
                                                   capsys):
    path = write(tmp_path, "d.csv", _dialects(recording)[name])
    out = tmp_path / "o"
    assert fit.main([str(path), "--links", "3", "--out", str(out), "--no-figures"]) == 0
    assert str(path) not in capsys.readouterr().err  # nothing to say about the file
    assert (out / "connection.csv").read_text() == good_fit  # bit-identical


def test_unix_time_stamps_fit_the_same_model(recording, table, good_fit, tmp_path, capsys):
    header, values = table
    values = values.copy()
    values[:, 0] = 1.7e9 + values[:, 0]
    path = _csv(tmp_path, "epoch.csv", header, values)
    traj = read_csv(path)
    assert traj.meta["t_offset"] == 1.7e9 and float(traj.t[0]) == 0.0
    out = tmp_path / "o"
    assert fit.main([str(path), "--links", "3", "--out", str(out), "--no-figures"]) == 0
    assert "uniformly" not in capsys.readouterr().err
    got = np.loadtxt(out / "connection.csv", delimiter=",", skiprows=1)
    want = np.loadtxt(good_fit.splitlines(), delimiter=",", skiprows=1)
    # the file's own time stamps are rounded to 2.4e-7 s at 1.7e9 s
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_wrapped_joint_angles_are_unwrapped(recording, table, tmp_path):
    header, values = table
    r = values[:, [header.index("r1"), header.index("r2")]]
    wrapped = values.copy()
    wrapped[:, [header.index("r1"), header.index("r2")]] = np.angle(np.exp(1j * (r + 2.8)))
    with pytest.warns(UserWarning, match=r"column 'r1': \d+ jump\(s\) of about 2π"):
        got = read_csv(_csv(tmp_path, "w.csv", header, wrapped))
    np.testing.assert_allclose(got.r[0].numpy(), r + 2.8, atol=1e-12)


# ---------------------------------------------------------------------------- options
@pytest.mark.parametrize("argv,fragments", [
    (["--grid", "0"], ["--grid must be >= 2"]),
    (["--grid", "100000000"], ["--grid must be <= 100000"]),
    (["--links", "1"], ["--links must be >= 2"]),
    (["--n-bins", "2"], ["n_bins must be >= 3", "got 2"]),
    (["--fourier-order", "30"], ["fourier_order"]),
    (["--window", "-1"], ["--window must be a positive number"]),
    (["--threads", "0"], ["--threads must be an integer >= 1"]),
    (["--fps", "-3"], ["--fps must be a positive number", "-3"]),
    (["--known", "ambient_flow:u_x=nan"], ["--known", "u_x='nan' must be a finite number"]),
    (["--set", "estimator.n_bins"], ["--set 'estimator.n_bins'", "section.key=value"]),
    (["--set", "regression.ridge=nan"], ["ridge must be a finite number", "nan"]),
    (["--set", "estimator.regression.nbins=3"], ["unknown key 'nbins'",
                                                  "did you mean 'n_bins'"]),
    (["--set", "convert.fpss=3"], ["[convert]", "unknown key 'fpss'", "did you mean 'fps'"]),
    (["--set", "convert.fps=-1"], ["[convert] fps must be > 0", "-1"]),
], ids=["grid-0", "grid-huge", "links-1", "n-bins-2", "fourier-order", "window", "threads",
        "fps-negative", "known-nan", "set-no-value", "set-nan", "set-typo", "convert-typo",
        "convert-range"])
def test_fit_options_checked_before_work(argv, fragments, recording, tmp_path, capsys,
                                         monkeypatch):
    monkeypatch.setattr("torchconn.fit.read_csv", must_not_run)
    out = tmp_path / "o"
    links = [] if argv[0] == "--links" else ["--links", "3"]
    code = fit.main([str(recording), *links, "--out", str(out), *argv])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)
    assert not out.exists()


@pytest.mark.parametrize("kind,text,fragments", [
    ("folder", None, ["--config", "is a folder, expected a TOML file"]),
    ("missing", None, ["--config", "not found"]),
    ("syntax", "[estimator\nn_bins = 3\n", ["invalid TOML", "line 1"]),
    ("latin-1", "# caf\u00e9\n".encode("latin-1"), ["line 1", "not UTF-8"]),
    ("wrong-type", "[estimator.regression]\nn_bins = 'many'\n",
     ["n_bins must be an integer", "'many'"]),
    ("unknown-section", "[estimatr]\nn_bins = 24\n", ["unknown config section", "estimatr"]),
    ("convert-wrong-type", "[convert]\nflip_y = 'yes'\n", ["[convert] flip_y", "true or false"]),
    ("estimator-not-a-table", "estimator = 5\n", ["[estimator] must be a table", "got 5"]),
], ids=lambda v: v if isinstance(v, str) and len(v) < 20 else None)
def test_fit_config_checked_before_work(kind, text, fragments, recording, tmp_path, capsys,
                                        monkeypatch):
    monkeypatch.setattr("torchconn.fit.read_csv", must_not_run)
    path = tmp_path / "c.toml"
    if kind == "folder":
        path.mkdir()
    elif text is not None:
        write(tmp_path, "c.toml", text)
    out = tmp_path / "o"
    code = fit.main([str(recording), "--links", "3", "--out", str(out), "--config", str(path)])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def test_fit_reads_a_config_with_a_byte_order_mark(recording, tmp_path, capsys, monkeypatch):
    seen = []
    monkeypatch.setattr("torchconn.fit.read_csv", lambda *a, **k: seen.append(1) or
                        must_not_run())
    path = write(tmp_path, "c.toml", b"\xef\xbb\xbf[estimator]\npool = true\n")
    fit.main([str(recording), "--links", "3", "--out", str(tmp_path / "o"), "--config",
              str(path)])
    assert seen, capsys.readouterr().err  # the config was read; the data were next


def test_fit_warns_that_conversion_flags_do_not_apply_to_csvs(recording, tmp_path, capsys):
    code = fit.main([str(recording), "--links", "3", "--out", str(tmp_path / "o"), "--fps",
                     "30", "--no-figures", "--metric", "no", "--folds", "0"])
    assert_warned(code, capsys.readouterr().err, ["--fps ignored", "trajectory CSVs"])


def test_fit_too_few_cycles_for_the_complexity_says_how_many_are_needed(recording, tmp_path,
                                                                        capsys):
    # 6 cycles at 32 samples per cycle; 48 bins half a spacing wide hold ~2 samples each
    out = tmp_path / "o"
    code = fit.main([str(recording), "--links", "3", "--out", str(out), "--metric", "no",
                     "--complexity", "fixed", "--window", "0.5"])
    assert_clean_failure(code, capsys.readouterr().err,
                         ["phase bins cannot be fitted", "this recording has 6.0 cycles",
                          "need at least", "cycles per trial", "--complexity"], out)


def test_fit_unwritable_out_is_found_before_fitting(recording, tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setattr("torchconn.fit.read_csv", must_not_run)
    code = fit.main([str(recording), "--links", "3", "--out", str(blocker / "sub")])
    assert_clean_failure(code, capsys.readouterr().err, ["--out", "cannot create"], None)


def test_subprocess_fit_binary_file(tmp_path):
    path = tmp_path / "x.csv"
    path.write_bytes(np.arange(100, dtype=np.float64).tobytes())
    done = run_module("torchconn.fit", str(path), "--links", "3", "--out", str(tmp_path / "o"))
    assert_clean_failure(done.returncode, done.stderr, ["x.csv", "binary data"],
                         tmp_path / "o")


# ---------------------------------------------------------------------------- Python API
@pytest.mark.parametrize("kwargs,error,match", [
    (dict(min_cycles=float("nan")), ValueError, r"read_csv: min_cycles must be a finite number"),
    (dict(min_cycles=float("inf")), ValueError, r"min_cycles must be a finite number, got inf"),
    (dict(min_cycles=-1), ValueError, r"min_cycles must be >= 0, got -1"),
    (dict(min_cycles="3"), ValueError, r"min_cycles must be a finite number, got '3'"),
    (dict(n_joints=True), ValueError, r"read_csv: n_joints must be an integer >= 1, got True"),
    (dict(n_joints=2.0), ValueError, r"n_joints must be an integer >= 1, got 2\.0"),
], ids=["min-cycles-nan", "min-cycles-inf", "min-cycles-negative", "min-cycles-str",
        "n-joints-bool", "n-joints-float"])
def test_read_csv_options_are_checked(kwargs, error, match, recording):
    with pytest.raises(error, match=match):
        read_csv(recording, **kwargs)


@pytest.mark.parametrize("paths", [5, None, [None], [3.0]])
def test_read_csv_paths_are_checked(paths):
    with pytest.raises(TypeError, match="read_csv: paths must be a file path"):
        read_csv(paths)


def test_trajectory_refuses_complex_and_converts_integers(recording):
    good = read_csv(recording)
    with pytest.raises(TypeError, match=r"Trajectory: r is a complex tensor"):
        Trajectory(t=good.t, pose=good.pose, r=good.r.to(torch.complex128))
    with pytest.warns(UserWarning, match=r"converted r \(torch\.int64\) to float64"):
        tr = Trajectory(t=good.t, pose=good.pose, r=torch.ones_like(good.r, dtype=torch.int64))
    assert tr.r.dtype == torch.float64
    with pytest.warns(UserWarning, match=r"converted t \(torch\.float32\)"):
        tr = Trajectory(t=good.t.float(), pose=good.pose, r=good.r)  # float32 rounding of t
    assert tr.t.dtype == torch.float64


def test_a_recording_held_wholly_in_float32_is_fitted(recording):
    # t in float32 too: its rounding is not jitter once t is float64
    good = read_csv(recording)
    with pytest.warns(UserWarning, match=r"converted t \(torch\.float32\)"):
        tr = Trajectory(t=good.t.float(), pose=good.pose.float(), r=good.r.float())
    torch.testing.assert_close(tr.t, good.t, rtol=0, atol=1e-5)
    with pytest.warns(UserWarning, match=r"torch\.float32 arrays; converted to float64"):
        est = ConnectionEstimator(held_out_folds=0).set_params(
            metric__enabled=False).fit(tr)
    assert bool(torch.isfinite(est.model_.connection(torch.zeros(1, dtype=torch.float64))).all())


def test_trajectory_accepts_unix_time_stamps():
    t = 1.7e9 + torch.arange(200, dtype=torch.float64) / 30  # spacing uniform up to rounding
    tr = Trajectory(t=t, pose=torch.zeros(200, 3, dtype=torch.float64),
                    r=torch.zeros(200, 2, dtype=torch.float64))
    assert tr.n_samples == 200


def test_estimator_converts_float32_and_refuses_negative_power(recording):
    good = read_csv(recording)
    with pytest.raises(ValueError, match=r"ConnectionEstimator\.fit: power of trial 0.*"
                                         r"negative.*metric__enabled=False"):
        ConnectionEstimator().fit(good.with_fields(power=-good.power))
    with pytest.warns(UserWarning, match=r"ConnectionEstimator\.fit: the trajectory holds "
                                         r"torch\.float32 arrays; converted to float64"):
        est = ConnectionEstimator(held_out_folds=0).set_params(
            metric__enabled=False).fit(good.to(torch.float32))
    assert est.model_.connection(torch.zeros(1, dtype=torch.float64)).dtype == torch.float64


@pytest.mark.parametrize("change,error,match", [
    (lambda tr: dict(pose=tr.pose.index_fill(1, torch.tensor([5]), math.inf)), ValueError,
     r"traj\.pose holds ±inf \(x of trial 0 of the flattened batch, sample 5\)"),
    (lambda tr: dict(r=tr.r * math.nan), ValueError,
     r"r1 \(traj\.r\) of trial 0 of the flattened batch has no finite sample"),
    (lambda tr: dict(phase=torch.zeros(tr.r.shape[:-1], dtype=torch.int64)), TypeError,
     r"phase must be a floating-point tensor of shape \(1, 192\)"),
    (lambda tr: dict(phase=torch.full(tr.r.shape[:-1], math.nan, dtype=torch.float64)),
     ValueError, r"phase holds ±inf, or a trial without one finite value"),
], ids=["pose-inf", "r-all-nan", "phase-integer", "phase-nan"])
def test_estimator_checks_its_input_before_work(change, error, match, recording, monkeypatch):
    good = read_csv(recording)
    monkeypatch.setattr("torchconn.regression.estimator._prepare", must_not_run)
    kwargs = change(good)
    phase = kwargs.pop("phase", None)
    with pytest.raises(error, match=match):
        ConnectionEstimator().fit(good.with_fields(**kwargs), phase)


def test_stage_options_refuse_nan():
    with pytest.raises(ValueError, match=r"Phaser\.min_cycles must be a finite number"):
        Phaser(min_cycles=math.nan)


def test_metric_with_too_few_cycles_says_how_many_are_needed():
    # 5-link, 3 cycles at 126 samples per cycle: the tied metric's 130 coefficients need 390
    seeds = [1]
    wave = FourierGait(torch.tensor([[0.0] * 4, [0.7, 0.0, -0.7, 0.0], [0.0, 0.7, 0.0, -0.7]],
                                    dtype=torch.float64))
    traj = simulate(NLinkSwimmer(5), wave, eta=0.025, n_cycles=3, samples_per_cycle=126,
                    seeds=seeds)
    with pytest.raises(ValueError, match=r"need at least 3·P = 390 \(about 3\.\d cycles at the "
                                         r"12\d samples per cycle of this recording\).*"
                                         r"or leave the metric out: metric__enabled=False"):
        ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).fit(traj)
    # and so it does: the connection alone fits
    est = ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).set_params(
        metric__enabled=False).fit(traj)
    assert est.model_.M is None
